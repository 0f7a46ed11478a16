"""The certifiers: reference (Algorithm 1), batched LARC, fixed-resolution; and ``certify``.

All of them run the same interval test on exact dyadic intervals
(:func:`larc_jax.batch.dyadic_ends`) and compare ``g(I)`` with the same rounding guard. The test
is the capsule test (:mod:`larc_jax.interval`, ``enclosure="capsules"``: the paper's model) or
the cascade (:mod:`larc_jax.cascade`, ``enclosure="hull"``, the default: the capsule test, then
the convex-hull test on the intervals it leaves open); every scheduler runs the same one, so
they take the same decisions:

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

import dataclasses
import enum
import time
from typing import Callable, Sequence

import numpy as np

from .batch import Batch, dyadic_ends, prepare
from .cascade import Links, cascade_np
from .defaults import (DEFAULT_COARSE_DEPTH, DEFAULT_ENCLOSURE, DEFAULT_MARGIN_M, DEFAULT_MAX_DEPTH, METHODS,
                       check_depth, check_enclosure, check_margin)
from .enclosure.capsule import CapsuleModel
from .enclosure.hull import HullModel, hull_model
from .enclosure.meshes import held_joint_states
from .errors import LarcInputError
from .interval import coordinate_scale, evaluate_interval_np, rounding_guard
from .results import DatasetResult, LeafTable
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


class _Names:
    """Global box-name codes: scene ``s``'s box ``k`` is code ``offset[s] + k``."""

    def __init__(self, scenes: Sequence[Scene]):
        unique = list(dict.fromkeys(id(s) for s in scenes))
        first = {u: next(s for s in scenes if id(s) == u) for u in unique}
        offsets, names, start = {}, [], 0
        for u in unique:
            s = first[u]
            offsets[u] = start
            names += [s.box_names[k] if k < len(s.box_names) else "" for k in range(s.n_boxes)]
            start += s.n_boxes
        self.box_names = tuple(names)
        self.offset = np.array([offsets[id(s)] for s in scenes], np.int64)
        self.has_boxes = np.array([s.n_boxes > 0 for s in scenes], bool)


def _leaf_table(names: _Names, traj, depth, index, a, b, g, cap, box, stage) -> LeafTable:
    traj = np.asarray(traj, np.int64)
    has = names.has_boxes[traj]
    return LeafTable(
        traj=traj, depth=np.asarray(depth, np.int16), index=np.asarray(index, np.int64),
        t0=np.asarray(a, np.float64), t1=np.asarray(b, np.float64), clearance_m=np.asarray(g, np.float64),
        certified=np.asarray(stage, np.int8) > 0, stage=np.asarray(stage, np.int8),
        capsule=np.where(has, np.asarray(cap, np.int64), -1).astype(np.int32),
        box=np.where(has, names.offset[traj] + np.asarray(box, np.int64), -1).astype(np.int32),
    )


def _larc_batched(batch: Batch, n_traj: int, names: _Names, max_depth, progress):
    traj = np.arange(n_traj, dtype=np.int64)
    index = np.zeros(n_traj, np.int64)
    frontier = np.zeros((n_traj, max_depth + 1), np.int64)
    parts = []
    for d in range(max_depth + 1):
        if len(traj) == 0:
            break
        depth = np.full(len(traj), d)
        frontier[:, d] = np.bincount(traj, minlength=n_traj)
        a, b, g, cap, box, stage = batch.evaluate_cascade(traj, depth, index, progress)
        passed = stage > 0  # NaN never passes (larc_jax.cascade)
        final = passed | (d == max_depth)
        parts.append(_leaf_table(names, traj[final], depth[final], index[final], a[final], b[final], g[final],
                                 cap[final], box[final], stage[final]))
        open_ = ~final
        traj = np.repeat(traj[open_], 2)
        index = np.stack([2 * index[open_], 2 * index[open_] + 1], axis=1).reshape(-1)
    return frontier, LeafTable.concatenate(parts)


def _fixed(batch: Batch, n_traj: int, names: _Names, depth_fixed, max_depth, progress):
    m = 2**depth_fixed
    traj = np.repeat(np.arange(n_traj, dtype=np.int64), m)
    index = np.tile(np.arange(m, dtype=np.int64), n_traj)
    depth = np.full(len(traj), depth_fixed)
    a, b, g, cap, box, stage = batch.evaluate_cascade(traj, depth, index, progress)
    frontier = np.zeros((n_traj, max(max_depth, depth_fixed) + 1), np.int64)
    frontier[:, depth_fixed] = m
    return frontier, LeafTable.concatenate([_leaf_table(names, traj, depth, index, a, b, g, cap, box, stage)])


