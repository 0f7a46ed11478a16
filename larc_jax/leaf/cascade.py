"""The enclosure cascade: the capsule test first, the convex-hull test on what it leaves open.

An interval passes the cascade when, for every link ``l`` and box ``k``, *either* all of the
link's capsules clear the box (paper eq. 7) *or* all of its hull parts
(:mod:`larc_jax.enclosure.hull`) do: each of the two unions contains the link's geometry, so
either proof shows the link more than rho from the box on the whole interval. The hull test
of one part against one box is::

    g_h = lb(part at q(t_m), box) - (radius_p + b_p(I) + rho) (1 + 2 eps)

with ``lb`` the obstacle kind's proven ``polytope_lower_bound`` (:mod:`larc_jax.obstacles`; for a
box :func:`larc_jax.obstacles.polytope.polytope_box_lower_bound`, its own rounding already subtracted), ``radius_p`` the padding (plus the containment slack) and
``b_p(I) = h_cov * sum_j a_pj * (omega_max_j(I) + slack_j)`` the part's motion radius from its
own motion constants (eq. 6, budget P3 of :mod:`larc_jax.leaf.interval`). The part is placed at the
same midpoint ``q(t_m)``, with the same covering radius and speed bound, as the capsules: both
stages read them from one :class:`~larc_jax.leaf.interval.IntervalEval`, so the hull stage inherits
the capsule stage's time handling (budget T). A part passes a box when ``g_h > G_p``, ``G_p``
the part's rounding guard (``RoundingBounds.hull_guard_m``: the capsule guard's formula with
the part's chain, vertices and motion constants, budget G1 and P3).

Every comparison below is of an *excess* ``g - G`` (capsule ``g_lk - G_l``, part ``g_h - G_p``):
``fl(g - G) > 0`` iff ``g > G``, so a leaf records the ``(g, G)`` of the enclosure that decided
it, and passes iff ``g > G``.

Order of work (all of it deterministic, so every scheduler takes the same decisions):

1. the capsule test on every interval (:mod:`larc_jax.leaf.interval`); intervals with
   ``g > guard`` pass ("capsule" stage); NaN fails;
2. for the others, one compacted call (:func:`interval_pairs`) gives every capsule-box
   clearance, the parts' link poses and motion radii, and for each part-box pair an *upper*
   bound of its hull clearance from 14 of its vertices (a point of the part is at least as far
   as the part). In an unculled batch without separate points, :func:`interval_pairs_bounded`
   gives the exact clearance of the 8 capsule-box pairs of least lower excess and a lower bound
   for the rest (sound in steps 3-5), and the intervals where a bound could change a decision or
   a record (:func:`exact_enough`; on Stage B 360 of 10,264) are computed again all-exact, so
   the results are those of every pair exact (a distance may differ in its last bit, computed in
   another program); on Stage B the call costs about 10.5 ms per 1,024 intervals instead of 16;
3. a (link, box) pair is sent to the hull test when its capsules fail (excess ``<= 0``) and
   every one of its parts could still pass (upper bound above its guard): otherwise the hull
   test could not change the outcome, and is skipped (skipping never certifies);
4. those (interval, part, box) triples (:func:`hull_pair_clearance`) in rounds
   (:func:`~larc_jax.leaf.rounds.hull_rounds`): first every triple on the GJK search's first
   axis alone (``iterations=0``, the direction from the part's centre to the obstacle: one
   support evaluation, about a thirteenth of the search); then
   :data:`~larc_jax.leaf.rounds.EARLY_ITERATIONS` steps with their upper bound
   (:func:`hull_pair_bounds`; ``+inf`` for a kind without one, none here) on the
   triples the first round left at or below their guard; then the full search (:data:`~larc_jax.obstacles.polytope.GJK_ITERATIONS`
   steps, from scratch) on those still undecided: at or below the guard, and an upper bound above
   ``guard - slack`` (:func:`~larc_jax.leaf.rounds.early_stop_slack`). Each round is a sound
   lower bound (stopping never certifies what the round did not prove); the search keeps the
   largest bound it meets, starting with that same axis, so a triple an early round passes the
   full search passes too, and one whose upper bound is at or below its guard less the slack the
   full search cannot pass (both up to the last bit of separately compiled evaluations;
   tests/test_cascade.py checks the decisions against the full search on every triple); a triple
   records the round that decided it (Stage B, LARC: the first axis decides 3,244 of 4,948
   triples, the middle round 1,593 of the other 1,704, the full search the last 111); a third
   round (:func:`~larc_jax.leaf.rounds.point_round`) takes the triples still at or below their
   guard whose obstacle is a point cloud's piece and searches each of the piece's points alone
   (:func:`hull_points_clearance`; R7 of :mod:`larc_jax.obstacles.convex_shapes`: the piece's
   hull fills the gaps between its points, the points do not); such a triple records the larger
   of its two sound values (a NaN stays NaN);
5. per (l, k) the excess is ``max(min_capsules, min_parts)`` (parts only where tested); the
   interval's is the minimum over (l, k); it passes ("hull" stage) when that is > 0.

The screen comes before step 2, on every interval the capsules fail, at every depth and in
every scheduler (:meth:`~larc_jax.engine.batch.Batch.evaluate_cascade`, :func:`cascade_np`):
:func:`link_upper_excess` computes step 2's upper bounds ``U`` for the parts of the one link
``l*`` whose capsule ``c*`` the capsule stage recorded, against the recorded item ``k*``. If
``min_p (U_p - G_p) <= 0`` (or NaN), steps 2-4 are skipped and the capsule record stands.
Why that is the record steps 2-5 would write: Step 3 tries ``(l*, k*)`` only if every part of
``l*`` could pass, so it does not; step 5 gives that pair its capsule excess ``e*``, the least
capsule excess of the interval, and every other pair at least its own capsule excess
(``max(capsules, parts)``), which is ``>= e*``; so step 5's minimum is ``e*`` on ``(l*, k*)``
with capsule ``c*``: the capsule record. Three exceptions, none of them able to pass a leaf the
cascade fails: step 2 computes the capsule clearances again (every pair exact, in another
program) and may differ from step 1's in the last bit (on the Stage B set 469 of LARC's 13,976
leaves differ, by at most 1.6e-16 m), so a leaf at ``e* <= 0`` by a last bit fails where steps
2-5 might pass it; ties between pairs may pick another pair of the same excess; a NaN hull
clearance on another tried pair would have recorded NaN (the leaf fails either way).
LARC computes the screen inside step 1's kernel (:func:`screened_interval`) in an unculled
batch: from step 1's own placement and speed maxima, for the parts of the recorded link only
(on the PIPER at most 2 of 11 parts), so a screened interval costs step 1 plus a few probes,
not a second placement of every part. Fixed-fine, whose capsules fail few of its intervals
(Stage B: 8,752 of 81,920), runs the plain step 1 and screens those in a call of their own
(:func:`link_upper_excess`; it places them again, and costs on Stage B about the time it spares),
as does an interval whose recorded pair the broad phase could not prove (evaluated again on
every pair) and a culled batch's intervals (one kernel per item-list width would compile it again).

:func:`combine` is step 5 (NumPy, shared by every scheduler); :func:`cascade_np` runs steps 1-5
on one interval with the NumPy float64 references (:func:`interval_pairs_np`,
:func:`hull_pair_clearance_np`) for the reference scheduler. Boxes, here, are any obstacle kind.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np

from ..enclosure.capsule import CapsuleModel
from ..enclosure.hull import HullModel
from .clearance import PAIR_EXACT_K, pair_clearances
from .interval import capsule_offsets, evaluate_interval, evaluate_interval_np, evaluate_placed, motion_radii
from .placement import place
from .rounds import EARLY_ITERATIONS, early_stop_slack, hull_rounds, point_round
from ..lazy_jax import jax, jnp, pytree_dataclass
from ..obstacles import scene_obstacles
from ..obstacles.polytope import GJK_ITERATIONS
from ..model.kinematics import link_poses
from ..model.robot import Robot, forward_kinematics_np

__all__ = ["PairDetails", "interval_pairs", "interval_pairs_np", "hull_pair_clearance",
           "hull_pair_clearance_np", "hull_pair_bounds", "hull_pair_rounds_np", "hull_points_clearance", "link_upper_excess", "link_upper_excess_np",
           "screened_interval", "interval_pairs_bounded", "exact_enough",
           "polytope_clearance", "polytope_clearance_np", "Links", "select_pairs",
           "combine", "cascade_np"]

@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class PairDetails:
    """What step 2 computes on one interval (JAX or NumPy arrays)."""

    g_capsule: jax.Array
    """(C, B) capsule-box clearances ``g_lk`` (eq. 7 as computed by the capsule stage), m;
    +inf for padding boxes."""
    T_part: jax.Array
    """(P, 3, 4) pose of each part's link at q(t_m): rotation | translation."""
    motion_b: jax.Array
    """(P,) motion radius of each part (P3), m."""
    g_upper: jax.Array
    """(P, B) upper bound of each part-box hull clearance, m; +inf for padding boxes."""


