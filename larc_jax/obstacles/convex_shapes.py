"""Posed convex shapes and convex pieces: oriented boxes, spheres, cylinders, cones, and the
pieces of meshes and point clouds (:mod:`larc_jax.obstacles.protocol`).

An item is a shape in its own frame, placed by ``p_world = centre + R x``: the points ``x`` of
the box ``[lo, hi]`` that, for a round shape (``rounded``), also lie within ``radius`` of the z
segment ``[-axis_half, axis_half]`` (:mod:`larc_jax.model.shapes`: a box is its box; a sphere, a
cylinder and a cone lie in the intersection of their box and capsule). A scene's axis-aligned
boxes join as items with ``centre = 0``, ``R = I`` and their own corners (exact). A piece of a
mesh or point cloud (:mod:`larc_jax.model.point_sets`, ``polytope``) is the hull of its
``vertices`` (base frame) grown by ``inflate``; it also carries its axis-aligned bounding box
as ``[lo, hi]`` (``R = I``). The capsule stage's segment kernels use that box alone (less
``inflate``: the exact segment-box distance, so the stage stays as cheap per item as for a box
and its broad phase exact); the polytope kernel (the hull and swept stages) takes the better of
the box's bound and the hull's (the GJK bound
:func:`~larc_jax.obstacles.polytope.polytope_hull_lower_bound`), less ``inflate``.

Why the bounds hold. Every kernel maps the robot's geometry into the shape frame, ``x = R^T (p -
centre)``, and calls the axis-aligned kernels of :mod:`larc_jax.obstacles.geometry` and
:mod:`larc_jax.obstacles.polytope` there: once against the box, and for a round shape once more
against the degenerate box ``[(0, 0, -axis_half), (0, 0, axis_half)]`` (the capsule's axis),
less ``radius``. The distance to an intersection is at least the distance to each of its sets,
so the larger of the two lower bounds is a lower bound (exact for boxes and spheres; beyond a
cylinder's rim at least ``1 / sqrt 2`` of the distance, :mod:`larc_jax.model.shapes`). What the mapping adds, with ``u`` the unit
roundoff of the geometry dtype and ``Q`` the rotation the user gave (the orthogonal polar factor
of the float64 matrix read from the quaternion):

* R1. The stored ``R`` is off ``Q`` by ``||R - Q||_2 <= rot_err`` (computed when the set is built:
  ``||R64^T R64 - I||_F``, which bounds the float64 matrix's distance to its polar factor, plus
  ``||R - R64||_F`` for a narrower dtype, plus 8 float64 eps, rounded up).
* R2. A point: ``fl(R^T fl(p - c))`` is within ``(rot_err + 8u) |p - c|_1`` of ``Q^T (p - c)``
  (one rounded subtraction, then three products and two sums per component, ``|R_ij| <= 1 + u``).
  A segment's points are convex combinations of its ends, so the mapped segment is within the
  larger end error of the exactly mapped one: subtracting it keeps a lower bound.
* R3. The segment-box distance in the shape frame has the absolute error ``32 u (|x0| + |x1|)``
  of budget G2 (:mod:`larc_jax.leaf.interval`), measured in shape-frame coordinates that the
  schedulers' guard (sized by the robot's reach) does not cover: it is subtracted here; the
  relative part stays with the schedulers' factor ``1 - K_DIST_REL eps``. The capsule's
  ``d - radius`` is lowered by ``24 u (d + radius)`` (G2's ``16 u d`` and the subtraction).
* R4. A polytope: the link pose becomes ``fl(R^T R_link)``, ``fl(R^T fl(t - c))``; each placed
  vertex is then within ``(2 rot_err + 16 u) (|v| + |t - c|_1)`` of ``Q^T`` applied to the
  computed world vertex (``||R_link||_2 <= 1 + O(L u)``, the entries of ``|R|^T |R_link|`` at
  most 1 + O(u)), so that much, with ``|v|`` bounded by the part's largest vertex 1-norm and a
  union's largest ``|t_i - c|_1``, is subtracted; the polytope kernel's own rounding is its own.
* R5. Building the set in a narrower dtype moves the centre by ``Δ = |c32 - c|_2`` (float64,
  rounded up): the box grows by ``Δ`` on every side and the radius by ``Δ`` (then every bound
  is rounded outwards, as budget G3 does for boxes), so the item tested contains the user's.
* R6. A piece's vertices rounded to a narrower dtype move by at most ``m = max_j |y32_j - y_j|``
  (float64, rounded up): the rounded hull grown by ``m`` holds the true one, so ``m`` joins
  ``inflate``. A piece's bound ``d - inflate`` is lowered by ``4 u (|d| + inflate)`` for the
  subtraction. Its bounding box is exact in float64 and rounded outwards in float32 (G3).
* R7. A cloud's piece (``separate``) is its points, each a ball of radius ``inflate`` (R6's
  share included). The hull of the points holds them, but a face of the hull spans the gaps
  between points (1 cm apart in a depth camera's cloud at a metre), so the hull bound can sit a
  millimetre below the distance to the nearest point. :meth:`points_lower_bound` runs the
  piece-hull search on each point alone (a one-vertex polytope: the obstacle's vertex is picked
  without choice, and the kernel's own rounding is subtracted as for any piece) and takes the
  least, less ``inflate`` as in R6: a lower bound on the distance to every ball of the piece.
  It costs one search per point, so the hull stage runs it only as a third round, on the
  (part, cloud piece) pairs the hull bound leaves failing (:mod:`larc_jax.leaf.cascade`).
* R8. The upper value of :meth:`polytope_bounds`, for stopping a failing pair early (never for
  certifying). The polytope bound is ``f(s_box, s_axis, s_hull)``, the values of up to three GJK
  searches (against the box, the axis, the piece's hull) put through R3's ``- radius``, the
  larger of, R4's subtraction and R6's ``- inflate``: each step non-decreasing in each value
  (``x - c - k u (|x| + c)`` with ``k u < 1`` included). Each search's last iterate bounds from
  above every lower bound its later steps can reach (:mod:`larc_jax.obstacles.polytope`, "An
  upper bound"), so ``f`` of the iterates bounds from above ``f`` of the full searches' values:
  the polytope bound the full search would give, up to the rounding of ``f``'s few operations,
  which the hull stage's slack covers (:func:`~larc_jax.leaf.rounds.early_stop_slack`). It is
  not an upper bound on the distance to a round shape (the distance to an intersection may
  exceed the distance to each of its sets); it need not be: it only predicts the full search.

The NumPy float64 twins (suffix ``_np``) run the same steps with the float64 kernels.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Sequence

import numpy as np

from ..lazy_jax import jax, jnp, pytree_dataclass
from ..model.scene import Scene
from ..model.shapes import local_geometry
from .aligned_boxes import boxes_outward
from .geometry import (point_box_distance, point_box_distance_np, segment_box_distance, segment_box_distance_np,
                       segment_box_lower_bound, segment_box_lower_bound_np)
from .polytope import (GJK_ITERATIONS, polytope_box_bounds, polytope_box_bounds_np, polytope_box_lower_bound,
                       polytope_hull_bounds, polytope_hull_bounds_np, polytope_hull_lower_bound,
                       polytope_hull_lower_bound_np)
from .protocol import ObstacleSet

__all__ = ["ConvexShapes", "shape_items", "piece_items", "piece_width", "piece_bounds", "padded_pieces"]

_EPS64 = float(np.finfo(np.float64).eps)


def shape_items(scene: Scene):
    """A scene's obstacle items (boxes, shapes, then mesh and cloud pieces) as float64 arrays:
    ``centre (N, 3), R (N, 3, 3), lo, hi (N, 3), axis_half, radius (N,), rounded (N,) bool,
    rot_err (N,)`` (R1); a piece is its axis-aligned bounding box here (its hull: :func:`piece_items`)."""
    nb, sh, ps = scene.n_boxes, scene.shapes, scene.point_sets
    lo_s, hi_s, axis_half_s, radius_s, rounded_s = local_geometry(sh)
    lo_p, hi_p = piece_bounds(ps)
    flat = nb + ps.count  # items with R = I exactly
    R = np.concatenate([np.broadcast_to(np.eye(3), (nb, 3, 3)), sh.R_world_shape, np.broadcast_to(np.eye(3), (ps.count, 3, 3))])
    defect = np.linalg.norm(np.einsum("nji,njk->nik", R, R) - np.eye(3), axis=(1, 2))
    posed = (np.arange(len(R)) >= nb) & (np.arange(len(R)) < nb + sh.count)
    rot_err = np.where(posed, defect + 8 * _EPS64, 0.0)
    zeros, falses = np.zeros(flat - nb), np.zeros(flat - nb, bool)
    return (np.concatenate([np.zeros((nb, 3)), sh.p_world_shape, np.zeros((ps.count, 3))]), R,
            np.concatenate([scene.lo, lo_s, lo_p]), np.concatenate([scene.hi, hi_s, hi_p]),
            np.concatenate([np.zeros(nb), axis_half_s, zeros]), np.concatenate([np.zeros(nb), radius_s, zeros]),
            np.concatenate([np.zeros(nb, bool), rounded_s, falses]), rot_err)


def piece_bounds(point_sets) -> tuple[np.ndarray, np.ndarray]:
    """``(lo, hi)`` (pieces, 3): each piece's axis-aligned bounding box, float64 (exact: its
    least and largest vertex coordinates) of a :class:`~larc_jax.model.point_sets.PointSets`."""
    V, sizes, _ = point_sets.arrays()
    if not len(sizes):
        return np.zeros((0, 3)), np.zeros((0, 3))
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    return np.minimum.reduceat(V, starts, axis=0), np.maximum.reduceat(V, starts, axis=0)


def padded_pieces(point_sets, k: int) -> np.ndarray:
    """(pieces, k, 3): each piece's vertices padded to ``k`` rows by repeating its first."""
    V, sizes, _ = point_sets.arrays()
    if np.any(sizes > k):
        raise ValueError(f"a piece has {int(sizes.max())} vertices, more than {k}")
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
    j = np.arange(k)
    return V[starts[:, None] + np.where(j[None, :] < sizes[:, None], j[None, :], 0)].reshape(len(sizes), k, 3)


