"""Interval clearance test and the three certifiers (reference, batched LARC, fixed-resolution).

The interval test (paper eqs. 4-7). For ``I = [t_m - h, t_m + h]`` of one trajectory, every
capsule ``l`` is placed at the midpoint configuration ``q(t_m)`` and inflated by the motion
radius ``b_l(I) = h * sum_j a_lj * omega_max_j(I)`` (eq. 6) with exact Hermite speed maxima
(eq. 5). The certificate clearance is::

    g(I) = min_{l, box} dist(segment_l(q(t_m)), box) - (r_l + b_l(I) + rho)

and the interval passes iff ``g(I) > guard`` where ``guard >= 0`` is the rounding guard below.
If it passes, every point of every link stays more than ``rho`` from every box on ``I``
(Theorem 1; see ``../shared/notes/architecture.md`` for the chain of inclusions).

Rounding guard. Every quantity in ``g`` is computed in floating point. ``guard`` is an
absolute bound, in metres, on how far the computed ``g`` can exceed the exact one:
``guard = ulps * eps(dtype) * (1 + scale)`` with ``scale`` the largest coordinate magnitude
involved (box corners and the arm's reach, in metres) and ``ulps`` 256 for float64 and 4096
for float32 (measured errors are far below; see tests/test_certify.py). In float32 mode each
interval's endpoints are also rounded *outwards* so that the float32 intervals still cover the
float64 horizon. NaN or infinite intermediate values always fail the test.

Certifiers (all through the same kernel, :func:`interval_clearance`):

* ``reference`` — Algorithm 1 of the paper, depth first, one trajectory, NumPy float64
  references of every kernel. Slow; the ground truth for tests.
* ``larc`` — batched in JAX: a level-by-level frontier over all trajectories of a dataset. At
  each depth the frontier intervals of every trajectory are evaluated in one jitted, vmapped
  call; passing intervals become certified leaves; inconclusive ones are bisected into the next
  frontier (or recorded as inconclusive leaves at ``max_depth``). Frontier arrays are padded to
  a few bucket sizes so a whole dataset compiles a handful of shapes.
* ``fine`` / ``coarse`` — every one of the ``2**depth`` intervals (depth 9 / 4).
"""

from __future__ import annotations

import dataclasses
import enum
import math
import time
from typing import Callable, Iterable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from .capsules import CapsuleModel, capsule_segments, capsule_segments_np
from .errors import LarcInputError
from .geometry import segment_box_distance, segment_box_distance_np
from .hermite import HermiteSpline, evaluate, evaluate_np, pad_waypoints, speed_max, speed_max_np
from .robot import JointType, Robot
from .scene import Scene, pad_scenes
from .trajectory import Trajectory, validate_trajectory

__all__ = [
    "Method",
    "Leaf",
    "TrajectoryResult",
    "DatasetResult",
    "certify",
    "interval_clearance",
    "interval_clearance_np",
    "rounding_guard",
    "DEFAULT_MARGIN_M",
    "DEFAULT_MAX_DEPTH",
    "DEFAULT_COARSE_DEPTH",
]

DEFAULT_MARGIN_M = 0.01
DEFAULT_MAX_DEPTH = 9
DEFAULT_COARSE_DEPTH = 4
GUARD_ULPS = {np.dtype(np.float64): 256, np.dtype(np.float32): 4096}
BUCKETS = tuple(2**k for k in range(2, 13))
"""Frontier arrays are padded to the next of these sizes, 4 .. 4096 (at most 2x waste, 11
compiled shapes); larger frontiers run in 4096-chunks. Small buckets matter when trajectories
are certified one at a time: a call costs ~0.1 ms plus ~10 us per padded interval on a CPU core,
so a 3-interval frontier padded to 64 would cost 5x what it needs."""


def _size_class(n: int, minimum: int) -> int:
    """Next power of two >= max(n, minimum): array sizes that vary between calls (waypoints,
    trajectories, scenes) are rounded up to these so a process compiles a few shapes, not one
    per distinct size (each compiled CPU executable also holds ~100 memory mappings)."""
    return 1 << (max(int(n), int(minimum)) - 1).bit_length()


class Method(str, enum.Enum):
    LARC = "larc"
    FINE = "fine"
    COARSE = "coarse"
    REFERENCE = "reference"