def _shell(radius, motion_b, margin, eps):
    """``(r + b + rho) (1 + 2 eps)``: an upper bound of the sum (budget G4)."""
    return (radius + motion_b + margin) * (1 + 2 * eps)


def interval_pairs(robot: Robot, capsules: CapsuleModel, hulls: HullModel, spline, obstacles,
                   a, b, margin, bounds) -> PairDetails:
    """Step 2 on one interval ``[a, b]`` (rebased) of one trajectory against one scene's obstacle
    set (kernel; batch with ``jax.vmap``)."""
    ev = evaluate_interval(robot, capsules, spline, obstacles, a, b, margin, bounds)
    T, motion_b, g_upper = _part_upper_bounds(robot, hulls, ev, obstacles, margin)
    return PairDetails(g_capsule=ev.g_pairs, T_part=T, motion_b=motion_b, g_upper=g_upper)


def interval_pairs_bounded(robot: Robot, capsules: CapsuleModel, hulls: HullModel, spline, obstacles, a, b, margin,
                           bounds, k: int = PAIR_EXACT_K) -> tuple[PairDetails, jax.Array]:
    """:func:`interval_pairs` with the ``k`` capsule-box pairs of least lower excess exact and the
    others at a lower bound (:func:`~larc_jax.leaf.clearance.pair_clearances`), and ``rest``, a
    lower bound of ``g_lk - G_l`` of every pair left at its bound (NaN if the placement is not
    finite). Lower bounds are sound in steps 3-5; the results are those of :func:`interval_pairs`
    when ``rest > 0`` (every pair a capsule fails is exact) and the interval's excess is below
    ``rest`` (its deciding pair is exact): :func:`exact_enough` (kernel; batch with ``jax.vmap``)."""
    pl = place(robot, capsules, spline, a, b, bounds)
    shell, dist_scale = capsule_offsets(pl, capsules, margin)
    g, rest = pair_clearances(pl.p_world_a, pl.p_world_b, shell, obstacles, k, dist_scale, bounds.guard_m)
    T, motion_b, g_upper = _part_upper_bounds(robot, hulls, pl, obstacles, margin)
    return (PairDetails(g_capsule=g, T_part=T, motion_b=motion_b, g_upper=g_upper),
            jnp.where(pl.finite, rest, jnp.nan))


