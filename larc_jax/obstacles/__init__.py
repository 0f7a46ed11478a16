"""Obstacles as a family of pytrees with one-item distance-lower-bound kernels
(:mod:`~larc_jax.obstacles.protocol`): axis-aligned boxes (:mod:`~larc_jax.obstacles.aligned_boxes`),
and posed convex shapes and the convex pieces of meshes and point clouds
(:mod:`~larc_jax.obstacles.convex_shapes`), used for every scene of a batch as soon as one scene
has one. :func:`scene_obstacles` and :func:`stack_scenes` are
the one place that turns scenes into obstacle sets: the schedulers call only these and the
protocol's kernels."""

from __future__ import annotations

from typing import Sequence

from ..model.scene import Scene
from .aligned_boxes import AlignedBoxes
from .convex_shapes import ConvexShapes
from .protocol import ObstacleSet

__all__ = ["ObstacleSet", "AlignedBoxes", "ConvexShapes", "scene_obstacles", "stack_scenes"]


def scene_obstacles(scene) -> ObstacleSet:
    """The obstacle set of one scene (float64, for the NumPy references); an obstacle set is
    returned as it is."""
    if isinstance(scene, ObstacleSet):
        return scene
    return ConvexShapes.from_scene(scene) if scene.posed else AlignedBoxes.from_scene(scene)


def stack_scenes(scenes: Sequence[Scene], dtype, n_items: int | None = None) -> ObstacleSet:
    """Scenes padded to one item count (masked) in the geometry ``dtype``, rounded outwards."""
    kind = ConvexShapes if any(s.posed for s in scenes) else AlignedBoxes
    return kind.stack(scenes, dtype, n_items)