def rounding_guard(dtype, scale: float) -> float:
    """Absolute bound (m) on the rounding error of a computed clearance ``g`` (module doc)."""
    dtype = np.dtype(dtype)
    if dtype not in GUARD_ULPS:
        raise LarcInputError(f"dtype {dtype} is not supported (float64 or float32)")
    return float(GUARD_ULPS[dtype] * np.finfo(dtype).eps * (1.0 + scale))


# ----------------------------------------------------------------------------------------------
# The interval test: JAX kernel for one interval, NumPy float64 reference
# ----------------------------------------------------------------------------------------------


def interval_clearance(robot: Robot, capsules: CapsuleModel, spline: HermiteSpline,
                       box_lo: jax.Array, box_hi: jax.Array, box_mask: jax.Array,
                       a: jax.Array, b: jax.Array, margin: jax.Array):
    """Certificate clearance of one interval ``[a, b]`` of one trajectory (paper eq. 4).

    Args:
      spline: one trajectory's Hermite curve.
      box_lo, box_hi: (B, 3) obstacle boxes, m; box_mask: (B,) which boxes are real.
      a, b: interval ends, s (``a <= b``); margin: rho, m.

    Returns:
      ``(g, capsule, box)``: g in metres (``+inf`` without boxes, NaN on non-finite input),
      and the capsule and box indices attaining the minimum.
    """
    t_mid = 0.5 * (a + b)
    h = 0.5 * (b - a)
    q_mid, _ = evaluate(spline, t_mid)
    omega_max = speed_max(spline, a, b)  # eq. 5
    motion_b = h * (capsules.motion_a @ omega_max)  # eq. 6
    p_world_a, p_world_b = capsule_segments(robot, capsules, q_mid)
    per_box = jax.vmap(segment_box_distance, in_axes=(None, None, 0, 0))
    dist = jax.vmap(per_box, in_axes=(0, 0, None, None))(p_world_a, p_world_b, box_lo, box_hi)
    g_cb = dist - (capsules.radius + motion_b + margin)[:, None]  # eq. 7
    g_cb = jnp.where(box_mask[None, :], g_cb, jnp.inf)
    flat = jnp.argmin(g_cb)
    g = jnp.min(g_cb)
    finite = (
        jnp.isfinite(q_mid).all() & jnp.isfinite(omega_max).all() & jnp.isfinite(motion_b).all()
        & jnp.isfinite(p_world_a).all() & jnp.isfinite(p_world_b).all()
    )
    g = jnp.where(finite, g, jnp.nan)  # NaN never certifies
    n_boxes = box_lo.shape[0]
    return g, flat // n_boxes, flat % n_boxes


def interval_clearance_np(robot: Robot, capsules: CapsuleModel, traj: Trajectory, scene: Scene,
                          a: float, b: float, margin: float):
    """NumPy float64 reference of :func:`interval_clearance` (same return values)."""
    t_mid = 0.5 * (a + b)
    h = 0.5 * (b - a)
    q_mid, _ = evaluate_np(traj.t, traj.q, traj.qd, t_mid)
    omega_max = speed_max_np(traj.t, traj.q, traj.qd, a, b)
    motion_b = h * (np.asarray(capsules.motion_a, np.float64) @ omega_max)
    p_a, p_b = capsule_segments_np(robot, capsules, q_mid)
    finite = all(np.isfinite(x).all() for x in (q_mid, omega_max, motion_b, p_a, p_b))
    if scene.n_boxes == 0:
        return (math.inf if finite else math.nan), 0, 0
    g_best, best = math.inf, (0, 0)
    radius = np.asarray(capsules.radius, np.float64)
    for c in range(capsules.n_capsules):
        for k in range(scene.n_boxes):
            g = segment_box_distance_np(p_a[c], p_b[c], scene.lo[k], scene.hi[k]) - (
                radius[c] + motion_b[c] + margin
            )
            if g < g_best or (math.isnan(g) and not math.isnan(g_best)):
                g_best, best = g, (c, k)
    return (g_best if finite else math.nan), best[0], best[1]


# ----------------------------------------------------------------------------------------------
# Results
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Leaf:
    """A terminal interval of the certificate tree."""

    depth: int
    index: int
    """Position among the ``2**depth`` intervals of that depth."""
    t0: float
    t1: float
    clearance_m: float
    """g(I), m (inf without boxes, nan on non-finite values)."""
    certified: bool
    capsule: str
    box: str