def exact_enough(links: "Links", cap_excess: np.ndarray, upper_excess: np.ndarray, rest: np.ndarray) -> np.ndarray:
    """(F,) bool: where :func:`interval_pairs_bounded` gives what :func:`interval_pairs` gives, from
    step 2's excesses (``cap_excess`` (F, C, B), ``upper_excess`` (F, P, B)) before steps 3-4. Each
    (l, k) pair's step-5 excess is at most ``max(capsule excess, least part upper excess)`` (at
    most the capsule excess where step 3 does not try it), so the interval's is at most their
    minimum ``u``; if ``rest > 0`` and ``u < rest`` (NaN: no), every pair a capsule fails and the
    deciding pair are exact, every value at a bound stays above the minimum, and steps 3-5 take
    the same decisions and record the same pair and values as with every pair exact."""
    cap = links.reduce_min(cap_excess, links.of_capsule)  # (F, L, B)
    upper = np.maximum(cap, links.reduce_min(upper_excess, links.of_part) + EXACT_ENOUGH_SLACK_M)
    u = np.where(cap > 0, cap, upper).min(axis=(1, 2), initial=np.inf)
    return (rest > 0) & (u < rest)


EXACT_ENOUGH_SLACK_M = 1e-9
"""Added to a part's upper excess in :func:`exact_enough`: a hull lower bound (step 4) is below the
part's upper bound in exact arithmetic; this covers the rounding of the two (a NaN stays NaN).
It only sends more intervals to the all-exact step 2; no verdict depends on it."""


