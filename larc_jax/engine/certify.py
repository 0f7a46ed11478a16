"""The certifiers: reference (Algorithm 1), batched LARC, fixed-resolution; and ``certify``.

All of them run the same interval test on exact dyadic intervals
(:func:`larc_jax.engine.batch.dyadic_ends`) with the same per-trajectory rounding bounds
(:func:`larc_jax.leaf.interval.trajectory_rounding`: rebase offset, time and speed slack, the guard of
every capsule and hull part). The test is the capsule test (:mod:`larc_jax.leaf.interval`,
``enclosure="capsules"``: the paper's model) or the cascade (:mod:`larc_jax.leaf.cascade`,
``enclosure="hull"``, the default: the capsule test, then the convex-hull test on the intervals
it leaves open); every scheduler runs the same one, so they take the same decisions; a leaf
passes iff its recorded clearance exceeds its recorded guard:

* ``reference`` — Algorithm 1 of the paper, depth first, one trajectory, NumPy float64
  references of every kernel. Slow; the ground truth for tests.
* ``larc`` — batched in JAX: a level-by-level frontier over all trajectories of a dataset. At
  each depth the frontier intervals of every trajectory are evaluated in one jitted, vmapped
  call; passing intervals become certified leaves; inconclusive ones are bisected into the next
  frontier (or recorded as inconclusive leaves at ``max_depth``). Frontier arrays are padded to
  a few bucket sizes (:mod:`larc_jax.engine.batch`) so a whole dataset compiles a handful of shapes.
  A batch of :data:`~larc_jax.engine.tree_pool.TREE_FROM_TRAJECTORIES` or more (any batch, after
  :func:`~larc_jax.engine.warm_up.warm_up_tree`) that the device tree runs
  (:func:`~larc_jax.engine.tree_pool.uses_tree`) runs as one jitted program instead
  (:mod:`larc_jax.engine.tree`): the same intervals, leaves and decisions; a leaf's clearance may
  differ in its last bits (XLA compiles the kernel inside the loop with its own fusions), far
  inside its guard.
* ``fine`` / ``coarse`` — every one of the ``2**depth`` intervals (depth 9 / 4).
"""

from __future__ import annotations

import dataclasses
import enum
import time
from typing import Callable, Sequence

import numpy as np

from .batch import Batch, dyadic_ends, prepare
from .buckets import MAX_BATCH_TRAJECTORIES
from ..compilation import CompileClock
from ..defaults import DEFAULT_COARSE_DEPTH, DEFAULT_MARGIN_M, DEFAULT_MAX_DEPTH, METHODS
from ..enclosure.capsule import CapsuleModel
from ..enclosure.hull import HullModel
from ..enclosure.meshes import held_joint_states
from ..errors import LarcInputError
from ..io import short_repr
from ..leaf.record import LeafRecord
from ..leaf.reference import LeafEnclosures, leaf_enclosures, leaf_test_np
from ..leaf.interval import geometry_dtype, trajectory_roundings
from ..obstacles import scene_obstacles
from .results import DatasetResult, LeafTable
from .tree_pool import run_tree_pool, uses_tree
from ..model.planes import check_plane_reach
from ..model.robot import Robot
from ..run_spec import RunSpec
from ..model.scene import Scene
from ..leaf.self_collision import SelfPairs, curve_ranges, load_separation, self_pairs
from ..enclosure.tracking import check_tracking_tolerance
from ..model.trajectory import Trajectory, validate_trajectory

__all__ = [
    "Method",
    "certify",
    "run_spec",
    "SPEC_KEYWORDS",
    "SPECULATE_INTERVALS",
    "speculated_levels",
    "DEFAULT_MARGIN_M",
    "DEFAULT_MAX_DEPTH",
    "DEFAULT_COARSE_DEPTH",
]


class _Default:
    """The value of a keyword argument of ``certify`` not given: the RunSpec's default."""

    def __repr__(self) -> str:
        return "<RunSpec default>"


_DEFAULT = _Default()


