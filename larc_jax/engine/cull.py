"""Culling the pieces of large scenes (a point cloud's or many meshes' pieces) per subtree of intervals.

A scene of thousands of pieces (:mod:`larc_jax.model.point_sets`) made every interval bound every
(capsule, piece) pair, although a link is ever near a few of them. Here the pieces are grouped
into clusters of at most :data:`CLUSTER_PIECES` neighbours (recursive median splits of their box
centres), each cluster enclosed by an axis-aligned box, and every trajectory's *nodes*, the dyadic
intervals of depth ``0 .. CULL_DEPTH``, get the capsule test (eq. 7, :mod:`larc_jax.leaf.interval`)
against the cluster boxes alone. An interval of depth ``d`` is then tested against the scene's
boxes and shapes and the pieces of the clusters its node kept (its own node for ``d <= CULL_DEPTH``,
else its ancestor at that depth), padded to one of a few :data:`WIDTHS`.

Why dropping a cluster is sound. The cluster box holds every member piece's obstacle (the hull of
its points grown by the cloud's point radius; the box of a piece is ``[min v - r, max v + r]``,
rounded outwards in float64, then outwards again to the geometry dtype, budget G3). A node whose
capsule test gives the box ``g - guard > CULL_SLACK_M >= 0`` has proven, by the interval test's own
soundness argument (eq. 4-7 with every rounding budget of :mod:`larc_jax.leaf.interval`), that every
link stays more than the margin from that box, hence from each member piece, over the node's
whole interval [a, b]. Every leaf below the node lies inside [a, b] (dyadic ends are monotone in
their fraction, :func:`~larc_jax.leaf.interval.dyadic_ends`), so its claim for the dropped pieces
is already proven; its own test decides the kept ones. NaN never drops a cluster (``g - guard >
s`` is False).

What a leaf records. ``g`` is the smaller (in ``g - guard``) of its own test's record and the
node's *floor*: the dropped cluster with the least ``g - guard``, recorded with the capsule that
gave it and the cluster's first piece. The floor is a lower bound of that piece's clearance over
the leaf, so the recorded ``g`` stays a lower bound of the leaf's true clearance, and a leaf passes
exactly where its own test does (the floor always passes). An interval whose node kept nothing
(no box, shape or piece of its scene) is not tested against obstacles at all: its node's test,
on finite numbers, proved every piece clear over it, and its record is the floor. The record is the all-pairs one
wherever that one's ``g - guard`` is at most ``CULL_SLACK_M``: a piece with leaf slack ``s`` has node
slack at most ``s`` (the leaf's inflated capsules lie inside the node's, up to rounding), so it was
kept. Above that, ``g`` may be below the all-pairs value; ``larc verify`` refutes only a stored
clearance *above* its recomputed one (:mod:`larc_jax.products.verify`).

Scenes of fewer than :data:`CULL_MIN_PIECES` pieces are not culled (their results are those of
every pair, as before). :class:`Cull` is built once per :class:`~larc_jax.engine.batch.Batch`;
its node test costs ``2**(CULL_DEPTH + 1) - 1`` intervals per trajectory against ``pieces /
CLUSTER_PIECES`` boxes.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from ..leaf.record import CULL_SLACK_M, LeafRecord
from ..model.scene import Scene
from ..obstacles import stack_scenes
from ..obstacles.convex_shapes import piece_bounds
from .kernels import item_margins

__all__ = ["Cull", "CullPart", "build_cull", "piece_clusters", "worth_culling", "CULL_MIN_PIECES", "CLUSTER_PIECES",
           "CULL_DEPTH", "CULL_SLACK_M", "WIDTHS"]

CULL_MIN_PIECES = 256
"""Pieces a scene needs before it is culled (below this, every interval bounds every pair)."""
CLUSTER_PIECES = 32
"""Pieces per cluster at most."""
CULL_DEPTH = 6
"""Deepest nodes tested against the cluster boxes (127 intervals per trajectory)."""
WIDTHS = (4, 64)
"""Items per interval after culling, rounded up to one of these (each a compiled shape); an
interval needing at least the whole scene's item count is tested against the whole scene, and one
needing none is not tested against obstacles at all (its node's floor is its record)."""


def worth_culling(scenes) -> bool:
    """Whether any scene has :data:`CULL_MIN_PIECES` pieces."""
    return any(len(s.point_sets.pieces) >= CULL_MIN_PIECES for s in scenes)


def _split(centres: np.ndarray, idx: np.ndarray, size: int) -> list[np.ndarray]:
    """Recursive median splits along the widest axis until every group has at most ``size``."""
    if len(idx) <= size:
        return [idx]
    c = centres[idx]
    axis = int(np.argmax(c.max(axis=0) - c.min(axis=0)))
    order = idx[np.argsort(c[:, axis], kind="stable")]
    half = len(order) // 2
    return _split(centres, order[:half], size) + _split(centres, order[half:], size)


def piece_clusters(scene: Scene, size: int | None = None):
    """``(members, lo, hi)``: the scene's pieces in clusters of at most ``size`` (default
    :data:`CLUSTER_PIECES`; ``members``, a list
    of item-index arrays, items numbered as :func:`~larc_jax.obstacles.convex_shapes.shape_items`:
    boxes, shapes, then pieces) and each cluster's box holding its pieces' obstacles, float64
    (module docstring: ``[min v - r, max v + r]`` rounded outwards)."""
    ps = scene.point_sets
    if not ps.pieces:
        return [], np.zeros((0, 3)), np.zeros((0, 3))
    r = np.asarray(ps.radius, np.float64)[np.asarray(ps.owner, np.int64)][:, None]
    lo, hi = piece_bounds(ps)
    lo, hi = lo - r, hi + r
    lo, hi = np.nextafter(lo, -np.inf), np.nextafter(hi, np.inf)  # the subtraction's rounding
    groups = _split((lo + hi) / 2, np.arange(len(ps.pieces)), CLUSTER_PIECES if size is None else size)
    first = scene.n_boxes + scene.shapes.count
    return ([g + first for g in groups], np.array([lo[g].min(axis=0) for g in groups]),
            np.array([hi[g].max(axis=0) for g in groups]))


@dataclasses.dataclass(frozen=True)
class CullPart:
    """The intervals ``rows`` (of one call) that are tested against the same number of items:
    ``sel`` the kernels' selection, ``(scene,)`` (every item) or ``(scene, items)`` ((F, W) item
    indices, padding the scene's masked last item), and each row's node floor."""

    rows: np.ndarray
    sel: tuple
    floor: LeafRecord | None

    def finish(self, record: LeafRecord) -> LeafRecord:
        """A stage record over ``sel``'s items made a record over the scene's items, with the
        node's floor where that has the smaller ``g - guard`` and the record passes."""
        if len(self.sel) == 1:
            return record
        items = self.sel[1]
        box = items[np.arange(len(items)), np.asarray(record.box)] if items.shape[1] else np.zeros(len(items), np.int64)
        box = np.where(np.isinf(record.clearance_m), 0, box)  # nothing real near: as every pair's argmin
        f = self.floor
        lower = (record.stage > 0) & (f.clearance_m - f.guard_m < record.clearance_m - record.guard_m)
        pick = lambda new, old: np.where(lower, new, old)  # noqa: E731
        return LeafRecord(pick(f.clearance_m, record.clearance_m), pick(f.guard_m, record.guard_m),
                          pick(f.capsule, record.capsule), pick(f.box, box), record.other, record.stage)


@dataclasses.dataclass(frozen=True)
class Cull:
    """Per trajectory and node: the clusters kept and the floor (module docstring)."""

    always: list
    """Per scene: the item indices never culled (boxes and shapes)."""
    members: list
    """Per scene: a list of clusters, each an array of item indices."""
    keep: np.ndarray
    """(trajectories, nodes, clusters) bool: the clusters each node kept."""
    floor: LeafRecord
    """Arrays (trajectories, nodes): each node's floor (``box``: the item named)."""
    pad_item: int
    """A masked item of every scene (the stacked set has one more item than its largest scene)."""
    n_items: int
    """Items per scene in the stacked set (padding included)."""

    @property
    def n_nodes(self) -> int:
        return self.keep.shape[1]

    def node(self, depth: np.ndarray, index: np.ndarray) -> np.ndarray:
        """The node of intervals ``(depth, index)``: itself up to :data:`CULL_DEPTH`, else its ancestor."""
        d = np.minimum(depth, CULL_DEPTH)
        return (1 << d) - 1 + (index >> (depth - d))

    def parts(self, traj: np.ndarray, depth: np.ndarray, index: np.ndarray, scene_of: np.ndarray) -> list[CullPart]:
        """The intervals grouped by the width of their item lists (module docstring)."""
        key = traj * self.n_nodes + self.node(depth, index)
        keys, inverse = np.unique(key, return_inverse=True)
        kt, kn = keys // self.n_nodes, keys % self.n_nodes
        scene = scene_of[kt]
        lists = [np.concatenate([self.always[s]] + [self.members[s][m] for m in np.flatnonzero(self.keep[t, n])])
                 for t, n, s in zip(kt, kn, scene)]
        count = np.array([len(x) for x in lists])
        width = np.array([0 if c == 0 else next((w for w in WIDTHS if w >= c), self.n_items) for c in count])
        width = np.where(width >= self.n_items, self.n_items, width)
        parts = []
        for w in np.unique(width):
            of_key = np.flatnonzero(width == w)
            rows = np.flatnonzero(np.isin(inverse, of_key))
            floor = LeafRecord(*(np.asarray(x)[kt[inverse[rows]], kn[inverse[rows]]] for x in self.floor))
            if w >= self.n_items:  # the whole scene: every pair, the node's floor is moot
                parts.append(CullPart(rows, (scene_of[traj[rows]],), None))
                continue
            table = np.full((len(keys), w), self.pad_item, np.int64)
            for k in of_key:
                table[k, : count[k]] = lists[k]
            parts.append(CullPart(rows, (scene_of[traj[rows]], table[inverse[rows]]), floor))
        return parts


def build_cull(scenes: list[Scene], scene_of: np.ndarray, n_items: int, dtype, run: Callable) -> Cull:
    """The :class:`Cull` of a batch: ``scenes`` the batch's stacked scenes (``n_items`` items each in
    the stacked set, the last always masked), ``scene_of`` each trajectory's; ``run(kernel, boxes,
    traj, depth, index, width)`` evaluates ``kernel`` on those intervals (the batch's calls).

    Level by level: a node is tested only against the clusters its parent kept (a cluster the
    parent dropped stays dropped: the parent's proof covers the child's interval), and a node
    whose parent kept none is not tested at all; its floor is the lower of its own and its parent's."""
    clusters = [piece_clusters(s) for s in scenes]
    n_clusters = max([len(c[0]) for c in clusters] + [1])
    boxes = stack_scenes([Scene(lo=c[1], hi=c[2]) if len(c[0]) else Scene(lo=np.zeros((0, 3)), hi=np.zeros((0, 3)))
                          for c in clusters], dtype, n_clusters)
    n_traj, n_nodes = len(scene_of), (1 << (CULL_DEPTH + 1)) - 1
    real = np.zeros((len(scenes), n_clusters), bool)
    first = np.zeros((len(scenes), n_clusters), np.int64)
    for s, (members, _, _) in enumerate(clusters):
        real[s, : len(members)] = True
        first[s, : len(members)] = [m[0] for m in members]
    keep = np.zeros((n_traj, n_nodes, n_clusters), bool)
    # the floor: its g - guard (to compare), then the record's g, guard, capsule and item
    f_slack, f_g = np.full((n_traj, n_nodes), np.inf), np.full((n_traj, n_nodes), np.inf)
    f_guard, f_cap, f_item = np.zeros((n_traj, n_nodes)), np.zeros((n_traj, n_nodes), np.int64), \
        np.zeros((n_traj, n_nodes), np.int64)
    floor = (f_slack, f_g, f_guard, f_cap, f_item)
    for d in range(CULL_DEPTH + 1):
        nodes = (1 << d) - 1 + np.arange(1 << d)
        parent = np.zeros(1, np.int64) if d == 0 else (1 << (d - 1)) - 1 + (np.arange(1 << d) >> 1)
        held = real[scene_of][:, None, :] if d == 0 else keep[:, parent]  # (trajectories, 2**d, clusters)
        keep[:, nodes] = held
        for arr in floor:
            arr[:, nodes] = arr[:, parent] if d else arr[:, :1]
        t, i = np.nonzero(held.any(axis=2))
        if not len(t):
            continue
        slack, g, guard, cap, finite = (np.asarray(x) for x in run(item_margins, boxes, t, np.full(len(t), d), i,
                                                                   n_clusters))
        h = held[t, i]
        kept = h & (~(slack > CULL_SLACK_M) | ~finite[:, None].astype(bool))  # NaN is kept
        keep[t, nodes[i]] = kept
        dropped = np.where(h & ~kept, slack, np.inf)
        m = dropped.argmin(axis=1)
        rows = np.arange(len(t))
        lower = dropped[rows, m] < f_slack[t, nodes[i]]
        t, n, m, rows = t[lower], nodes[i][lower], m[lower], rows[lower]
        f_slack[t, n], f_g[t, n], f_guard[t, n] = dropped[rows, m], g[rows, m], guard[rows, m]
        f_cap[t, n], f_item[t, n] = cap[rows, m], first[scene_of[t], m]
    return Cull(always=[np.arange(s.n_boxes + s.shapes.count) for s in scenes], members=[c[0] for c in clusters],
                keep=keep, floor=LeafRecord(f_g, f_guard, f_cap, f_item, np.full(f_g.shape, -1, np.int64),
                                            np.zeros(f_g.shape, np.int8)), pad_item=n_items - 1, n_items=n_items)