def _part_upper_bounds(robot: Robot, hulls: HullModel, pl, obstacles, margin, parts=None):
    """The parts' link poses (P, 3, 4), motion radii (P,) and hull clearance upper bounds (P, B)
    on an interval placed as ``pl`` (:class:`~larc_jax.leaf.placement.Placement` or the
    :class:`~larc_jax.leaf.interval.IntervalEval` that holds one): step 2's, and the screen's;
    with ``parts`` (M,) indices, those parts' alone (each part's numbers computed alike)."""
    eps = float(jnp.finfo(pl.speed.dtype).eps)
    gdtype = robot.T_parent_joint.dtype
    of = (lambda x: x) if parts is None else (lambda x: jnp.asarray(x)[parts])  # noqa: E731
    T = link_poses(robot, pl.q_mid.astype(gdtype))[of(jnp.asarray(hulls.link_index))]  # (P, 3, 4)
    motion_b = motion_radii(of(hulls.motion_a), pl.h_cov, pl.speed)  # eq. 6, the parts' own a_pj
    probes = jnp.einsum("pij,pqj->pqi", T[:, :, :3], of(hulls.probes).astype(gdtype)) + T[:, None, :, 3]
    d = obstacles.nearest_point_distances(probes)  # (P, B)
    # An upper bound, used only to skip pairs that cannot pass: no rounding care needed.
    g_upper = d.astype(motion_b.dtype) - _shell(of(hulls.radius), motion_b, margin, eps)[:, None]
    return T, motion_b, jnp.where(obstacles.mask[None, :], g_upper, jnp.inf)


def link_upper_excess(robot: Robot, capsules: CapsuleModel, hulls: HullModel, spline, item, a, b, margin, bounds,
                      on_link) -> jax.Array:
    """The screen ahead of step 2 on one interval ``[a, b]`` (rebased) and one obstacle ``item``
    (:meth:`~larc_jax.obstacles.ObstacleSet.take` of one item): the least, over the parts with
    ``on_link`` (P,) bool, of step 2's upper bound ``g_upper`` minus the part's guard ``G_p``
    (kernel; batch with ``jax.vmap``).

    Where the capsule stage fails an interval on (capsule c, item k), the link ``l`` of ``c`` has
    capsule excess ``<= 0`` against ``k``. If this value (the parts of ``l``) is ``<= 0`` or NaN,
    step 3 does not try ``(l, k)`` and step 5 gives it its capsule excess: the interval fails the
    hull stage whatever steps 2-4 compute elsewhere, and keeps its capsule record without
    running them (module docstring, "The screen"); it computes the same numbers as step 2 (one
    placement, :func:`_part_upper_bounds`)."""
    return _placed_upper_excess(robot, hulls, place(robot, capsules, spline, a, b, bounds), item, margin, bounds,
                                on_link)


def _placed_upper_excess(robot: Robot, hulls: HullModel, pl, item, margin, bounds, on_link, parts=None) -> jax.Array:
    """:func:`link_upper_excess` on an interval placed as ``pl`` (``on_link`` over ``parts`` if given)."""
    one = jax.tree.map(lambda x: x[None], item)  # a one-item set: step 2's code path
    _, _, g_upper = _part_upper_bounds(robot, hulls, pl, one, margin, parts)
    guard = bounds.hull_guard_m if parts is None else bounds.hull_guard_m[parts]
    return jnp.min(jnp.where(on_link, g_upper[:, 0] - guard, jnp.inf))


def screened_interval(robot: Robot, capsules: CapsuleModel, hulls: HullModel, link_of, spline, obstacles, a, b,
                      margin, bounds, k: int | None = None):
    """Step 1 and the screen from one placement: ``(ev, excess)``, ``ev`` the capsule test of
    :func:`~larc_jax.leaf.interval.evaluate_interval` (broad phase ``k``) and ``excess`` the
    screen (:func:`link_upper_excess`) on the (link, item) pair ``ev`` records; ``link_of =
    (Links.of_capsule, Links.part_table)``. Only read where the capsules fail. The placement
    and the speed maxima are computed once for both, and only the recorded link's parts are
    bounded (at most M, not P: on the PIPER 2 of 11) (kernel; batch with ``jax.vmap``)."""
    pl = place(robot, capsules, spline, a, b, bounds)
    ev = evaluate_placed(pl, capsules, obstacles, margin, bounds, k)
    parts = link_of[1][link_of[0][ev.capsule]]  # (M,): the link's parts, -1 padded
    return ev, _placed_upper_excess(robot, hulls, pl, obstacles.take(ev.box), margin, bounds, parts >= 0,
                                    jnp.maximum(parts, 0))


