"""The certifiers: reference (Algorithm 1), batched LARC, fixed-resolution; and ``certify``.

All of them run the same interval test (:mod:`larc_jax.interval`) on exact dyadic intervals
(:func:`larc_jax.batch.dyadic_ends`) and compare ``g(I)`` with the same rounding guard:

* ``reference`` — Algorithm 1 of the paper, depth first, one trajectory, NumPy float64
  references of every kernel. Slow; the ground truth for tests.
* ``larc`` — batched in JAX: a level-by-level frontier over all trajectories of a dataset. At
  each depth the frontier intervals of every trajectory are evaluated in one jitted, vmapped
  call; passing intervals become certified leaves; inconclusive ones are bisected into the next
  frontier (or recorded as inconclusive leaves at ``max_depth``). Frontier arrays are padded to
  a few bucket sizes (:mod:`larc_jax.batch`) so a whole dataset compiles a handful of shapes.
* ``fine`` / ``coarse`` — every one of the ``2**depth`` intervals (depth 9 / 4).
"""

from __future__ import annotations

import enum
import time
from typing import Callable, Sequence

import numpy as np

from .batch import Batch, dyadic_ends, prepare
from .defaults import (DEFAULT_COARSE_DEPTH, DEFAULT_MARGIN_M, DEFAULT_MAX_DEPTH, METHODS, check_depth,
                       check_margin)
from .enclosure.capsule import CapsuleModel
from .errors import LarcInputError
from .interval import coordinate_scale, evaluate_interval_np, rounding_guard
from .results import DatasetResult, Leaf, TrajectoryResult
from .robot import Robot
from .scene import Scene
from .trajectory import Trajectory, validate_trajectory

__all__ = [
    "Method",
    "certify",
    "DEFAULT_MARGIN_M",
    "DEFAULT_MAX_DEPTH",
    "DEFAULT_COARSE_DEPTH",
]


class Method(str, enum.Enum):
    LARC = "larc"
    FINE = "fine"
    COARSE = "coarse"
    REFERENCE = "reference"


assert tuple(m.value for m in Method) == METHODS


def _leaves(capsules, scenes, traj, depth, index, a, b, g, cap, box, passed):
    """``(trajectory, Leaf)`` for each terminal interval (arrays of equal length)."""
    out = []
    for i in range(len(traj)):
        s = scenes[traj[i]]
        out.append((int(traj[i]), Leaf(
            depth=int(depth[i]), index=int(index[i]), t0=float(a[i]), t1=float(b[i]),
            clearance_m=float(g[i]), certified=bool(passed[i]),
            capsule=capsules.names[int(cap[i])] if s.n_boxes else "",
            box=s.box_names[int(box[i])] if s.n_boxes and s.box_names else "",
        )))
    return out


def _larc_batched(batch: Batch, trajectories, scenes, capsules, max_depth, progress):
    N = len(trajectories)
    traj = np.arange(N, dtype=np.int64)
    index = np.zeros(N, np.int64)
    frontier = np.zeros((N, max_depth + 1), np.int64)
    leaves: list[list[Leaf]] = [[] for _ in range(N)]
    for d in range(max_depth + 1):
        if len(traj) == 0:
            break
        depth = np.full(len(traj), d)
        frontier[:, d] = np.bincount(traj, minlength=N)
        a, b, g, cap, box = batch.evaluate(traj, depth, index, progress)
        passed = g > batch.guard  # NaN compares False: never certifies
        final = passed | (d == max_depth)
        for k, leaf in _leaves(capsules, scenes, traj[final], depth[final], index[final],
                               a[final], b[final], g[final], cap[final], box[final], passed[final]):
            leaves[k].append(leaf)
        open_ = ~final
        traj = np.repeat(traj[open_], 2)
        index = np.stack([2 * index[open_], 2 * index[open_] + 1], axis=1).reshape(-1)
    return frontier, leaves


def _fixed(batch: Batch, trajectories, scenes, capsules, depth_fixed, max_depth, progress):
    N = len(trajectories)
    m = 2**depth_fixed
    traj = np.repeat(np.arange(N, dtype=np.int64), m)
    index = np.tile(np.arange(m, dtype=np.int64), N)
    depth = np.full(len(traj), depth_fixed)
    a, b, g, cap, box = batch.evaluate(traj, depth, index, progress)
    passed = g > batch.guard
    leaves: list[list[Leaf]] = [[] for _ in range(N)]
    for k, leaf in _leaves(capsules, scenes, traj, depth, index, a, b, g, cap, box, passed):
        leaves[k].append(leaf)
    frontier = np.zeros((N, max(max_depth, depth_fixed) + 1), np.int64)
    frontier[:, depth_fixed] = m
    return frontier, leaves