@dataclasses.dataclass(frozen=True)
class TrajectoryResult:
    id: str
    method: str
    certified: bool
    evaluations: int
    frontier_sizes: tuple[int, ...]
    """Intervals evaluated at each depth 0..max_depth."""
    min_clearance_m: float
    """Smallest g(I) over the leaves, m (> 0 iff certified, up to the rounding guard)."""
    leaves: tuple[Leaf, ...]
    duration_s: float
    scene: str = ""

    @property
    def first_inconclusive(self) -> Leaf | None:
        bad = [leaf for leaf in self.leaves if not leaf.certified]
        return min(bad, key=lambda leaf: leaf.t0) if bad else None


@dataclasses.dataclass(frozen=True)
class DatasetResult:
    method: str
    trajectories: tuple[TrajectoryResult, ...]
    frontier_sizes: tuple[int, ...]
    """Dataset frontier size per depth (sum over trajectories)."""
    margin_m: float
    max_depth: int
    wall_time_s: float

    def __iter__(self):
        return iter(self.trajectories)

    def __len__(self) -> int:
        return len(self.trajectories)

    def __getitem__(self, i) -> TrajectoryResult:
        return self.trajectories[i]

    def to_dataframe(self):
        """One row per trajectory (pandas)."""
        import pandas as pd

        rows = []
        for r in self.trajectories:
            bad = r.first_inconclusive
            rows.append(dict(
                id=r.id, scene=r.scene, method=r.method, certified=r.certified,
                evaluations=r.evaluations, min_clearance_m=r.min_clearance_m,
                duration_s=r.duration_s,
                blocked_t0=bad.t0 if bad else np.nan, blocked_t1=bad.t1 if bad else np.nan,
                blocked_capsule=bad.capsule if bad else "", blocked_box=bad.box if bad else "",
            ))
        return pd.DataFrame(rows)

    def leaves_dataframe(self):
        """Every leaf of every trajectory (pandas)."""
        import pandas as pd

        rows = [dict(id=r.id, **dataclasses.asdict(leaf)) for r in self.trajectories for leaf in r.leaves]
        cols = ["id", "depth", "index", "t0", "t1", "clearance_m", "certified", "capsule", "box"]
        return pd.DataFrame(rows, columns=cols)


# ----------------------------------------------------------------------------------------------
# Batched evaluation
# ----------------------------------------------------------------------------------------------


@jax.jit
def _evaluate_intervals(robot, capsules, splines, box_lo, box_hi, box_mask, traj, scene, a, b, margin):
    """Evaluate F intervals: interval i belongs to trajectory ``traj[i]`` in scene ``scene[i]``."""

    def one(k, s, ai, bi):
        spline = jax.tree.map(lambda x: x[k], splines)
        return interval_clearance(robot, capsules, spline, box_lo[s], box_hi[s], box_mask[s], ai, bi, margin)

    return jax.vmap(one)(traj, scene, a, b)


_build_splines = jax.jit(jax.vmap(HermiteSpline.from_waypoints))


def _cast(tree, dtype):
    return jax.tree.map(
        lambda x: np.asarray(x, dtype) if np.issubdtype(np.asarray(x).dtype, np.floating) else x, tree
    )