def hull_pair_clearance(hulls: HullModel, part, T_part, item, motion_b, margin,
                        iterations: int = GJK_ITERATIONS) -> jax.Array:
    """Step 4 on one (part, obstacle) pair: ``g_h`` of the module docstring (kernel; ``vmap`` it).

    Args:
      part: index of the part; T_part: (3, 4) its link's pose at q(t_m) (geometry dtype); item:
        one obstacle (:meth:`~larc_jax.obstacles.ObstacleSet.take`); motion_b: the part's motion
        radius b_p(I), m (float64); margin: rho, m; iterations: GJK steps after the first axis
      (static; 0: the first round of step 4).
    """
    return polytope_clearance(hulls.vertices, part, hulls.centre[part], hulls.radius[part], T_part[:, :3],
                              T_part[:, 3], item, motion_b, margin, iterations)


def hull_points_clearance(hulls: HullModel, part, T_part, item, motion_b, margin) -> jax.Array:
    """Step 4's third round on one (part, obstacle) pair, as :func:`hull_pair_clearance` but to
    the nearest of the obstacle's separate points
    (:meth:`~larc_jax.obstacles.ObstacleSet.points_lower_bound`; ``-inf`` for other items)
    (kernel; ``vmap`` it)."""
    eps = float(jnp.finfo(motion_b.dtype).eps)
    lb = item.points_lower_bound(hulls.vertices, part, hulls.centre[part], T_part[:, :3], T_part[:, 3])
    return lb.astype(motion_b.dtype) - _shell(hulls.radius[part], motion_b, margin, eps)


def hull_pair_bounds(hulls: HullModel, part, T_part, item, motion_b, margin, iterations: int = EARLY_ITERATIONS):
    """``(g_h, upper)``: :func:`hull_pair_clearance` and an upper bound of the same clearance up to
    rounding (the search's last iterate less the same shell; only to stop searching, module
    docstring step 4; ``+inf`` for a kind without one) (kernel; ``vmap`` it)."""
    eps = float(jnp.finfo(motion_b.dtype).eps)
    lb, ub = item.polytope_bounds(hulls.vertices, part, hulls.centre[part], T_part[:, :3], T_part[:, 3], iterations)
    shell = _shell(hulls.radius[part], motion_b, margin, eps)
    return lb.astype(motion_b.dtype) - shell, ub.astype(motion_b.dtype) - shell


def polytope_clearance(vertices, part, centre, radius, R, t, item, motion, margin,
                       iterations: int = GJK_ITERATIONS) -> jax.Array:
    """``lb(conv(R vertices[part] + t), item) - (radius + motion + rho) (1 + 2 eps)``: the clearance
    of a polytope placed by ``R, t`` ((3, 3), (3,); or a stack of placements, the hull of their
    union: :mod:`larc_jax.obstacles.polytope`) and grown by ``radius`` (m) and a motion radius
    ``motion`` (m, float64), to one obstacle (kernel; the hull test and the swept test,
    :mod:`larc_jax.leaf.swept`)."""
    eps = float(jnp.finfo(motion.dtype).eps)
    lb = item.polytope_lower_bound(vertices, part, centre, R, t, iterations)
    return lb.astype(motion.dtype) - _shell(radius, motion, margin, eps)


# ----------------------------------------------------------------------------------------------
# NumPy float64 references
# ----------------------------------------------------------------------------------------------