class Method(str, enum.Enum):
    LARC = "larc"
    FINE = "fine"
    COARSE = "coarse"
    REFERENCE = "reference"


assert tuple(m.value for m in Method) == METHODS


class _Names:
    """Global obstacle-name codes: scene ``s``'s obstacle ``k`` (its boxes, then its shapes) is
    code ``offset[s] + k``."""

    def __init__(self, scenes: Sequence[Scene]):
        unique = list(dict.fromkeys(id(s) for s in scenes))
        first = {u: next(s for s in scenes if id(s) == u) for u in unique}
        offsets, names, start = {}, [], 0
        for u in unique:
            s = first[u]
            offsets[u] = start
            names += list(s.obstacle_names)
            start += s.n_obstacles
        self.box_names = tuple(names)
        self.offset = np.array([offsets[id(s)] for s in scenes], np.int64)
        self.has_boxes = np.array([s.n_obstacles > 0 for s in scenes], bool)

    def part(self, sl: slice) -> "_Names":
        """The codes of the trajectories ``sl`` (same global box names)."""
        out = object.__new__(_Names)
        out.box_names, out.offset, out.has_boxes = self.box_names, self.offset[sl], self.has_boxes[sl]
        return out


def _leaf_table(names: _Names, traj, depth, index, a, b, rec: LeafRecord) -> LeafTable:
    """The leaves ``(traj, depth, index)``, ``[a, b]``, with what the leaf test recorded (:mod:`larc_jax.leaf.record`)."""
    traj = np.asarray(traj, np.int64)
    other = np.asarray(rec.other, np.int64)
    has = names.has_boxes[traj] & (other < 0)
    stage = np.asarray(rec.stage, np.int8)
    return LeafTable(
        traj=traj, depth=np.asarray(depth, np.int16), index=np.asarray(index, np.int64),
        t0=np.asarray(a, np.float64), t1=np.asarray(b, np.float64), clearance_m=np.asarray(rec.clearance_m, np.float64),
        guard_m=np.asarray(rec.guard_m, np.float64), certified=stage > 0, stage=stage,
        capsule=np.where(has | (other >= 0), np.asarray(rec.capsule, np.int64), -1).astype(np.int32),
        box=np.where(has, names.offset[traj] + np.asarray(rec.box, np.int64), -1).astype(np.int32),
        other_capsule=other.astype(np.int32),
    )


SPECULATE_INTERVALS = 256
"""A frontier of fewer intervals is evaluated together with its descendants down as many levels
as fit in this many intervals, in one call (:func:`_larc_batched`). A call has a fixed cost on
the host and in XLA's dispatch whatever its size (measured on PIPER's Stage B scenes, 2 CPU
cores: the all-pairs capsule kernel takes 0.20 ms for 4 intervals, 0.66 ms for 64, 1.77 ms for 256), so
a small frontier (one trajectory certified alone: 1, 2, 4, ... intervals at the first depths)
is cheaper evaluated ahead than a level at a time. The value was chosen by the median time of
24 Stage B trajectories certified one per call: 5.44 / 4.61 / 4.33 / 4.99 ms with capsules and
44.0 / 39.3 / 32.3 / 32.5 ms with the hull cascade for 64 / 128 / 256 / 512."""


def speculated_levels(frontier: int, depth: int, max_depth: int) -> int:
    """Levels below ``depth`` evaluated ahead for a frontier of ``frontier`` intervals: the largest
    ``s`` with ``frontier * (2**(s+1) - 1) <= SPECULATE_INTERVALS`` and ``depth + s <= max_depth``."""
    s = 0
    while depth + s < max_depth and frontier * (2 ** (s + 2) - 1) <= SPECULATE_INTERVALS:
        s += 1
    return s


