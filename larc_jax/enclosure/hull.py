"""Convex-hull enclosures of the links ("parts"), their containment proof and motion constants.

The hull stage of the certificate (:mod:`larc_jax.leaf.cascade`) encloses each link's collision
geometry by the convex hulls of one or two *parts*, each padded like the capsules (the run's
``padding_m``, :class:`~larc_jax.run_spec.RunSpec`): a part is ``conv(V) + B(0, radius)`` with
``V`` its vertex table in the link frame. A hull is the tightest convex enclosure of a part, so a
link that clears a box by 2 mm is not rejected because a capsule around it is 20 mm fatter.

Parts. A link's elements (:func:`~larc_jax.enclosure.meshes.link_elements`: mesh triangles or
primitives, widened over the stroke of an unstated finger joint) go whole into one part, by
which side of a plane their centroid lies on (``hull_parts`` of the robot file, chosen by
:func:`choose_split` when fitting: the principal-axis cut that shrinks the summed hull volume
most, if by at least 10 %). Any rule is sound: every element lies wholly in one part, so the
link lies in the union of its parts.

Containment proof (:func:`support_set`). A part holds its elements iff ``conv(V)`` holds all
their vertices ``X``. Qhull gives the hull's vertices ``H`` and facets. If the facets form a
closed surface (every edge in exactly two triangles; checked) lying on supporting planes of
``H`` (every point of ``H`` on the inner side of every facet plane, to 1e-12 m; checked), that
surface is the boundary of ``conv(H)`` and the intersection of the facets' half-spaces is
``conv(H)`` itself. Every other point ``x`` of ``X`` is then either

* inside every facet plane by at least ``TAU`` (1e-9 m, a million times the rounding of a
  plane evaluation): inside ``conv(H)``; or
* close to some facet: it is projected onto that facet's plane, and if the projection's
  barycentric weights in the facet triangle are non-negative (to 1e-9), the clipped weights give
  a point ``y`` of the facet, so ``d(x, conv(H)) <= |x - y|``; the largest such distance is the
  *slack* (about 1e-16 m on PIPER), added to the part's radius; or
* otherwise kept as an extra vertex of ``V`` (never needed on PIPER).

If a check fails the part keeps every point of ``X`` (sound, slower). So ``X`` lies in
``conv(V) + B(0, slack)`` and the mesh in ``conv(V) + B(0, padding + slack)``. The part's radius
is ``padding + slack + PROOF_ALLOWANCE_M`` (:func:`part_radius`): the checker's independent proof
(:mod:`larc_jax.enclosure.proof`) adds its own float64 rounding bounds, of order 1e-14 m, to
every witness distance; 1 nm on top keeps that proof valid with no padding at all, and costs the
certificate 1 nm of clearance.
:func:`verify_support` re-checks it independently through support functions (every direction
of a dense sphere grid: ``max_X n . x <= max_V n . v + slack``).

Motion constants for a part (paper eq. 6) come from its own vertices and radius
(:func:`~larc_jax.enclosure.motion.motion_constants_points`: the capsule derivation over a
point set). :func:`hull_model` builds (and caches per process) the :class:`HullModel` of a
robot from its meshes and the split planes of its robot file.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
from pathlib import Path
from typing import Sequence

import numpy as np

from ..errors import LarcInputError
from ..lazy_jax import jax, pytree_dataclass
from ..model.robot import Robot
from .meshes import link_elements, robot_urdf_model
from .motion import motion_constants_points

__all__ = ["HullModel", "HullPart", "by_vertex_class", "build_hulls", "hull_model", "choose_split", "choose_hull_parts", "support_set",
           "verify_support", "part_radius", "TAU", "PROOF_ALLOWANCE_M"]

TAU = 1e-9
"""Interior margin (m) beyond which a point is inside the hull by the facet test (module doc)."""
PROOF_ALLOWANCE_M = 1e-9
"""Added to every part's radius so that the checker's containment proof, which charges its own
rounding bounds (~1e-14 m) to each witness distance, holds even with no padding (module doc)."""


def part_radius(padding_m: float, slack_m: float) -> float:
    """The radius of a part: the padding, the construction's containment slack and
    :data:`PROOF_ALLOWANCE_M` (module docstring), rounded up."""
    return float(np.nextafter(padding_m + slack_m + PROOF_ALLOWANCE_M, np.inf))


_CONVEX_TOL = 1e-12
"""Largest excess (m) of a hull vertex over a facet plane accepted as rounding (module doc)."""
_MIN_GAIN = 0.10
"""A link is split in two parts when that shrinks its summed hull volume by at least this much."""


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class HullModel:
    """Hull parts of the links (module docstring), with their motion constants."""

    vertices: jax.Array
    """(P, K, 3) vertex table of each part in its link frame, m; a part with fewer than K
    vertices repeats its first one (the support function is unchanged)."""
    centre: jax.Array
    """(P, 3) centre of each part's bounding box in the link frame, m (seeds the distance search)."""
    probes: jax.Array
    """(P, 14, 3) the part's vertices extreme along the 6 axis and 8 diagonal directions of its
    link frame: points of the part, so their distance to a box bounds the part's from *above*
    (the cascade skips a pair whose hull stage cannot pass)."""
    radius: jax.Array
    """(P,) padding plus the containment slack plus the proof allowance, m (:func:`part_radius`): the
    part is conv(vertices) + B(0, radius)."""
    motion_a: jax.Array
    """(P, n) a_pj for each part and active joint (paper eq. 6; larc_jax.enclosure.motion)."""

    names: tuple[str, ...] = dataclasses.field(metadata=dict(static=True))
    link_names: tuple[str, ...] = dataclasses.field(metadata=dict(static=True))
    link_index: tuple[int, ...] = dataclasses.field(metadata=dict(static=True))
    n_vertices: tuple[int, ...] = dataclasses.field(metadata=dict(static=True))
    """Real vertex count of each part (the rest of its row is padding)."""
    padding_m: float = dataclasses.field(metadata=dict(static=True))

    @property
    def n_parts(self) -> int:
        return len(self.names)

    def vertex_classes(self, most: int = 3) -> tuple[int, ...]:
        """Column counts (ascending, the last the table's K) splitting the parts into at most
        ``most`` classes by vertex count (:func:`by_vertex_class`): the classes minimise the
        columns read summed over the parts.

        Why: the support search of the hull stage reads every column of a part's row, so padding
        a 122-vertex part to the largest part's 691 multiplies that reading by 5.7 (measured on
        PIPER, 1024 pairs a call: the first axis 2.8x, the full search 1.65x cheaper on the 136
        columns of its class; before the support's two-reduction choice, 4.2x and 2.5x)."""
        return _vertex_classes(self.n_vertices, int(np.shape(self.vertices)[1]), most)

    def first_columns(self, n: int) -> "HullModel":
        """This model with its vertex table cut to the first ``n`` columns: the same support, bit
        for bit, for every part with at most ``n`` vertices (its row holds them all, then copies of
        its first vertex, which neither change a maximum nor its first index); the others' rows
        are cut short and must not be evaluated."""
        if n >= np.shape(self.vertices)[1]:
            return self
        return dataclasses.replace(self, vertices=self.vertices[:, :n])

    def on_links(self, links) -> "HullModel":
        """The parts of ``links`` only (e.g. those of a capsule model that excludes a fixed base)."""
        keep = [p for p, link in enumerate(self.link_names) if link in set(links)]
        if len(keep) == self.n_parts:
            return self
        sel = np.asarray(keep, np.int64)
        take = lambda x: np.asarray(x)[sel]  # noqa: E731
        return dataclasses.replace(
            self, vertices=take(self.vertices), centre=take(self.centre), probes=take(self.probes),
            radius=take(self.radius), motion_a=take(self.motion_a), names=tuple(self.names[p] for p in keep),
            link_names=tuple(self.link_names[p] for p in keep), link_index=tuple(self.link_index[p] for p in keep),
            n_vertices=tuple(self.n_vertices[p] for p in keep))