@dataclasses.dataclass
class _Batch:
    """Host-side padded dataset ready for the kernel."""

    robot: Robot
    capsules: CapsuleModel
    splines: HermiteSpline
    box_lo: np.ndarray
    box_hi: np.ndarray
    box_mask: np.ndarray
    scene_of: np.ndarray
    t_start: np.ndarray
    t_end: np.ndarray
    margin: np.ndarray
    dtype: np.dtype
    guard: float

    def endpoints(self, traj: np.ndarray, depth: np.ndarray, index: np.ndarray):
        """Interval ends from (trajectory, depth, index); exact dyadic fractions of the horizon.

        Neighbours compute their shared end from the same fraction, so the cover has no gaps;
        the horizon ends are taken verbatim.
        """
        n = np.ldexp(1.0, depth)
        f0, f1 = index / n, (index + 1) / n
        ts, te = self.t_start[traj], self.t_end[traj]
        a = np.where(f0 == 0.0, ts, ts + (te - ts) * f0)
        b = np.where(f1 == 1.0, te, ts + (te - ts) * f1)
        return a, b

    def evaluate(self, traj, depth, index, on_chunk: Callable[[int], None] | None = None):
        a, b = self.endpoints(traj, depth, index)
        if self.dtype == np.float32:  # round outwards so float32 intervals still cover I
            a = np.nextafter(a.astype(np.float32), np.float32(-np.inf))
            b = np.nextafter(b.astype(np.float32), np.float32(np.inf))
        F = len(traj)
        g = np.empty(F)
        cap = np.empty(F, np.int64)
        box = np.empty(F, np.int64)
        for start in range(0, F, BUCKETS[-1]):
            stop = min(F, start + BUCKETS[-1])
            size = next(s for s in BUCKETS if s >= stop - start)
            pad = size - (stop - start)
            sl = slice(start, stop)
            # Padding repeats the chunk's first interval; its results are dropped below.
            tr = np.concatenate([traj[sl], np.repeat(traj[start], pad)])
            aa = np.concatenate([a[sl], np.repeat(a[start], pad)]).astype(self.dtype)
            bb = np.concatenate([b[sl], np.repeat(b[start], pad)]).astype(self.dtype)
            with jax.enable_x64(self.dtype == np.float64):
                out = _evaluate_intervals(
                    self.robot, self.capsules, self.splines, self.box_lo, self.box_hi,
                    self.box_mask, tr, self.scene_of[tr], aa, bb, self.margin,
                )
                gg, cc, bx = (np.asarray(x) for x in out)
            g[sl], cap[sl], box[sl] = gg[: stop - start], cc[: stop - start], bx[: stop - start]
            if on_chunk:
                on_chunk(stop - start)
        return a, b, g, cap, box


def _scene_scale(scenes: Sequence[Scene], robot: Robot, capsules: CapsuleModel) -> float:
    """Bound on every coordinate magnitude (m) in the clearance: box corners, and any capsule
    point (sum of joint-origin offsets, held/active prismatic travel, farthest capsule point)."""
    corners = [np.abs(s.lo).max() for s in scenes if s.n_boxes] + [np.abs(s.hi).max() for s in scenes if s.n_boxes]
    offsets = float(np.linalg.norm(np.asarray(robot.T_parent_joint)[:, :3, 3], axis=1).sum())
    travel = float(np.abs(np.asarray(robot.q_held)).sum())
    for k, jtype in zip(robot.q_index, robot.joint_type):
        if k >= 0 and jtype == JointType.PRISMATIC:
            travel += max(abs(float(robot.q_lower[k])), abs(float(robot.q_upper[k])))
    ends = np.concatenate([np.asarray(capsules.p_link_a), np.asarray(capsules.p_link_b)])
    far = float(np.linalg.norm(ends, axis=1).max() + np.asarray(capsules.radius).max())
    return max(float(max(corners, default=0.0)), offsets + travel + far)


def _prepare(trajectories, scenes, robot, capsules, margin, dtype) -> _Batch:
    dtype = np.dtype(dtype)
    # Shapes are rounded up to size classes (see _size_class); padded knots lie after t_K and
    # are never touched by an interval inside the horizon (hermite.pad_waypoints), padded
    # trajectories and scenes repeat the first one and are never indexed by an interval.
    n_knots = _size_class(max(t.n_waypoints for t in trajectories), 16)
    padded = [pad_waypoints(t.t, t.q, t.qd, n_knots) for t in trajectories]
    padded += padded[:1] * (_size_class(len(padded), 1) - len(padded))
    unique = list(dict.fromkeys(id(s) for s in scenes))
    scene_list = [next(s for s in scenes if id(s) == u) for u in unique]
    scene_of = np.array([unique.index(id(s)) for s in scenes], np.int64)
    lo, hi, mask = pad_scenes(scene_list + scene_list[:1] * (_size_class(len(scene_list), 1) - len(scene_list)))
    with jax.enable_x64(dtype == np.float64):
        splines = _build_splines(
            np.stack([p[0] for p in padded]).astype(dtype),
            np.stack([p[1] for p in padded]).astype(dtype),
            np.stack([p[2] for p in padded]).astype(dtype),
        )
    return _Batch(
        robot=_cast(robot, dtype), capsules=_cast(capsules, dtype), splines=splines,
        box_lo=lo.astype(dtype), box_hi=hi.astype(dtype), box_mask=mask, scene_of=scene_of,
        t_start=np.array([t.t[0] for t in trajectories]), t_end=np.array([t.t[-1] for t in trajectories]),
        margin=np.asarray(margin, dtype), dtype=dtype,
        guard=rounding_guard(dtype, _scene_scale(scene_list, robot, capsules)),
    )


