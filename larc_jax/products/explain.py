"""Explaining a certificate: the interval that blocks it, or its tightest interval, recomputed.

:func:`explain` takes one trajectory's :class:`~larc_jax.engine.results.TrajectoryResult` and
recomputes, with the NumPy float64 reference kernels, everything the leaf test saw on one leaf
``I = [t_m - h, t_m + h]``, with the run spec the result carries (enclosure, tracking tolerance,
self-collision test, dtype): the leaf's record from :func:`~larc_jax.leaf.reference.leaf_test_np`
(the test that decided it, its clearance and guard); the capsule segments at the midpoint
configuration ``q(t_m)``, the motion radii ``b_l(I) = h * sum_j a_lj * max_I |qdot_j|`` (paper
eqs. 5-6) and the capsule test's clearance ``g(I)`` with its capsule/box pair, from
:func:`~larc_jax.leaf.interval.evaluate_interval_np`; and, where the record is not a capsule/box pair,
what decided the leaf: the hull part (placed at ``q(t_m)``, its motion radius, the polytope
kernel's proven bound, :mod:`larc_jax.leaf.cascade`) or the self-collision pair (its relative motion
radius, :mod:`larc_jax.leaf.self_collision`). By default (:func:`choose_leaf`) the leaf is the *first
inconclusive* one of an uncertified trajectory (the one the ``larc certify`` table names) or, for a
certified one, the leaf with the smallest clearance.

:func:`~larc_jax.products.explain_draw.render` draws it (re-exported here with :class:`Explanation`).
"""

from __future__ import annotations

import math

import numpy as np

from ..enclosure.capsule import CapsuleModel
from ..enclosure.tracking import check_tracking_tolerance
from ..engine.results import Leaf, TrajectoryResult
from ..errors import LarcInputError
from ..leaf.cascade import hull_pair_rounds_np, interval_pairs_np
from ..leaf.interval import evaluate_interval_np, trajectory_rounding
from ..leaf.placement import motion_radii
from ..leaf.record import LeafRecord, Stage
from ..leaf.reference import LeafEnclosures, leaf_enclosures, leaf_test_np
from ..leaf.self_collision import SelfPairs, curve_ranges, load_separation, segment_segment_distance_np, self_pairs
from ..model.robot import Robot
from ..model.scene import Scene
from ..model.shapes import shape_project
from ..model.trajectory import Trajectory
from ..obstacles import scene_obstacles
from ..run_spec import RunSpec
from .explain_draw import DecidingPair, DecidingPart, Explanation, describe_leaf, render, tool_capsules

__all__ = ["Explanation", "choose_leaf", "describe_leaf", "explain", "render", "segment_box_closest_points",
           "segment_closest_points", "segment_segment_closest_points", "polytope_box_closest_points", "tool_capsules"]


def choose_leaf(result: TrajectoryResult, which: str = "first", at: float | None = None) -> Leaf:
    """The leaf to explain.

    ``which="first"``: the first inconclusive leaf of an uncertified trajectory (the one the
    ``larc certify`` table names), else the leaf with the smallest clearance; ``"worst"``: the
    leaf with the smallest clearance; ``at=t``: the leaf whose interval contains time ``t``.
    """
    if not result.leaves:
        raise LarcInputError(f"{result.id}: the result has no leaves to explain")
    if at is not None:
        for leaf in result.leaves:
            if leaf.t0 <= at <= leaf.t1:
                return leaf
        raise LarcInputError(
            f"{result.id}: time {at} s is outside the horizon "
            f"[{result.leaves[0].t0}, {result.leaves[-1].t1}] s"
        )
    if which not in ("first", "worst"):
        raise LarcInputError(f"leaf choice must be 'first' or 'worst', got {which!r}")
    bad = result.first_inconclusive
    if which == "first" and bad is not None:
        return bad

    def key(leaf):  # NaN (non-finite values) first: it never certifies
        g = leaf.clearance_m
        return (-math.inf if math.isnan(g) else g, leaf.t0)

    return min(result.leaves, key=key)


def segment_closest_points(p0, p1, project, iters: int = 200):
    """Closest points between segment [p0, p1] and a convex set given by its nearest-point map
    ``project``: ternary search on the convex function s -> |p(s) - project(p(s))| (exact up to
    the search tolerance; for drawing only)."""

    def point(s):
        return p0 + s * (p1 - p0)

    def dist(s):
        x = point(s)
        return float(np.linalg.norm(x - project(x)))

    grid = np.linspace(0.0, 1.0, 65)
    k = int(np.argmin([dist(s) for s in grid]))
    a, b = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
    for _ in range(iters):
        m1, m2 = a + (b - a) / 3, b - (b - a) / 3
        if dist(m1) <= dist(m2):
            b = m2
        else:
            a = m1
    x = point(0.5 * (a + b))
    return x, project(x)