def piece_items(scene: Scene, k_vertices: int):
    """The hull part of a scene's items: ``vertices (N, K, 3)`` (a piece's vertices, padded by
    repeating its first; other items a zero row), ``polytope (N,)``, ``inflate (N,)`` (a cloud's
    point radius), ``separate (N,)`` (a cloud's piece: its points are the obstacle), float64."""
    n, start, ps = scene.n_obstacles, scene.n_boxes + scene.shapes.count, scene.point_sets
    V = np.zeros((n, k_vertices, 3))
    polytope, inflate, separate = np.zeros(n, bool), np.zeros(n), np.zeros(n, bool)
    if ps.count:
        at, owner = slice(start, start + ps.count), np.asarray(ps.owner, np.int64)
        V[at] = padded_pieces(ps, k_vertices)
        polytope[at], inflate[at] = True, np.asarray(ps.radius, np.float64)[owner]
        separate[at] = (np.asarray(ps.kinds) == "points")[owner]
    return V, polytope, inflate, separate


def piece_width(scenes: Sequence[Scene]) -> int:
    """Vertices per item in a set of ``scenes`` (static): the largest piece's count, rounded up
    to a power of two (at least 4) so that few widths are ever compiled; 1 without pieces."""
    most = max([len(v) for s in scenes for v in s.point_sets.pieces] + [0])
    return 1 if most == 0 else 1 << (max(most, 4) - 1).bit_length()


