"""The containment proof of every enclosure a run uses, re-made by the checker (NumPy float64).

``larc verify`` does not trust the robot file's enclosures: before it checks a leaf,
:func:`prove_enclosures` proves that every enclosure the leaf test will use contains the
collision geometry of its link, and ``larc verify-capsules`` (:func:`prove_robot_file`) proves
every enclosure a robot file can give (its capsules, its stated-finger capsules, the hull parts
of both). Nothing here imports JAX.

What is proven. For every link the model covers (all links with collision geometry except
those the certificate excludes), every element of its geometry
(:func:`~larc_jax.enclosure.meshes.link_elements`: mesh triangles of the files whose hashes were
checked, primitives replaced by circumscribed polyhedra, at the URDF's scales and origins, and
copied to both ends of the stroke of every unstated finger joint, whose limits come from the
URDF) lies wholly inside *one* enclosure of its link: every vertex of the element passes the
same enclosure's test. An enclosure is convex and an element is the convex hull of its vertices
(a widened element the hull of its swept copies), so the link lies in the union of its
enclosures. Motion constants, strokes and rounding guards are never read from the robot file:
the loader derives them from the URDF (:mod:`~larc_jax.enclosure.motion`).

* A capsule: :func:`~larc_jax.enclosure.fit.inside_capsule` with its radius less ``padding_m``,
  as ``larc fit-capsules`` proves it (the distance and its float64 rounding bound).
* A hull part ``conv(V) + B(0, r)`` exactly as the cascade uses it (built by
  :func:`~larc_jax.enclosure.hull.hull_model` from the meshes and the file's split planes;
  ``r`` is ``padding_m`` plus the construction's slack and 1 nm of allowance for this proof's
  rounding bounds, :func:`~larc_jax.enclosure.hull.part_radius`, and is proven whole). A point ``y`` is in
  it (:class:`HullPartTest`) if

  (a) *strictly inside*: Qhull triangulates ``conv(V)``; the triangles, their corners points of
      ``V``, are oriented outward and checked to form a closed oriented surface (each directed
      edge once, its reverse once; nothing else of Qhull is trusted). If ``y`` lies on the inner
      side of every triangle's plane by more than the float64 rounding bound of that orientation
      test, every triangle subtends a negative signed solid angle at ``y``; their sum, 4 pi times
      the (integer) winding number of the surface around ``y``, is then non-zero, while any
      point outside ``conv(V)`` has winding number 0 (a ray leaving ``conv(V)`` never meets the
      surface): ``y`` is in ``conv(V)``. No convexity check is needed; or

  (b) *witnessed*: ``y`` is a point of ``V``, or a point ``z`` of ``conv(V)`` has ``|y - z|``
      plus its rounding bound ``<= r``: ``z`` the nearest point of ``V``, or the nearest point
      of a surface triangle whose plane ``y`` is not certainly inside of (its projection onto
      the plane, if inside the triangle, or the nearest point of an edge), each a convex
      combination of corners.

Rounding. The orientation ``n . (y - a)`` with ``n = (b - a) x (c - a)`` is evaluated as one
product ``[y, |y|, 1] . [n, s, s |a| - n . a]`` that adds its own bound
``s (|y| + |a|)``, ``s = _ORIENT_SLACK |b - a| |c - a|`` (``_ORIENT_SLACK`` = 32 eps: the
differences, the cross product and the dot products err by about 8 eps of
``|b - a| |c - a| (|y| + |a|)``; the rest is headroom for the norms in the bound). A witness distance is below
its computed value plus ``_WITNESS_SLACK (|y| + |a| + |b| + |c|)`` (``z`` a float sum of at most
three corners with weights >= 0 summing to 1 up to rounding, then one difference and one norm:
about 5 eps; 64 eps taken).

An unproven enclosure raises :class:`EnclosureNotProven` (a :class:`LarcInputError`: exit 2
for ``verify-capsules``; ``larc verify`` reports it as a refutation, exit 1) naming the file,
the link, the element (collision entry: mesh and triangle, or primitive), the enclosures tried
and the vertex that fails, with its distance.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Callable, Sequence

import numpy as np

from ..errors import LarcInputError
from ..model.robot import Robot
from .capsule import CapsuleModel
from .fit import inside_capsule, point_segment_distance
from .hull import HullModel, build_parts, hull_model, part_radius
from .meshes import link_collisions, link_elements, links_with_geometry, stroke_shifts

__all__ = ["EnclosureNotProven", "ContainmentProof", "HullPartTest", "prove_enclosures", "prove_robot_file"]

_EPS = float(np.finfo(np.float64).eps)
_ORIENT_SLACK = 32 * _EPS
_WITNESS_SLACK = 64 * _EPS
_BLOCK = 4096
"""Points per block of the (points x facets) orientation matrix: bounded memory."""


class EnclosureNotProven(LarcInputError):
    """An enclosure does not provably contain its link's geometry (module docstring)."""