def interval_pairs_np(robot: Robot, capsules: CapsuleModel, hulls: HullModel, traj, obstacles, a: float,
                      b: float, margin: float, bounds, ev=None) -> PairDetails:
    """NumPy float64 reference of :func:`interval_pairs` on the leaf ``[a, b]`` in the
    trajectory's own time axis (``traj``: a Trajectory, ``obstacles``: an obstacle set or a Scene
    (:func:`~larc_jax.obstacles.scene_obstacles`), ``bounds``:
    :func:`~larc_jax.leaf.interval.trajectory_rounding`; ``ev``: the leaf's
    :func:`~larc_jax.leaf.interval.evaluate_interval_np`, if computed)."""
    obstacles = scene_obstacles(obstacles)
    ev = ev if ev is not None else evaluate_interval_np(robot, capsules, traj, obstacles, a, b, margin, bounds)
    eps = float(np.finfo(np.float64).eps)
    T_all = forward_kinematics_np(robot, ev.q_mid)
    T = np.stack([T_all[li][:3, :] for li in hulls.link_index])
    motion_b = motion_radii(np.asarray(hulls.motion_a, np.float64), ev.h_cov, np.asarray(ev.speed, np.float64))
    U = np.full((hulls.n_parts, max(obstacles.n_items, 1)), np.inf)
    probes = np.asarray(hulls.probes, np.float64)
    radius = np.asarray(hulls.radius, np.float64)
    for p in range(hulls.n_parts):
        world = probes[p] @ T[p, :, :3].T + T[p, :, 3]
        for k in (k for k in range(obstacles.n_items) if obstacles.mask[k]):
            U[p, k] = obstacles.take(k).point_distance_np(world).min() - _shell(radius[p], motion_b[p], margin, eps)
    return PairDetails(g_capsule=np.asarray(ev.g_pairs, np.float64), T_part=T, motion_b=motion_b, g_upper=U)


def link_upper_excess_np(robot: Robot, capsules: CapsuleModel, hulls: HullModel, traj, obstacles, a: float,
                         b: float, margin: float, bounds, item: int, on_link) -> float:
    """NumPy float64 reference of :func:`link_upper_excess` on the leaf ``[a, b]`` in the
    trajectory's own time axis and item ``item`` of ``obstacles`` (as :func:`interval_pairs_np`)."""
    d = interval_pairs_np(robot, capsules, hulls, traj, obstacles, a, b, margin, bounds)
    excess = d.g_upper[:, item] - np.asarray(bounds.hull_guard_m, np.float64)
    return float(np.min(np.where(np.asarray(on_link, bool), excess, np.inf)))


def hull_pair_clearance_np(hulls: HullModel, part: int, T_part, item, motion_b: float, margin: float,
                           guard: float | None = None) -> float:
    """NumPy float64 reference of :func:`hull_pair_clearance` (``item``: one obstacle); with the
    triple's ``guard``, what step 4 records (every round, :func:`hull_pair_rounds_np`)."""
    if guard is None:
        return polytope_clearance_np(hulls.vertices[part], hulls.centre[part], float(hulls.radius[part]),
                                     np.asarray(T_part, np.float64)[:, :3], np.asarray(T_part, np.float64)[:, 3],
                                     item, motion_b, margin, GJK_ITERATIONS)
    return hull_pair_rounds_np(hulls, part, T_part, item, motion_b, margin, guard)[0]


def hull_pair_rounds_np(hulls: HullModel, part: int, T_part, item, motion_b: float, margin: float,
                        guard: float) -> tuple[float, int]:
    """What step 4 records for one triple (NumPy float64, every round: :func:`hull_rounds`, then
    :func:`point_round`), and the GJK steps of the round that decided it."""
    T_part = np.asarray(T_part, np.float64)
    V, c, R, t = hulls.vertices[part], hulls.centre[part], T_part[:, :3], T_part[:, 3]
    eps = float(np.finfo(np.float64).eps)
    shell = _shell(float(hulls.radius[part]), motion_b, margin, eps)

    def value(iterations: int) -> float:
        return polytope_clearance_np(V, c, float(hulls.radius[part]), R, t, item, motion_b, margin, iterations)

    def early(redo):
        lb, ub = item.polytope_bounds_np(np.asarray(V, np.float64), np.asarray(c, np.float64), R, t, EARLY_ITERATIONS)
        return np.array([lb - shell]), np.array([ub - shell])

    guard = np.array([guard], np.float64)
    g, steps = hull_rounds(np.array([value(0)]), guard, lambda redo: np.array([value(GJK_ITERATIONS)]),
                           early, early_stop_slack(np.float64))

    def points(redo):
        lb = item.points_lower_bound_np(hulls.vertices[part], hulls.centre[part], T_part[:, :3], T_part[:, 3])
        return np.array([lb - shell])

    return float(point_round(g, guard, np.atleast_1d(item.separate_points()), points)[0]), int(steps[0])