def _larc_batched(batch: Batch, n_traj: int, names: _Names, max_depth, progress, on_compile=None):
    """The level-by-level frontier. A small frontier is evaluated with its descendants a few
    levels down in one call (:data:`SPECULATE_INTERVALS`); the levels are then walked on the
    host exactly as one call per level would: an interval's test does not depend on what else
    is evaluated with it, so the leaves, decisions and counted evaluations (``frontier``: only
    the intervals the frontier reaches) are those of one call per level."""
    traj = np.arange(n_traj, dtype=np.int64)
    index = np.zeros(n_traj, np.int64)
    frontier = np.zeros((n_traj, max_depth + 1), np.int64)
    parts = []
    d = 0
    while d <= max_depth and len(traj):
        s = speculated_levels(len(traj), d, max_depth)
        # Every descendant of the frontier down to depth d + s, level by level: node m of level j
        # below frontier interval i is at offset base[j] + i * 2**j + m.
        f = len(traj)
        base = np.concatenate([[0], np.cumsum([f << j for j in range(s + 1)])])
        all_traj = np.concatenate([np.repeat(traj, 1 << j) for j in range(s + 1)])
        all_index = np.concatenate([((index << j)[:, None] + np.arange(1 << j)).reshape(-1) for j in range(s + 1)])
        all_depth = np.concatenate([np.full(f << j, d + j) for j in range(s + 1)])
        a_all, b_all, rec_all = batch.evaluate_cascade(all_traj, all_depth, all_index, progress, on_compile,
                                                       may_bisect=all_depth < max_depth)
        pos, sub = np.arange(f), np.zeros(f, np.int64)  # open intervals: frontier position, node below it
        for j in range(s + 1):
            rows = base[j] + (pos << j) + sub
            t, dj, ix = all_traj[rows], d + j, all_index[rows]
            frontier[:, dj] = np.bincount(t, minlength=n_traj)
            rec = rec_all.take(rows)
            passed = rec.stage > 0  # g > guard; NaN never passes (larc_jax.leaf.record)
            final = passed | (dj == max_depth)
            parts.append(_leaf_table(names, t[final], np.full(int(final.sum()), dj), ix[final], a_all[rows][final],
                                     b_all[rows][final], rec.take(final)))
            open_ = ~final
            pos = np.repeat(pos[open_], 2)
            sub = np.stack([2 * sub[open_], 2 * sub[open_] + 1], axis=1).reshape(-1)
        last = base[s] + (pos << s) + (sub >> 1)  # the open intervals of depth d + s (each twice)
        traj = all_traj[last]
        index = 2 * all_index[last] + (sub & 1)
        d += s + 1
    return frontier, LeafTable.concatenate(parts)


def _fixed(batch: Batch, n_traj: int, names: _Names, depth_fixed, max_depth, progress, on_compile=None):
    m = 2**depth_fixed
    traj = np.repeat(np.arange(n_traj, dtype=np.int64), m)
    index = np.tile(np.arange(m, dtype=np.int64), n_traj)
    depth = np.full(len(traj), depth_fixed)
    a, b, rec = batch.evaluate_cascade(traj, depth, index, progress, on_compile)
    frontier = np.zeros((n_traj, max(max_depth, depth_fixed) + 1), np.int64)
    frontier[:, depth_fixed] = m
    return frontier, LeafTable.concatenate([_leaf_table(names, traj, depth, index, a, b, rec)])


def _reference(trajectories, scenes, names: _Names, robot, enc: LeafEnclosures, margin, max_depth, bounds, progress,
               pairs: SelfPairs | None = None, skips=None):
    frontier = np.zeros((len(trajectories), max_depth + 1), np.int64)
    rows, records = [], []  # (traj, depth, index, a, b) and the LeafRecord of each leaf
    for k, (traj, scene, bnd) in enumerate(zip(trajectories, scenes, bounds)):
        ts, te = float(traj.t[0]), float(traj.t[-1])
        obstacles = scene_obstacles(scene)

        def certify_node(d: int, i: int) -> bool:  # Algorithm 1
            a, b = (float(x) for x in dyadic_ends(ts, te, d, i))
            frontier[k, d] += 1
            rec = leaf_test_np(robot, enc, traj, obstacles, a, b, margin, bnd, pairs,
                               None if skips is None else skips[k])
            if progress:
                progress(1)
            passed = bool(rec.stage > 0)
            if passed or d == max_depth:
                rows.append((k, d, i, a, b))
                records.append(rec)
                return passed
            left = certify_node(d + 1, 2 * i)
            right = certify_node(d + 1, 2 * i + 1)
            return left and right

        certify_node(0, 0)
    cols = list(zip(*rows)) if rows else [[]] * 5
    return frontier, LeafTable.concatenate([_leaf_table(names, *cols, LeafRecord.stack(records))])