@dataclasses.dataclass(frozen=True)
class ContainmentProof:
    """What a proof covered."""

    links: int
    elements: int
    """Collision elements proven (the fingers' twice: stroke enclosed, then stated)."""
    capsules: int
    stated_capsules: int
    hull_parts: int
    """Hull parts proven (the fingers' twice)."""
    padding_m: float
    seconds: float


@dataclasses.dataclass(frozen=True)
class _Enclosure:
    """One enclosure of a link: its name and label for messages, and its tests on points (N, 3)."""

    name: str
    label: str
    contains: Callable[[np.ndarray], np.ndarray]
    """Which points are proven inside (float64 rounding included)."""
    distance: Callable[[np.ndarray], np.ndarray]
    """How far the points are from the proven core, m (for the message; an upper bound for a hull)."""


def _capsule(capsules: CapsuleModel, c: int) -> _Enclosure:
    a, b = (np.asarray(x[c], np.float64) for x in (capsules.p_link_a, capsules.p_link_b))
    core = float(capsules.radius[c]) - capsules.padding_m
    name = f"'{capsules.names[c]}'"
    label = f"capsule {name} (radius {float(capsules.radius[c])!r} m less padding_m {capsules.padding_m!r} m)"
    return _Enclosure(name, label, lambda p: inside_capsule(p, a, b, core),
                      lambda p: point_segment_distance(p, a, b) - core)


