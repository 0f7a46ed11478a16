"""The batched, jitted kernels of :class:`~larc_jax.engine.batch.Batch`: each vmaps one leaf-test
kernel (:mod:`larc_jax.leaf`) over F intervals or T (enclosure, obstacle) pairs.

An interval ``i`` belongs to trajectory ``traj[i]`` (its spline row and rounding bounds) and is
tested against the items ``obstacles.take(sel[:, i])``: ``sel`` is a tuple ``(scene,)`` (every
item of its scene) or ``(scene, items)`` (an (F, W) list of item indices: a culled interval,
:mod:`larc_jax.engine.cull`). Only the outputs a caller reads leave a call (XLA drops the rest).
"""

from __future__ import annotations

import dataclasses
import functools

from ..lazy_jax import jax, jnp
from ..leaf.cascade import (hull_pair_bounds, hull_pair_clearance, hull_points_clearance, interval_pairs,
                            interval_pairs_bounded, link_upper_excess, screened_interval)
from ..leaf.clearance import BROAD_PHASE_K
from ..leaf.interval import evaluate_interval
from ..leaf.placement import place
from ..leaf.rounds import EARLY_ITERATIONS
from ..leaf.self_collision import self_stage
from ..leaf.swept import swept_capsule_clearance, swept_part_clearance, swept_placement
from ..model.spline_batch import SplineRow
from ..obstacles.polytope import GJK_ITERATIONS

__all__ = ["evaluate_intervals", "evaluate_intervals_broad", "evaluate_intervals_screened",
           "evaluate_intervals_screened_broad", "item_margins", "batched_interval_pairs",
           "batched_interval_pairs_bounded", "hull_screen", "hull_first_axis", "hull_early", "hull_pairs",
           "self_intervals", "swept_intervals", "swept_capsules", "swept_parts"]


def batched_intervals(robot, capsules, splines, obstacles, bounds, traj, sel, a, b, margin, k):
    """Evaluate F intervals: interval i belongs to trajectory ``traj[i]`` and is tested against the
    items ``obstacles.take(sel[:, i])`` (:meth:`Batch.selection`: its scene's items, or a culled
    list of them, :mod:`larc_jax.engine.cull`). Only ``(g, guard, capsule, box, exact)`` leave the call (XLA drops the record's other fields)."""

    def one(t, s, ai, bi):
        spline = SplineRow(splines, t)  # read in place, not copied per interval
        bnd = jax.tree.map(lambda x: x[t], bounds)
        ev = evaluate_interval(robot, capsules, spline, obstacles.take(s), ai, bi, margin, bnd, k)
        return ev.g, ev.guard, ev.capsule, ev.box, ev.exact

    return jax.vmap(one)(traj, sel, a, b)


@jax.jit
def evaluate_intervals(robot, capsules, splines, obstacles, bounds, traj, sel, a, b, margin):
    """The interval test with every capsule-obstacle pair exact."""
    return batched_intervals(robot, capsules, splines, obstacles, bounds, traj, sel, a, b, margin, None)


@jax.jit
def evaluate_intervals_broad(robot, capsules, splines, obstacles, bounds, traj, sel, a, b, margin):
    """The interval test through the broad phase (:data:`~larc_jax.leaf.clearance.BROAD_PHASE_K` exact
    pairs per interval); intervals whose ``exact`` is False are evaluated again all-pairs."""
    return batched_intervals(robot, capsules, splines, obstacles, bounds, traj, sel, a, b, margin, BROAD_PHASE_K)


@jax.jit
def batched_interval_pairs(robot, capsules, hulls, splines, obstacles, bounds, traj, sel, a, b, margin):
    """Step 2 of the cascade (larc_jax.leaf.cascade) on F intervals, as ``evaluate_intervals``: the
    fields of :class:`~larc_jax.leaf.cascade.PairDetails` as a tuple (what the compilation cache keeps)."""

    def one(k, s, ai, bi):
        spline = SplineRow(splines, k)
        bnd = jax.tree.map(lambda x: x[k], bounds)
        d = interval_pairs(robot, capsules, hulls, spline, obstacles.take(s), ai, bi, margin, bnd)
        return d.g_capsule, d.T_part, d.motion_b, d.g_upper

    return jax.vmap(one)(traj, sel, a, b)


def screened_kernel(k: int | None):
    """Step 1 of the cascade and the screen before step 2 on F intervals, as ``evaluate_intervals``
    (``k``: its broad phase) with ``link_of`` (:func:`~larc_jax.leaf.cascade.screened_interval`):
    its outputs and the screen's excess (F,). One jitted function per ``k``, each with its own name."""

    def kernel(robot, capsules, hulls, link_of, splines, obstacles, bounds, traj, sel, a, b, margin):
        def one(t, s, ai, bi):
            bnd = jax.tree.map(lambda x: x[t], bounds)
            ev, excess = screened_interval(robot, capsules, hulls, link_of, SplineRow(splines, t), obstacles.take(s),
                                           ai, bi, margin, bnd, k)
            return ev.g, ev.guard, ev.capsule, ev.box, ev.exact, excess

        return jax.vmap(one)(traj, sel, a, b)

    kernel.__name__ = kernel.__qualname__ = "evaluate_intervals_screened" + ("" if k is None else "_broad")
    return jax.jit(kernel)


evaluate_intervals_screened = screened_kernel(None)
evaluate_intervals_screened_broad = screened_kernel(BROAD_PHASE_K)