def _items(value, kind, what: str) -> list:
    """A single ``kind`` or a list/tuple of them, as a list; LarcInputError naming the entry."""
    if isinstance(value, kind):
        return [value]
    if not isinstance(value, (list, tuple)):
        raise LarcInputError(f"certify: {what} must be a {kind.__name__} or a list of them, got {type(value).__name__}")
    for i, item in enumerate(value):
        if not isinstance(item, kind):
            raise LarcInputError(f"certify: {what}[{i}] is a {type(item).__name__}, not a {kind.__name__}")
    return list(value)


SPEC_KEYWORDS = {"method": "method", "margin": "margin_m", "max_depth": "max_depth", "coarse_depth": "coarse_depth",
                 "dtype": "dtype", "enclosure": "enclosure", "padding": "padding_m", "swept": "swept",
                 "tracking_tolerance": "tracking_tolerance", "self_collision": "self_collision",
                 "self_margin": "self_margin_m", "self_skip": "self_skip"}
"""The keyword arguments of :func:`certify` that a :class:`RunSpec` holds, and its field for each."""


def run_spec(spec: RunSpec | None = None, **options) -> RunSpec:
    """``spec``, or the RunSpec that :func:`certify`'s keyword arguments ``options`` give (those
    not given: its defaults); both given: :class:`LarcInputError`."""
    given = {SPEC_KEYWORDS[k]: v for k, v in options.items() if v is not _DEFAULT}
    if spec is not None:
        if not isinstance(spec, RunSpec):
            raise LarcInputError(f"certify: spec must be a RunSpec (larc_jax.RunSpec), got {type(spec).__name__}")
        if given:
            raise LarcInputError(f"certify: give either spec or its keyword arguments, not both "
                                 f"(got spec and {', '.join(sorted(given))})")
        return spec
    method = given.get("method", METHODS[0])
    try:
        given["method"] = Method(method).value
    except (ValueError, TypeError):
        raise LarcInputError(f"certify: unknown method {short_repr(method)} ({', '.join(METHODS)})") from None
    try:
        return RunSpec(**given)
    except LarcInputError as exc:
        raise LarcInputError(f"certify: {exc}") from None


def _model_spec(spec: RunSpec, robot: Robot, capsules: CapsuleModel) -> RunSpec:
    """``spec`` with its model fields (stated joints, active joints, links left out) those of
    ``robot`` and ``capsules``; a spec that states others is refused (it was meant for another model)."""
    hold = tuple(sorted((robot.joint_names[i], float(robot.q_held[i])) for i in range(robot.n_links)
                        if robot.joint_names[i] in robot.stated_joints))
    model = dict(hold=hold, joints=tuple(robot.active_joint_names), ignore_links=tuple(capsules.excluded_links))
    for key, value in model.items():
        stated = getattr(spec, key)
        if stated and (stated != value if key == "joints" else not set(stated) <= set(value)):
            raise LarcInputError(f"certify: spec.{key} {list(stated)} is not the model's {list(value)} (load the "
                                 "robot file with them, or leave the field empty)")
    return dataclasses.replace(spec, **model)


