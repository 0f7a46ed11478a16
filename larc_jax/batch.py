"""Host-side batching for the JAX certifiers: padded arrays, size classes, bucketed calls.

A dataset of trajectories (each with its own waypoint count, duration and scene) becomes one
:class:`Batch`: splines padded to a common knot count, scenes padded to a common box count
(masked), per-trajectory horizons. :meth:`Batch.evaluate` runs the interval test on any list
of (trajectory, depth, index) intervals in jitted, vmapped calls whose sizes are padded to a
few buckets, so a process compiles a handful of shapes rather than one per frontier size.

Several devices. With more than one device (all GPUs of a machine, or CPU devices forced with
``XLA_FLAGS=--xla_force_host_platform_device_count=N``) each batch of intervals is sharded
along the interval axis over a 1-D mesh (``jax.sharding``); every interval is still evaluated
by the same kernel on one device, so results are identical to a single-device run.

Interval ends are exact dyadic fractions of the horizon (:func:`dyadic_ends`), shared by every
certifier: neighbours compute their common end from the same fraction, so a cover has no gaps.
They are computed in each trajectory's own time axis (what a leaf reports) and handed to the
kernel rebased with outward rounding (:func:`~larc_jax.interval.rebase_ends`, budget T1).
Geometry arrays are cast to the geometry dtype (boxes rounded outwards); times, splines and the
per-trajectory rounding bounds are float64.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from .compilation import cached_kernel_call
from .enclosure.capsule import CapsuleModel
from .hermite import HermiteSpline, SplineRow, pad_waypoints
from .interval import RoundingBounds, evaluate_interval, rebase_ends
from .robot import Robot
from .scene import Scene, pad_scenes
from .self_collision import SelfPairs, self_clearance

__all__ = ["Batch", "prepare", "dyadic_ends", "size_class", "BUCKETS"]

BUCKETS = tuple(2**k for k in range(2, 13))
"""Frontier arrays are padded to the next of these sizes, 4 .. 4096 (at most 2x waste, 11
compiled shapes); larger frontiers run in 4096-chunks. Small buckets matter when trajectories
are certified one at a time: a call costs ~0.1 ms plus ~10 us per padded interval on a CPU core,
so a 3-interval frontier padded to 64 would cost 5x what it needs."""


def size_class(n: int, minimum: int) -> int:
    """Next power of two >= max(n, minimum): array sizes that vary between calls (waypoints,
    trajectories, scenes) are rounded up to these so a process compiles a few shapes, not one
    per distinct size (each compiled CPU executable also holds ~100 memory mappings)."""
    return 1 << (max(int(n), int(minimum)) - 1).bit_length()


def dyadic_ends(t_start, t_end, depth, index):
    """Ends of interval ``index`` of the ``2**depth`` equal parts of ``[t_start, t_end]``
    (NumPy, elementwise). The fractions are exact; the horizon ends are taken verbatim."""
    n = np.ldexp(1.0, depth)
    f0, f1 = index / n, (index + 1) / n
    a = np.where(f0 == 0.0, t_start, t_start + (t_end - t_start) * f0)
    b = np.where(f1 == 1.0, t_end, t_start + (t_end - t_start) * f1)
    return a, b


_SEEN: set = set()
"""Call signatures (function, shapes, dtypes, static structure) seen by :func:`_call` with an
``on_compile`` listener: a call with a new one compiles first (or loads from the persistent
cache). Tracked only when someone listens, so the default path pays nothing."""


def _call(fn, args, on_compile: Callable[[bool], None] | None):
    """``fn(*args)``, telling ``on_compile`` (True, then False) when the call compiles."""
    if on_compile is None:
        return fn(*args)
    leaves = jax.tree.leaves(args)
    sig = (fn, jax.tree.structure(args), tuple((np.shape(x), str(getattr(x, "dtype", type(x)))) for x in leaves),
           jax.config.jax_enable_x64)
    new = sig not in _SEEN
    if new:
        on_compile(True)
    try:
        return fn(*args)
    finally:
        _SEEN.add(sig)
        if new:
            on_compile(False)


@jax.jit
def _evaluate_intervals(robot, capsules, splines, box_lo, box_hi, box_mask, bounds, traj, scene, a, b, margin):
    """Evaluate F intervals: interval i belongs to trajectory ``traj[i]`` in scene ``scene[i]``.
    Only ``(g, guard, capsule, box)`` leave the call (XLA drops the record's other fields)."""

    def one(k, s, ai, bi):
        spline = SplineRow(splines, k)  # read in place, not copied per interval
        bnd = jax.tree.map(lambda x: x[k], bounds)
        ev = evaluate_interval(robot, capsules, spline, box_lo[s], box_hi[s], box_mask[s], ai, bi, margin, bnd)
        return ev.g, ev.guard, ev.capsule, ev.box

    return jax.vmap(one)(traj, scene, a, b)


def _evaluate_intervals_cached(*args):
    """:func:`_evaluate_intervals`, through its export kept in the compilation cache when that
    is on (:func:`larc_jax.compilation.cached_kernel_call`; one device)."""
    return cached_kernel_call(_evaluate_intervals, args)


@jax.jit
def _evaluate_intervals_self(robot, capsules, splines, box_lo, box_hi, box_mask, bounds, traj, scene, a, b, margin,
                             self_check):
    """:func:`_evaluate_intervals` with the self test (:mod:`larc_jax.self_collision`):
    ``self_check = (first, second, motion_a, margin_self, skip)``, ``skip`` (trajectories, P): the
    pairs proven apart for each trajectory. Returns ``(g, guard, capsule, box, other)``:
    the box pair or the capsule pair (``other`` its second capsule, -1 for a box pair) with the
    smallest ``g - guard``, so a leaf passes iff both tests pass."""
    first, second, motion_pair, margin_self, skip = self_check

    def one(k, s, ai, bi):
        spline = SplineRow(splines, k)
        bnd = jax.tree.map(lambda x: x[k], bounds)
        ev = evaluate_interval(robot, capsules, spline, box_lo[s], box_hi[s], box_mask[s], ai, bi, margin, bnd)
        gs, gds, c1, c2 = self_clearance(ev.p_world_a, ev.p_world_b, capsules.radius, ev.h_cov,
                                         ev.omega_max + bnd.omega_slack, bnd.guard_m, first, second, motion_pair,
                                         margin_self, skip[k])
        gs = jnp.where(jnp.isfinite(ev.g) | jnp.isinf(ev.g), gs, jnp.nan)  # non-finite geometry: NaN
        worse = (gs - gds < ev.g - ev.guard) | jnp.isnan(gs)
        return (jnp.where(worse, gs, ev.g), jnp.where(worse, gds, ev.guard), jnp.where(worse, c1, ev.capsule),
                jnp.where(worse, 0, ev.box), jnp.where(worse, c2, -1))

    return jax.vmap(one)(traj, scene, a, b)


def _evaluate_intervals_self_cached(*args):
    """:func:`_evaluate_intervals_self` through the compilation cache (as :func:`_evaluate_intervals_cached`)."""
    return cached_kernel_call(_evaluate_intervals_self, args)


_build_splines = jax.jit(jax.vmap(HermiteSpline.from_waypoints))


def _geometry(robot: Robot, capsules: CapsuleModel, dtype):
    """Robot and capsule arrays in the geometry dtype; radii and motion constants stay float64
    (they enter the float64 sums, budget P3/G4)."""
    cast = lambda x: np.asarray(x, dtype) if np.issubdtype(np.asarray(x).dtype, np.floating) else x  # noqa: E731
    robot_g = jax.tree.map(cast, robot)
    capsules_g = dataclasses.replace(
        capsules, p_link_a=cast(capsules.p_link_a), p_link_b=cast(capsules.p_link_b),
        radius=np.asarray(capsules.radius, np.float64), motion_a=np.asarray(capsules.motion_a, np.float64))
    return robot_g, capsules_g


def _boxes_outward(lo: np.ndarray, hi: np.ndarray, dtype):
    """Box corners in ``dtype``, rounded outwards so the box tested contains the user's (G3)."""
    lo_g, hi_g = lo.astype(dtype), hi.astype(dtype)
    inf = np.asarray(np.inf, dtype)
    lo_g = np.where(lo_g > lo, np.nextafter(lo_g, -inf), lo_g)
    hi_g = np.where(hi_g < hi, np.nextafter(hi_g, inf), hi_g)
    return lo_g, hi_g


@dataclasses.dataclass
class Batch:
    """Host-side padded dataset ready for the kernel."""

    robot: Robot
    capsules: CapsuleModel
    splines: HermiteSpline
    """Splines on rebased knots (float64), padded."""
    bounds: RoundingBounds
    """Per-trajectory rounding bounds, stacked (leading axis = trajectory)."""
    box_lo: np.ndarray
    box_hi: np.ndarray
    box_mask: np.ndarray
    scene_of: np.ndarray
    t_start: np.ndarray
    """Horizon start per trajectory, in its own time axis, s."""
    t_end: np.ndarray
    margin: np.ndarray
    dtype: np.dtype
    """Geometry dtype (times and the curve are always float64)."""
    devices: tuple = ()
    """Devices the interval axis is sharded over (one device: no sharding)."""
    self_pairs: SelfPairs | None = None
    """Capsule pairs of the self test (:mod:`larc_jax.self_collision`); None: boxes only."""
    self_skip: np.ndarray | None = None
    """(padded trajectories, P) bool: pairs proven apart for each trajectory (:meth:`SelfPairs.skip_mask`)."""

    def _put(self, *arrays):
        """Shard interval-axis arrays over :attr:`devices` (a 1-D mesh); the rest of the inputs
        (robot, splines, boxes) are replicated by ``jit``."""
        if len(self.devices) <= 1:
            return arrays
        from jax.sharding import Mesh, NamedSharding, PartitionSpec

        sharding = NamedSharding(Mesh(np.array(self.devices), ("interval",)), PartitionSpec("interval"))
        return tuple(jax.device_put(x, sharding) for x in arrays)

    def endpoints(self, traj: np.ndarray, depth: np.ndarray, index: np.ndarray):
        """Interval ends from (trajectory, depth, index): :func:`dyadic_ends`."""
        return dyadic_ends(self.t_start[traj], self.t_end[traj], depth, index)

    def _rebased(self, traj, a, b):
        """Interval ends as the kernel takes them: rebased, rounded outwards (budget T1)."""
        return rebase_ends(a, b, np.asarray(self.bounds.offset_s)[traj])

    def _kernel_args(self, traj, a, b):
        ar, br = self._rebased(traj, a, b)
        return (self.robot, self.capsules, self.splines, self.box_lo, self.box_hi, self.box_mask, self.bounds,
                traj, self.scene_of[traj], ar, br, self.margin)

    def cost_analysis(self, traj, depth, index) -> dict:
        """XLA's cost analysis (``flops``, ``bytes accessed``, ...) of the compiled kernel for
        these intervals (one call, no padding): for benchmarks."""
        a, b = self.endpoints(traj, depth, index)
        with jax.enable_x64(True):
            cost = _evaluate_intervals.lower(*self._kernel_args(traj, a, b)).compile().cost_analysis()
        return dict(cost[0] if isinstance(cost, (list, tuple)) else cost)

    def evaluate(self, traj, depth, index, on_chunk: Callable[[int], None] | None = None,
                 on_compile: Callable[[bool], None] | None = None):
        """``(a, b, g, guard, capsule, box)`` for every interval (NumPy arrays; ``a, b`` in the
        trajectory's own time axis), and ``other`` (the second capsule of a self-collision pair,
        -1 for a box pair) when the batch has :attr:`self_pairs`; ``on_chunk(n)`` after each
        chunk of ``n`` intervals, ``on_compile(True/False)`` around a compiling call."""
        a, b = self.endpoints(traj, depth, index)
        ar, br = self._rebased(traj, a, b)
        F = len(traj)
        outs = [np.empty(F), np.empty(F), np.empty(F, np.int64), np.empty(F, np.int64)]
        extra = ()
        if self.self_pairs is not None:
            outs.append(np.empty(F, np.int64))
            sp = self.self_pairs
            extra = ((sp.first, sp.second, sp.motion_a, np.asarray(sp.margin_m, np.float64), self.self_skip),)
        for start in range(0, F, BUCKETS[-1]):
            stop = min(F, start + BUCKETS[-1])
            size = next(s for s in BUCKETS if s >= stop - start)
            size = -(-size // max(1, len(self.devices))) * max(1, len(self.devices))  # whole shards
            pad = size - (stop - start)
            sl = slice(start, stop)
            # Padding repeats the chunk's first interval; its results are dropped below.
            tr = np.concatenate([traj[sl], np.repeat(traj[start], pad)])
            aa = np.concatenate([ar[sl], np.repeat(ar[start], pad)])
            bb = np.concatenate([br[sl], np.repeat(br[start], pad)])
            with jax.enable_x64(True):
                tr_s, sc_s, aa, bb = self._put(tr, self.scene_of[tr], aa, bb)
                if self.self_pairs is None:
                    kernel = _evaluate_intervals if len(self.devices) > 1 else _evaluate_intervals_cached
                else:
                    kernel = _evaluate_intervals_self if len(self.devices) > 1 else _evaluate_intervals_self_cached
                out = _call(kernel, (
                    self.robot, self.capsules, self.splines, self.box_lo, self.box_hi,
                    self.box_mask, self.bounds, tr_s, sc_s, aa, bb, self.margin,
                ) + extra, on_compile)
            n = stop - start
            for dst, x in zip(outs, out):
                dst[sl] = np.asarray(x)[:n]
            if on_chunk:
                on_chunk(n)
        return (a, b, *outs)


def prepare(trajectories, scenes: Sequence[Scene], robot: Robot, capsules: CapsuleModel,
            margin: float, dtype, bounds: Sequence[RoundingBounds], devices=None,
            on_compile: Callable[[bool], None] | None = None, self_pairs: SelfPairs | None = None,
            self_skip: Sequence[np.ndarray] | None = None) -> Batch:
    """Pad a validated dataset into a :class:`Batch` (one scene and one
    :func:`~larc_jax.interval.trajectory_rounding` per trajectory).

    ``devices``: the devices to shard each interval batch over (default: every device of JAX's
    default backend, e.g. all local GPUs; on a CPU, one device unless XLA is asked for more).
    ``on_compile``: see :meth:`Batch.evaluate`.
    """
    dtype = np.dtype(dtype)
    # Shapes are rounded up to size classes (see size_class); padded knots lie after t_K and
    # are never touched by an interval inside the horizon (hermite.pad_waypoints), padded
    # trajectories and scenes repeat the first one and are never indexed by an interval.
    n_knots = size_class(max(t.n_waypoints for t in trajectories), 16)
    padded = [pad_waypoints(t.t - float(bd.offset_s), t.q, t.qd, n_knots) for t, bd in zip(trajectories, bounds)]
    n_pad = size_class(len(padded), 1) - len(padded)
    padded += padded[:1] * n_pad
    stacked = jax.tree.map(lambda *x: np.stack(x), *(list(bounds) + list(bounds[:1]) * n_pad))
    unique = list(dict.fromkeys(id(s) for s in scenes))
    scene_list = [next(s for s in scenes if id(s) == u) for u in unique]
    scene_of = np.array([unique.index(id(s)) for s in scenes], np.int64)
    lo, hi, mask = pad_scenes(scene_list + scene_list[:1] * (size_class(len(scene_list), 1) - len(scene_list)))
    with jax.enable_x64(True):
        splines = _call(_build_splines, tuple(np.stack([p[i] for p in padded]).astype(np.float64) for i in range(3)),
                        on_compile)
    robot_g, capsules_g = _geometry(robot, capsules, dtype)
    box_lo, box_hi = _boxes_outward(lo, hi, dtype)
    return Batch(
        robot=robot_g, capsules=capsules_g, splines=splines, bounds=stacked,
        box_lo=box_lo, box_hi=box_hi, box_mask=mask, scene_of=scene_of,
        t_start=np.array([t.t[0] for t in trajectories]), t_end=np.array([t.t[-1] for t in trajectories]),
        margin=np.asarray(margin, np.float64), dtype=dtype,
        devices=tuple(jax.devices() if devices is None else devices), self_pairs=self_pairs,
        self_skip=None if self_skip is None else np.stack(list(self_skip) + list(self_skip[:1]) * n_pad),
    )