def segment_box_closest_points(p0, p1, lo, hi, iters: int = 200):
    """Closest points between segment [p0, p1] and box [lo, hi] (for drawing only)."""
    return segment_closest_points(p0, p1, lambda x: np.clip(x, lo, hi), iters)


def segment_segment_closest_points(p0, p1, q0, q1, iters: int = 200):
    """Closest points between segments [p0, p1] and [q0, q1] (for drawing only)."""
    d = q1 - q0
    return segment_closest_points(
        p0, p1, lambda x: q0 + float(np.clip(np.dot(x - q0, d) / max(float(np.dot(d, d)), 1e-300), 0.0, 1.0)) * d, iters)


def polytope_box_closest_points(vertices, lo, hi):
    """Closest points between the polytope conv(``vertices``) (K, 3) and the box [lo, hi], for
    drawing: bounded least squares (scipy, BVLS) on the vertex weights and the box point, the
    weights' sum held at 1 by a heavy row. The part point returned is a convex combination of the
    vertices and the box point its nearest box point, so their distance is never below the true
    distance (and meets it up to the solver's tolerance)."""
    from scipy.optimize import lsq_linear

    V = np.asarray(vertices, np.float64)
    K, heavy = len(V), 1e3
    A = np.zeros((4, K + 3))
    A[:3, :K], A[:3, K:], A[3, :K] = V.T, -np.eye(3), heavy
    upper = np.where(hi > lo, hi, np.nextafter(lo, np.inf))  # the solver wants lower < upper (flat boxes)
    fit = lsq_linear(A, np.r_[0.0, 0.0, 0.0, heavy], bounds=(np.r_[np.zeros(K), lo], np.r_[np.ones(K), upper]),
                     method="bvls")
    weights = np.maximum(fit.x[:K], 0.0)
    x = (weights / weights.sum()) @ V if weights.sum() > 0 else V[0]
    return x, np.clip(x, lo, hi)


def _deciding_part(robot: Robot, enc: LeafEnclosures, traj, scene: Scene, leaf: Leaf, margin: float, bounds, ev,
                   record: LeafRecord) -> DecidingPart | None:
    """The hull part whose clearance ``record`` holds (None if it holds a capsule's): the part of
    the recorded capsule's link with the least excess on the recorded box, as
    :func:`~larc_jax.leaf.cascade.combine` picks it."""
    k = int(record.box)
    if enc.links is None or not 0 <= k < scene.n_boxes or not math.isfinite(record.clearance_m):
        return None
    hulls, lo, hi = enc.hulls, scene.lo[k], scene.hi[k]  # drawn; clearances through the protocol:
    item = scene_obstacles(scene).take(k)
    on_link = np.flatnonzero(enc.links.of_part == enc.links.of_capsule[int(record.capsule)])
    if not len(on_link):
        return None
    d = interval_pairs_np(robot, enc.capsules, hulls, traj, scene, leaf.t0, leaf.t1, margin, bounds, ev)
    guard = np.asarray(bounds.hull_guard_m, np.float64)[on_link]
    g, steps = np.array([hull_pair_rounds_np(hulls, p, d.T_part[p], item, d.motion_b[p], margin, gd)
                         for p, gd in zip(on_link, guard)]).T
    best = int(np.argmin(g - guard))
    if not (g[best] == record.clearance_m and guard[best] == record.guard_m):
        return None  # the capsules decided the worst (link, box) pair
    p, T = int(on_link[best]), np.asarray(d.T_part[on_link[best]], np.float64)
    V, c, R, t = hulls.vertices[p], hulls.centre[p], T[:, :3], T[:, 3]
    # The bound the cascade recorded: that of the round that decided the triple (cascade step 4).
    lb = item.polytope_lower_bound_np(V, c, R, t, int(steps[best]))
    placed = np.asarray(hulls.vertices[p][: hulls.n_vertices[p]], np.float64) @ T[:, :3].T + T[:, 3]
    return DecidingPart(index=p, name=hulls.names[p], vertices_m=placed, radius_m=float(hulls.radius[p]),
                        motion_b_m=float(d.motion_b[p]), lower_bound_m=float(lb), reach_m=float(lb - g[best]),
                        closest=polytope_box_closest_points(placed, lo, hi))


def _deciding_pair(pairs: SelfPairs, ev, first: int, second: int) -> DecidingPair:
    """The numbers of the self pair (``first``, ``second``) on the placed leaf ``ev``."""
    p = int(np.flatnonzero((pairs.first == first) & (pairs.second == second))[0])
    b = motion_radii(pairs.motion_a[p: p + 1], ev.h_cov, np.asarray(ev.speed, np.float64))[0]
    pa, pb = ev.p_world_a, ev.p_world_b
    closest = segment_segment_closest_points(pa[first], pb[first], pa[second], pb[second])
    return DecidingPair(motion_b_m=float(b), margin_m=float(pairs.margin_m), closest=closest,
                        distance_m=segment_segment_distance_np(pa[first], pb[first], pa[second], pb[second]))