def _check_inputs(trajectories, scenes, robot, capsules, dtype, progress):
    """Everything ``certify`` is given beyond the run spec, checked as the command line checks it."""
    trajectories = _items(trajectories, Trajectory, "trajectories")
    if not trajectories:
        raise LarcInputError("certify: no trajectories given")
    if isinstance(scenes, Scene):
        scenes = [scenes] * len(trajectories)
    scenes = _items(scenes, Scene, "scenes")
    if len(scenes) != len(trajectories):
        raise LarcInputError(f"certify: {len(trajectories)} trajectories but {len(scenes)} scenes")
    if not isinstance(robot, Robot):
        raise LarcInputError(f"certify: robot must be a Robot (larc_jax.load_robot), got {type(robot).__name__}")
    if not isinstance(capsules, CapsuleModel):
        raise LarcInputError(f"certify: capsules must be a CapsuleModel (larc_jax.load_capsules), got "
                             f"{type(capsules).__name__}")
    if (np.shape(capsules.motion_a) != (capsules.n_capsules, robot.n_joints)
            or any(not 0 <= i < robot.n_links or robot.link_names[i] != name
                   for i, name in zip(capsules.link_index, capsules.link_names))):
        raise LarcInputError("certify: the capsule model was built for another robot (load_capsules(path, robot))")
    dtype = geometry_dtype(dtype)
    if progress is not None and not callable(progress):
        raise LarcInputError(f"certify: progress must be a function of the interval count, got {short_repr(progress)}")
    trajectories = [validate_trajectory(t, robot) for t in trajectories]
    root = robot.link_names[0]
    for s in scenes:
        if s.frame and s.frame != root:
            raise LarcInputError(f"{s.source or s.name or 'Scene'}: frame '{s.frame}' is not the robot base frame "
                                 f"'{root}'")
    return trajectories, scenes, dtype