class HullPartTest:
    """Membership proof for ``conv(V) + B(0, radius)`` (module docstring, (a) and (b))."""

    def __init__(self, vertices: np.ndarray, radius: float):
        from scipy.spatial import cKDTree

        self.V = np.ascontiguousarray(np.asarray(vertices, np.float64).reshape(-1, 3))
        self.radius = float(radius)
        self.facets = self._closed_surface()
        self._tree = cKDTree(self.V)
        if self.facets is not None:
            tri = self.V[self.facets]
            a, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
            n = np.cross(e1, e2)
            slack = _ORIENT_SLACK * np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1)
            # [y, |y|, 1] @ plane: the orientation n . y - n . a plus its rounding bound, one product
            self._plane = np.concatenate([n, slack[:, None], (slack * np.linalg.norm(a, axis=1)
                                                              - (n * a).sum(axis=1))[:, None]], axis=1).T
            self._unit = 1.0 / np.maximum(np.linalg.norm(n, axis=1), np.finfo(np.float64).tiny)

    def _closed_surface(self) -> np.ndarray | None:
        """(F, 3) corner indices of outward triangles forming a closed oriented surface, or None."""
        from scipy.spatial import ConvexHull, QhullError

        try:
            hull = ConvexHull(self.V)
        except (QhullError, ValueError):
            return None  # flat or tiny: points are proven by witnesses alone
        simp = np.array(hull.simplices, np.int64)
        tri = self.V[simp]
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        flip = (normal * hull.equations[:, :3]).sum(axis=1) < 0  # Qhull's outward normals choose the order
        simp[flip] = simp[flip][:, [0, 2, 1]]
        edges = np.concatenate([simp[:, [0, 1]], simp[:, [1, 2]], simp[:, [2, 0]]])
        n = len(self.V)
        code, reverse = edges[:, 0] * n + edges[:, 1], edges[:, 1] * n + edges[:, 0]
        if len(np.unique(code)) != len(code) or not np.isin(reverse, code).all():
            return None  # not a closed oriented surface: (a) cannot be used
        return simp

    def contains(self, points: np.ndarray) -> np.ndarray:
        """Which points are proven inside the part."""
        return self.distance_bound(points) <= self.radius

    def distance_bound(self, points: np.ndarray) -> np.ndarray:
        """Upper bounds on the distances of ``points`` (N, 3) to ``conv(V)``, float64 rounding
        included: 0 for points proven inside (a) or points of ``V``; else the best witness (b)
        (``inf``: none)."""
        points = np.asarray(points, np.float64).reshape(-1, 3)
        out = np.full(len(points), np.inf)
        rows, facets = [], []
        for s in range(0, len(points) if self.facets is not None else 0, _BLOCK):
            y = points[s:s + _BLOCK]
            # orientation plus its rounding bound, per (point, facet): < 0 is certainly inside
            excess = np.concatenate([y, np.linalg.norm(y, axis=1)[:, None], np.ones((len(y), 1))], axis=1) @ self._plane
            inside = excess.max(axis=1) < 0
            out[s:s + _BLOCK][inside] = 0.0
            # witnesses are sought on the facets a point is not certainly inside of, for the points
            # roughly within the radius of every facet plane (a choice of effort, not of soundness)
            rest = np.flatnonzero(~inside)
            near = rest[(excess[rest] * self._unit).max(axis=1) <= 2 * self.radius + 1e-9]
            r, f = np.nonzero(excess[near] >= 0)
            rows.append(near[r] + s)
            facets.append(f)
        rest = np.flatnonzero(out > 0)
        d, k = self._tree.query(points[rest])
        out[rest] = np.where((points[rest] == self.V[k]).all(axis=1), 0.0,
                             d + _WITNESS_SLACK * (2 * np.linalg.norm(points[rest], axis=1)
                                                   + np.linalg.norm(self.V[k], axis=1)))
        if rows:
            r, f = np.concatenate(rows), np.concatenate(facets)
            np.minimum.at(out, r, _facet_witness(points[r], self.V[self.facets[f]]))
        return out


def _facet_witness(y: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Upper bounds on the distances of points ``y`` (N, 3) to triangles ``tri`` (N, 3, 3),
    rounding included: the nearest of the projection onto the triangle's plane (when its
    barycentric weights are >= 0) and the nearest points of the three edges, each a convex
    combination of the corners (so a point of the triangle up to rounding); ``inf`` for a
    degenerate triangle's projection."""
    a, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    d = y - a
    a11, a12, a22 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
    b1, b2 = (d * e1).sum(1), (d * e2).sum(1)
    det = a11 * a22 - a12 * a12
    good = det > 0
    det = np.where(good, det, 1.0)
    mu1, mu2 = (b1 * a22 - b2 * a12) / det, (b2 * a11 - b1 * a12) / det
    w = np.stack([1.0 - mu1 - mu2, mu1, mu2], axis=1)
    good &= (w >= 0).all(axis=1) & (w.sum(axis=1) > 0)
    z = np.einsum("nk,nkd->nd", w / np.where(good, w.sum(axis=1), 1.0)[:, None], tri)
    best = np.where(good, np.linalg.norm(y - z, axis=1), np.inf)
    for i, j in ((0, 1), (1, 2), (2, 0)):
        p, q = tri[:, i], tri[:, j]
        pq = q - p
        t = np.clip(((y - p) * pq).sum(1) / np.maximum((pq * pq).sum(1), np.finfo(np.float64).tiny), 0.0, 1.0)
        best = np.minimum(best, np.linalg.norm(y - ((1.0 - t)[:, None] * p + t[:, None] * q), axis=1))
    return best + _WITNESS_SLACK * (np.linalg.norm(y, axis=1) + np.linalg.norm(tri, axis=2).sum(axis=1))


