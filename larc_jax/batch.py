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

from .cascade import Links, combine, hull_pair_clearance, interval_pairs, select_pairs
from .enclosure.capsule import CapsuleModel
from .enclosure.hull import HullModel
from .hermite import HermiteSpline, pad_waypoints
from .interval import coordinate_scale, evaluate_interval, rounding_guard
from .robot import Robot
from .scene import Scene, pad_scenes

__all__ = ["Batch", "prepare", "dyadic_ends", "size_class", "BUCKETS", "CASCADE_BUCKETS"]

BUCKETS = tuple(2**k for k in range(2, 13))
"""Frontier arrays are padded to the next of these sizes, 4 .. 4096 (at most 2x waste, 11
compiled shapes); larger frontiers run in 4096-chunks. Small buckets matter when trajectories
are certified one at a time: a call costs ~0.1 ms plus ~10 us per padded interval on a CPU core,
so a 3-interval frontier padded to 64 would cost 5x what it needs."""


CASCADE_BUCKETS = (64, 1024, 4096)
"""Sizes of the cascade's second-stage calls (larc_jax.cascade): coarser than :data:`BUCKETS`,
because those kernels take seconds to compile and their calls are fewer; a small call padded
to 64 costs a few ms."""


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


@jax.jit
def _evaluate_intervals(robot, capsules, splines, box_lo, box_hi, box_mask, traj, scene, a, b, margin):
    """Evaluate F intervals: interval i belongs to trajectory ``traj[i]`` in scene ``scene[i]``.
    Only ``(g, capsule, box)`` leave the call (XLA drops the record's other fields)."""

    def one(k, s, ai, bi):
        spline = jax.tree.map(lambda x: x[k], splines)
        ev = evaluate_interval(robot, capsules, spline, box_lo[s], box_hi[s], box_mask[s], ai, bi, margin)
        return ev.g, ev.capsule, ev.box

    return jax.vmap(one)(traj, scene, a, b)


@jax.jit
def _interval_pairs(robot, capsules, hulls, splines, box_lo, box_hi, box_mask, traj, scene, a, b, margin):
    """Step 2 of the cascade (larc_jax.cascade) on F intervals, as ``_evaluate_intervals``."""

    def one(k, s, ai, bi):
        spline = jax.tree.map(lambda x: x[k], splines)
        return interval_pairs(robot, capsules, hulls, spline, box_lo[s], box_hi[s], box_mask[s], ai, bi, margin)

    return jax.vmap(one)(traj, scene, a, b)