def explain(robot: Robot, capsules: CapsuleModel, traj: Trajectory, scene: Scene,
            result: TrajectoryResult, leaf: Leaf | None = None) -> Explanation:
    """Recompute the leaf test on ``leaf`` (default: ``choose_leaf(result)``) of ``traj`` with
    the run spec of the result (``result.spec``: margin, enclosure, tracking tolerance,
    self-collision test, dtype; a result without one: the capsule test at ``result.margin_m``).
    The leaf's decision is that of the whole test (:attr:`Explanation.stage`); the capsule numbers
    are the capsule test's, and :attr:`Explanation.part` or :attr:`Explanation.pair` hold the hull
    part or self pair whose clearance the leaf records.

    ``traj`` must already be in the robot's joint order (``read_trajectory(path, robot)``).
    """
    leaf = leaf or choose_leaf(result)
    spec = result.spec or RunSpec(method="reference", margin_m=result.margin_m, enclosure="capsules")
    capsules = capsules.with_padding(spec.padding_m)  # as certify placed them (RunSpec.padding_m)
    delta = check_tracking_tolerance(spec.tolerance_arg(), robot)
    enc = leaf_enclosures(robot, capsules, spec.enclosure, delta, swept=spec.swept)
    bounds = trajectory_rounding(traj, robot, enc.capsules, spec.dtype, enc.hulls)
    pairs, skip = None, None
    if spec.self_collision:
        pairs = self_pairs(robot, capsules, spec.self_margin_m, spec.self_skip, proven=load_separation(robot))
        pairs = pairs if pairs.n_pairs else None
        skip = None if pairs is None else pairs.skip_mask(*curve_ranges(traj, delta))
    record = leaf_test_np(robot, enc, traj, scene, leaf.t0, leaf.t1, spec.margin_m, bounds, pairs, skip)
    g, guard, c_dec, k_dec, other, stage = record
    # The capsule test's placed capsules (radii grown by any tracking tolerance).
    ev = evaluate_interval_np(robot, enc.capsules, traj, scene, leaf.t0, leaf.t1, spec.margin_m, bounds)
    c, k = int(ev.capsule), int(ev.box)
    closest, dist, part, pair = None, math.nan, None, None
    if other >= 0:  # a self-collision pair decided the leaf: its two capsules
        c, k = int(c_dec), -1
        pair = _deciding_pair(pairs, ev, c, int(other))
        closest, dist = pair.closest, pair.distance_m
    elif scene.n_obstacles:
        if enc.links is not None and stage != Stage.SWEPT:  # the hull test may have decided the worst pair
            c, k = int(c_dec), int(k_dec)
            part = _deciding_part(robot, enc, traj, scene, leaf, spec.margin_m, bounds, ev, record)
        if k < scene.n_boxes:
            closest = segment_box_closest_points(ev.p_world_a[c], ev.p_world_b[c], scene.lo[k], scene.hi[k])
        elif k < scene.n_boxes + scene.shapes.count:  # a posed shape
            s = k - scene.n_boxes
            closest = segment_closest_points(ev.p_world_a[c], ev.p_world_b[c],
                                             lambda x: shape_project(scene.shapes, s, x))
        else:  # a piece of a mesh or point cloud: the capsule test measures its bounding box
            Y = scene.point_sets.pieces[k - scene.n_boxes - scene.shapes.count]
            closest = segment_box_closest_points(ev.p_world_a[c], ev.p_world_b[c], Y.min(axis=0), Y.max(axis=0))
        dist = float(np.linalg.norm(closest[0] - closest[1]))
    else:
        c = k = -1
    passed = stage > 0
    stage_name = "" if not passed else "self" if other >= 0 else Stage(int(stage)).label
    return Explanation(
        trajectory_id=result.id, certified=result.certified, leaf=leaf, t_mid=float(ev.t_mid) + float(bounds.offset_s),
        h=float(ev.h_cov),
        q_mid=ev.q_mid, seg_a=ev.p_world_a, seg_b=ev.p_world_b, radius=np.asarray(enc.capsules.radius, np.float64),
        motion_b=ev.motion_b, margin_m=float(spec.margin_m), clearance_m=float(ev.g), capsule=c,
        box=k, distance_m=dist, closest=closest, stage=stage_name, decided_clearance_m=float(g),
        guard_m=float(guard), other_capsule=int(other), part=part, pair=pair,
    )