def _reference(trajectories, scenes, names: _Names, robot, capsules, hulls, margin, max_depth, guard, progress):
    frontier = np.zeros((len(trajectories), max_depth + 1), np.int64)
    rows = []  # (traj, depth, index, a, b, g, capsule, box, stage)
    links = Links.of(capsules, hulls) if hulls is not None else None
    for k, (traj, scene) in enumerate(zip(trajectories, scenes)):
        ts, te = float(traj.t[0]), float(traj.t[-1])

        def certify_node(d: int, i: int) -> bool:  # Algorithm 1
            a, b = (float(x) for x in dyadic_ends(ts, te, d, i))
            frontier[k, d] += 1
            if links is None:
                ev = evaluate_interval_np(robot, capsules, traj, scene, a, b, margin)
                g, cap, box, stage = ev.g, ev.capsule, ev.box, int(ev.g > guard)
            else:
                g, cap, box, stage = cascade_np(robot, capsules, hulls, links, traj, scene, a, b, margin, guard)
            if progress:
                progress(1)
            passed = stage > 0
            if passed or d == max_depth:
                rows.append((k, d, i, a, b, g, cap, box, stage))
                return passed
            left = certify_node(d + 1, 2 * i)
            right = certify_node(d + 1, 2 * i + 1)
            return left and right

        certify_node(0, 0)
    cols = list(zip(*rows)) if rows else [[]] * 9
    return frontier, LeafTable.concatenate([_leaf_table(names, *cols)])


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
    devices=None,
    enclosure: str = DEFAULT_ENCLOSURE,
    hulls: HullModel | None = None,
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
      devices: JAX devices to shard the intervals over (default: all devices of the default
        backend; see :mod:`larc_jax.batch`). Results do not depend on it.
      enclosure: ``hull`` (default: the cascade of :mod:`larc_jax.cascade`) or ``capsules``
        (the capsule test alone, the paper's model).
      hulls: the hull parts for the cascade (default: built from the robot's meshes and the
        robot file's ``hull_parts``, :func:`~larc_jax.enclosure.hull.hull_model`).

    The gripper: links below held prismatic joints (fingers) are enclosed over their whole
    stroke unless the robot states their value (``load_robot_file(path, hold={...})``); the
    result says which (``held_joints``).

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
    check_enclosure(enclosure, "certify: enclosure")
    if enclosure == "hull":
        hulls = hulls if hulls is not None else hull_model(robot, capsules.hull_parts, capsules.padding_m)
        Links.of(capsules, hulls)  # the same links, or a clear error
    else:
        hulls = None
    start = time.perf_counter()
    names = _Names(scenes)
    if method == Method.REFERENCE:
        guard = rounding_guard(np.float64, coordinate_scale(scenes, robot, capsules))
        frontier, leaves = _reference(trajectories, scenes, names, robot, capsules, hulls, margin, max_depth,
                                      guard, progress)
    else:
        batch = prepare(trajectories, scenes, robot, capsules, margin, dtype, devices, hulls=hulls)
        guard = batch.guard
        if method == Method.LARC:
            frontier, leaves = _larc_batched(batch, len(trajectories), names, max_depth, progress)
        else:
            depth = max_depth if method == Method.FINE else coarse_depth
            frontier, leaves = _fixed(batch, len(trajectories), names, depth, max_depth, progress)
    wall = time.perf_counter() - start
    result = _dataset_result(method.value, trajectories, scenes, names, capsules, frontier, leaves,
                             np.full(len(trajectories), guard), float(margin), max_depth, wall)
    return dataclasses.replace(result, enclosure=enclosure, held_joints=held_joint_states(robot))


def _dataset_result(method, trajectories, scenes, names, capsules, frontier, leaves: LeafTable, guard,
                    margin, max_depth, wall) -> DatasetResult:
    n = len(trajectories)
    bad = np.bincount(leaves.traj, weights=~leaves.certified, minlength=n) > 0
    nan = np.bincount(leaves.traj, weights=np.isnan(leaves.clearance_m), minlength=n) > 0
    g_min = np.full(n, np.inf)
    np.minimum.at(g_min, leaves.traj, np.where(np.isnan(leaves.clearance_m), np.inf, leaves.clearance_m))
    return DatasetResult(
        method=method, ids=tuple(t.id for t in trajectories), scene_names=tuple(s.name for s in scenes),
        certified=~bad, evaluations=frontier.sum(axis=1), frontier=frontier,
        min_clearance_m=np.where(nan, np.nan, g_min), duration_s=np.array([t.duration for t in trajectories]),
        guard_m=np.asarray(guard, np.float64), leaves=leaves, capsule_names=tuple(capsules.names),
        box_names=names.box_names, margin_m=margin, max_depth=max_depth, wall_time_s=wall,
    )