@jax.jit
def _hull_pairs(hulls, part, T_part, lo, hi, motion_b, margin):
    """Step 4 of the cascade on T (part, box) pairs."""
    return jax.vmap(hull_pair_clearance, in_axes=(None, 0, 0, 0, 0, 0, None))(
        hulls, part, T_part, lo, hi, motion_b, margin)


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
    hulls: HullModel | None = None
    """Hull parts for the cascade (larc_jax.cascade); None: the capsule test alone."""

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

    def _bucketed(self, call, items, on_chunk=None, buckets=BUCKETS):
        """Run ``call(*chunk)`` over the per-item arrays ``items`` in chunks padded to
        ``buckets`` (padding repeats the chunk's first item; its results are dropped).
        Returns the outputs (a pytree of arrays) concatenated over the items."""
        n = len(items[0])
        parts = []
        for start in range(0, n, buckets[-1]):
            stop = min(n, start + buckets[-1])
            size = next(s for s in buckets if s >= stop - start)
            size = -(-size // max(1, len(self.devices))) * max(1, len(self.devices))  # whole shards
            pad = size - (stop - start)
            chunk = [np.concatenate([x[start:stop], np.repeat(x[start:start + 1], pad, axis=0)]) for x in items]
            with jax.enable_x64(self.dtype == np.float64):
                out = call(*self._put(*chunk))
                parts.append(jax.tree.map(lambda x: np.asarray(x)[: stop - start], out))
            if on_chunk:
                on_chunk(stop - start)
        return jax.tree.map(lambda *xs: np.concatenate(xs), *parts)

    def evaluate_cascade(self, traj, depth, index, on_chunk: Callable[[int], None] | None = None):
        """The cascade (larc_jax.cascade) on every interval: ``(a, b, g, capsule, box, stage)``,
        stage 1 for intervals the capsule test passes, 2 for those only the hull test passes,
        0 for the rest. Without :attr:`hulls`, the capsule test alone."""
        a, b, g, cap, box = self.evaluate(traj, depth, index, on_chunk)
        stage = (g > self.guard).astype(np.int8)
        open_ = np.flatnonzero(~(g > self.guard) & ~np.isnan(g))
        if self.hulls is None or not len(open_):
            return a, b, g, cap, box, stage
        aa, bb = a[open_], b[open_]
        tr = traj[open_]
        d = self._bucketed(
            lambda t, sc, x, y: _interval_pairs(self.robot, self.capsules, self.hulls, self.splines, self.box_lo,
                                                self.box_hi, self.box_mask, t, sc, x, y, self.margin),
            [tr, self.scene_of[tr], aa, bb], buckets=CASCADE_BUCKETS)
        links = Links.of(self.capsules, self.hulls)
        tried, triples = select_pairs(links, d.g_capsule, d.g_upper, self.guard)
        g_hull = np.zeros(0)
        if len(triples):
            i, p, k = triples.T
            sc = self.scene_of[tr[i]]
            g_hull = self._bucketed(
                lambda pp, T, lo, hi, mb: _hull_pairs(self.hulls, pp, T, lo, hi, mb, self.margin),
                [p, d.T_part[i, p], self.box_lo[sc, k], self.box_hi[sc, k], d.motion_b[i, p]],
                buckets=CASCADE_BUCKETS)
        g2, cap2, box2, passed = combine(links, d.g_capsule, tried, triples, g_hull, self.guard)
        g, cap, box = g.copy(), cap.copy(), box.copy()
        g[open_], cap[open_], box[open_] = g2, cap2, box2
        stage[open_] = np.where(passed, 2, 0)
        return a, b, g, cap, box, stage

    def _interval_ends(self, a, b):
        """Interval ends as the kernel receives them (float32: rounded outwards, so that the
        float32 intervals still cover the float64 ones)."""
        if self.dtype == np.float32:
            a = np.nextafter(a.astype(np.float32), np.float32(-np.inf))
            b = np.nextafter(b.astype(np.float32), np.float32(np.inf))
        return a.astype(self.dtype), b.astype(self.dtype)

    def evaluate(self, traj, depth, index, on_chunk: Callable[[int], None] | None = None):
        """``(a, b, g, capsule, box)`` for every interval (NumPy arrays): the capsule test;
        ``a, b`` as the kernel received them."""
        a, b = self._interval_ends(*self.endpoints(traj, depth, index))
        g, cap, box = self._bucketed(
            lambda t, sc, x, y: _evaluate_intervals(self.robot, self.capsules, self.splines, self.box_lo,
                                                    self.box_hi, self.box_mask, t, sc, x, y, self.margin),
            [traj, self.scene_of[traj], a, b], on_chunk)
        return a, b, g, cap.astype(np.int64), box.astype(np.int64)


def prepare(trajectories, scenes: Sequence[Scene], robot: Robot, capsules: CapsuleModel,
            margin: float, dtype, devices=None, hulls: HullModel | None = None) -> Batch:
    """Pad a validated dataset into a :class:`Batch` (one scene per trajectory).

    ``devices``: the devices to shard each interval batch over (default: every device of JAX's
    default backend, e.g. all local GPUs; on a CPU, one device unless XLA is asked for more).
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
        splines = _build_splines(
            np.stack([p[0] for p in padded]).astype(dtype),
            np.stack([p[1] for p in padded]).astype(dtype),
            np.stack([p[2] for p in padded]).astype(dtype),
        )
    return Batch(
        robot=_cast(robot, dtype), capsules=_cast(capsules, dtype), splines=splines,
        box_lo=lo.astype(dtype), box_hi=hi.astype(dtype), box_mask=mask, scene_of=scene_of,
        t_start=np.array([t.t[0] for t in trajectories]), t_end=np.array([t.t[-1] for t in trajectories]),
        margin=np.asarray(margin, dtype), dtype=dtype,
        guard=rounding_guard(dtype, coordinate_scale(scene_list, robot, capsules)),
        devices=tuple(jax.devices() if devices is None else devices),
        hulls=None if hulls is None else _cast(hulls, dtype),
    )