@jax.jit
def batched_interval_pairs_bounded(robot, capsules, hulls, splines, obstacles, bounds, traj, sel, a, b, margin):
    """:func:`batched_interval_pairs` through :func:`~larc_jax.leaf.cascade.interval_pairs_bounded`:
    its fields and ``rest`` (F,)."""

    def one(k, s, ai, bi):
        bnd = jax.tree.map(lambda x: x[k], bounds)
        d, rest = interval_pairs_bounded(robot, capsules, hulls, SplineRow(splines, k), obstacles.take(s), ai, bi, margin,
                                         bnd)
        return d.g_capsule, d.T_part, d.motion_b, d.g_upper, rest

    return jax.vmap(one)(traj, sel, a, b)


@jax.jit
def hull_screen(robot, capsules, hulls, splines, bounds, traj, a, b, items, on_link, margin):
    """The screen before step 2 (:func:`~larc_jax.leaf.cascade.link_upper_excess`) on F intervals,
    each against one obstacle (``items``) and the parts ``on_link`` (F, P) of one link: (F,)."""

    def one(t, ai, bi, item, mask):
        bnd = jax.tree.map(lambda x: x[t], bounds)
        return link_upper_excess(robot, capsules, hulls, SplineRow(splines, t), item, ai, bi, margin, bnd, mask)

    return jax.vmap(one)(traj, a, b, items, on_link)


def hull_pairs_kernel(iterations: int, upper: bool = False):
    """Step 4 of the cascade on T (part, obstacle) pairs (``items``: one obstacle per pair) with
    ``iterations`` GJK steps: (T,) clearances, or with ``upper`` (T, 2) clearances and upper bounds
    (:func:`~larc_jax.leaf.cascade.hull_pair_bounds`); one jitted function per round, each with its
    own name (the compilation cache keys kernels by name)."""

    def kernel(hulls, part, T_part, items, motion_b, margin):
        if upper:
            one = lambda *args: jnp.stack(hull_pair_bounds(*args, iterations=iterations))  # noqa: E731
        else:
            one = functools.partial(hull_pair_clearance, iterations=iterations)
        return jax.vmap(one, in_axes=(None, 0, 0, 0, 0, None))(hulls, part, T_part, items, motion_b, margin)

    kernel.__name__ = kernel.__qualname__ = f"_hull_pairs_{iterations}" + ("_bounds" if upper else "")
    return jax.jit(kernel)


hull_first_axis = hull_pairs_kernel(0)
hull_early = hull_pairs_kernel(EARLY_ITERATIONS, upper=True)
hull_pairs = hull_pairs_kernel(GJK_ITERATIONS)


@jax.jit
def hull_points(hulls, part, T_part, items, motion_b, margin):
    """Step 4's third round (:func:`~larc_jax.leaf.cascade.hull_points_clearance`) on T (part,
    obstacle) pairs, with the signature of the other rounds."""
    return jax.vmap(hull_points_clearance, in_axes=(None, 0, 0, 0, 0, None))(hulls, part, T_part, items, motion_b,
                                                                            margin)


@jax.jit
def self_intervals(robot, capsules, splines, bounds, traj, a, b, self_check):
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
def swept_intervals(robot, capsules, hulls, tables, splines, obstacles, bounds, traj, sel, a, b, margin):
    """Step 1 of the swept stage (:func:`~larc_jax.leaf.swept.swept_placement`) on F intervals, as
    ``evaluate_intervals``: the fields of :class:`~larc_jax.leaf.swept.SweptPlacement` as a tuple."""

    def one(k, s, ai, bi):
        bnd = jax.tree.map(lambda x: x[k], bounds)
        d = swept_placement(robot, capsules, hulls, tables, SplineRow(splines, k), obstacles.take(s), ai, bi, margin,
                            bnd)
        return tuple(getattr(d, f.name) for f in dataclasses.fields(d))

    return jax.vmap(one)(traj, sel, a, b)


@jax.jit
def swept_capsules(capsules, capsule, R_ends, t_ends, items, swept_e, margin):
    """Step 1b of the swept stage on T (capsule, obstacle) pairs (``items``: one obstacle per pair)."""
    return jax.vmap(swept_capsule_clearance, in_axes=(None, 0, 0, 0, 0, 0, None))(
        capsules, capsule, R_ends, t_ends, items, swept_e, margin)


@jax.jit
def swept_parts(hulls, part, T_mid, R_ends, t_ends, items, motion_b, swept_e, margin):
    """Step 2 of the swept stage on T (part, obstacle) pairs (``items``: one obstacle per pair)."""
    return jax.vmap(swept_part_clearance, in_axes=(None, 0, 0, 0, 0, 0, 0, 0, None))(
        hulls, part, T_mid, R_ends, t_ends, items, motion_b, swept_e, margin)


@jax.jit
def item_margins(robot, capsules, splines, obstacles, bounds, traj, sel, a, b, margin):
    """The capsule test of F intervals, per item: the least ``g - guard`` over the capsules (NaN
    where the pair's is), that pair's ``g``, guard and capsule ((F, W) each), and whether the
    placement was finite (F,) (:mod:`larc_jax.engine.cull`: its nodes against the cluster boxes, and
    which items a culled leaf's later stages need)."""

    def one(t, s, ai, bi):
        bnd = jax.tree.map(lambda x: x[t], bounds)
        ev = evaluate_interval(robot, capsules, SplineRow(splines, t), obstacles.take(s), ai, bi, margin, bnd, None)
        slack = ev.g_pairs - bnd.guard_m[:, None]  # (C, W)
        cap = slack.argmin(axis=0)
        at = lambda x: jnp.take_along_axis(x, cap[None], axis=0)[0]  # noqa: E731
        return at(slack), at(ev.g_pairs), bnd.guard_m[cap], cap, ~jnp.isnan(ev.g)

    return jax.vmap(one)(traj, sel, a, b)
