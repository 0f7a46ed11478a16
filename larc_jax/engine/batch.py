"""Host-side batching for the JAX certifiers: padded arrays, size classes, bucketed calls.

A dataset of trajectories (each with its own waypoint count, duration and scene) becomes one
:class:`Batch`: splines padded to a common knot count (their range-maximum tables ragged,
each its own length: :mod:`larc_jax.model.spline_batch`), scenes stacked into one obstacle set
padded to a common item count (masked; :func:`~larc_jax.obstacles.stack_scenes`), per-trajectory
horizons. :meth:`Batch.evaluate` runs the interval test on any list of (trajectory, depth,
index) intervals in jitted, vmapped calls (:mod:`larc_jax.engine.kernels`) padded to a few
bucket sizes (:mod:`larc_jax.engine.buckets`), so a process compiles a handful of shapes, not one per frontier size. A scene of
many mesh or cloud pieces is culled per subtree of intervals (:mod:`larc_jax.engine.cull`): each
interval then meets the items its subtree kept, in lists of a few widths.

Several devices (all GPUs, or CPU devices forced with ``XLA_FLAGS=--xla_force_host_platform_device_count=N``):
each batch of intervals is sharded along its axis over a 1-D mesh; each interval still runs on one device.

Interval ends are exact dyadic fractions of the horizon (:func:`dyadic_ends`), shared by every
certifier: neighbours compute their common end from the same fraction, so a cover has no gaps.
They are computed in each trajectory's own time axis (what a leaf reports) and handed to the
kernel rebased with outward rounding (:func:`~larc_jax.leaf.interval.rebase_ends`, budget T1).
Geometry arrays are cast to the geometry dtype (obstacles rounded outwards); times, splines and the
per-trajectory rounding bounds are float64.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Sequence

import numpy as np

from ..compilation import cached_kernel, tracked_call
from ..enclosure.capsule import CapsuleModel
from ..enclosure.hull import HullModel, by_vertex_class
from ..lazy_jax import jax  # importing this module loads JAX and registers the pytrees (lazy_jax)
from ..leaf.cascade import Links, PairDetails, combine, exact_enough, select_pairs
from ..leaf.rounds import early_stop_slack, hull_rounds, point_round
from ..leaf.clearance import BROAD_PHASE_K
from ..leaf.interval import RoundingBounds, dyadic_ends, rebase_ends
from ..leaf.record import LeafRecord, Stage, box_record, compose, needs_hull, self_record
from ..leaf.self_collision import SelfPairs
from ..leaf.swept import SweptPlacement, SweptTables, swept_links, swept_record
from ..model.hermite import pad_waypoints_batch
from ..model.robot import Robot
from ..model.scene import Scene
from ..model.spline_batch import SplineBatch, spline_batch
from ..obstacles import ObstacleSet, stack_scenes
from .buckets import BUCKETS, CALL_BYTES, CASCADE_BUCKETS, CULLED_BUCKETS, PAIR_BUCKETS, PAIR_BYTES, size_class
from .cull import CULL_DEPTH, WIDTHS, Cull, CullPart, build_cull, worth_culling
from .kernels import (batched_interval_pairs, batched_interval_pairs_bounded, evaluate_intervals, evaluate_intervals_broad,
                      evaluate_intervals_screened, evaluate_intervals_screened_broad, hull_early, hull_first_axis,
                      hull_pairs, hull_points, hull_screen, item_margins, self_intervals, swept_capsules,
                      swept_intervals, swept_parts)

__all__ = ["Batch", "prepare", "dyadic_ends"]


def _geometry(robot: Robot, capsules: CapsuleModel, dtype):
    """Robot and capsule arrays in the geometry dtype; radii and motion constants stay float64
    (they enter the float64 sums, budget P3/G4)."""
    cast = lambda x: np.asarray(x, dtype) if np.issubdtype(np.asarray(x).dtype, np.floating) else x  # noqa: E731
    robot_g = jax.tree.map(cast, robot)
    capsules_g = dataclasses.replace(
        capsules, p_link_a=cast(capsules.p_link_a), p_link_b=cast(capsules.p_link_b),
        radius=np.asarray(capsules.radius, np.float64), motion_a=np.asarray(capsules.motion_a, np.float64))
    return robot_g, capsules_g


def _hulls_geometry(hulls: HullModel, dtype) -> HullModel:
    """Hull vertex tables in the geometry dtype; radii and motion constants stay float64 (as
    for capsules). A float32 vertex is rounded once: covered by the part's guard (G1)."""
    cast = lambda x: np.asarray(x, dtype)  # noqa: E731
    return dataclasses.replace(hulls, vertices=cast(hulls.vertices), centre=cast(hulls.centre),
                               probes=cast(hulls.probes), radius=np.asarray(hulls.radius, np.float64),
                               motion_a=np.asarray(hulls.motion_a, np.float64))