def _up(x: np.ndarray, dtype) -> np.ndarray:
    """``x`` in ``dtype``, rounded up (never below the float64 value)."""
    g = x.astype(dtype)
    return np.where(g < x, np.nextafter(g, np.asarray(np.inf, dtype)), g)


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class ConvexShapes(ObstacleSet):
    """Posed convex shapes (module docstring); JAX or NumPy arrays, a batch of scenes adds a leading axis."""

    centre: Any
    """(..., N, 3) shape origins in the base frame, m."""
    rotation: Any
    """(..., N, 3, 3) ``R_world_shape``."""
    lo: Any
    """(..., N, 3) box minimum corner in the shape frame, m."""
    hi: Any
    """(..., N, 3) box maximum corner in the shape frame, m."""
    axis_half: Any
    """(..., N) half length of the capsule's z segment, m."""
    radius: Any
    """(..., N) capsule radius, m."""
    rounded: Any
    """(..., N) whether the capsule applies."""
    rot_err: Any
    """(..., N) bound on ``||R - Q||_2`` (R1)."""
    mask: Any
    """(..., N) which items are real."""
    vertices: Any = None
    """(..., N, K, 3) a piece's vertices in the base frame, m (other items: unused)."""
    polytope: Any = None
    """(..., N) whether the item is a piece (tested as the hull of its vertices)."""
    inflate: Any = None
    """(..., N) subtracted from a piece's distances: a cloud's point radius, and the vertices'
    rounding in a narrower dtype (rounded up), m."""
    separate: Any = None
    """(..., N) whether the item is a cloud's piece: its points are the obstacle (each a ball of
    radius ``inflate``), the hull only holds them (:meth:`points_lower_bound`)."""
    any_rounded: bool = dataclasses.field(default=True, metadata=dict(static=True))
    """Whether any item is round (static): without one the kernels skip the capsule test, so a
    scene of rotated boxes costs one box kernel per pair, not two."""
    any_polytope: bool = dataclasses.field(default=False, metadata=dict(static=True))
    """Whether any item is a piece (static): without one the kernels skip the hull bounds."""

    @staticmethod
    def from_scene(scene: Scene) -> "ConvexShapes":
        """The items of one scene, float64, unpadded (for the NumPy references)."""
        c, R, lo, hi, z, r, rounded, rot_err = shape_items(scene)
        V, polytope, inflate, separate = piece_items(scene, piece_width([scene]))
        return ConvexShapes(centre=c, rotation=R, lo=lo, hi=hi, axis_half=z, radius=r, rounded=rounded,
                            rot_err=rot_err, mask=np.ones(len(c), bool), vertices=V, polytope=polytope,
                            inflate=inflate, separate=separate, any_rounded=bool(rounded.any()),
                            any_polytope=bool(polytope.any()))

    @staticmethod
    def stack(scenes: Sequence[Scene], dtype, n_items: int | None = None) -> "ConvexShapes":
        """Scenes padded to ``n_items`` items (default: the largest scene, at least 1) in ``dtype``,
        every bound rounded outwards (R1, R5). Padding items are masked degenerate boxes at 0."""
        dtype = np.dtype(dtype)
        N = max([s.n_obstacles for s in scenes] + [1]) if n_items is None else n_items
        S = len(scenes)
        c, lo, hi = np.zeros((S, N, 3)), np.zeros((S, N, 3)), np.zeros((S, N, 3))
        R = np.broadcast_to(np.eye(3), (S, N, 3, 3)).copy()
        z, r, rot_err = np.zeros((S, N)), np.zeros((S, N)), np.zeros((S, N))
        rounded, mask = np.zeros((S, N), bool), np.zeros((S, N), bool)
        K = piece_width(scenes)
        V, polytope, inflate = np.zeros((S, N, K, 3)), np.zeros((S, N), bool), np.zeros((S, N))
        separate = np.zeros((S, N), bool)
        for i, s in enumerate(scenes):
            n = s.n_obstacles
            c[i, :n], R[i, :n], lo[i, :n], hi[i, :n], z[i, :n], r[i, :n], rounded[i, :n], rot_err[i, :n] = shape_items(s)
            V[i, :n], polytope[i, :n], inflate[i, :n], separate[i, :n] = piece_items(s, K)
            mask[i, :n] = True
        V_g = V.astype(dtype)  # a rounded vertex moves: the piece's distances are lowered by the most (R6)
        moved_v = np.linalg.norm(V_g.astype(np.float64) - V, axis=-1).max(axis=-1)
        inflate = np.where(moved_v > 0, inflate + moved_v * (1 + 4 * _EPS64) + np.finfo(np.float64).tiny, inflate)
        c_g, R_g = c.astype(dtype), R.astype(dtype)
        shift = np.linalg.norm(c_g.astype(np.float64) - c, axis=-1)
        shift = np.where(shift > 0, shift * (1 + 4 * _EPS64) + np.finfo(np.float64).tiny, 0.0)  # R5, rounded up
        moved = np.linalg.norm((R_g.astype(np.float64) - R).reshape(S, N, 9), axis=-1)
        rot_err = np.where(moved > 0, rot_err + moved * (1 + 4 * _EPS64) + 8 * _EPS64, rot_err)
        lo_g, hi_g = boxes_outward(lo - shift[..., None], hi + shift[..., None], dtype)
        return ConvexShapes(centre=c_g, rotation=R_g, lo=lo_g, hi=hi_g, axis_half=_up(z + shift, dtype),
                            radius=_up(r + shift, dtype), rounded=rounded, rot_err=_up(rot_err, dtype), mask=mask,
                            vertices=V_g, polytope=polytope, inflate=_up(inflate, dtype), separate=separate,
                            any_rounded=bool(rounded.any()), any_polytope=bool(polytope.any()))

    # -- JAX kernels (one item) ------------------------------------------------------------------

    def _to_local(self, p):
        """``p`` (..., 3) in the shape frame, and the error bound of R2 per point."""
        d = p - self.centre
        x = jnp.matmul(d, self.rotation, precision=jax.lax.Precision.HIGHEST)  # R^T d, row-wise
        u = float(jnp.finfo(x.dtype).eps) / 2
        return x, (self.rot_err + 8 * u) * jnp.abs(d).sum(axis=-1)

    def _axis(self):
        z = jnp.zeros(3, self.lo.dtype).at[2].set(self.axis_half)
        return -z, z

    def _segment(self, p0, p1, box_kernel):
        x0, e0 = self._to_local(p0)
        x1, e1 = self._to_local(p1)
        u = float(jnp.finfo(x0.dtype).eps) / 2
        d = box_kernel(x0, x1, self.lo, self.hi)
        if self.any_rounded:
            lo_z, hi_z = self._axis()
            d_axis = box_kernel(x0, x1, lo_z, hi_z)
            d_cap = d_axis - self.radius - 24 * u * (jnp.abs(d_axis) + self.radius)  # R3
            d = jnp.where(self.rounded, jnp.maximum(d, d_cap), d)
        return d - jnp.maximum(e0, e1) - 32 * u * (jnp.abs(x0).sum() + jnp.abs(x1).sum())  # R2, R3

    def _piece(self, d_box, d_hull):
        """A piece's bound: the better of its bounding box's and its hull's, less ``inflate``
        (R6, with the subtraction's rounding); other items keep ``d_box``."""
        return jnp.where(self.polytope, self._less_inflate(jnp.maximum(d_box, d_hull)), d_box)

    def _less_inflate(self, d):
        """``d - inflate``, lowered by the subtraction's rounding (R6)."""
        u = float(jnp.finfo(d.dtype).eps) / 2
        return d - self.inflate - 4 * u * (jnp.abs(d) + self.inflate)

    def segment_distance(self, p0, p1):
        # A piece: its bounding box's exact distance (the capsule stage stays cheap and its broad
        # phase exact; the hull and swept stages use the piece's hull, polytope_lower_bound).
        d = self._segment(p0, p1, segment_box_distance)
        return self._piece(d, d) if self.any_polytope else d

    def segment_lower_bound(self, p0, p1):
        d = self._segment(p0, p1, segment_box_lower_bound)
        return self._piece(d, d) if self.any_polytope else d

    def point_distance(self, p):
        x, _ = self._to_local(p)
        d = point_box_distance(x, self.lo, self.hi)
        if self.any_rounded:
            lo_z, hi_z = self._axis()
            d_cap = point_box_distance(x, lo_z, hi_z) - self.radius
            d = jnp.where(self.rounded, jnp.maximum(d, d_cap), d)
        if self.any_polytope:  # the nearest vertex: at least the distance to the piece
            gap = p[..., None, :] - self.vertices
            near = jnp.sqrt(jnp.min(jnp.sum(gap * gap, axis=-1), axis=-1)) - self.inflate
            d = jnp.where(self.polytope, near, d)
        return d

    def polytope_lower_bound(self, vertices, part, centre, R, t, iterations: int = GJK_ITERATIONS):
        return self._polytope(vertices, part, centre, R, t, iterations, upper=False)

    def polytope_bounds(self, vertices, part, centre, R, t, iterations: int = GJK_ITERATIONS):
        # (lower, upper): the searches' last iterates through the same steps as their lower bounds
        # (R8), so the full search's bound stays at or below the upper one.
        return self._polytope(vertices, part, centre, R, t, iterations, upper=True)

    def _polytope(self, vertices, part, centre, R, t, iterations, upper):
        dtype = R.dtype
        u = float(jnp.finfo(dtype).eps) / 2
        M = self.rotation.astype(dtype)
        dt = t - self.centre.astype(dtype)
        hi_prec = jax.lax.Precision.HIGHEST
        if R.ndim == 3:  # a union of placements (the swept stage)
            R_local = jnp.einsum("ji,pjk->pik", M, R, precision=hi_prec)
            t_max = jnp.max(jnp.abs(dt).sum(axis=-1))
        else:
            R_local = jnp.matmul(M.T, R, precision=hi_prec)
            t_max = jnp.abs(dt).sum()
        t_local = jnp.matmul(dt, M, precision=hi_prec)
        box = polytope_box_bounds if upper else polytope_box_lower_bound
        d = box(vertices, part, centre, R_local, t_local, self.lo, self.hi, iterations)
        d_axis = box(vertices, part, centre, R_local, t_local, *self._axis(), iterations) if self.any_rounded else None
        d_hull = None
        if self.any_polytope:
            hull = polytope_hull_bounds if upper else polytope_hull_lower_bound
            d_hull = hull(vertices, part, centre, R, t, self.vertices, iterations)
        v_max = jnp.max(jnp.abs(vertices[part].astype(dtype)).sum(axis=-1))

        def bound(d, d_axis, d_hull):  # non-decreasing in each search's value (R8)
            if d_axis is not None:
                d_cap = d_axis - self.radius - 4 * u * (jnp.abs(d_axis) + self.radius)
                d = jnp.where(self.rounded, jnp.maximum(d, d_cap), d)
            d = d - (2 * self.rot_err + 16 * u) * (v_max + t_max)  # R4
            return d if d_hull is None else self._piece(d, d_hull)

        if not upper:
            return bound(d, d_axis, d_hull)
        pick = lambda x, i: None if x is None else x[i]  # noqa: E731
        return tuple(bound(pick(d, i), pick(d_axis, i), pick(d_hull, i)) for i in (0, 1))

    def points_lower_bound(self, vertices, part, centre, R, t, iterations: int = GJK_ITERATIONS):
        # R7: each point of a cloud's piece is a polytope of one vertex, searched on its own; the
        # nearest bounds the distance to the piece's points (padding rows repeat the first).
        one = jax.vmap(lambda y: polytope_hull_lower_bound(vertices, part, centre, R, t, y[None], iterations))
        d = self._less_inflate(jnp.min(one(self.vertices)).astype(self.inflate.dtype))
        return jnp.where(self.separate, d, -jnp.inf)

    def separate_points(self) -> np.ndarray:
        return np.zeros(np.shape(self.mask), bool) if self.separate is None else np.asarray(self.separate, bool)

    # -- NumPy float64 twins -----------------------------------------------------------------------

    def _to_local_np(self, p):
        d = np.asarray(p, np.float64) - np.asarray(self.centre, np.float64)
        x = d @ np.asarray(self.rotation, np.float64)
        return x, (float(self.rot_err) + 4 * _EPS64) * np.abs(d).sum(axis=-1)

    def _axis_np(self):
        z = np.array([0.0, 0.0, float(self.axis_half)])
        return -z, z

    def _segment_np(self, p0, p1, box_kernel) -> float:
        x0, e0 = self._to_local_np(p0)
        x1, e1 = self._to_local_np(p1)
        u = _EPS64 / 2
        d = box_kernel(x0, x1, self.lo, self.hi)
        if bool(self.rounded):
            d_axis = box_kernel(x0, x1, *self._axis_np())
            r = float(self.radius)
            d = max(d, d_axis - r - 24 * u * (abs(d_axis) + r))
        return d - max(float(e0), float(e1)) - 32 * u * float(np.abs(x0).sum() + np.abs(x1).sum())

    def _piece_np(self, d_box: float, d_hull) -> float:
        if not self._is_piece():
            return d_box
        return self._less_inflate_np(max(d_box, float(d_hull)))

    def _less_inflate_np(self, d: float) -> float:
        e = float(self.inflate)
        return d - e - 2 * _EPS64 * (abs(d) + e)

    def _is_piece(self) -> bool:
        return self.polytope is not None and bool(self.polytope)

    def segment_distance_np(self, p0, p1) -> float:
        return self._piece_np(*(self._segment_np(p0, p1, segment_box_distance_np),) * 2)

    def segment_lower_bound_np(self, p0, p1) -> float:
        d = self._segment_np(p0, p1, segment_box_lower_bound_np)
        return self._piece_np(d, d)

    def point_distance_np(self, p):
        x, _ = self._to_local_np(p)
        d = point_box_distance_np(x, self.lo, self.hi)
        if bool(self.rounded):
            d = np.maximum(d, point_box_distance_np(x, *self._axis_np()) - float(self.radius))
        if self._is_piece():
            gap = np.asarray(p, np.float64)[..., None, :] - np.asarray(self.vertices, np.float64)
            d = np.sqrt((gap * gap).sum(axis=-1).min(axis=-1)) - float(self.inflate)
        return d

    def polytope_lower_bound_np(self, V, centre, R, t, iterations: int = GJK_ITERATIONS) -> float:
        return self.polytope_bounds_np(V, centre, R, t, iterations)[0]

    def polytope_bounds_np(self, V, centre, R, t, iterations: int = GJK_ITERATIONS) -> tuple[float, float]:
        M = np.asarray(self.rotation, np.float64)
        R, t = np.asarray(R, np.float64), np.asarray(t, np.float64)
        dt = t - np.asarray(self.centre, np.float64)
        R_local = np.einsum("ji,...jk->...ik", M, R)
        t_local = dt @ M
        u = _EPS64 / 2
        searches = [polytope_box_bounds_np(V, centre, R_local, t_local, self.lo, self.hi, iterations)]
        if bool(self.rounded):
            searches.append(polytope_box_bounds_np(V, centre, R_local, t_local, *self._axis_np(), iterations))
        if self._is_piece():
            hull = polytope_hull_bounds_np(V, centre, R, t, self.vertices, iterations)
        t_max = float(np.abs(dt).reshape(-1, 3).sum(axis=-1).max())
        v_max = float(np.abs(np.asarray(V, np.float64)).sum(axis=-1).max())

        def bound(i: int) -> float:  # the JAX kernel's composition, on the lower (0) or upper (1) values
            d = searches[0][i]
            if bool(self.rounded):
                d_axis, r = searches[1][i], float(self.radius)
                d = max(d, d_axis - r - 4 * u * (abs(d_axis) + r))
            d = d - (2 * float(self.rot_err) + 16 * u) * (v_max + t_max)
            return self._piece_np(d, hull[i]) if self._is_piece() else d

        return bound(0), bound(1)

    def points_lower_bound_np(self, V, centre, R, t, iterations: int = GJK_ITERATIONS) -> float:
        if not (self.separate is not None and bool(self.separate)):
            return -math.inf
        one = [polytope_hull_lower_bound_np(V, centre, R, t, y[None], iterations)
               for y in np.asarray(self.vertices, np.float64)]
        return self._less_inflate_np(float(np.min(one)))  # np.min: a NaN propagates