def _reference(trajectories, scenes, robot, capsules, margin, max_depth, guard, progress):
    frontier = np.zeros((len(trajectories), max_depth + 1), np.int64)
    all_leaves = []
    for k, (traj, scene) in enumerate(zip(trajectories, scenes)):
        leaves: list[Leaf] = []
        ts, te = float(traj.t[0]), float(traj.t[-1])

        def certify_node(d: int, i: int) -> bool:  # Algorithm 1
            a, b = (float(x) for x in dyadic_ends(ts, te, d, i))
            frontier[k, d] += 1
            ev = evaluate_interval_np(robot, capsules, traj, scene, a, b, margin)
            if progress:
                progress(1)
            passed = ev.g > guard
            if passed or d == max_depth:
                leaves.extend(leaf for _, leaf in _leaves(
                    capsules, [scene], [0], [d], [i], [a], [b], [ev.g], [ev.capsule], [ev.box], [passed]))
                return bool(passed)
            left = certify_node(d + 1, 2 * i)
            right = certify_node(d + 1, 2 * i + 1)
            return left and right

        certify_node(0, 0)
        all_leaves.append(leaves)
    return frontier, all_leaves


def _check_inputs(trajectories, scenes, robot, capsules, margin, max_depth, coarse_depth):
    if not trajectories:
        raise LarcInputError("certify: no trajectories given")
    if isinstance(scenes, Scene):
        scenes = [scenes] * len(trajectories)
    scenes = list(scenes)
    if len(scenes) != len(trajectories):
        raise LarcInputError(f"certify: {len(trajectories)} trajectories but {len(scenes)} scenes")
    check_margin(margin, "certify: margin")
    check_depth(max_depth, "certify: max_depth")
    check_depth(coarse_depth, "certify: coarse_depth")
    trajectories = [validate_trajectory(t, robot) for t in trajectories]
    for s in scenes:
        if not (np.isfinite(s.lo).all() and np.isfinite(s.hi).all()) or (s.lo > s.hi).any():
            raise LarcInputError(f"{s.source or s.name or '<scene>'}: boxes must be finite with min <= max")
    if capsules.motion_a.shape[1] != robot.n_joints:
        raise LarcInputError("certify: capsule model was built for another robot (joint count differs)")
    return trajectories, scenes


def certify(
    trajectories: Sequence[Trajectory] | Trajectory,
    scenes: Sequence[Scene] | Scene,
    robot: Robot,
    capsules: CapsuleModel,
    *,
    method: Method | str = Method.LARC,
    margin: float = DEFAULT_MARGIN_M,
    max_depth: int = DEFAULT_MAX_DEPTH,
    coarse_depth: int = DEFAULT_COARSE_DEPTH,
    dtype=np.float64,
    progress: Callable[[int], None] | None = None,
) -> DatasetResult:
    """Certify trajectories against their scenes in one call.

    Args:
      trajectories: one or many (each may have its own waypoint count and duration).
      scenes: one scene for all, or one per trajectory.
      method: ``larc`` (batched adaptive), ``fine`` (all ``2**max_depth`` intervals),
        ``coarse`` (all ``2**coarse_depth``), ``reference`` (Algorithm 1 in NumPy).
      margin: clearance margin rho, m.
      dtype: float64 (default) or float32 (with the float32 rounding guard; see
        :mod:`larc_jax.interval`).
      progress: called with the number of intervals evaluated after each chunk.

    Returns a :class:`DatasetResult`; its ``to_dataframe()`` gives one row per trajectory.
    JAX computations run with 64-bit types enabled only inside this call (scoped, not global).
    """
    if isinstance(trajectories, Trajectory):
        trajectories = [trajectories]
    try:
        method = Method(method)
    except ValueError:
        raise LarcInputError(f"certify: unknown method {method!r} ({', '.join(METHODS)})") from None
    trajectories, scenes = _check_inputs(trajectories, scenes, robot, capsules, margin, max_depth, coarse_depth)
    start = time.perf_counter()
    if method == Method.REFERENCE:
        guard = rounding_guard(np.float64, coordinate_scale(scenes, robot, capsules))
        frontier, leaves = _reference(trajectories, scenes, robot, capsules, margin, max_depth, guard, progress)
    else:
        batch = prepare(trajectories, scenes, robot, capsules, margin, dtype)
        guard = batch.guard
        if method == Method.LARC:
            frontier, leaves = _larc_batched(batch, trajectories, scenes, capsules, max_depth, progress)
        else:
            depth = max_depth if method == Method.FINE else coarse_depth
            frontier, leaves = _fixed(batch, trajectories, scenes, capsules, depth, max_depth, progress)
    wall = time.perf_counter() - start
    results = []
    for k, traj in enumerate(trajectories):
        lv = tuple(sorted(leaves[k], key=lambda leaf: leaf.t0))
        g = np.array([leaf.clearance_m for leaf in lv])
        results.append(TrajectoryResult(
            id=traj.id, method=method.value,
            certified=bool(all(leaf.certified for leaf in lv)),
            evaluations=int(frontier[k].sum()), frontier_sizes=tuple(int(x) for x in frontier[k]),
            min_clearance_m=float(np.nan if np.isnan(g).any() else g.min()),
            leaves=lv, duration_s=traj.duration, scene=scenes[k].name,
            margin_m=float(margin), max_depth=max_depth, guard_m=float(guard),
        ))
    return DatasetResult(
        method=method.value, trajectories=tuple(results),
        frontier_sizes=tuple(int(x) for x in frontier.sum(axis=0)),
        margin_m=float(margin), max_depth=max_depth, wall_time_s=wall,
    )
