"""Axis-aligned boxes: the first obstacle kind (:mod:`larc_jax.obstacles.protocol`).

A box is ``[lo, hi]`` (base frame, m, ``lo <= hi``). Its kernels are those of
:mod:`larc_jax.obstacles.geometry` (the exact segment-box distance, the AABB-gap lower bound, the
point-box distance) and :mod:`larc_jax.obstacles.polytope` (the GJK polytope-box lower bound), which meet
the protocol's contract (their module docstrings: budget G2 of :mod:`larc_jax.leaf.interval` for the
exact distance, an a-posteriori rounding bound subtracted for the two lower bounds).

Built from :class:`~larc_jax.model.scene.Scene` objects (which keep ``lo``/``hi``): one scene as it is
(float64, for the NumPy references), or several padded to one item count with masked padding
boxes (degenerate at the origin) and cast to the geometry dtype with outward rounding (budget
G3: ``lo`` down, ``hi`` up, so the box tested contains the user's).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Sequence

import numpy as np

from .geometry import (point_box_distance, point_box_distance_np, segment_box_distance, segment_box_distance_np,
                        segment_box_lower_bound, segment_box_lower_bound_np)
from ..lazy_jax import jnp, pytree_dataclass
from .polytope import (GJK_ITERATIONS, polytope_box_bounds, polytope_box_bounds_np, polytope_box_lower_bound,
                       polytope_box_lower_bound_np)
from ..model.scene import Scene, pad_scenes
from .protocol import ObstacleSet

__all__ = ["AlignedBoxes", "boxes_outward"]


def boxes_outward(lo: np.ndarray, hi: np.ndarray, dtype):
    """Box corners in ``dtype``, rounded outwards so the box tested contains the user's (G3)."""
    lo_g, hi_g = lo.astype(dtype), hi.astype(dtype)
    inf = np.asarray(np.inf, dtype)
    lo_g = np.where(lo_g > lo, np.nextafter(lo_g, -inf), lo_g)
    hi_g = np.where(hi_g < hi, np.nextafter(hi_g, inf), hi_g)
    return lo_g, hi_g


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class AlignedBoxes(ObstacleSet):
    """Axis-aligned boxes (JAX or NumPy arrays; a batch of scenes adds a leading axis)."""

    lo: Any
    """(..., N, 3) minimum corners, m (geometry dtype)."""
    hi: Any
    """(..., N, 3) maximum corners, m."""
    mask: Any
    """(..., N) which boxes are real."""

    @staticmethod
    def from_scene(scene: Scene) -> "AlignedBoxes":
        """The boxes of one scene, float64, unpadded (for the NumPy references)."""
        return AlignedBoxes(lo=scene.lo, hi=scene.hi, mask=np.ones(scene.n_boxes, bool))

    @staticmethod
    def stack(scenes: Sequence[Scene], dtype, n_items: int | None = None) -> "AlignedBoxes":
        """Scenes padded to ``n_items`` boxes (default: the largest scene, at least 1), in the
        geometry ``dtype`` rounded outwards: arrays (S, N, 3), (S, N, 3), (S, N)."""
        lo, hi, mask = pad_scenes(scenes, n_items)
        lo_g, hi_g = boxes_outward(lo, hi, np.dtype(dtype))
        return AlignedBoxes(lo=lo_g, hi=hi_g, mask=mask)

    def segment_distance(self, p0, p1):
        return segment_box_distance(p0, p1, self.lo, self.hi)

    def segment_distance_np(self, p0, p1) -> float:
        return segment_box_distance_np(p0, p1, self.lo, self.hi)

    def segment_lower_bound(self, p0, p1):
        return segment_box_lower_bound(p0, p1, self.lo, self.hi)

    def segment_lower_bound_np(self, p0, p1) -> float:
        return segment_box_lower_bound_np(p0, p1, self.lo, self.hi)

    def point_distance(self, p):
        return point_box_distance(p, self.lo, self.hi)

    def point_distance_np(self, p):
        return point_box_distance_np(p, self.lo, self.hi)

    def nearest_point_distances(self, points):
        """The set-level helper of :class:`ObstacleSet` (one scene's boxes; ``points`` (P, Q, 3)),
        with the values :func:`point_box_distance` gives, bit for bit: the square root is taken
        after the least squared distance over the Q points, not on each (it is monotone and
        correctly rounded, so the two agree), and the squares are summed axis by axis on (N, P, Q)
        arrays, in the order of the kernel's sum, instead of over a minor axis of length 3. The
        points' axis is the minor one, reduced last: with the items' axis minor instead, (P, Q, N),
        the screen of larc_jax.leaf.cascade made step 1's kernel 1.9x as slow as without it on one
        core, against 1.2-1.3x this way (Stage B, a 4,096-interval call; the values are the same bits)."""
        f = 0
        for i in range(3):
            x = points[None, :, :, i]
            gap = jnp.maximum(jnp.maximum(self.lo[:, i, None, None] - x, x - self.hi[:, i, None, None]), 0)
            f = f + gap * gap
        return jnp.where(self.mask[:, None], jnp.sqrt(f.min(axis=2)), jnp.inf).T

    def polytope_lower_bound(self, vertices, part, centre, R, t, iterations: int = GJK_ITERATIONS):
        return polytope_box_lower_bound(vertices, part, centre, R, t, self.lo, self.hi, iterations)

    def polytope_lower_bound_np(self, V, centre, R, t, iterations: int = GJK_ITERATIONS) -> float:
        return polytope_box_lower_bound_np(V, centre, R, t, self.lo, self.hi, iterations)

    def polytope_bounds(self, vertices, part, centre, R, t, iterations: int = GJK_ITERATIONS):
        return polytope_box_bounds(vertices, part, centre, R, t, self.lo, self.hi, iterations)

    def polytope_bounds_np(self, V, centre, R, t, iterations: int = GJK_ITERATIONS) -> tuple[float, float]:
        return polytope_box_bounds_np(V, centre, R, t, self.lo, self.hi, iterations)