@functools.lru_cache(maxsize=64)
def _vertex_classes(n_vertices: tuple[int, ...], K: int, most: int) -> tuple[int, ...]:
    need = [min(K, -(-n // 8) * 8) for n in n_vertices]  # whole rows of 8
    sizes = sorted(set(need) - {K})
    choices = [c + (K,) for r in range(most) for c in itertools.combinations(sizes, r)]
    return min(choices, key=lambda c: (sum(min(x for x in c if x >= n) for n in need), len(c)))


CLASS_ITEM_COLUMNS = 128
"""Per-pair work of a hull-stage call that does not read the vertex table, in vertex columns
(measured on PIPER, 1024 pairs a call, when this was set: the first axis cost ~37 columns' worth,
the full search ~234). The support's two-reduction choice (:func:`~larc_jax.obstacles.polytope.first_max`)
made a column 3-5x cheaper, so the same work is now ~220 and ~720 columns' worth; 512 here
changed neither Stage B's leaves nor its warm time (0.286 s against 0.288 s, LARC, cascade), so
the value stayed."""
CLASS_CALL_COLUMNS = 64 * 256
"""Fixed cost of one call, in pair-columns (~0.2 ms of a 2-core CPU: about 64 pairs of 256
columns)."""


def by_vertex_class(hulls: HullModel, parts: np.ndarray, run, buckets: Sequence[int]) -> np.ndarray:
    """``run(hulls_c, idx)`` (an array over ``idx``) for the items ``idx`` whose ``parts`` fall in
    one group of vertex classes (:meth:`HullModel.vertex_classes`), ``hulls_c`` the model cut to
    the group's columns (:meth:`HullModel.first_columns`): the results, put back in the order of
    ``parts``. Adjacent classes are merged into groups where that is estimated cheaper (calls
    padded to ``buckets``, each costing :data:`CLASS_CALL_COLUMNS` plus its padded pairs times
    their columns and :data:`CLASS_ITEM_COLUMNS`): a few pairs of a small class ride along
    with a larger class's call instead of paying a call of their own."""
    cls = np.asarray(hulls.vertex_classes())
    of_part = np.searchsorted(cls, np.asarray(hulls.n_vertices))[np.asarray(parts, np.int64)]  # class index
    counts = np.bincount(of_part, minlength=len(cls))

    def padded(n):
        top = buckets[-1]
        return (n // top) * top + next((b for b in buckets if b >= n % top), top) if n % top else n

    def cost(cuts):  # groups end at the classes in ``cuts``
        starts = (0,) + tuple(c + 1 for c in cuts[:-1])
        return sum(CLASS_CALL_COLUMNS + padded(int(counts[a:b + 1].sum())) * (int(cls[b]) + CLASS_ITEM_COLUMNS)
                   for a, b in zip(starts, cuts) if counts[a:b + 1].sum())

    used = len(cls) - 1
    options = [c + (used,) for r in range(used + 1) for c in itertools.combinations(range(used), r)]
    cuts = min(options, key=cost)
    out = np.zeros(0)
    start = 0
    for end in cuts:
        idx = np.flatnonzero((of_part >= start) & (of_part <= end))
        start = end + 1
        if len(idx):
            g = np.asarray(run(hulls.first_columns(int(cls[end])), idx))
            out = np.empty((len(parts),) + g.shape[1:], g.dtype) if out.shape[0] != len(parts) else out
            out[idx] = g
    return out


@dataclasses.dataclass(frozen=True)
class HullPart:
    """One part before packing: its link, vertex set and containment slack."""

    name: str
    link: str
    vertices: np.ndarray
    slack_m: float
    n_elements: int


def _unique_points(elements: np.ndarray) -> np.ndarray:
    """Distinct points (exact float64 equality; sorted through a bytes view, which is fast)."""
    X = np.ascontiguousarray(np.asarray(elements, np.float64).reshape(-1, 3)) + 0.0  # -0.0 -> 0.0
    _, idx = np.unique(X.view(np.dtype((np.void, 24))).ravel(), return_index=True)
    return X[np.sort(idx)]


def _closed_surface(simplices: np.ndarray) -> bool:
    edges = np.sort(np.concatenate([simplices[:, [0, 1]], simplices[:, [1, 2]], simplices[:, [0, 2]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return bool((counts == 2).all())


def support_set(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Vertices ``V`` (a subset of ``points``) and slack ``s`` with every point in
    ``conv(V) + B(0, s)`` (module docstring: the containment proof)."""
    from scipy.spatial import ConvexHull, QhullError

    X = _unique_points(points)
    try:
        hull = ConvexHull(X)
    except (QhullError, ValueError):
        return X, 0.0  # flat or tiny sets: every point is kept, exact
    H = X[hull.vertices]
    planes = hull.equations  # a . x + b <= 0 inside, |a| = 1
    if not _closed_surface(hull.simplices) or (H @ planes[:, :3].T + planes[:, 3]).max() > _CONVEX_TOL:
        return X, 0.0
    rest = np.setdiff1d(np.arange(len(X)), hull.vertices)
    if not len(rest):
        return H, 0.0  # every point is a hull vertex (e.g. a box's 8 corners)
    r_parts, f_parts, e_parts = [], [], []
    for start in range(0, len(rest), 2048):  # (points, facets) in blocks: bounded memory
        excess = X[rest[start:start + 2048]] @ planes[:, :3].T + planes[:, 3]
        rows = np.flatnonzero(excess.max(axis=1) > -TAU)
        excess = excess[rows]
        rr, ff = np.nonzero(excess > -TAU)  # points near a facet plane, and those facets
        r_parts.append(rows[rr] + start)
        f_parts.append(ff)
        e_parts.append(excess[rr, ff])
    r, f, ex = np.concatenate(r_parts), np.concatenate(f_parts), np.concatenate(e_parts)
    if not len(r):
        return H, 0.0
    x = X[rest[r]]
    y = x - ex[:, None] * planes[f, :3]  # projection onto the facet's plane
    lam = _barycentric(X[hull.simplices[f]], y)  # (N, 3)
    ok = lam.min(axis=1) >= -TAU
    w = np.clip(lam, 0.0, None)
    w /= np.where(w.sum(axis=1) > 0, w.sum(axis=1), 1.0)[:, None]
    dist = np.linalg.norm(x - np.einsum("nk,nkd->nd", w, X[hull.simplices[f]]), axis=1)
    dist = np.where(ok, dist, np.inf)
    best = np.full(len(rest), np.inf)
    np.minimum.at(best, r, dist)  # the best witness facet of each near point
    near = np.zeros(len(rest), bool)
    near[r] = True
    keep = near & ~np.isfinite(best)
    slack = float(best[near & np.isfinite(best)].max(initial=0.0))
    V = np.concatenate([H, X[rest[keep]]]) if keep.any() else H
    return V, slack


def _barycentric(tri: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(N, 3) barycentric weights of points ``y`` (N, 3) in the planes of triangles ``tri``
    (N, 3, 3); a degenerate triangle gets weights of -inf (never a witness)."""
    e1, e2, d = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], y - tri[:, 0]
    a11, a12, a22 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
    det = a11 * a22 - a12 * a12
    good = det > 0
    det = np.where(good, det, 1.0)
    b1, b2 = (d * e1).sum(1), (d * e2).sum(1)
    mu1, mu2 = (b1 * a22 - b2 * a12) / det, (b2 * a11 - b1 * a12) / det
    lam = np.stack([1.0 - mu1 - mu2, mu1, mu2], axis=1)
    return np.where(good[:, None], lam, -np.inf)


def verify_support(points: np.ndarray, V: np.ndarray, slack: float, n_dirs: int = 4096) -> float:
    """Largest ``max_X n.x - max_V n.v - slack`` over a Fibonacci sphere of unit directions
    (<= ~1e-15 when ``X`` lies in ``conv(V) + B(0, slack)``); an independent check of
    :func:`support_set`."""
    k = np.arange(n_dirs) + 0.5
    z = 1.0 - 2.0 * k / n_dirs
    phi = np.pi * (1.0 + 5.0**0.5) * k
    n = np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], axis=1)
    X = _unique_points(points)
    return float(((X @ n.T).max(axis=0) - (V @ n.T).max(axis=0) - slack).max())


def _hull_volume(elements: np.ndarray) -> float:
    from scipy.spatial import ConvexHull, QhullError

    try:
        return float(ConvexHull(_unique_points(elements)).volume)
    except (QhullError, ValueError):
        return 0.0


def split_mask(elements: np.ndarray, normal, offset: float) -> np.ndarray:
    """Elements whose centroid lies on the near side of the plane ``n . x = offset`` (part a)."""
    return elements.mean(axis=1) @ np.asarray(normal, float) <= float(offset)


def choose_split(elements: np.ndarray, fractions: Sequence[float] = (0.3, 0.4, 0.5, 0.6, 0.7)):
    """``(normal, offset)`` of the cut across the principal axis of the element centroids that
    shrinks the summed hull volume most, or ``None`` if no cut gains ``_MIN_GAIN``."""
    c = elements.mean(axis=1)
    centre = c.mean(axis=0)
    _, _, vt = np.linalg.svd(c - centre, full_matrices=False)
    normal = vt[0]
    s = c @ normal
    whole = _hull_volume(elements)
    best = None
    for frac in fractions:
        offset = float(np.quantile(s, frac))
        m = s <= offset
        if m.all() or not m.any():
            continue
        vol = _hull_volume(elements[m]) + _hull_volume(elements[~m])
        if best is None or vol < best[0]:
            best = (vol, offset)
    if best is None or best[0] > (1.0 - _MIN_GAIN) * whole:
        return None
    return tuple(round(float(x), 9) for x in normal), round(best[1], 9)


def choose_hull_parts(robot: Robot, progress=None) -> tuple:
    """Split planes ``((link, normal, offset), ...)`` for the links that gain from two parts
    (:func:`choose_split`), for the robot file's ``hull_parts``."""
    out = []
    for link in robot.link_names:
        e = link_elements(robot, link)
        if not len(e):
            continue
        if progress:
            progress(f"splitting {link}")
        plane = choose_split(e)
        if plane is not None:
            out.append((link,) + plane)
    return tuple(out)


def build_parts(robot: Robot, hull_parts: Sequence[tuple] = (), links: Sequence[str] | None = None) -> list[HullPart]:
    """The parts of every link with collision geometry, split by the planes ``hull_parts``
    (``(link, normal, offset)`` entries; other links are one part)."""
    planes = {p[0]: (p[1], p[2]) for p in hull_parts}
    unknown = sorted(set(planes) - set(robot.link_names))
    if unknown:
        raise LarcInputError(f"hull_parts names links {unknown} that {robot.urdf_path} does not have")
    out = []
    for link in links if links is not None else robot.link_names:
        e = link_elements(robot, link)
        if not len(e):
            continue
        if link in planes:
            m = split_mask(e, *planes[link])
            groups = [(f"{link}_a", e[m]), (f"{link}_b", e[~m])] if m.any() and not m.all() else [(link, e)]
        else:
            groups = [(link, e)]
        for name, g in groups:
            V, slack = support_set(g)
            out.append(HullPart(name, link, V, slack, len(g)))
    if not out:
        raise LarcInputError(f"{robot.urdf_path}: no link has collision geometry")
    return out


def build_hulls(robot: Robot, hull_parts: Sequence[tuple] = (), padding_m: float = 0.001,
                parts: Sequence[HullPart] | None = None) -> HullModel:
    """The :class:`HullModel` of ``robot`` (module docstring); ``hull_parts``: split planes;
    ``parts``: :func:`build_parts` of them, if already built."""
    parts = build_parts(robot, hull_parts) if parts is None else parts
    K = max(len(p.vertices) for p in parts)
    table = np.stack([np.concatenate([p.vertices, np.repeat(p.vertices[:1], K - len(p.vertices), 0)]) for p in parts])
    radius = np.array([part_radius(padding_m, p.slack_m) for p in parts])
    lo, hi = np.stack([p.vertices.min(axis=0) for p in parts]), np.stack([p.vertices.max(axis=0) for p in parts])
    link_index = tuple(robot.link_index(p.link) for p in parts)
    dirs = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1]] + [[x, y, z] for x in (1, -1) for y in (1, -1) for z in (1, -1)],
                    float)
    dirs = np.concatenate([dirs[:3], -dirs[:3], dirs[3:]])
    probes = np.stack([p.vertices[np.argmax(p.vertices @ dirs.T, axis=0)] for p in parts])
    return HullModel(
        vertices=table, centre=(lo + hi) / 2, probes=probes, radius=radius,
        motion_a=motion_constants_points(robot, link_index, [p.vertices for p in parts], radius),
        names=tuple(p.name for p in parts), link_names=tuple(p.link for p in parts), link_index=link_index,
        n_vertices=tuple(len(p.vertices) for p in parts), padding_m=float(padding_m),
    )


def _geometry_hashes(robot: Robot) -> tuple:
    """SHA-256 of the URDF (the robot's, checked against the file by
    :func:`~larc_jax.enclosure.meshes.robot_urdf_model`) and of every collision mesh's bytes as
    they are now (:func:`~larc_jax.model.urdf.current_sha256`: hashed again whenever the file's
    status changed): any change of content rebuilds the hulls, whatever the file's size and
    modification time.

    The mesh paths are a function of the URDF's bytes, path and package folders alone
    (:func:`~larc_jax.model.urdf.resolve_uri` reads no file), kept per process (:func:`_mesh_paths`);
    every call still hashes the URDF and every mesh as they are now, and where the URDF changed or
    a file is unreadable the full check runs and raises its error naming the file and the link."""
    from ..model.urdf import current_sha256

    paths = _mesh_paths(str(robot.urdf_path), robot.urdf_sha256, tuple(robot.package_dirs))
    try:
        fresh = current_sha256(robot.urdf_path, "URDF file") == robot.urdf_sha256
        meshes = tuple((p, current_sha256(p)) for p in paths) if fresh else None
    except LarcInputError:
        meshes = None
    if meshes is None:
        robot_urdf_model(robot)  # raises the error naming the file (and the link, for a missing mesh)
        meshes = tuple((p, current_sha256(p)) for p in paths)
    return (robot.urdf_sha256,) + meshes


@functools.lru_cache(maxsize=16)
def _mesh_paths(urdf_path: str, urdf_sha256: str, package_dirs: tuple) -> tuple[str, ...]:
    """The collision meshes' paths of the URDF with these bytes at this path with these package
    folders, in the URDF's order (:func:`_geometry_hashes`)."""
    from ..model.urdf import load_urdf_model, resolve_uri

    model = load_urdf_model(urdf_path, dict(package_dirs), sha256=urdf_sha256)  # refuses a missing mesh
    return tuple(str(resolve_uri(col.geometry.mesh.filename, Path(urdf_path), dict(package_dirs)))
                 for link in model.links for col in link.collisions
                 if col.geometry is not None and col.geometry.mesh is not None)


def _robot_content(robot: Robot) -> str:
    """SHA-256 of every field of ``robot`` (arrays by dtype, shape and bytes; the rest by repr)."""
    import hashlib

    h = hashlib.sha256()
    for f in dataclasses.fields(robot):
        value = getattr(robot, f.name)
        if hasattr(value, "shape"):
            a = np.ascontiguousarray(np.asarray(value))
            h.update(f"{f.name} {a.dtype} {a.shape}".encode() + a.tobytes())
        else:
            h.update(f"{f.name} {value!r}".encode())
    return h.hexdigest()


def _kept_parts(key: dict, robot: Robot, hull_parts: Sequence[tuple]) -> list[HullPart] | None:
    """:func:`build_parts`, kept on disk under ``key`` while the compilation cache is on
    (:mod:`larc_jax.model.robot_cache`): a later process skips reading the meshes and Qhull.
    None when a geometry file's content changed between ``key["geometry"]`` and the end of the
    build (the parts may mix old and new content, so they are neither kept nor returned)."""
    import json

    from ..model.robot_cache import keep_arrays, kept_arrays

    kept = kept_arrays("hull_parts", key)
    if kept is not None:
        try:
            meta = json.loads(str(kept["meta"]))
            return [HullPart(m["name"], m["link"], kept[f"v{k}"], float(m["slack_m"]), int(m["n_elements"]))
                    for k, m in enumerate(meta)]
        except (KeyError, ValueError, TypeError):  # unreadable: build again
            pass
    parts = build_parts(robot, hull_parts)
    if _geometry_hashes(robot) != key["geometry"]:
        return None  # a file changed while it was read: these parts belong to no key
    meta = [{"name": p.name, "link": p.link, "slack_m": p.slack_m, "n_elements": int(p.n_elements)} for p in parts]
    keep_arrays("hull_parts", key, {"meta": np.array(json.dumps(meta)),
                                    **{f"v{k}": np.asarray(p.vertices, np.float64) for k, p in enumerate(parts)}})
    return parts


_CACHE: dict = {}
_BUILD_TRIES = 3  # builds whose files changed underneath before hull_model gives up


def hull_model(robot: Robot, hull_parts: Sequence[tuple] = (), padding_m: float = 0.001) -> HullModel:
    """:func:`build_hulls`, cached per process on everything the result depends on (the geometry
    files' contents, the robot's joints, held values and stated joints, the planes, the padding);
    the parts also on disk while the compilation cache is on (:func:`_kept_parts`)."""
    planes = tuple((l, tuple(float(x) for x in n), float(o)) for l, n, o in hull_parts)
    for _ in range(_BUILD_TRIES):
        key = (_geometry_hashes(robot), _robot_content(robot), planes, float(padding_m))
        if key in _CACHE:
            return _CACHE[key]
        parts = _kept_parts({"geometry": key[0], "robot": key[1], "planes": planes}, robot, hull_parts)
        if parts is not None:
            if len(_CACHE) > 16:
                _CACHE.clear()
            _CACHE[key] = build_hulls(robot, hull_parts, padding_m, parts=parts)
            return _CACHE[key]
    raise LarcInputError(f"{robot.urdf_path}: the robot's geometry files kept changing while their hulls were "
                     f"built ({_BUILD_TRIES} tries); certify once they are no longer being written")