def _hull_part(name: str, vertices: np.ndarray, radius: float) -> _Enclosure:
    test = HullPartTest(vertices, radius)
    return _Enclosure(name, f"hull part {name} (radius {float(radius)!r} m)", test.contains,
                      lambda p: test.distance_bound(p) - test.radius)


def _element_label(robot: Robot, link: str, e: int) -> str:
    """Which collision entry (mesh file and triangle, or primitive) element ``e`` of ``link`` is."""
    start = 0
    for k, (_, geom, mesh) in enumerate(link_collisions(robot, link)):
        count = len(mesh[1]) if mesh is not None else 1
        if e < start + count:
            what = (f"mesh {geom.mesh.filename} triangle {e - start}" if mesh is not None else
                    next(kind for kind in ("box", "sphere", "cylinder") if getattr(geom, kind) is not None))
            widened = " widened over the finger stroke" if len(stroke_shifts(robot, link)) > 1 else ""
            return f"element {e} (collision {k}: {what}{widened})"
        start += count
    return f"element {e}"


def _prove_link(robot: Robot, link: str, elems: "_LinkPoints", enclosures: Sequence[_Enclosure], kind: str,
                source: str) -> int:
    """Every element of ``link`` inside one of ``enclosures``, or :class:`EnclosureNotProven`."""
    if not enclosures:
        raise EnclosureNotProven(f"{source}: link '{link}' has collision geometry but no {kind}")
    inside = np.zeros(len(elems.elements), bool)
    for enc in enclosures:  # each tries the elements no earlier one holds
        todo = np.flatnonzero(~inside)
        rows = np.unique(elems.inverse[todo])
        ok = np.zeros(len(elems.points), bool)
        ok[rows] = enc.contains(elems.points[rows])
        inside[todo] = ok[elems.inverse[todo]].all(axis=1)
    if inside.all():
        return len(inside)
    e = int(np.flatnonzero(~inside)[0])
    y = elems.elements[e]
    per_enclosure = [enc.contains(y) for enc in enclosures]
    best = max(range(len(enclosures)), key=lambda k: int(per_enclosure[k].sum()))
    v = int(np.flatnonzero(~per_enclosure[best])[0])
    d = float(enclosures[best].distance(y[v][None])[0])
    raise EnclosureNotProven(
        f"{source}: link '{link}' {_element_label(robot, link, e)} is not inside any of its {kind}s "
        f"({', '.join(enc.name for enc in enclosures)}) as far as float64 can prove: its vertex {v} at "
        f"{[round(float(x), 9) for x in y[v]]} m (link frame) lies {d:.6g} m beyond {enclosures[best].label}")


@dataclasses.dataclass(frozen=True)
class _LinkPoints:
    """A link's elements (E, P, 3), their distinct vertices (N, 3) and each vertex's row (E, P)."""

    elements: np.ndarray
    points: np.ndarray
    inverse: np.ndarray

    @staticmethod
    def of(robot: Robot, link: str) -> "_LinkPoints":
        elements = link_elements(robot, link)
        X = np.ascontiguousarray(elements.reshape(-1, 3), np.float64) + 0.0  # -0.0 -> 0.0
        _, first, inverse = np.unique(X.view(np.dtype((np.void, 24))).ravel(), return_index=True,
                                      return_inverse=True)
        return _LinkPoints(elements, X[first], inverse.reshape(elements.shape[:2]))


def _model_parts(hulls: HullModel) -> list[tuple[str, str, np.ndarray, float]]:
    """``(link, name, vertices, radius)`` of every part of ``hulls``, as the cascade uses it."""
    return [(link, f"{p} '{hulls.names[p]}'", np.asarray(hulls.vertices[p], np.float64)[:hulls.n_vertices[p]],
             float(hulls.radius[p])) for p, link in enumerate(hulls.link_names)]