def certify(
    trajectories: Sequence[Trajectory] | Trajectory,
    scenes: Sequence[Scene] | Scene,
    robot: Robot,
    capsules: CapsuleModel,
    *,
    spec: RunSpec | None = None,
    method: Method | str = _DEFAULT,
    margin: float = _DEFAULT,
    max_depth: int = _DEFAULT,
    coarse_depth: int = _DEFAULT,
    dtype=_DEFAULT,
    progress: Callable[[int], None] | None = None,
    devices=None,
    on_compile: Callable[[bool], None] | None = None,
    enclosure: str = _DEFAULT,
    padding: float = _DEFAULT,
    swept: bool = _DEFAULT,
    hulls: HullModel | None = None,
    tracking_tolerance=_DEFAULT,
    self_collision: bool = _DEFAULT,
    self_margin: float = _DEFAULT,
    self_skip=_DEFAULT,
) -> DatasetResult:
    """Certify trajectories against their scenes in one call.

    Args:
      spec: the run's parameters as one :class:`~larc_jax.run_spec.RunSpec` (the result carries it,
        ``result.spec``). The keyword arguments below that it holds (``method`` ... ``self_skip``,
        defaults those of :class:`RunSpec`) are a convenience that builds one; giving both is an error.
      trajectories: one or many (each may have its own waypoint count and duration).
      scenes: one scene for all, or one per trajectory.
      method: ``larc`` (batched adaptive: the device tree, :mod:`larc_jax.engine.tree_pool`, for a
        batch it runs, else the frontier driven from the host; the same decisions), ``fine``
        (all ``2**max_depth`` intervals),
        ``coarse`` (all ``2**coarse_depth``), ``reference`` (Algorithm 1 in NumPy).
      margin: clearance margin rho, m.
      dtype: geometry dtype, float64 (default) or float32: forward kinematics and distances in
        that dtype (times, the curve and the sums stay float64; the guard accounts for it, see
        :mod:`larc_jax.leaf.interval`). ``method="reference"`` is always float64.
      progress: called with the number of intervals evaluated after each chunk (with ``larc``, a
        small frontier's descendants evaluated ahead count too, :data:`SPECULATE_INTERVALS`; the
        result's ``evaluations`` counts only the intervals the frontier reached).
      devices: JAX devices to shard the intervals over (default: all devices of the default
        backend; see :mod:`larc_jax.engine.batch`). Results do not depend on it.
      on_compile: called with ``True`` before a kernel shape new to this process is compiled
        (or loaded from the persistent cache, :mod:`larc_jax.compilation`), ``False`` after.
      enclosure: ``hull`` (default: the cascade of :mod:`larc_jax.leaf.cascade`) or ``capsules``
        (the capsule test alone, the paper's model).
      padding: the padding on every enclosure beyond its proven containment of the meshes, m
        (``RunSpec.padding_m``; default: 1 mm for ``capsules``, 0 for ``hull``): a certified
        trajectory keeps every link mesh more than ``margin + padding`` from every box.
      swept: run the swept stage (:mod:`larc_jax.leaf.swept`; ``RunSpec.swept``, default off) where
        the midpoint tests leave a leaf open: a second-order enclosure of each link's motion.
      hulls: the hull parts for the cascade (default: built from the robot's meshes and the
        robot file's ``hull_parts`` with the run's padding, :func:`~larc_jax.enclosure.hull.hull_model`;
        parts built with another padding are refused).

    The gripper: links below held prismatic joints (fingers) are enclosed over their whole
    stroke unless the robot states their value (``load_robot_file(path, hold={...})``); the
    result says which (``held_joints``).
      tracking_tolerance: joint tracking error delta_j the certificate allows (rad, m for a
        prismatic joint): one number, one per active joint, or a mapping joint name -> number
        (others 0). The certificate then holds for every executed trajectory within delta_j of
        the planned one at every instant (:mod:`larc_jax.enclosure.tracking`); None: the plan only.
      self_collision: also certify that no two links of a checked pair come within
        ``self_margin`` (m, default 0: touching fails) at any time (:mod:`larc_jax.leaf.self_collision`
        says which pairs are checked); a leaf then passes iff both tests pass, and records the
        blocking box or capsule pair. ``self_skip``: link pairs ``"LINK:LINK"`` not to check
        (named in the result).

    Returns a :class:`DatasetResult`; its ``to_dataframe()`` gives one row per trajectory, its
    ``compile_time_s`` the part of ``wall_time_s`` spent compiling. Links that ``capsules``
    excludes (:meth:`CapsuleModel.without_links`) are named in the result. JAX computations run
    with 64-bit types enabled only inside this call (scoped, not global).
    """
    spec = run_spec(spec, method=method, margin=margin, max_depth=max_depth, coarse_depth=coarse_depth, dtype=dtype,
                    enclosure=enclosure, padding=padding, swept=swept, tracking_tolerance=tracking_tolerance,
                    self_collision=self_collision, self_margin=self_margin, self_skip=self_skip)
    method, margin, max_depth, enclosure = Method(spec.method), spec.margin_m, spec.max_depth, spec.enclosure
    trajectories, scenes, dtype = _check_inputs(trajectories, scenes, robot, capsules, spec.dtype, progress)
    spec = _model_spec(spec, robot, capsules)
    capsules = capsules.with_padding(spec.padding_m)  # the run's padding on every enclosure (RunSpec.padding_m)
    if hulls is not None and isinstance(hulls, HullModel) and hulls.padding_m != spec.padding_m:
        raise LarcInputError(f"certify: hulls were built with padding_m {hulls.padding_m!r}, but the run's padding_m "
                             f"is {spec.padding_m!r} (build them with hull_model(robot, parts, padding_m), or leave "
                             "hulls out)")
    delta = check_tracking_tolerance(spec.tolerance_arg(), robot)
    pairs = self_pairs(robot, capsules, spec.self_margin_m, spec.self_skip, proven=load_separation(robot)) \
        if spec.self_collision else None
    check_pairs = pairs if pairs is not None and pairs.n_pairs else None
    skips = None
    if check_pairs is not None:  # pairs proven apart where each trajectory's curve goes
        skips = [check_pairs.skip_mask(*curve_ranges(t, delta)) for t in trajectories]
    enc = leaf_enclosures(robot, capsules, enclosure, delta, hulls, spec.swept)  # radii grown by sum_j a_lj delta_j
    check_plane_reach(scenes, robot, enc.capsules)  # a plane is its square only where the robot cannot go
    planned_capsules, capsules, hulls = capsules, enc.capsules, enc.hulls
    start = time.perf_counter()
    names = _Names(scenes)
    bounds = trajectory_roundings(trajectories, robot, capsules, dtype, hulls)
    with CompileClock() as clock:
        if method == Method.REFERENCE:
            frontier, leaves = _reference(trajectories, scenes, names, robot, enc, margin, max_depth, bounds,
                                          progress, check_pairs, skips)
        else:
            # Trajectories are prepared (padded into device arrays) MAX_BATCH_TRAJECTORIES at a
            # time, so memory does not grow with the dataset; each interval's result does not
            # depend on its batch.
            frontiers, parts = [], []
            for lo in range(0, len(trajectories), MAX_BATCH_TRAJECTORIES):
                sl = slice(lo, lo + MAX_BATCH_TRAJECTORIES)
                part, n_part = names.part(sl), len(trajectories[sl])
                batch = prepare(trajectories[sl], scenes[sl], robot, capsules, margin, dtype, bounds[sl], devices,
                                on_compile, hulls, self_pairs=check_pairs,
                                self_skip=None if skips is None else skips[sl], swept=enc.swept)
                if method == Method.LARC and uses_tree(batch, n_part):  # the whole tree as one device program
                    tree = run_tree_pool(batch, n_part, max_depth, on_compile, progress)
                    f, lv = tree.frontier, _leaf_table(part, tree.traj, tree.depth, tree.index, tree.t0, tree.t1,
                                                       tree.record)  # sorted by trajectory, then time
                elif method == Method.LARC:  # what the tree does not run: the frontier driven from here
                    f, lv = _larc_batched(batch, n_part, part, max_depth, progress, on_compile)
                else:
                    depth = max_depth if method == Method.FINE else spec.coarse_depth
                    f, lv = _fixed(batch, n_part, part, depth, max_depth, progress, on_compile)
                del batch
                frontiers.append(f)
                parts.append(dataclasses.replace(lv, traj=lv.traj + lo))
            frontier = np.concatenate(frontiers)
            leaves = LeafTable.concatenate(parts) if len(parts) > 1 else parts[0]
    wall = time.perf_counter() - start
    result = _dataset_result(method.value, trajectories, scenes, names, planned_capsules, frontier, leaves, bounds,
                             float(margin), max_depth, wall, compile_time_s=min(wall, clock.seconds),
                             dtype=np.dtype(dtype).name)
    result = dataclasses.replace(result, enclosure=enclosure, held_joints=held_joint_states(robot), spec=spec)
    if delta is not None:
        result = dataclasses.replace(result, tracking_tolerance=tuple(
            (name, float(x)) for name, x in zip(robot.active_joint_names, delta)))
    if pairs is not None:
        result = dataclasses.replace(result, self_margin_m=pairs.margin_m, self_skipped=pairs.skipped)
    return result