def polytope_clearance_np(V, centre, radius: float, R, t, item, motion: float, margin: float,
                          iterations: int = GJK_ITERATIONS) -> float:
    """NumPy float64 reference of :func:`polytope_clearance` (``V``: the polytope's points)."""
    eps = float(np.finfo(np.float64).eps)
    lb = item.polytope_lower_bound_np(np.asarray(V, np.float64), np.asarray(centre, np.float64),
                                      np.asarray(R, np.float64), np.asarray(t, np.float64), iterations)
    return lb - _shell(radius, motion, margin, eps)


# ----------------------------------------------------------------------------------------------
# Steps 3 and 5 (host side, NumPy; shared by every scheduler)
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Links:
    """Which link each capsule and each part belongs to (links numbered 0..L-1)."""

    of_capsule: np.ndarray
    """(C,) link number of each capsule."""
    of_part: np.ndarray
    """(P,) link number of each part."""
    n_links: int

    @staticmethod
    def of(capsules: CapsuleModel, hulls: HullModel) -> "Links":
        links = list(dict.fromkeys(capsules.link_names))
        missing = sorted(set(hulls.link_names) ^ set(links))
        if missing:
            from ..errors import LarcInputError

            raise LarcInputError(f"capsules and hull parts cover different links: {missing}")
        return Links(np.array([links.index(l) for l in capsules.link_names]),
                     np.array([links.index(l) for l in hulls.link_names]), len(links))

    @functools.cached_property
    def part_table(self) -> np.ndarray:
        """(L, M) the parts of each link, ``-1`` padded (M: the most parts a link has); built on
        first use, then kept (a batch reads it at every level)."""
        count = np.bincount(self.of_part, minlength=self.n_links)
        table = np.full((self.n_links, max(1, int(count.max(initial=0)))), -1)
        for l in range(self.n_links):
            table[l, :count[l]] = np.flatnonzero(self.of_part == l)
        return table

    def reduce_min(self, values: np.ndarray, owner: np.ndarray) -> np.ndarray:
        """(..., E, B) values per capsule or part -> (..., L, B) minimum per link."""
        out = np.full(values.shape[:-2] + (self.n_links, values.shape[-1]), np.inf)
        for e, l in enumerate(owner):
            out[..., l, :] = np.minimum(out[..., l, :], values[..., e, :])  # NaN propagates
        return out


