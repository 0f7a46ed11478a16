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
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Sequence

import jax
import numpy as np

from .compilation import cached_kernel_call
from .enclosure.capsule import CapsuleModel
from .hermite import HermiteSpline, SplineRow, pad_waypoints
from .interval import coordinate_scale, evaluate_interval, rounding_guard
from .robot import Robot
from .scene import Scene, pad_scenes

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
def _evaluate_intervals(robot, capsules, splines, box_lo, box_hi, box_mask, traj, scene, a, b, margin):
    """Evaluate F intervals: interval i belongs to trajectory ``traj[i]`` in scene ``scene[i]``.
    Only ``(g, capsule, box)`` leave the call (XLA drops the record's other fields)."""

    def one(k, s, ai, bi):
        spline = SplineRow(splines, k)  # read in place, not copied per interval
        ev = evaluate_interval(robot, capsules, spline, box_lo[s], box_hi[s], box_mask[s], ai, bi, margin)
        return ev.g, ev.capsule, ev.box

    return jax.vmap(one)(traj, scene, a, b)


def _evaluate_intervals_cached(*args):
    """:func:`_evaluate_intervals`, through its export kept in the compilation cache when that
    is on (:func:`larc_jax.compilation.cached_kernel_call`; one device)."""
    return cached_kernel_call(_evaluate_intervals, args)


_build_splines = jax.jit(jax.vmap(HermiteSpline.from_waypoints))


def _cast(tree, dtype):
    return jax.tree.map(
        lambda x: np.asarray(x, dtype) if np.issubdtype(np.asarray(x).dtype, np.floating) else x, tree
    )


@dataclasses.dataclass
class Batch:
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
    devices: tuple = ()
    """Devices the interval axis is sharded over (one device: no sharding)."""

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

    def _kernel_args(self, traj, a, b):
        return (self.robot, self.capsules, self.splines, self.box_lo, self.box_hi, self.box_mask,
                traj, self.scene_of[traj], a.astype(self.dtype), b.astype(self.dtype), self.margin)

    def cost_analysis(self, traj, depth, index) -> dict:
        """XLA's cost analysis (``flops``, ``bytes accessed``, ...) of the compiled kernel for
        these intervals (one call, no padding): for benchmarks."""
        a, b = self.endpoints(traj, depth, index)
        with jax.enable_x64(self.dtype == np.float64):
            cost = _evaluate_intervals.lower(*self._kernel_args(traj, a, b)).compile().cost_analysis()
        return dict(cost[0] if isinstance(cost, (list, tuple)) else cost)

    def evaluate(self, traj, depth, index, on_chunk: Callable[[int], None] | None = None,
                 on_compile: Callable[[bool], None] | None = None):
        """``(a, b, g, capsule, box)`` for every interval (NumPy arrays); ``on_chunk(n)`` after
        each chunk of ``n`` intervals, ``on_compile(True/False)`` around a compiling call."""
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
            size = -(-size // max(1, len(self.devices))) * max(1, len(self.devices))  # whole shards
            pad = size - (stop - start)
            sl = slice(start, stop)
            # Padding repeats the chunk's first interval; its results are dropped below.
            tr = np.concatenate([traj[sl], np.repeat(traj[start], pad)])
            aa = np.concatenate([a[sl], np.repeat(a[start], pad)]).astype(self.dtype)
            bb = np.concatenate([b[sl], np.repeat(b[start], pad)]).astype(self.dtype)
            with jax.enable_x64(self.dtype == np.float64):
                tr_s, sc_s, aa, bb = self._put(tr, self.scene_of[tr], aa, bb)
                kernel = _evaluate_intervals if len(self.devices) > 1 else _evaluate_intervals_cached
                out = _call(kernel, (
                    self.robot, self.capsules, self.splines, self.box_lo, self.box_hi,
                    self.box_mask, tr_s, sc_s, aa, bb, self.margin,
                ), on_compile)
                gg, cc, bx = (np.asarray(x) for x in out)
            g[sl], cap[sl], box[sl] = gg[: stop - start], cc[: stop - start], bx[: stop - start]
            if on_chunk:
                on_chunk(stop - start)
        return a, b, g, cap, box


def prepare(trajectories, scenes: Sequence[Scene], robot: Robot, capsules: CapsuleModel,
            margin: float, dtype, devices=None, on_compile: Callable[[bool], None] | None = None) -> Batch:
    """Pad a validated dataset into a :class:`Batch` (one scene per trajectory).

    ``devices``: the devices to shard each interval batch over (default: every device of JAX's
    default backend, e.g. all local GPUs; on a CPU, one device unless XLA is asked for more).
    ``on_compile``: see :meth:`Batch.evaluate`.
    """
    dtype = np.dtype(dtype)
    # Shapes are rounded up to size classes (see size_class); padded knots lie after t_K and
    # are never touched by an interval inside the horizon (hermite.pad_waypoints), padded
    # trajectories and scenes repeat the first one and are never indexed by an interval.
    n_knots = size_class(max(t.n_waypoints for t in trajectories), 16)
    padded = [pad_waypoints(t.t, t.q, t.qd, n_knots) for t in trajectories]
    padded += padded[:1] * (size_class(len(padded), 1) - len(padded))
    unique = list(dict.fromkeys(id(s) for s in scenes))
    scene_list = [next(s for s in scenes if id(s) == u) for u in unique]
    scene_of = np.array([unique.index(id(s)) for s in scenes], np.int64)
    lo, hi, mask = pad_scenes(scene_list + scene_list[:1] * (size_class(len(scene_list), 1) - len(scene_list)))
    with jax.enable_x64(dtype == np.float64):
        splines = _call(_build_splines, (
            np.stack([p[0] for p in padded]).astype(dtype),
            np.stack([p[1] for p in padded]).astype(dtype),
            np.stack([p[2] for p in padded]).astype(dtype),
        ), on_compile)
    return Batch(
        robot=_cast(robot, dtype), capsules=_cast(capsules, dtype), splines=splines,
        box_lo=lo.astype(dtype), box_hi=hi.astype(dtype), box_mask=mask, scene_of=scene_of,
        t_start=np.array([t.t[0] for t in trajectories]), t_end=np.array([t.t[-1] for t in trajectories]),
        margin=np.asarray(margin, dtype), dtype=dtype,
        guard=rounding_guard(dtype, coordinate_scale(scene_list, robot, capsules)),
        devices=tuple(jax.devices() if devices is None else devices),
    )