def _leaf_records(capsules, scenes, traj, depth, index, a, b, g, cap, box, passed):
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


def _larc_batched(batch: _Batch, trajectories, scenes, capsules, max_depth, progress):
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
        for k, leaf in _leaf_records(capsules, scenes, traj[final], depth[final], index[final],
                                     a[final], b[final], g[final], cap[final], box[final], passed[final]):
            leaves[k].append(leaf)
        open_ = ~final
        traj = np.repeat(traj[open_], 2)
        index = np.stack([2 * index[open_], 2 * index[open_] + 1], axis=1).reshape(-1)
    return frontier, leaves


def _fixed(batch: _Batch, trajectories, scenes, capsules, depth_fixed, max_depth, progress):
    N = len(trajectories)
    m = 2**depth_fixed
    traj = np.repeat(np.arange(N, dtype=np.int64), m)
    index = np.tile(np.arange(m, dtype=np.int64), N)
    depth = np.full(len(traj), depth_fixed)
    a, b, g, cap, box = batch.evaluate(traj, depth, index, progress)
    passed = g > batch.guard
    leaves: list[list[Leaf]] = [[] for _ in range(N)]
    for k, leaf in _leaf_records(capsules, scenes, traj, depth, index, a, b, g, cap, box, passed):
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

        def ends(d, i):
            f0, f1 = i / 2.0**d, (i + 1) / 2.0**d
            return (ts if f0 == 0 else ts + (te - ts) * f0), (te if f1 == 1 else ts + (te - ts) * f1)

        def certify_node(d: int, i: int) -> bool:  # Algorithm 1
            a, b = ends(d, i)
            frontier[k, d] += 1
            g, c, bx = interval_clearance_np(robot, capsules, traj, scene, a, b, margin)
            if progress:
                progress(1)
            passed = g > guard
            if passed or d == max_depth:
                leaves.append(Leaf(d, i, a, b, float(g), bool(passed),
                                   capsules.names[c] if scene.n_boxes else "",
                                   scene.box_names[bx] if scene.n_boxes and scene.box_names else ""))
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
    if not (isinstance(margin, (int, float)) and math.isfinite(margin) and margin > 0):
        raise LarcInputError(f"certify: margin must be a finite number > 0 m (paper eq. 3), got {margin!r}")
    for name, depth in (("max_depth", max_depth), ("coarse_depth", coarse_depth)):
        if not isinstance(depth, int) or not 0 <= depth <= 20:
            raise LarcInputError(f"certify: {name} must be an integer in 0..20, got {depth!r}")
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
      dtype: float64 (default) or float32 (with the float32 rounding guard; see module doc).
      progress: called with the number of intervals evaluated after each chunk.

    Returns a :class:`DatasetResult`; its ``to_dataframe()`` gives one row per trajectory.
    JAX computations run with 64-bit types enabled only inside this call (scoped, not global).
    """
    if isinstance(trajectories, Trajectory):
        trajectories = [trajectories]
    try:
        method = Method(method)
    except ValueError:
        raise LarcInputError(f"certify: unknown method {method!r} (larc, fine, coarse, reference)") from None
    trajectories, scenes = _check_inputs(trajectories, scenes, robot, capsules, margin, max_depth, coarse_depth)
    start = time.perf_counter()
    if method == Method.REFERENCE:
        guard = rounding_guard(np.float64, _scene_scale(scenes, robot, capsules))
        frontier, leaves = _reference(trajectories, scenes, robot, capsules, margin, max_depth, guard, progress)
    else:
        batch = _prepare(trajectories, scenes, robot, capsules, margin, dtype)
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
        ))
    return DatasetResult(
        method=method.value, trajectories=tuple(results),
        frontier_sizes=tuple(int(x) for x in frontier.sum(axis=0)),
        margin_m=float(margin), max_depth=max_depth, wall_time_s=wall,
    )
