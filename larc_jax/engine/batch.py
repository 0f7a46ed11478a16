"""Host-side batching for the JAX certifiers: padded arrays, size classes, bucketed calls.

A dataset of trajectories (each with its own waypoint count, duration and scene) becomes one
:class:`Batch`: splines padded to a common knot count (their range-maximum tables ragged,
each its own length: :mod:`larc_jax.model.spline_batch`), scenes stacked into one obstacle set
padded to a common item count (masked; :func:`~larc_jax.obstacles.stack_scenes`), per-trajectory
horizons. :meth:`Batch.evaluate` runs the interval test on any list
of (trajectory, depth, index) intervals in jitted, vmapped calls whose sizes are padded to a
few buckets, so a process compiles a handful of shapes rather than one per frontier size.

Several devices. With more than one device (all GPUs of a machine, or CPU devices forced with
``XLA_FLAGS=--xla_force_host_platform_device_count=N``) each batch of intervals is sharded
along the interval axis over a 1-D mesh (``jax.sharding``); every interval is still evaluated
by the same kernel on one device, so results are identical to a single-device run.

Interval ends are exact dyadic fractions of the horizon (:func:`dyadic_ends`), shared by every
certifier: neighbours compute their common end from the same fraction, so a cover has no gaps.
They are computed in each trajectory's own time axis (what a leaf reports) and handed to the
kernel rebased with outward rounding (:func:`~larc_jax.leaf.interval.rebase_ends`, budget T1).
Geometry arrays are cast to the geometry dtype (obstacles rounded outwards); times, splines and the
per-trajectory rounding bounds are float64.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Callable, Sequence

import numpy as np

from ..leaf.cascade import Links, PairDetails, combine, hull_pair_clearance, interval_pairs, select_pairs, two_rounds
from ..leaf.clearance import BROAD_PHASE_K
from ..compilation import cached_kernel, tracked_call
from ..enclosure.capsule import CapsuleModel
from ..enclosure.hull import HullModel, by_vertex_class
from ..model.hermite import pad_waypoints
from ..model.spline_batch import SplineBatch, SplineRow, spline_batch
from ..leaf.interval import RoundingBounds, dyadic_ends, evaluate_interval, rebase_ends
from ..leaf.record import LeafRecord, Stage, box_record, compose, needs_hull, self_record
from ..lazy_jax import jax  # importing this module loads JAX and registers the pytrees (lazy_jax)
from ..obstacles import ObstacleSet, stack_scenes
from ..obstacles.polytope import GJK_ITERATIONS
from ..leaf.placement import place
from ..model.robot import Robot
from ..model.scene import Scene
from ..leaf.self_collision import SelfPairs, self_stage
from ..leaf.swept import (SweptPlacement, SweptTables, swept_capsule_clearance, swept_links, swept_part_clearance,
                          swept_placement, swept_record)

__all__ = ["Batch", "prepare", "dyadic_ends", "size_class", "BUCKETS", "CASCADE_BUCKETS", "MAX_BATCH_TRAJECTORIES"]

BUCKETS = tuple(2**k for k in range(2, 13))
"""Frontier arrays are padded to the next of these sizes, 4 .. 4096 (at most 2x waste, 11
compiled shapes); larger frontiers run in 4096-chunks. Small buckets matter when trajectories
are certified one at a time: a call costs ~0.1 ms plus ~10 us per padded interval on a CPU core,
so a 3-interval frontier padded to 64 would cost 5x what it needs."""


MAX_BATCH_TRAJECTORIES = 1024
"""Trajectories :func:`~larc_jax.engine.certify.certify` prepares into one :class:`Batch` (larger
datasets run batch after batch): bounds the padded spline and bound arrays, so memory does not
grow with the dataset."""


CASCADE_BUCKETS = (64, 256, 1024)
"""Sizes of the cascade's second-stage calls (larc_jax.leaf.cascade): fewer than :data:`BUCKETS`,
because those kernels take seconds to compile; a small call padded to 64 costs a few ms. Larger
counts run in 1024-chunks: a GJK pair costs ~30 us on a CPU core, so padding a remainder to 4096
(the former largest size) cost more than the extra calls (on Stage B, 57 % of the padded pairs
were real)."""


PAIR_BUCKETS = (16, 32, 64, 128, 256, 512, 1024)
"""Sizes of the cascade's step-2 calls (:func:`~larc_jax.leaf.cascade.interval_pairs`, ~1.2 s to
compile each): a ladder of 2, because one trajectory's open frontier is typically a few dozen to
a few hundred intervals (on Stage B one at a time, the median call held 119: 4.1 ms padded to 256,
2.6 ms at 128)."""


PAIR_BYTES = 512
"""Device memory per capsule-obstacle pair per interval that the all-pairs kernel may hold (XLA
keeps each pair's candidate points; measured ~380 bytes on the CPU), rounded up."""
CALL_BYTES = 2**30
"""Device memory one interval call may take for its pairs (:attr:`Batch.max_chunk`)."""


def size_class(n: int, minimum: int) -> int:
    """Next power of two >= max(n, minimum): array sizes that vary between calls (waypoints,
    trajectories, scenes) are rounded up to these so a process compiles a few shapes, not one
    per distinct size (each compiled CPU executable also holds ~100 memory mappings)."""
    return 1 << (max(int(n), int(minimum)) - 1).bit_length()


def _intervals(robot, capsules, splines, obstacles, bounds, traj, scene, a, b, margin, k):
    """Evaluate F intervals: interval i belongs to trajectory ``traj[i]`` in scene ``scene[i]``.
    Only ``(g, guard, capsule, box, exact)`` leave the call (XLA drops the record's other fields)."""

    def one(t, s, ai, bi):
        spline = SplineRow(splines, t)  # read in place, not copied per interval
        bnd = jax.tree.map(lambda x: x[t], bounds)
        ev = evaluate_interval(robot, capsules, spline, obstacles.take(s), ai, bi, margin, bnd, k)
        return ev.g, ev.guard, ev.capsule, ev.box, ev.exact

    return jax.vmap(one)(traj, scene, a, b)


@jax.jit
def _evaluate_intervals(robot, capsules, splines, obstacles, bounds, traj, scene, a, b, margin):
    """The interval test with every capsule-obstacle pair exact."""
    return _intervals(robot, capsules, splines, obstacles, bounds, traj, scene, a, b, margin, None)


@jax.jit
def _evaluate_intervals_broad(robot, capsules, splines, obstacles, bounds, traj, scene, a, b, margin):
    """The interval test through the broad phase (:data:`~larc_jax.leaf.clearance.BROAD_PHASE_K` exact
    pairs per interval); intervals whose ``exact`` is False are evaluated again all-pairs."""
    return _intervals(robot, capsules, splines, obstacles, bounds, traj, scene, a, b, margin, BROAD_PHASE_K)


@jax.jit
def _interval_pairs(robot, capsules, hulls, splines, obstacles, bounds, traj, scene, a, b, margin):
    """Step 2 of the cascade (larc_jax.leaf.cascade) on F intervals, as ``_evaluate_intervals``: the
    fields of :class:`~larc_jax.leaf.cascade.PairDetails` as a tuple (what the compilation cache keeps)."""

    def one(k, s, ai, bi):
        spline = SplineRow(splines, k)
        bnd = jax.tree.map(lambda x: x[k], bounds)
        d = interval_pairs(robot, capsules, hulls, spline, obstacles.take(s), ai, bi, margin, bnd)
        return d.g_capsule, d.T_part, d.motion_b, d.g_upper

    return jax.vmap(one)(traj, scene, a, b)


def _hull_pairs_kernel(iterations: int):
    """Step 4 of the cascade on T (part, obstacle) pairs (``items``: one obstacle per pair) with
    ``iterations`` GJK steps: one jitted function per round, each with its own name (the
    compilation cache keys kernels by name)."""

    def kernel(hulls, part, T_part, items, motion_b, margin):
        one = functools.partial(hull_pair_clearance, iterations=iterations)
        return jax.vmap(one, in_axes=(None, 0, 0, 0, 0, None))(hulls, part, T_part, items, motion_b, margin)

    kernel.__name__ = kernel.__qualname__ = f"_hull_pairs_{iterations}"
    return jax.jit(kernel)


_hull_first_axis = _hull_pairs_kernel(0)
_hull_pairs = _hull_pairs_kernel(GJK_ITERATIONS)


@jax.jit
def _self_intervals(robot, capsules, splines, bounds, traj, a, b, self_check):
    """The self stage (:func:`~larc_jax.leaf.self_collision.self_stage`) on F intervals of trajectories
    ``traj``: ``self_check = (first, second, motion_a, margin_self, skip)``, ``skip``
    (trajectories, P): the pairs proven apart for each trajectory. Returns ``(g, guard, capsule,
    other)`` of the capsule pair with the smallest ``g - guard`` (NaN on non-finite geometry)."""
    first, second, motion_pair, margin_self, skip = self_check

    def one(k, ai, bi):
        bnd = jax.tree.map(lambda x: x[k], bounds)
        placed = place(robot, capsules, SplineRow(splines, k), ai, bi, bnd)
        return self_stage(placed, capsules.radius, bnd, first, second, motion_pair, margin_self, skip[k])

    return jax.vmap(one)(traj, a, b)


@jax.jit
def _swept_intervals(robot, capsules, hulls, tables, splines, obstacles, bounds, traj, scene, a, b, margin):
    """Step 1 of the swept stage (:func:`~larc_jax.leaf.swept.swept_placement`) on F intervals, as
    ``_evaluate_intervals``: the fields of :class:`~larc_jax.leaf.swept.SweptPlacement` as a tuple."""

    def one(k, s, ai, bi):
        bnd = jax.tree.map(lambda x: x[k], bounds)
        d = swept_placement(robot, capsules, hulls, tables, SplineRow(splines, k), obstacles.take(s), ai, bi, margin,
                            bnd)
        return tuple(getattr(d, f.name) for f in dataclasses.fields(d))

    return jax.vmap(one)(traj, scene, a, b)


@jax.jit
def _swept_capsules(capsules, capsule, R_ends, t_ends, items, swept_e, margin):
    """Step 1b of the swept stage on T (capsule, obstacle) pairs (``items``: one obstacle per pair)."""
    return jax.vmap(swept_capsule_clearance, in_axes=(None, 0, 0, 0, 0, 0, None))(
        capsules, capsule, R_ends, t_ends, items, swept_e, margin)


@jax.jit
def _swept_parts(hulls, part, T_mid, R_ends, t_ends, items, motion_b, swept_e, margin):
    """Step 2 of the swept stage on T (part, obstacle) pairs (``items``: one obstacle per pair)."""
    return jax.vmap(swept_part_clearance, in_axes=(None, 0, 0, 0, 0, 0, 0, 0, None))(
        hulls, part, T_mid, R_ends, t_ends, items, motion_b, swept_e, margin)


def _geometry(robot: Robot, capsules: CapsuleModel, dtype):
    """Robot and capsule arrays in the geometry dtype; radii and motion constants stay float64
    (they enter the float64 sums, budget P3/G4)."""
    cast = lambda x: np.asarray(x, dtype) if np.issubdtype(np.asarray(x).dtype, np.floating) else x  # noqa: E731
    robot_g = jax.tree.map(cast, robot)
    capsules_g = dataclasses.replace(
        capsules, p_link_a=cast(capsules.p_link_a), p_link_b=cast(capsules.p_link_b),
        radius=np.asarray(capsules.radius, np.float64), motion_a=np.asarray(capsules.motion_a, np.float64))
    return robot_g, capsules_g


def _hulls_geometry(hulls: HullModel, dtype) -> HullModel:
    """Hull vertex tables in the geometry dtype; radii and motion constants stay float64 (as
    for capsules). A float32 vertex is rounded once: covered by the part's guard (G1)."""
    cast = lambda x: np.asarray(x, dtype)  # noqa: E731
    return dataclasses.replace(hulls, vertices=cast(hulls.vertices), centre=cast(hulls.centre),
                               probes=cast(hulls.probes), radius=np.asarray(hulls.radius, np.float64),
                               motion_a=np.asarray(hulls.motion_a, np.float64))


@dataclasses.dataclass
class Batch:
    """Host-side padded dataset ready for the kernel."""

    robot: Robot
    capsules: CapsuleModel
    splines: SplineBatch
    """Splines on rebased knots (float64), padded."""
    bounds: RoundingBounds
    """Per-trajectory rounding bounds, stacked (leading axis = trajectory)."""
    obstacles: ObstacleSet
    """Every scene's obstacles, padded to one item count (leading axis = scene), geometry dtype."""
    scene_of: np.ndarray
    t_start: np.ndarray
    """Horizon start per trajectory, in its own time axis, s."""
    t_end: np.ndarray
    margin: np.ndarray
    dtype: np.dtype
    """Geometry dtype (times and the curve are always float64)."""
    devices: tuple = ()
    """Devices the interval axis is sharded over (one device: no sharding)."""
    hulls: HullModel | None = None
    """Hull parts for the cascade (larc_jax.leaf.cascade); None: the capsule test alone."""
    self_pairs: SelfPairs | None = None
    """Capsule pairs of the self test (:mod:`larc_jax.leaf.self_collision`); None: obstacles only."""
    self_skip: np.ndarray | None = None
    """(padded trajectories, P) bool: pairs proven apart for each trajectory (:meth:`SelfPairs.skip_mask`)."""
    swept: SweptTables | None = None
    """The swept stage's chain tables (:mod:`larc_jax.leaf.swept`); None: no swept stage."""

    def _put(self, *arrays):
        """Shard interval-axis arrays over :attr:`devices` (a 1-D mesh); the rest of the inputs
        (robot, splines, obstacles) are replicated by ``jit``."""
        if len(self.devices) <= 1:
            return arrays
        from jax.sharding import Mesh, NamedSharding, PartitionSpec

        sharding = NamedSharding(Mesh(np.array(self.devices), ("interval",)), PartitionSpec("interval"))
        return tuple(jax.device_put(x, sharding) for x in arrays)

    @functools.cached_property
    def max_chunk(self) -> int:
        """Intervals per kernel call at most: the all-pairs interval kernel holds about
        :data:`PAIR_BYTES` per capsule-obstacle pair, so a call may not exceed :data:`CALL_BYTES`
        (a scene of thousands of mesh or cloud pieces gets small chunks; box scenes are never
        limited below the largest bucket)."""
        pairs = max(1, self.capsules.n_capsules * self.obstacles.n_items)
        return max(4, 1 << max(0, (CALL_BYTES // (PAIR_BYTES * pairs)).bit_length() - 1))

    def endpoints(self, traj: np.ndarray, depth: np.ndarray, index: np.ndarray):
        """Interval ends from (trajectory, depth, index): :func:`dyadic_ends`."""
        return dyadic_ends(self.t_start[traj], self.t_end[traj], depth, index)

    def _rebased(self, traj, a, b):
        """Interval ends as the kernel takes them: rebased, rounded outwards (budget T1)."""
        return rebase_ends(a, b, np.asarray(self.bounds.offset_s)[traj])

    def _kernel_args(self, traj, a, b):
        ar, br = self._rebased(traj, a, b)
        return (self.robot, self.capsules, self.splines, self.obstacles, self.bounds, traj, self.scene_of[traj], ar,
                br, self.margin)

    def cost_analysis(self, traj, depth, index, broad_phase: bool = True) -> dict:
        """XLA's cost analysis (``flops``, ``bytes accessed``, ...) of the compiled kernel for
        these intervals (one call, no padding; the broad-phase kernel, or the all-pairs one):
        for benchmarks."""
        a, b = self.endpoints(traj, depth, index)
        kernel = _evaluate_intervals_broad if broad_phase else _evaluate_intervals
        with jax.enable_x64(True):
            cost = kernel.lower(*self._kernel_args(traj, a, b)).compile().cost_analysis()
        return dict(cost[0] if isinstance(cost, (list, tuple)) else cost)

    def _bucketed(self, call, items, on_chunk=None, buckets=BUCKETS, on_compile=None):
        """Run ``call(*chunk)`` over the per-item arrays ``items`` in chunks padded to
        ``buckets`` (padding repeats the chunk's first item; its results are dropped) and
        sharded over :attr:`devices`. Returns the outputs (a pytree of NumPy arrays)
        concatenated over the items; ``on_chunk(n)`` after each chunk of ``n`` items."""
        n = len(items[0])
        parts = []
        buckets = tuple(s for s in buckets if s <= self.max_chunk) or buckets[:1]  # memory: PAIR_BYTES
        for start in range(0, n, buckets[-1]):
            stop = min(n, start + buckets[-1])
            size = next(s for s in buckets if s >= stop - start)
            size = -(-size // max(1, len(self.devices))) * max(1, len(self.devices))  # whole shards
            pad = size - (stop - start)
            chunk = [np.concatenate([x[start:stop], np.repeat(x[start:start + 1], pad, axis=0)]) for x in items]
            with jax.enable_x64(True):
                out = call(*self._put(*chunk))
                parts.append(jax.tree.map(lambda x: np.asarray(x)[: stop - start], out))
            if on_chunk:
                on_chunk(stop - start)
        return jax.tree.map(lambda *xs: np.concatenate(xs), *parts)

    def evaluate(self, traj, depth, index, on_chunk: Callable[[int], None] | None = None,
                 on_compile: Callable[[bool], None] | None = None):
        """``(a, b, record)`` for every interval (``a, b`` in the trajectory's own time axis, NumPy
        arrays; ``record`` a :class:`~larc_jax.leaf.record.LeafRecord` of NumPy arrays): the capsule
        test, and with :attr:`self_pairs` the self test too, composed by
        :func:`~larc_jax.leaf.record.compose`; ``on_chunk(n)`` after each chunk of ``n`` intervals,
        ``on_compile(True/False)`` around a compiling call."""
        a, b, capsule_test, self_test = self._tests(traj, depth, index, on_chunk, on_compile)
        return a, b, compose(capsule_test, self_test)

    def _tests(self, traj, depth, index, on_chunk, on_compile):
        """``(a, b, capsule_test, self_test)``: the :class:`~larc_jax.leaf.record.LeafRecord` of the
        capsule stage and of the self stage (None without :attr:`self_pairs`)."""
        a, b = self.endpoints(traj, depth, index)
        ar, br = self._rebased(traj, a, b)
        run = self._kernel(_evaluate_intervals_broad if self.use_broad_phase else _evaluate_intervals, on_compile)
        g, guard, cap, box, exact = self._bucketed(run, [traj, self.scene_of[traj], ar, br], on_chunk)
        redo = np.flatnonzero(~exact.astype(bool))
        if len(redo):  # the broad phase could not prove its pick: every pair, exactly
            g[redo], guard[redo], cap[redo], box[redo], _ = self._bucketed(
                self._kernel(_evaluate_intervals, on_compile),
                [traj[redo], self.scene_of[traj[redo]], ar[redo], br[redo]])
        self_test = None
        if self.self_pairs is not None:
            sp = self.self_pairs
            check = (sp.first, sp.second, sp.motion_a, np.asarray(sp.margin_m, np.float64), self.self_skip)
            call = _self_intervals if len(self.devices) > 1 else cached_kernel(_self_intervals)
            gs, gds, c1, c2 = self._bucketed(
                lambda t, x, y: tracked_call(call, (self.robot, self.capsules, self.splines, self.bounds, t, x, y,
                                                    check), on_compile), [traj, ar, br])
            self_test = self_record(gs, gds, c1.astype(np.int64), c2.astype(np.int64))
        return a, b, box_record(g, guard, cap.astype(np.int64), box.astype(np.int64), Stage.CAPSULE), self_test

    @property
    def use_broad_phase(self) -> bool:
        """The broad phase pays when a scene has more capsule-obstacle pairs than it evaluates exactly."""
        return self.capsules.n_capsules * self.obstacles.n_items > 2 * BROAD_PHASE_K

    def _kernel(self, kernel, on_compile):
        call = kernel if len(self.devices) > 1 else cached_kernel(kernel)
        return lambda t, sc, x, y: tracked_call(call, (self.robot, self.capsules, self.splines, self.obstacles,
                                                       self.bounds, t, sc, x, y, self.margin), on_compile)

    def evaluate_cascade(self, traj, depth, index, on_chunk: Callable[[int], None] | None = None,
                         on_compile: Callable[[bool], None] | None = None):
        """The leaf test (:mod:`larc_jax.leaf.record`) on every interval: ``(a, b, record)`` as
        :meth:`evaluate`, with the hull stage (larc_jax.leaf.cascade) where
        :func:`~larc_jax.leaf.record.needs_hull` (the capsules fail a box and the self test, if any,
        passes), then the swept stage (:mod:`larc_jax.leaf.swept`, with :attr:`swept`) where the leaf
        is still open; ``record.stage`` is CAPSULE, HULL, SWEPT or NONE (``stage > 0`` iff ``g >
        guard``). Without :attr:`hulls`, no hull stage; without :attr:`swept`, no swept stage."""
        a, b, record, self_test = self._tests(traj, depth, index, on_chunk, on_compile)
        open_ = np.flatnonzero(needs_hull(record, self_test))
        if self.hulls is not None and len(open_):
            record = record.put(open_, self._hull_stage(traj[open_], a[open_], b[open_], on_compile))
        open_ = np.flatnonzero(needs_hull(record, self_test))
        if self.swept is not None and len(open_):
            record = record.put(open_, self._swept_stage(traj[open_], a[open_], b[open_], on_compile))
        return a, b, compose(record, self_test)

    def _swept_stage(self, tr, a, b, on_compile) -> LeafRecord:
        """The swept stage (:mod:`larc_jax.leaf.swept`) on the intervals ``(tr, a, b)``."""
        ar, br = self._rebased(tr, a, b)
        call = _swept_intervals if len(self.devices) > 1 else cached_kernel(_swept_intervals)
        parts_call = _swept_parts if len(self.devices) > 1 else cached_kernel(_swept_parts)
        caps_call = _swept_capsules if len(self.devices) > 1 else cached_kernel(_swept_capsules)
        d = SweptPlacement(*self._bucketed(
            lambda t, sc, x, y: tracked_call(call, (self.robot, self.capsules, self.hulls, self.swept, self.splines,
                                             self.obstacles, self.bounds, t, sc, x, y, self.margin), on_compile),
            [tr, self.scene_of[tr], ar, br], buckets=CASCADE_BUCKETS))
        links = swept_links(self.capsules, None if self.hulls is None else Links.of(self.capsules, self.hulls))
        G_c = np.asarray(self.bounds.guard_m)[tr]  # (F', C)

        def clear_capsules(triples):
            i, c, k = triples.T
            leaves, tree = jax.tree.flatten(self.obstacles.take((self.scene_of[tr[i]], k)))  # one item per triple
            return self._bucketed(
                lambda cc, R, t, e, *it: tracked_call(caps_call, (self.capsules, cc, R, t, jax.tree.unflatten(tree, it),
                                                                  e, self.margin), on_compile),
                [c, d.R_capsule[i, c], d.t_capsule[i, c], d.e_capsule[i, c], *leaves], buckets=CASCADE_BUCKETS)

        def clear_parts(triples):
            i, p, k = triples.T
            leaves, tree = jax.tree.flatten(self.obstacles.take((self.scene_of[tr[i]], k)))  # one item per triple

            def run(hulls, idx):
                ii, pi = i[idx], p[idx]
                return self._bucketed(
                    lambda pp, Tm, R, t, mb, e, *it: tracked_call(
                        parts_call, (hulls, pp, Tm, R, t, jax.tree.unflatten(tree, it), mb, e, self.margin),
                        on_compile),
                    [pi, d.T_mid[ii, pi], d.R_ends[ii, pi], d.t_ends[ii, pi], d.motion_b[ii, pi], d.swept_e[ii, pi],
                     *(x[idx] for x in leaves)], buckets=CASCADE_BUCKETS)

            return by_vertex_class(self.hulls, p, run, CASCADE_BUCKETS), np.asarray(self.bounds.hull_guard_m)[tr][i, p]

        g, guard, cap, box, _ = swept_record(links, d.g_capsule, G_c, self.hulls is not None, clear_capsules,
                                             clear_parts)
        return box_record(g, guard, cap.astype(np.int64), box.astype(np.int64), Stage.SWEPT)

    def _hull_round(self, kernel, d: PairDetails, tr, triples, on_compile) -> np.ndarray:
        """One round of step 4 (``kernel``: :data:`_hull_first_axis` or :data:`_hull_pairs`) on the
        ``(interval, part, obstacle)`` triples of the intervals ``tr``, a call per vertex class."""
        call = kernel if len(self.devices) > 1 else cached_kernel(kernel)
        i, p, k = triples.T
        leaves, tree = jax.tree.flatten(self.obstacles.take((self.scene_of[tr[i]], k)))  # one obstacle per triple

        def run(hulls, idx):
            return self._bucketed(
                lambda pp, T, mb, *it: tracked_call(call, (hulls, pp, T, jax.tree.unflatten(tree, it), mb,
                                                           self.margin), on_compile),
                [p[idx], d.T_part[i[idx], p[idx]], d.motion_b[i[idx], p[idx]], *(x[idx] for x in leaves)],
                buckets=CASCADE_BUCKETS)

        return by_vertex_class(self.hulls, p, run, CASCADE_BUCKETS)

    def _hull_stage(self, tr, a, b, on_compile) -> LeafRecord:
        """The hull stage (steps 2-5 of larc_jax.leaf.cascade) on the intervals ``(tr, a, b)``."""
        ar, br = self._rebased(tr, a, b)
        pairs_call = _interval_pairs if len(self.devices) > 1 else cached_kernel(_interval_pairs)
        d = PairDetails(*self._bucketed(
            lambda t, sc, x, y: tracked_call(pairs_call, (self.robot, self.capsules, self.hulls, self.splines,
                                                   self.obstacles, self.bounds, t, sc, x, y, self.margin),
                                      on_compile),
            [tr, self.scene_of[tr], ar, br], buckets=PAIR_BUCKETS))
        links = Links.of(self.capsules, self.hulls)
        G_c = np.asarray(self.bounds.guard_m)[tr]  # (F', C)
        G_p = np.asarray(self.bounds.hull_guard_m)[tr]  # (F', P)
        tried, triples = select_pairs(links, d.g_capsule - G_c[:, :, None], d.g_upper - G_p[:, :, None])
        g_hull = guard_hull = np.zeros(0)
        if len(triples):
            i, p, k = triples.T
            guard_hull = G_p[i, p]
            first = self._hull_round(_hull_first_axis, d, tr, triples, on_compile)
            g_hull = two_rounds(first, guard_hull,
                                lambda redo: self._hull_round(_hull_pairs, d, tr, triples[redo], on_compile))
        g, guard, cap, box, _ = combine(links, d.g_capsule, G_c, tried, triples, g_hull, guard_hull)
        return box_record(g, guard, cap, box, Stage.HULL)


def prepare(trajectories, scenes: Sequence[Scene], robot: Robot, capsules: CapsuleModel,
            margin: float, dtype, bounds: Sequence[RoundingBounds], devices=None,
            on_compile: Callable[[bool], None] | None = None, hulls: HullModel | None = None,
            self_pairs: SelfPairs | None = None, self_skip: Sequence[np.ndarray] | None = None,
            swept: SweptTables | None = None) -> Batch:
    """Pad a validated dataset into a :class:`Batch` (one scene and one
    :func:`~larc_jax.leaf.interval.trajectory_rounding` per trajectory).

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
    obstacles = stack_scenes(scene_list + scene_list[:1] * (size_class(len(scene_list), 1) - len(scene_list)), dtype)
    splines = spline_batch(*(np.stack([p[i] for p in padded]).astype(np.float64) for i in range(3)),
                           n_knots=np.array([t.n_waypoints for t in trajectories] + [trajectories[0].n_waypoints] * n_pad),
                           accel=swept is not None,  # the swept stage reads accelerations
                           call=lambda fn, args: tracked_call(fn, args, on_compile))
    robot_g, capsules_g = _geometry(robot, capsules, dtype)
    return Batch(
        robot=robot_g, capsules=capsules_g, splines=splines, bounds=stacked,
        obstacles=obstacles, scene_of=scene_of,
        t_start=np.array([t.t[0] for t in trajectories]), t_end=np.array([t.t[-1] for t in trajectories]),
        margin=np.asarray(margin, np.float64), dtype=dtype,
        devices=tuple(jax.devices() if devices is None else devices),
        hulls=None if hulls is None else _hulls_geometry(hulls, dtype), self_pairs=self_pairs,
        self_skip=None if self_skip is None else np.stack(list(self_skip) + list(self_skip[:1]) * n_pad),
        swept=swept,
    )