def _dataset_result(method, trajectories, scenes, names, capsules, frontier, leaves: LeafTable, bounds,
                    margin, max_depth, wall, compile_time_s: float = 0.0, dtype: str = "float64") -> DatasetResult:
    n = len(trajectories)
    bad = np.bincount(leaves.traj, weights=~leaves.certified, minlength=n) > 0
    nan = np.bincount(leaves.traj, weights=np.isnan(leaves.clearance_m), minlength=n) > 0
    g_min = np.full(n, np.inf)
    np.minimum.at(g_min, leaves.traj, np.where(np.isnan(leaves.clearance_m), np.inf, leaves.clearance_m))
    return DatasetResult(
        method=method, ids=tuple(t.id for t in trajectories), scene_names=tuple(s.name for s in scenes),
        certified=~bad, evaluations=frontier.sum(axis=1), frontier=frontier,
        min_clearance_m=np.where(nan, np.nan, g_min), duration_s=np.array([t.duration for t in trajectories]),
        guard_m=np.array([np.max(b.guard_m) for b in bounds], np.float64), leaves=leaves,
        capsule_names=tuple(capsules.names), box_names=names.box_names, margin_m=margin, max_depth=max_depth,
        wall_time_s=wall, time_offset_s=np.array([float(b.offset_s) for b in bounds], np.float64),
        compile_time_s=compile_time_s, excluded_links=capsules.excluded_links, dtype=dtype,
    )