@dataclasses.dataclass
class Batch:
    """Host-side padded dataset ready for the kernel."""

    robot: Robot
    capsules: CapsuleModel
    splines: SplineBatch
    """Splines on rebased knots (float64), padded."""
    bounds: RoundingBounds
    """Per-trajectory rounding bounds, stacked (leading axis = trajectory)."""
    obstacles: ObstacleSet
    """Every scene's obstacles, padded to one item count (leading axis = scene), geometry dtype."""
    scene_of: np.ndarray
    t_start: np.ndarray
    """Horizon start per trajectory, in its own time axis, s."""
    t_end: np.ndarray
    margin: np.ndarray
    dtype: np.dtype
    """Geometry dtype (times and the curve are always float64)."""
    devices: tuple = ()
    """Devices the interval axis is sharded over (one device: no sharding)."""
    hulls: HullModel | None = None
    """Hull parts for the cascade (larc_jax.leaf.cascade); None: the capsule test alone."""
    self_pairs: SelfPairs | None = None
    """Capsule pairs of the self test (:mod:`larc_jax.leaf.self_collision`); None: obstacles only."""
    self_skip: np.ndarray | None = None
    """(padded trajectories, P) bool: pairs proven apart for each trajectory (:meth:`SelfPairs.skip_mask`)."""
    swept: SweptTables | None = None
    """The swept stage's chain tables (:mod:`larc_jax.leaf.swept`); None: no swept stage."""
    cull: Cull | None = None
    """The pieces each subtree of intervals keeps (:mod:`larc_jax.engine.cull`); None: every item."""
    links: Links | None = None
    """Which link each capsule and hull part belongs to (given :attr:`hulls`), built once per batch."""

    def _put(self, *arrays):
        """Shard interval-axis arrays over :attr:`devices` (a 1-D mesh); the rest of the inputs
        (robot, splines, obstacles) are replicated by ``jit``."""
        if len(self.devices) <= 1:
            return arrays
        from jax.sharding import Mesh, NamedSharding, PartitionSpec

        sharding = NamedSharding(Mesh(np.array(self.devices), ("interval",)), PartitionSpec("interval"))
        return tuple(jax.device_put(x, sharding) for x in arrays)

    def max_chunk(self, width: int | None = None) -> int:
        """Intervals per call at most when each meets ``width`` items (default: a whole scene): the
        all-pairs kernel holds ~:data:`PAIR_BYTES` per capsule-obstacle pair, and a call at most
        :data:`CALL_BYTES` (thousands of pieces: small chunks; boxes: never below the largest bucket)."""
        pairs = max(1, self.capsules.n_capsules * (self.obstacles.n_items if width is None else width))
        return max(4, 1 << max(0, (CALL_BYTES // (PAIR_BYTES * pairs)).bit_length() - 1))

    def endpoints(self, traj: np.ndarray, depth: np.ndarray, index: np.ndarray):
        """Interval ends from (trajectory, depth, index): :func:`dyadic_ends`."""
        return dyadic_ends(self.t_start[traj], self.t_end[traj], depth, index)

    def _rebased(self, traj, a, b):
        """Interval ends as the kernel takes them: rebased, rounded outwards (budget T1)."""
        return rebase_ends(a, b, np.asarray(self.bounds.offset_s)[traj])

    def kernel_args(self, traj, a, b) -> tuple:
        """The arguments of :func:`~larc_jax.engine.kernels.evaluate_intervals` for intervals ``(traj, a,
        b)`` (own time axis) against every item of their scenes."""
        ar, br = self._rebased(traj, a, b)
        return (self.robot, self.capsules, self.splines, self.obstacles, self.bounds, traj, (self.scene_of[traj],),
                ar, br, self.margin)

    def bucketed(self, call, items, on_chunk=None, buckets=BUCKETS, width: int | None = None):
        """Run ``call(*chunk)`` over the per-item arrays ``items`` in chunks padded to ``buckets``
        (repeating the chunk's first item; results dropped), at most :meth:`max_chunk` ``(width)``
        long, sharded over :attr:`devices`: the outputs (NumPy pytree) concatenated over the items;
        ``on_chunk(n)`` after each chunk of ``n`` items."""
        n = len(items[0])
        parts = []
        buckets = tuple(s for s in buckets if s <= self.max_chunk(width)) or buckets[:1]  # memory: PAIR_BYTES
        for start in range(0, n, buckets[-1]):
            stop = min(n, start + buckets[-1])
            size = next(s for s in buckets if s >= stop - start)
            size = -(-size // max(1, len(self.devices))) * max(1, len(self.devices))  # whole shards
            pad = size - (stop - start)
            chunk = [np.concatenate([x[start:stop], np.repeat(x[start:start + 1], pad, axis=0)]) for x in items]
            with jax.enable_x64(True):
                out = call(*self._put(*chunk))
                parts.append(jax.tree.map(lambda x: np.asarray(x)[: stop - start], out))
            if on_chunk:
                on_chunk(stop - start)
        return jax.tree.map(lambda *xs: np.concatenate(xs), *parts)

    def _over(self, kernel, head, sel, tr, ar, br, on_chunk=None, on_compile=None, buckets=BUCKETS):
        """``kernel(*head, splines, obstacles, bounds, tr, sel, ar, br, margin)`` over intervals,
        bucketed (``sel``: :meth:`selection`'s tuple, split into arrays for the padding)."""
        call = kernel if len(self.devices) > 1 else cached_kernel(kernel)
        n_sel = len(sel)
        return self.bucketed(
            lambda t, *rest: tracked_call(call, (*head, self.splines, self.obstacles, self.bounds, t,
                                                 tuple(rest[:n_sel]), *rest[n_sel:], self.margin), on_compile),
            [tr, *sel, ar, br], on_chunk, buckets, width=_width(sel, self.obstacles.n_items))

    def evaluate(self, traj, depth, index, on_chunk: Callable[[int], None] | None = None,
                 on_compile: Callable[[bool], None] | None = None):
        """``(a, b, record)`` for every interval (``a, b`` in its own time axis; ``record`` a NumPy
        :class:`~larc_jax.leaf.record.LeafRecord`): the capsule test, with :attr:`self_pairs` the self
        test too (:func:`~larc_jax.leaf.record.compose`); ``on_chunk(n)`` after each chunk of ``n``
        intervals, ``on_compile(True/False)`` around a compiling call."""
        return self._leaf_test(traj, depth, index, on_chunk, on_compile, cascade=False)

    def evaluate_cascade(self, traj, depth, index, on_chunk: Callable[[int], None] | None = None,
                         on_compile: Callable[[bool], None] | None = None, may_bisect: np.ndarray | None = None):
        """The leaf test (:mod:`larc_jax.leaf.record`) on every interval: ``(a, b, record)`` as
        :meth:`evaluate`, with the hull stage (larc_jax.leaf.cascade, given :attr:`hulls`) where
        :func:`~larc_jax.leaf.record.needs_hull`, then the swept stage (:mod:`larc_jax.leaf.swept`, given
        :attr:`swept`) where still open; ``record.stage`` is CAPSULE, HULL, SWEPT or NONE (> 0 iff g > guard).

        ``may_bisect`` (bool per interval; LARC: those above its deepest level): in a culled batch
        (:mod:`larc_jax.engine.cull`), such an interval meeting more items than the widest list
        fails untested (``g`` NaN) above the deepest culled nodes (its children meet their own
        lists), below them when the capsules fail on a pair computed exactly (no recomputation, no
        later stage); it is bisected, and nothing is certified that a test did not prove. Given
        ``may_bisect`` in an unculled batch, step 1 computes the screen too
        (:func:`~larc_jax.leaf.cascade.screened_interval`). Without the swept stage, an interval the
        screen proves the hull stage fails (:func:`~larc_jax.leaf.cascade.link_upper_excess`, at every
        depth, every method) keeps its capsule record: what steps 2-5 would record but for the
        rounding of step 1's clearances (larc_jax.leaf.cascade, "The screen")."""
        return self._leaf_test(traj, depth, index, on_chunk, on_compile, cascade=True, may_bisect=may_bisect)

    def selection(self, traj, depth, index) -> list[CullPart]:
        """The intervals grouped by the items they are tested against: one part (every item of
        their scene) without :attr:`cull`, else :meth:`Cull.parts <larc_jax.engine.cull.Cull.parts>`."""
        if self.cull is None:
            return [CullPart(np.arange(len(traj)), (self.scene_of[traj],), None)]
        return self.cull.parts(traj, depth, index, self.scene_of)

    def _leaf_test(self, traj, depth, index, on_chunk, on_compile, cascade: bool, may_bisect=None):
        a, b = self.endpoints(traj, depth, index)
        rows, records = [], []
        for part in self.selection(traj, depth, index):
            r = part.rows
            record, self_test = self._stages(traj[r], a[r], b[r], part.sel, on_chunk, on_compile, cascade,
                                             None if may_bisect is None else np.asarray(may_bisect)[r],
                                             np.broadcast_to(depth, np.shape(traj))[r] < CULL_DEPTH)
            rows.append(r)
            records.append(compose(part.finish(record), self_test))
        if len(records) == 1:
            return a, b, records[0]
        order = np.argsort(np.concatenate(rows))
        return a, b, LeafRecord(*(np.concatenate(cols)[order] for cols in zip(*records)))

    def _stages(self, traj, a, b, sel, on_chunk, on_compile, cascade: bool, may_bisect=None, shallow=None):
        """``(record, self_test)`` of intervals ``(traj, a, b)`` tested against ``sel``'s items: the
        capsule stage's record, with the hull and swept stages' where they ran (``cascade``), and
        the self stage's (None without :attr:`self_pairs`); ``may_bisect`` and ``shallow`` (depth
        below CULL_DEPTH) per interval, as :meth:`evaluate_cascade` says."""
        ar, br = self._rebased(traj, a, b)  # width 0 (culled, nothing near): the node's floor is the record
        head = (self.robot, self.capsules)
        width = _width(sel, self.obstacles.n_items)
        broad = self.capsules.n_capsules * width > 2 * BROAD_PHASE_K and self.use_broad_phase
        buckets = BUCKETS if len(sel) == 1 else CULLED_BUCKETS
        wide = may_bisect is not None and self.cull is not None and width > WIDTHS[-1]
        untested = np.asarray(may_bisect) & np.asarray(shallow) if wide else np.zeros(len(traj), bool)
        g, guard, cap, box, exact = np.full(len(traj), np.inf), np.zeros(len(traj)), *np.zeros((2, len(traj)), int), \
            np.ones(len(traj), bool)
        g[untested] = np.nan
        test = np.flatnonzero(~untested) if width else np.zeros(0, np.int64)
        # The screen (below, larc_jax.leaf.cascade: the hull stage alone decides the leaf) comes from
        # step 1's own placement for LARC in an unculled batch, at every level (a culled batch would
        # compile it for every width); fixed-fine screens its open intervals in a call of their own.
        hull_last = cascade and self.hulls is not None and self.swept is None  # the hull stage, then no other
        screened = hull_last and may_bisect is not None and self.cull is None
        upper = np.full(len(traj), np.nan)  # the screen's excess where step 1 gave it (NaN: not given)
        if len(test):  # every interval (no untested one): the arrays as they are, not copies
            t = slice(None) if len(test) == len(traj) else test
            kernel = ((evaluate_intervals_screened_broad if broad else evaluate_intervals_screened) if screened
                      else evaluate_intervals_broad if broad else evaluate_intervals)
            out = self._over(kernel, (*head, self.hulls, (self.links.of_capsule, self.links.part_table)) if screened else head,
                             sel if len(test) == len(traj) else _rows(sel, test), traj[t], ar[t], br[t], on_chunk,
                             on_compile, buckets)
            g[t], guard[t], cap[t], box[t], exact[t] = out[:5]
            upper[t] = out[5] if screened else np.nan
        if on_chunk and len(traj) > len(test):
            on_chunk(len(traj) - len(test))
        defer = may_bisect & ~(g > guard) if wide else np.zeros(len(traj), bool)
        redo = np.flatnonzero(~exact.astype(bool) & ~defer)
        upper[redo] = np.nan  # its pick may change
        if len(redo):  # the broad phase could not prove its pick: every pair, exactly
            g[redo], guard[redo], cap[redo], box[redo], _ = self._over(
                evaluate_intervals, head, _rows(sel, redo), traj[redo], ar[redo], br[redo], on_compile=on_compile,
                buckets=BUCKETS if len(sel) == 1 else CULLED_BUCKETS[:2])  # culled: two shapes per width
        self_test = None
        if self.self_pairs is not None:
            sp = self.self_pairs
            check = (sp.first, sp.second, sp.motion_a, np.asarray(sp.margin_m, np.float64), self.self_skip)
            call = self_intervals if len(self.devices) > 1 else cached_kernel(self_intervals)
            gs, gds, c1, c2 = self.bucketed(
                lambda t, x, y: tracked_call(call, (self.robot, self.capsules, self.splines, self.bounds, t, x, y,
                                                    check), on_compile), [traj, ar, br])
            self_test = self_record(gs, gds, c1.astype(np.int64), c2.astype(np.int64))
        record = box_record(g, guard, cap.astype(np.int64), box.astype(np.int64), Stage.CAPSULE)
        open_ = np.flatnonzero(needs_hull(record, self_test) & ~defer)
        if hull_last and len(open_):  # where steps 2-4 cannot pass the leaf, its capsule record stands
            open_ = open_[~self._hopeless(traj[open_], ar[open_], br[open_], _rows(sel, open_), cap[open_],
                                          box[open_], upper[open_], on_compile)]
        if cascade and len(open_) and (self.hulls is not None or self.swept is not None):
            later = self._later_stages if self.cull is None else self._narrowed_stages
            record = record.put(open_, later(traj[open_], a[open_], b[open_], _rows(sel, open_), on_compile))
        return record, self_test

    def _later_stages(self, tr, a, b, sel, on_compile) -> LeafRecord:
        """The hull stage, then the swept stage where the leaf is still open, on intervals the
        capsule stage left open (finite, the self test passed)."""
        record = self._hull_stage(tr, a, b, sel, on_compile) if self.hulls is not None else None
        if self.swept is None:
            return record
        open_ = np.arange(len(tr)) if record is None else np.flatnonzero(needs_hull(record, None))
        swept = self._swept_stage(tr[open_], a[open_], b[open_], _rows(sel, open_), on_compile) if len(open_) else None
        return swept if record is None else record if swept is None else record.put(open_, swept)

    def _narrowed_stages(self, tr, a, b, sel, on_compile) -> LeafRecord:
        """:meth:`_later_stages` in a culled batch, on the items some capsule fails alone (every
        other item's pairs are decided by the capsules: their least ``g - guard`` joins the record
        as :func:`~larc_jax.leaf.cascade.combine` would take it), so a wide interval's hull stage
        costs the few items near it, not the scene. Returned in ``sel``'s item numbering."""
        ar, br = self._rebased(tr, a, b)
        slack, g, guard, cap, _ = self._over(item_margins, (self.robot, self.capsules), sel, tr, ar, br,
                                             on_compile=on_compile, buckets=CULLED_BUCKETS)
        need = ~(slack > 0)  # failing or NaN (a padding item is +inf)
        count = need.sum(axis=1)
        width = next((w for w in WIDTHS if w >= count.max()), slack.shape[1])
        if width >= slack.shape[1] or not count.all():  # nothing to gain; or a row none fails (never: stay whole)
            return self._later_stages(tr, a, b, sel, on_compile)
        rows = np.arange(len(tr))
        order = np.argsort(~need, axis=1, kind="stable")[:, :width]  # the needed items first, in sel's numbering
        items = order if len(sel) == 1 else np.take_along_axis(sel[1], order, axis=1)
        narrow = (sel[0], np.where(np.take_along_axis(need, order, axis=1), items, self.cull.pad_item))
        sub = self._later_stages(tr, a, b, narrow, on_compile)
        passed = np.where(need, np.inf, slack)
        m = passed.argmin(axis=1)
        lower = (sub.stage > 0) & (passed[rows, m] < sub.clearance_m - sub.guard_m)
        pick = lambda new, old: np.where(lower, new, old)  # noqa: E731
        return LeafRecord(pick(g[rows, m], sub.clearance_m), pick(guard[rows, m], sub.guard_m),
                          pick(cap[rows, m], sub.capsule), pick(m, order[rows, sub.box]), sub.other, sub.stage)

    @property
    def use_broad_phase(self) -> bool:
        """The broad phase pays when a scene has more capsule-obstacle pairs than it evaluates exactly."""
        return self.capsules.n_capsules * self.obstacles.n_items > 2 * BROAD_PHASE_K

    def _items(self, sel, i, k):
        """One obstacle per ``(interval i, selected item k)`` pair: the pytree leaves and their tree."""
        return jax.tree.flatten(self._item_set(sel, i, k))

    def _item_set(self, sel, i, k) -> ObstacleSet:
        """One obstacle per ``(interval i, selected item k)`` pair, as an obstacle set (NumPy)."""
        return self.obstacles.take((sel[0][i], k) if len(sel) == 1 else (sel[0][i], sel[1][i, k]))

    def _swept_stage(self, tr, a, b, sel, on_compile) -> LeafRecord:
        """The swept stage (:mod:`larc_jax.leaf.swept`) on the intervals ``(tr, a, b)``."""
        ar, br = self._rebased(tr, a, b)
        parts_call = swept_parts if len(self.devices) > 1 else cached_kernel(swept_parts)
        caps_call = swept_capsules if len(self.devices) > 1 else cached_kernel(swept_capsules)
        d = SweptPlacement(*self._over(swept_intervals, (self.robot, self.capsules, self.hulls, self.swept), sel, tr,
                                       ar, br, on_compile=on_compile, buckets=CASCADE_BUCKETS))
        links = swept_links(self.capsules, self.links)
        G_c = np.asarray(self.bounds.guard_m)[tr]  # (F', C)

        def clear_capsules(triples):
            i, c, k = triples.T
            leaves, tree = self._items(sel, i, k)
            return self.bucketed(
                lambda cc, R, t, e, *it: tracked_call(caps_call, (self.capsules, cc, R, t, jax.tree.unflatten(tree, it),
                                                                  e, self.margin), on_compile),
                [c, d.R_capsule[i, c], d.t_capsule[i, c], d.e_capsule[i, c], *leaves], buckets=CASCADE_BUCKETS, width=1)

        def clear_parts(triples):
            i, p, k = triples.T
            leaves, tree = self._items(sel, i, k)

            def run(hulls, idx):
                ii, pi = i[idx], p[idx]
                return self.bucketed(
                    lambda pp, Tm, R, t, mb, e, *it: tracked_call(
                        parts_call, (hulls, pp, Tm, R, t, jax.tree.unflatten(tree, it), mb, e, self.margin),
                        on_compile),
                    [pi, d.T_mid[ii, pi], d.R_ends[ii, pi], d.t_ends[ii, pi], d.motion_b[ii, pi], d.swept_e[ii, pi],
                     *(x[idx] for x in leaves)], buckets=CASCADE_BUCKETS, width=1)

            return by_vertex_class(self.hulls, p, run, CASCADE_BUCKETS), np.asarray(self.bounds.hull_guard_m)[tr][i, p]

        g, guard, cap, box, _ = swept_record(links, d.g_capsule, G_c, self.hulls is not None, clear_capsules,
                                             clear_parts)
        return box_record(g, guard, cap.astype(np.int64), box.astype(np.int64), Stage.SWEPT)

    def _hopeless(self, tr, ar, br, sel, cap, box, upper, on_compile) -> np.ndarray:
        """Where the hull stage surely fails intervals ``(tr, ar, br)`` (rebased) the capsules fail on
        (capsule ``cap``, item ``box`` of ``sel``): :func:`~larc_jax.leaf.cascade.link_upper_excess`, given
        by step 1 as ``upper`` (:func:`~larc_jax.leaf.cascade.screened_interval`), computed here where NaN."""
        ask = np.flatnonzero(np.isnan(upper))
        if len(ask):
            links, (leaves, tree) = self.links, self._items(sel, ask, box[ask])
            call = hull_screen if len(self.devices) > 1 else cached_kernel(hull_screen)
            upper = upper.copy()
            upper[ask] = self.bucketed(lambda t, x, y, m, *it: tracked_call(call, (
                self.robot, self.capsules, self.hulls, self.splines, self.bounds, t, x, y, jax.tree.unflatten(tree, it),
                m, self.margin), on_compile), [tr[ask], ar[ask], br[ask], links.of_part[None, :] ==
                links.of_capsule[cap[ask]][:, None], *leaves], buckets=CASCADE_BUCKETS, width=1)
        return ~(upper > 0)

    def _hull_round(self, kernel, d: PairDetails, sel, triples, on_compile) -> np.ndarray:
        """One round of step 4 (:data:`hull_first_axis`, :data:`hull_early`, :data:`hull_pairs`,
        :func:`hull_points`) on the ``(interval, part, obstacle)`` triples of the intervals ``sel``, a
        call per vertex class."""
        call = kernel if len(self.devices) > 1 else cached_kernel(kernel)
        i, p, k = triples.T
        leaves, tree = self._items(sel, i, k)

        def run(hulls, idx):
            return self.bucketed(
                lambda pp, T, mb, *it: tracked_call(call, (hulls, pp, T, jax.tree.unflatten(tree, it), mb,
                                                           self.margin), on_compile),
                [p[idx], d.T_part[i[idx], p[idx]], d.motion_b[i[idx], p[idx]], *(x[idx] for x in leaves)],
                buckets=CASCADE_BUCKETS, width=1)

        return by_vertex_class(self.hulls, p, run, CASCADE_BUCKETS)

    def _hull_stage(self, tr, a, b, sel, on_compile) -> LeafRecord:
        """The hull stage (steps 2-5 of larc_jax.leaf.cascade) on the intervals ``(tr, a, b)``."""
        ar, br = self._rebased(tr, a, b)
        links, head = self.links, (self.robot, self.capsules, self.hulls)
        G_c = np.asarray(self.bounds.guard_m)[tr]  # (F', C)
        G_p = np.asarray(self.bounds.hull_guard_m)[tr]  # (F', P)
        # A few capsule pairs exact, every pair again where that could change a result (exact_enough);
        # only without separate points (their third round may lift a part above its upper bound).
        bounded = self.cull is None and not self.obstacles.separate_points().any()
        fields = self._over(batched_interval_pairs_bounded if bounded else batched_interval_pairs, head, sel, tr, ar, br,
                            on_compile=on_compile, buckets=PAIR_BUCKETS)
        redo = np.flatnonzero(~exact_enough(links, fields[0] - G_c[:, :, None], fields[3] - G_p[:, :, None],
                                            fields[4])) if bounded else []
        if len(redo):
            for x, y in zip(fields, self._over(batched_interval_pairs, head, _rows(sel, redo), tr[redo], ar[redo],
                                               br[redo], on_compile=on_compile, buckets=PAIR_BUCKETS)):
                x[redo] = y
        d = PairDetails(*fields[:4])
        tried, triples = select_pairs(links, d.g_capsule - G_c[:, :, None], d.g_upper - G_p[:, :, None])
        g_hull = guard_hull = np.zeros(0)
        if len(triples):
            i, p, k = triples.T
            guard_hull = G_p[i, p]
            first = self._hull_round(hull_first_axis, d, sel, triples, on_compile)

            def early(redo):
                out = self._hull_round(hull_early, d, sel, triples[redo], on_compile)
                return out[:, 0], out[:, 1]

            g_hull, _ = hull_rounds(first, guard_hull,
                                    lambda redo: self._hull_round(hull_pairs, d, sel, triples[redo], on_compile),
                                    early, early_stop_slack(self.dtype))
            g_hull = point_round(g_hull, guard_hull, self._item_set(sel, i, k).separate_points(),
                                 lambda redo: self._hull_round(hull_points, d, sel, triples[redo], on_compile))
        g, guard, cap, box, _ = combine(links, d.g_capsule, G_c, tried, triples, g_hull, guard_hull)
        return box_record(g, guard, cap, box, Stage.HULL)


def _width(sel: tuple, n_items: int) -> int:
    """Items each interval of a selection meets."""
    return n_items if len(sel) == 1 else sel[1].shape[1]


def _rows(sel: tuple, rows) -> tuple:
    """A selection's intervals ``rows``."""
    return tuple(x[rows] for x in sel)


def prepare(trajectories, scenes: Sequence[Scene], robot: Robot, capsules: CapsuleModel,
            margin: float, dtype, bounds: Sequence[RoundingBounds], devices=None,
            on_compile: Callable[[bool], None] | None = None, hulls: HullModel | None = None,
            self_pairs: SelfPairs | None = None, self_skip: Sequence[np.ndarray] | None = None,
            swept: SweptTables | None = None) -> Batch:
    """Pad a validated dataset into a :class:`Batch` (one scene and one
    :func:`~larc_jax.leaf.interval.trajectory_rounding` per trajectory). ``devices``: those to shard
    each interval batch over (default: every device of JAX's default backend, e.g. all local GPUs;
    on a CPU, one device unless XLA is asked for more). ``on_compile``: see :meth:`Batch.evaluate`."""
    dtype = np.dtype(dtype)
    # Shapes are rounded up to size classes (see size_class); padded knots lie after t_K and
    # are never touched by an interval inside the horizon (hermite.pad_waypoints), padded
    # trajectories (the first one's knots, no table rows) and scenes repeat the first one and are
    # never indexed by an interval.
    n_knots = size_class(max(t.n_waypoints for t in trajectories), 16)
    n_pad = size_class(len(trajectories), 1) - len(trajectories)
    padded = pad_waypoints_batch([(t.t - float(bd.offset_s), t.q, t.qd) for t, bd in zip(trajectories, bounds)],
                                 n_knots, len(trajectories) + n_pad)
    stacked = jax.tree.map(lambda *x: np.stack(x), *(list(bounds) + list(bounds[:1]) * n_pad))
    unique = list(dict.fromkeys(id(s) for s in scenes))
    scene_list = [next(s for s in scenes if id(s) == u) for u in unique]
    scene_of = np.array([unique.index(id(s)) for s in scenes], np.int64)
    scene_list += scene_list[:1] * (size_class(len(scene_list), 1) - len(scene_list))
    cull = worth_culling(scene_list)
    # A culled batch gives every scene a masked last item: what a culled interval's list is padded with.
    obstacles = stack_scenes(scene_list, dtype, max(s.n_obstacles for s in scene_list) + 1 if cull else None)
    splines = spline_batch(*padded, n_knots=np.array([t.n_waypoints for t in trajectories] + [0] * n_pad),
                           accel=swept is not None,  # the swept stage reads accelerations
                           call=lambda fn, args: tracked_call(cached_kernel(fn), args, on_compile))
    robot_g, capsules_g = _geometry(robot, capsules, dtype)
    links = None if hulls is None else Links.of(capsules, hulls)
    batch = Batch(
        robot=robot_g, capsules=capsules_g, splines=splines, bounds=stacked,
        obstacles=obstacles, scene_of=scene_of,
        t_start=np.array([t.t[0] for t in trajectories]), t_end=np.array([t.t[-1] for t in trajectories]),
        margin=np.asarray(margin, np.float64), dtype=dtype,
        devices=tuple(jax.devices() if devices is None else devices),
        hulls=None if hulls is None else _hulls_geometry(hulls, dtype), self_pairs=self_pairs,
        self_skip=None if self_skip is None else np.stack(list(self_skip) + list(self_skip[:1]) * n_pad),
        swept=swept, links=links,
    )
    if cull:
        def run(kernel, boxes, traj, depth, index, width):
            ar, br = batch._rebased(traj, *batch.endpoints(traj, depth, index))
            call = kernel if len(batch.devices) > 1 else cached_kernel(kernel)
            return batch.bucketed(lambda t, sc, x, y: tracked_call(call, (
                batch.robot, batch.capsules, batch.splines, boxes, batch.bounds, t, (sc,), x, y, batch.margin), on_compile),
                [traj, scene_of[traj], ar, br], buckets=CULLED_BUCKETS, width=width)

        batch = dataclasses.replace(batch, cull=build_cull(scene_list, scene_of, obstacles.n_items, dtype, run))
    return batch
