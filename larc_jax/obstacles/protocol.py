"""The obstacle protocol: what every kind of obstacle gives the schedulers.

An *obstacle set* is a frozen-dataclass pytree of one kind (axis-aligned boxes,
:mod:`larc_jax.obstacles.aligned_boxes`; posed convex shapes, :mod:`larc_jax.obstacles.convex_shapes`): array fields with a leading item axis ``N`` (and, for a
batch of scenes, a scene axis before it), a ``mask`` (N,) of real items (padding items are never
real), and static structure as plain Python values. The schedulers (:mod:`larc_jax.leaf.interval`,
:mod:`larc_jax.leaf.clearance`, :mod:`larc_jax.leaf.cascade`, :mod:`larc_jax.engine.batch`, the NumPy reference
paths) never read a kind's fields: they call the kernels below, so a new kind is one module.

One item is the set with its item axis indexed away (:meth:`ObstacleSet.take`), the same
pytree type; its kernels are one-item JAX kernels (jit- and vmap-able), each with a NumPy
float64 twin (suffix ``_np``) for the reference scheduler and ``larc verify``:

- ``segment_distance(p0, p1)``: distance from the segment ``[p0, p1]`` (m) to the item, exact or a
  lower bound (the capsule stage);
- ``segment_lower_bound(p0, p1)``: a cheap lower bound of that distance (the broad phase);
- ``point_distance(p)``: distance from points ``p`` (..., 3) to the item; only used for an *upper*
  bound that skips work, so it needs no rounding care (a kind may also override the set-level
  :meth:`ObstacleSet.nearest_point_distances`, the form the hull stage calls, with a faster
  equivalent);
- ``polytope_lower_bound(vertices, part, centre, R, t, iterations)``: a lower bound on the distance from the
  polytope ``conv(R vertices[part] + t)`` to the item (the hull stage; the twin takes the part's
  vertex array ``V`` instead of ``vertices, part``). ``R, t`` may also be a stack of placements
  ((m, 3, 3), (m, 3)): the polytope is then the hull of their union (the swept stage,
  :mod:`larc_jax.leaf.swept`), whose support is the largest of the placements' supports.
  ``iterations`` (static) is the number of GJK steps after the first axis
  (:mod:`larc_jax.obstacles.polytope`); 0 gives the first axis's bound alone, the cheap first
  round of the hull stage (:mod:`larc_jax.leaf.cascade`, step 4);
- ``polytope_bounds(vertices, part, centre, R, t, iterations)``: ``(polytope_lower_bound,
  upper)``, ``upper`` an upper bound, up to rounding, on every ``polytope_lower_bound`` a longer
  search could give (the searches' last iterates: :func:`larc_jax.obstacles.polytope.polytope_box_bounds`;
  for posed shapes R8 of :mod:`larc_jax.obstacles.convex_shapes`), with which the hull stage stops
  searching a pair that cannot pass (never to certify). Both kinds here give one; the default, for
  a kind that does not, is ``+inf`` (never stops a failing pair early; a passing pair stops in
  every kind alike, so a certified leaf records the same round whichever kind a batch stacks a
  box-only scene as);
- ``points_lower_bound(vertices, part, centre, R, t, iterations)``: for an item that is a set of
  separate points (a point cloud's piece, :meth:`ObstacleSet.separate_points`), a lower bound on
  the distance from the polytope to its nearest point (the hull stage's third round); ``-inf``
  for any other item (the default: a kind without such items need not define it).

Soundness contract. Every distance kernel but ``point_distance`` returns a LOWER bound on the
true Euclidean distance, valid for the numbers as computed (its own rounding already
subtracted, or bounded by the schedulers' relative factor ``1 - K_DIST_REL eps`` and absolute
guard, budget G2 of :mod:`larc_jax.leaf.interval`, which the kind's docstring must show it meets);
never NaN for finite input; NaN for non-finite input (NaN never certifies: every comparison
``g > guard`` fails). A kind also builds itself from scenes (:func:`larc_jax.obstacles.scene_obstacles`,
:func:`larc_jax.obstacles.stack_scenes`), rounding its coordinates outwards when it casts them to a
narrower geometry dtype, so the item tested contains the user's (budget G3).

The set-level helpers (:meth:`ObstacleSet.segment_distances` ...) vmap the one-item kernels over
the items; a padding item's value there is ``+inf`` (never nearer than anything).
"""