def select_pairs(links: Links, cap_excess: np.ndarray, upper_excess: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Step 3. ``cap_excess`` (F, C, B) = ``g_lk - G_l``, ``upper_excess`` (F, P, B) = hull
    upper bound ``- G_p``.

    Returns ``tried`` (F, L, B), the (interval, link, box) pairs sent to the hull test, and the
    triples ``(interval, part, box)`` (T, 3) to evaluate (every part of every tried link)."""
    cap = links.reduce_min(cap_excess, links.of_capsule)
    upper = links.reduce_min(upper_excess, links.of_part)
    tried = ~(cap > 0) & (upper > 0) & ~np.isnan(cap)
    i, l, k = np.nonzero(tried)
    triples = [np.stack([i[links.of_part[p] == l], np.full(np.sum(links.of_part[p] == l), p),
                         k[links.of_part[p] == l]], axis=1) for p in range(len(links.of_part))]
    triples = np.concatenate(triples) if triples else np.zeros((0, 3), np.int64)
    order = np.lexsort((triples[:, 2], triples[:, 1], triples[:, 0]))
    return tried, triples[order].astype(np.int64)


def combine(links: Links, g_capsule: np.ndarray, guard_capsule: np.ndarray, tried: np.ndarray,
            triples: np.ndarray, g_hull: np.ndarray, guard_hull: np.ndarray):
    """Step 5: per interval ``(g, guard, capsule, box, passed)`` from the capsule clearances
    ``g_capsule`` (F, C, B) and guards ``guard_capsule`` (F, C), the tried pairs, and the hull
    clearances ``g_hull`` (T,) and guards ``guard_hull`` (T,) of the triples.

    The recorded ``(g, guard)`` are those of the enclosure deciding the worst (link, box) pair
    (``passed == g > guard``); ``capsule`` is the capsule of the blocking link with the least
    excess against the blocking box."""
    F, C, B = g_capsule.shape
    cap_ex = g_capsule - guard_capsule[:, :, None]
    cap = links.reduce_min(cap_ex, links.of_capsule)  # (F, L, B)
    hull = np.full(cap.shape, np.inf)
    if len(triples):
        i, p, k = triples.T
        np.minimum.at(hull, (i, links.of_part[p], k), g_hull - guard_hull)  # a NaN propagates
    use_hull = tried & (hull > cap)
    value = np.where(use_hull, hull, cap)
    value = np.where(tried & (np.isnan(hull) | np.isnan(cap)), np.nan, value)
    flat = value.reshape(F, -1)
    nan = np.isnan(flat).any(axis=1)
    best = np.argmin(np.where(np.isnan(flat), -np.inf, flat), axis=1)
    link, box = best // B, best % B
    rows = np.arange(F)
    on_link = links.of_capsule[None, :] == link[:, None]  # (F, C)
    capsule = np.argmin(np.where(on_link, cap_ex[rows, :, box], np.inf), axis=1)
    g = g_capsule[rows, capsule, box].astype(np.float64)
    guard = guard_capsule[rows, capsule].astype(np.float64)
    hull_won = use_hull.reshape(F, -1)[rows, best]
    if hull_won.any() and len(triples):
        # The deciding part: the one with the least excess on that (interval, link, box), ties
        # and NaN as np.argmin takes them (the first NaN, else the first least, in triple order).
        i, p, k = triples.T
        ex = g_hull - guard_hull
        on = np.flatnonzero(hull_won[i] & (links.of_part[p] == link[i]) & (k == box[i]))
        nan_ex = np.isnan(ex[on])
        order = on[np.lexsort((on, np.where(nan_ex, 0.0, ex[on]), ~nan_ex, i[on]))]
        first = order[np.r_[True, i[order][1:] != i[order][:-1]]]  # one triple per interval
        g[i[first]], guard[i[first]] = g_hull[first], guard_hull[first]
    g = np.where(nan, np.nan, g)
    return g, guard, capsule, box, g > guard


def cascade_np(robot: Robot, capsules: CapsuleModel, hulls: HullModel, links: Links, traj, obstacles, a: float,
               b: float, margin: float, bounds, ev=None, screen: bool = True):
    """Steps 1-5 on one leaf ``[a, b]`` (the trajectory's own time axis) with the NumPy
    references: ``(g, guard, capsule, box, stage)``; ``ev``: the leaf's capsule test
    (:func:`~larc_jax.leaf.interval.evaluate_interval_np`), computed if None; ``screen``: the
    screen first (module docstring), as every scheduler runs it (False: steps 2-5 whatever it
    finds, for the tests that compare the two)."""
    obstacles = scene_obstacles(obstacles)
    ev = ev if ev is not None else evaluate_interval_np(robot, capsules, traj, obstacles, a, b, margin, bounds)
    if ev.g > ev.guard or math.isnan(ev.g):
        return ev.g, ev.guard, ev.capsule, ev.box, int(ev.g > ev.guard)
    d = interval_pairs_np(robot, capsules, hulls, traj, obstacles, a, b, margin, bounds, ev)
    G_c = np.asarray(bounds.guard_m, np.float64)
    G_p = np.asarray(bounds.hull_guard_m, np.float64)
    on_link = links.of_part == links.of_capsule[ev.capsule]  # the screen: link_upper_excess_np's value
    if screen and not np.min(np.where(on_link, d.g_upper[:, ev.box] - G_p, np.inf)) > 0:  # NaN: hopeless too
        return ev.g, ev.guard, ev.capsule, ev.box, 0
    tried, triples = select_pairs(links, (d.g_capsule - G_c[:, None])[None], (d.g_upper - G_p[:, None])[None])
    guard_hull = G_p[triples[:, 1]] if len(triples) else np.zeros(0)
    g_hull = np.array([hull_pair_clearance_np(hulls, p, d.T_part[p], obstacles.take(k), d.motion_b[p], margin, gd)
                       for (_, p, k), gd in zip(triples, guard_hull)])
    g, guard, c, bx, passed = combine(links, d.g_capsule[None], G_c[None], tried, triples, g_hull, guard_hull)
    return float(g[0]), float(guard[0]), int(c[0]), int(bx[0]), 2 if passed[0] else 0