def _prove_model(robot: Robot, capsules: CapsuleModel, parts: list | None, source: str, progress,
                 links: Sequence[str] | None = None) -> tuple[int, int, int]:
    """Prove ``capsules`` (and the hull ``parts``, :func:`_model_parts`) on ``links`` (default:
    every link with collision geometry not excluded): ``(links, elements, hull parts)`` counted."""
    wanted = [l for l in links_with_geometry(robot) if l not in capsules.excluded_links]
    wanted = [l for l in wanted if links is None or l in links]
    by_link: dict[str, list[_Enclosure]] = {}
    for link, name, V, r in parts or []:
        by_link.setdefault(link, []).append(_hull_part(name, V, r))
    n = 0
    for link in wanted:
        if progress:
            progress(link)
        elems = _LinkPoints.of(robot, link)
        if not len(elems.elements):
            continue
        n += _prove_link(robot, link, elems, [_capsule(capsules, c) for c, l in enumerate(capsules.link_names)
                                              if l == link], "capsule", source)
        if parts is not None:
            _prove_link(robot, link, elems, by_link.get(link, []), "hull part", source)
    return len(wanted), n, sum(len(by_link.get(l, [])) for l in wanted)


def prove_enclosures(robot: Robot, capsules: CapsuleModel, hull: bool, *, source: str = "robot file",
                     progress=None) -> HullModel | None:
    """Prove every enclosure a run with ``capsules`` uses (module docstring): the capsules (the
    stated-finger ones where the robot states the finger joints: the loader chose them) and,
    with ``hull``, the hull parts the cascade builds from the robot file's split planes, which
    are returned (give them to :func:`~larc_jax.leaf.reference.leaf_enclosures`: the parts
    used are the parts proven). Raises :class:`EnclosureNotProven`."""
    hulls = hull_model(robot, capsules.hull_parts, capsules.padding_m).on_links(capsules.link_names) if hull else None
    _prove_model(robot, capsules, _model_parts(hulls) if hull else None, source, progress)
    return hulls


def prove_robot_file(path=None, *, progress=None) -> ContainmentProof:
    """``larc verify-capsules``: load the robot file at ``path`` (``None``: PIPER's shipped one)
    and prove every enclosure it can give: its capsules and hull parts with the finger strokes
    enclosed, and, for the links below a finger joint, its stated capsules and hull parts with
    the fingers stated (placed alone in their own frames, so one opening proves them all)."""
    from .robot_file import default_capsule_path, load_robot_file

    start = time.perf_counter()
    source = str(path if path is not None else default_capsule_path())
    robot, capsules = load_robot_file(path)
    hulls = hull_model(robot, capsules.hull_parts, capsules.padding_m).on_links(capsules.link_names)
    n_links, n_elems, n_parts = _prove_model(robot, capsules, _model_parts(hulls), source, progress)
    n_stated = 0
    fingers = [l for l in capsules.link_names if len(stroke_shifts(robot, l)) > 1]
    if fingers:
        held = {j: float(robot.q_held[robot.joint_names.index(j)]) for j in robot.stroke_joints}
        robot_s, capsules_s = load_robot_file(path, hold=held)
        parts = [(p.link, f"'{p.name}' (fingers stated)", p.vertices, part_radius(capsules_s.padding_m, p.slack_m))
                 for p in build_parts(robot_s, capsules_s.hull_parts, fingers)]  # as hull_model builds them
        _, e, k = _prove_model(robot_s, capsules_s, parts, source, progress, links=fingers)
        n_elems, n_parts = n_elems + e, n_parts + k
        n_stated = sum(1 for l in capsules_s.link_names if l in fingers)
    return ContainmentProof(links=n_links, elements=n_elems, capsules=capsules.n_capsules, stated_capsules=n_stated,
                            hull_parts=n_parts, padding_m=capsules.padding_m, seconds=time.perf_counter() - start)