from __future__ import annotations

import abc
import math
import dataclasses

import numpy as np

from ..lazy_jax import jax, jnp
from .polytope import GJK_ITERATIONS

__all__ = ["ObstacleSet"]


class ObstacleSet(abc.ABC):
    """Base of every obstacle kind (a frozen-dataclass pytree; module docstring)."""

    mask: np.ndarray
    """(..., N) which items are real (padding items are not)."""

    @property
    def n_items(self) -> int:
        """Items per scene, padding included (static)."""
        return int(np.shape(self.mask)[-1])

    def take(self, index):
        """The set with its leading axis indexed by ``index`` (an item, a scene, or a gather of
        them; NumPy or JAX arrays, traced indices included). Static fields are kept."""
        return type(self)(**{f.name: getattr(self, f.name) if f.metadata.get("static") else getattr(self, f.name)[index]
                             for f in dataclasses.fields(self)})

    # One-item kernels (JAX) and their NumPy float64 twins: see the module docstring.

    @abc.abstractmethod
    def segment_distance(self, p0, p1): ...

    @abc.abstractmethod
    def segment_distance_np(self, p0, p1) -> float: ...

    @abc.abstractmethod
    def segment_lower_bound(self, p0, p1): ...

    @abc.abstractmethod
    def segment_lower_bound_np(self, p0, p1) -> float: ...

    @abc.abstractmethod
    def point_distance(self, p): ...

    @abc.abstractmethod
    def point_distance_np(self, p): ...

    @abc.abstractmethod
    def polytope_lower_bound(self, vertices, part, centre, R, t, iterations: int = GJK_ITERATIONS): ...

    @abc.abstractmethod
    def polytope_lower_bound_np(self, V, centre, R, t, iterations: int = GJK_ITERATIONS) -> float: ...

    def polytope_bounds(self, vertices, part, centre, R, t, iterations: int = GJK_ITERATIONS):
        lb = self.polytope_lower_bound(vertices, part, centre, R, t, iterations)
        return lb, jnp.full_like(lb, jnp.inf)

    def polytope_bounds_np(self, V, centre, R, t, iterations: int = GJK_ITERATIONS) -> tuple[float, float]:
        return self.polytope_lower_bound_np(V, centre, R, t, iterations), math.inf

    def points_lower_bound(self, vertices, part, centre, R, t, iterations: int = GJK_ITERATIONS):
        return jnp.full((), -jnp.inf, R.dtype)

    def points_lower_bound_np(self, V, centre, R, t, iterations: int = GJK_ITERATIONS) -> float:
        return -np.inf

    def separate_points(self) -> np.ndarray:
        """(..., N) bool (NumPy): the items made of separate points, for which
        ``points_lower_bound`` can beat ``polytope_lower_bound``; none by default."""
        return np.zeros(np.shape(self.mask), bool)

    # Set-level helpers (JAX): the one-item kernels over every item of one scene's set.

    def segment_distances(self, p_a, p_b):
        """(S, N) ``segment_distance`` of segments ``[p_a[s], p_b[s]]`` (S, 3) to every item."""
        return self._over_items(type(self).segment_distance, p_a, p_b)

    def segment_lower_bounds(self, p_a, p_b):
        """(S, N) ``segment_lower_bound`` of every segment and item."""
        return self._over_items(type(self).segment_lower_bound, p_a, p_b)

    def point_distances(self, points):
        """(M, N) ``point_distance`` of points (M, 3) to every item."""
        return self._over_items(type(self).point_distance, points)

    def nearest_point_distances(self, points):
        """(P, N): for each group of points ``points[p]`` (P, Q, 3), the ``point_distance`` of its
        nearest point to every item (an upper bound's input: no rounding care)."""
        P, Q = points.shape[:2]
        return self.point_distances(points.reshape(P * Q, 3)).reshape(P, Q, -1).min(axis=1)

    def _over_items(self, kernel, *per_row):
        def one(item, *row):
            return jnp.where(item.mask, kernel(item, *row), jnp.inf)

        per_item = jax.vmap(one, in_axes=(0,) + (None,) * len(per_row))
        return jax.vmap(per_item, in_axes=(None,) + (0,) * len(per_row))(self, *per_row)
