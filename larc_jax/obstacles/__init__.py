"""Obstacles as a family of pytrees with one-item distance-lower-bound kernels
(:mod:`~larc_jax.obstacles.protocol`); axis-aligned boxes are the first kind
(:mod:`~larc_jax.obstacles.aligned_boxes`). :func:`scene_obstacles` and :func:`stack_scenes` are
the one place that turns scenes into obstacle sets: the schedulers call only these and the
protocol's kernels."""

from __future__ import annotations

from typing import Sequence

from ..model.scene import Scene
from .aligned_boxes import AlignedBoxes
from .protocol import ObstacleSet

__all__ = ["ObstacleSet", "AlignedBoxes", "scene_obstacles", "stack_scenes"]


def scene_obstacles(scene) -> ObstacleSet:
    """The obstacle set of one scene (float64, for the NumPy references); an obstacle set is
    returned as it is."""
    return scene if isinstance(scene, ObstacleSet) else AlignedBoxes.from_scene(scene)


def stack_scenes(scenes: Sequence[Scene], dtype, n_items: int | None = None) -> ObstacleSet:
    """Scenes padded to one item count (masked) in the geometry ``dtype``, rounded outwards."""
    return AlignedBoxes.stack(scenes, dtype, n_items)
