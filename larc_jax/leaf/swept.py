"""The swept test: a second-order enclosure of a link's motion over one interval.

The midpoint test (:mod:`larc_jax.leaf.interval`, :mod:`larc_jax.leaf.cascade`) grows each
enclosure placed at ``q(t_m)`` by the motion radius ``b = h sum_j a_lj max|qdot_j|`` (eq. 6): a
first-order bound that shrinks only linearly with the interval and inflates in every direction.
The swept test instead encloses the motion by the convex hull of the enclosure at the two ends
of the interval, grown by a radius that shrinks *quadratically*.

Chord bound. Let ``p(t)`` be a point rigidly attached to a link, on ``[a', b']``. The Hermite
curve is C1 with a piecewise-continuous second derivative, so Peano's kernel gives
``p(t) - L(t) = -int G(t, s) p''(s) ds`` with ``L`` the chord through ``p(a'), p(b')``,
``G >= 0`` and ``int G(t, s) ds = (t - a')(b' - t) / 2 <= (b' - a')^2 / 8``. Hence

    |p(t) - L(t)| <= (b' - a')^2 / 8 * max ||p''||                                    (C)

and ``L(t)`` is a convex combination of ``p(a')`` and ``p(b')``. Every point of an enclosure
``E`` (capsule: ``seg + B(r)``; hull part: ``conv(V) + B(r)``) therefore stays, on ``[a', b']``,
in ``conv(E(a') U E(b')) + B(e)``, ``e`` the right-hand side of (C) maximised over the points;
``conv(E(a') U E(b')) = conv(X(a') U X(b')) + B(r)`` for the generating points ``X`` (the
segment ends, the part's vertices). Its distance to an obstacle is bounded below by the
obstacle kind's ``polytope_lower_bound`` (GJK, :mod:`larc_jax.obstacles.polytope`) on the point
set ``X(a') U X(b')``, placed in the base frame: the support function of the union is the larger
of the two supports, so the bound applies unchanged.

Acceleration of a point (the bound of ``max ||p''||``). A point ``p`` of the link moves with
``pdot = sum_j qdot_j v_j``, ``v_j = axis_j x (p - o_j)`` (revolute) or ``axis_j`` (prismatic).
Differentiating, ``p'' = sum_j qddot_j v_j + sum_j qdot_j d/dt v_j``. The axis ``axis_j`` and the
origin ``o_j`` are fixed in the parent link of joint j, which turns with angular velocity
``w_j = sum_{k before j} qdot_k axis_k`` (the active revolute joints above j). With ``u = p - o_j``
and ``u_rel = sum_{k >= j} qdot_k v_k`` (the velocity of ``p`` relative to that parent link),
``d/dt axis_j = w_j x axis_j`` and ``d/dt u = w_j x u + u_rel``; by the Jacobi identity
``(w x a) x u + a x (w x u) = w x (a x u)``, so

    d/dt v_j = w_j x (axis_j x u) + axis_j x u_rel,
    |d/dt v_j| <= |w_j| dist(p, axis_j) + |u_rel| <= S_j a_lj + sum_{k >= j} |qdot_k| a_lk

(for a prismatic j, ``d/dt v_j = w_j x axis_j``, a subset of the same bound with ``a_lj = 1``),
where ``S_j = sum_{k before j} |qdot_k|`` over the active joints above j on the link's chain and
``a_lj`` are the motion constants (:mod:`larc_jax.enclosure.motion`: ``dist(p, axis_j) <= a_lj`` for
every point of the enclosure in every configuration, and ``|v_k| <= a_lk``). Summing and
regrouping the pairs ``(j, k)``::

    ||p''|| <= P_l = sum_k a_lk ( |qddot_k| + |qdot_k| (|qdot_k| + 2 S_k) )            (A)

every term monotone in ``|qdot|`` and ``|qddot|``, so their maxima over the interval give a bound
over the interval: the speed bound of the placement (eq. 5, budget P2) and the acceleration
maxima of :func:`~larc_jax.model.hermite.accel_max` plus their slack (budget P2').

Floating point (budget of :mod:`larc_jax.leaf.interval`). The ends are evaluated at the rebased
``a, b``; T3 makes them the curve at ``a', b'`` with ``|a' - a|, |b' - b| <= 6u T <= tau``, and
``a' <= b'`` (rounding is monotone). Every ``t`` in ``[a, b]`` outside ``[a', b']`` is within
``tau`` of an end, where the point is within ``tau W_l`` (``W_l = sum_j a_lj (omega_j +
slack_j)``, P3) of its place at that end. So with ``D = (fl(b - a) + 2 tau)(1 + 2 eps) >= b' - a'``::

    e_l = (D^2 / 8 * P_l + tau W_l) (1 + (4n + 128) eps)

(``n`` non-negative sums and products in ``S``, as many in (A) and ``W``, ``64 u`` for the
motion constants, all doubled) bounds the distance of every point of the enclosure on ``[a, b]``
from ``conv(E(a') U E(b'))``. The maxima of speed and acceleration are taken over
``[max(a - tau, t'_0), min(b + tau, t'_K)]``, which holds ``[a', b']`` (T5). The computed ends
``q^(a'), q^(b')`` and their placement are off the exact ones as the midpoint's are (P1, G1), so
the enclosure's rounding guard ``G`` (capsule or part) covers them: each generating point is
within ``G`` of its exact place, hence so is every convex combination. The test of one
enclosure and obstacle is then::

    g_swept = lb(X(a') U X(b'), obstacle) - (r + e + rho) (1 + 2 eps)   >   G

Composition. Per enclosure and obstacle the swept clearance and the midpoint clearance are two
proofs of the same claim, so the larger decides (a NaN in either fails). Per (link, obstacle)
the link passes if all its capsules pass or all its hull parts pass (the cascade's rule,
:mod:`larc_jax.leaf.cascade`); the interval passes if every (link, obstacle) pair does. The
stage runs where the earlier stages left a leaf open (:mod:`larc_jax.leaf.record`); as it
re-derives every midpoint clearance, its verdict is never weaker than theirs.

Order of work (as the cascade's, :mod:`larc_jax.leaf.cascade`): step 1, one kernel per interval
(:func:`swept_placement`): every capsule's clearance, the better of midpoint and swept, and the
parts' placements; steps 3-5 on the host (:func:`swept_record`): a (link, obstacle) pair whose
capsules fail goes to step 2, one kernel per (part, obstacle) (:func:`swept_part_clearance`: the
better of the part's midpoint and swept clearances), and the cascade's ``combine`` decides. Each
kernel has its NumPy float64 twin; :func:`swept_stage_np` runs the stage on one leaf with them
(the reference scheduler and ``larc verify``).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..enclosure.capsule import CapsuleModel
from ..enclosure.hull import HullModel
from ..lazy_jax import jax, jnp, pytree_dataclass
from ..model.hermite import accel_max, accel_max_np, evaluate, evaluate_np
from ..model.kinematics import link_poses
from ..model.robot import Robot, forward_kinematics_np
from ..obstacles import scene_obstacles
from .cascade import Links, combine, polytope_clearance, polytope_clearance_np, select_pairs
from .interval import evaluate_placed, evaluate_placed_np, rebase_ends
from .placement import motion_radii, place, place_np

__all__ = ["SweptTables", "SweptPlacement", "swept_tables", "swept_links", "chain_before", "swept_radii",
           "swept_placement", "swept_placement_np", "capsule_ends", "swept_capsule_clearance",
           "swept_capsule_clearance_np", "swept_part_clearance", "swept_part_clearance_np", "swept_record",
           "swept_stage_np"]

EPS64 = float(np.finfo(np.float64).eps)


def chain_before(robot: Robot, link_index) -> np.ndarray:
    """(E, n, n) float64: ``[e, k, j] = 1`` when active joint ``j`` lies above active joint ``k``
    on the chain of link ``link_index[e]`` (the ``S_k`` of (A) in the module docstring)."""
    n = robot.n_joints
    out = np.zeros((len(link_index), n, n))
    for e, li in enumerate(link_index):
        above: list[int] = []
        for i in robot.ancestors(li)[1:]:  # root to link
            j = robot.q_index[i]
            if j < 0:
                continue
            out[e, j, above] = 1.0
            above.append(j)
    return out


def swept_radii(motion_a, before, span, tau, speed, accel):
    """``e`` of the module docstring for enclosures with motion constants ``motion_a`` (E, n) and
    chain orders ``before`` (E, n, n), on an interval of computed length ``span = fl(b - a)`` with
    time slack ``tau``, speed bound ``speed`` (n,) and acceleration bound ``accel`` (n,) (with
    their slacks): (E,), m. JAX or NumPy arrays (float64)."""
    n = speed.shape[-1]
    if isinstance(speed, np.ndarray):
        S = np.einsum("ekj,j->ek", before, speed)
        W = np.asarray(motion_a, np.float64) @ speed
        P = (np.asarray(motion_a, np.float64) * (accel + speed * (speed + 2 * S))).sum(axis=-1)
    else:
        full = jax.lax.Precision.HIGHEST
        S = jnp.einsum("ekj,j->ek", before, speed, precision=full)
        W = jnp.matmul(motion_a, speed, precision=full)
        P = (motion_a * (accel + speed * (speed + 2 * S))).sum(axis=-1)  # (A)
    D = (span + 2 * tau) * (1 + 2 * EPS64)
    return (D * D * 0.125 * P + tau * W) * (1 + (4 * n + 128) * EPS64)


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class SweptTables:
    """The chain data of the swept test (arrays; built once per run by :func:`swept_tables`)."""

    capsule_before: jax.Array
    """(C, n, n) :func:`chain_before` of the capsules."""
    part_before: jax.Array
    """(P, n, n) of the hull parts ((0, n, n) without them)."""


def swept_tables(robot: Robot, capsules: CapsuleModel, hulls: HullModel | None) -> SweptTables:
    """The :class:`SweptTables` of a run (``hulls``: the cascade's, or None)."""
    n = robot.n_joints
    return SweptTables(
        capsule_before=chain_before(robot, capsules.link_index),
        part_before=chain_before(robot, hulls.link_index) if hulls is not None else np.zeros((0, n, n)))


def swept_links(capsules: CapsuleModel, links: Links | None) -> Links:
    """The links the composition groups enclosures by: the cascade's, or the capsules' alone."""
    if links is not None:
        return links
    names = list(dict.fromkeys(capsules.link_names))
    return Links(np.array([names.index(name) for name in capsules.link_names]), np.zeros(0, np.int64), len(names))


def _best(mid, swept):
    """The larger of two proofs of one claim; NaN if either is NaN (NaN never certifies)."""
    xp = np if isinstance(mid, np.ndarray) else jnp
    return xp.where(xp.isnan(mid) | xp.isnan(swept), np.nan, xp.maximum(mid, swept))


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class SweptPlacement:
    """Step 1 of the swept stage on one interval (JAX or NumPy arrays)."""

    g_capsule: jax.Array
    """(C, B) each capsule's midpoint clearance to each item (eq. 7), m; +inf for padding items; NaN
    on non-finite geometry (the swept test raises it where it fails: :func:`swept_capsule_clearance`)."""
    R_capsule: jax.Array
    """(C, 2, 3, 3) each capsule's link rotation at the two ends."""
    t_capsule: jax.Array
    """(C, 2, 3) its link translation at the two ends, m."""
    e_capsule: jax.Array
    """(C,) its swept radius ``e``, m."""
    T_mid: jax.Array
    """(P, 3, 4) each part's link pose at q(t_m)."""
    R_ends: jax.Array
    """(P, 2, 3, 3) its rotations at the two ends."""
    t_ends: jax.Array
    """(P, 2, 3) its translations at the two ends, m."""
    motion_b: jax.Array
    """(P,) its midpoint motion radius (eq. 6), m."""
    swept_e: jax.Array
    """(P,) its swept radius ``e`` (module docstring), m."""


def _ends(T_a, T_b, links):
    """The placements of enclosures on ``links`` at the two ends: ``R`` (E, 2, 3, 3), ``t`` (E, 2, 3)."""
    xp = np if isinstance(T_a, np.ndarray) else jnp
    links = xp.asarray(links, dtype=np.int64) if xp is np else xp.asarray(links)
    return (xp.stack([T_a[links, :3, :3], T_b[links, :3, :3]], axis=1),
            xp.stack([T_a[links, :3, 3], T_b[links, :3, 3]], axis=1))


def swept_placement(robot: Robot, capsules: CapsuleModel, hulls: HullModel | None, tables: SweptTables, spline,
                    obstacles, a, b, margin, bounds) -> SweptPlacement:
    """Step 1 of the swept stage on one interval ``[a, b]`` (rebased) of one trajectory against one
    scene's obstacle set (kernel; batch with ``jax.vmap``): every capsule's clearance (midpoint and
    swept), and the parts' placements for step 2 (:func:`swept_part_clearance`). Arguments as
    :func:`~larc_jax.leaf.interval.evaluate_interval`; ``hulls`` None for the capsules alone.

    Every polytope is read from its link-frame table (the capsules' segment ends, the parts'
    vertices), shared by all intervals, and placed by the stack of the two end poses: nothing is
    copied per interval."""
    gdtype = robot.T_parent_joint.dtype
    pl = place(robot, capsules, spline, a, b, bounds)
    g_mid = evaluate_placed(pl, capsules, obstacles, margin, bounds).g_pairs  # (C, B), eq. 7
    lo = jnp.maximum(a - bounds.tau_s, bounds.t_start)  # T5
    hi = jnp.minimum(b + bounds.tau_s, bounds.t_end)
    accel = accel_max(spline, lo, hi) + bounds.accel_slack  # P2'
    q_a, _ = evaluate(spline, a)
    q_b, _ = evaluate(spline, b)
    T_a = link_poses(robot, q_a.astype(gdtype))
    T_b = link_poses(robot, q_b.astype(gdtype))
    e_cap = swept_radii(capsules.motion_a, tables.capsule_before, b - a, bounds.tau_s, pl.speed, accel)
    R_cap, t_cap = _ends(T_a, T_b, capsules.link_index)
    finite = (pl.finite & jnp.isfinite(accel).all() & jnp.isfinite(T_a).all() & jnp.isfinite(T_b).all()
              & jnp.isfinite(e_cap).all())
    g_cap = jnp.where(finite, g_mid, jnp.nan)  # NaN never certifies
    if hulls is None:
        P = jnp.zeros(0, pl.speed.dtype)
        return SweptPlacement(g_cap, R_cap, t_cap, e_cap, jnp.zeros((0, 3, 4), gdtype), jnp.zeros((0, 2, 3, 3), gdtype),
                              jnp.zeros((0, 2, 3), gdtype), P, P)
    links = jnp.asarray(hulls.link_index)
    T_mid = link_poses(robot, pl.q_mid.astype(gdtype))[links]
    R, t = _ends(T_a, T_b, hulls.link_index)
    return SweptPlacement(g_cap, R_cap, t_cap, e_cap, T_mid, R, t,
                          motion_radii(hulls.motion_a, pl.h_cov, pl.speed),  # eq. 6
                          swept_radii(hulls.motion_a, tables.part_before, b - a, bounds.tau_s, pl.speed, accel))


def capsule_ends(capsules: CapsuleModel):
    """(C, 2, 3) the capsules' segment ends in their link frames: the polytopes of their swept test."""
    xp = np if isinstance(capsules.p_link_a, np.ndarray) else jnp
    return xp.stack([capsules.p_link_a, capsules.p_link_b], axis=1)


def swept_capsule_clearance(capsules: CapsuleModel, capsule, R_ends, t_ends, item, swept_e, margin):
    """Step 1b on one (capsule, obstacle) pair whose midpoint test fails: the capsule's swept
    clearance, m (kernel; ``vmap`` it)."""
    ends = capsule_ends(capsules).astype(R_ends.dtype)
    return polytope_clearance(ends, capsule, ends[capsule].mean(axis=0), capsules.radius[capsule], R_ends, t_ends,
                              item, swept_e, margin)


def swept_part_clearance(hulls: HullModel, part, T_mid, R_ends, t_ends, item, motion_b, swept_e, margin):
    """Step 2 on one (part, obstacle) pair: the better of the part's midpoint clearance (the hull
    test, :mod:`larc_jax.leaf.cascade`) and its swept clearance, m (kernel; ``vmap`` it)."""
    mid = polytope_clearance(hulls.vertices, part, hulls.centre[part], hulls.radius[part], T_mid[:, :3], T_mid[:, 3],
                             item, motion_b, margin)
    swept = polytope_clearance(hulls.vertices, part, hulls.centre[part], hulls.radius[part], R_ends, t_ends, item,
                               swept_e, margin)
    return _best(mid, swept)


# ----------------------------------------------------------------------------------------------
# NumPy float64 twins, and the whole stage on one leaf
# ----------------------------------------------------------------------------------------------


def swept_placement_np(robot: Robot, capsules: CapsuleModel, hulls: HullModel | None, tables: SweptTables, traj,
                       obstacles, a: float, b: float, margin: float, bounds) -> SweptPlacement:
    """NumPy float64 twin of :func:`swept_placement` (``traj``: a Trajectory; ``[a, b]`` rebased)."""
    obstacles = scene_obstacles(obstacles)
    t = np.asarray(traj.t, np.float64) - float(bounds.offset_s)
    tau = float(bounds.tau_s)
    pl = place_np(robot, capsules, traj, a, b, bounds)
    g_mid = np.asarray(evaluate_placed_np(pl, capsules, obstacles, margin, bounds).g_pairs, np.float64)
    accel = accel_max_np(t, traj.q, traj.qd, max(a - tau, t[0]), min(b + tau, t[-1])) \
        + np.asarray(bounds.accel_slack, np.float64)
    T_a = np.asarray(forward_kinematics_np(robot, evaluate_np(t, traj.q, traj.qd, a)[0]), np.float64)
    T_b = np.asarray(forward_kinematics_np(robot, evaluate_np(t, traj.q, traj.qd, b)[0]), np.float64)
    speed = np.asarray(pl.speed, np.float64)
    e_cap = swept_radii(capsules.motion_a, np.asarray(tables.capsule_before), b - a, tau, speed, accel)
    R_cap, t_cap = _ends(T_a, T_b, capsules.link_index)
    finite = bool(pl.finite) and all(bool(np.isfinite(x).all()) for x in (accel, T_a, T_b, e_cap))
    g_cap = g_mid if finite else np.full(g_mid.shape, np.nan)
    if hulls is None:
        return SweptPlacement(g_cap, R_cap, t_cap, e_cap, np.zeros((0, 3, 4)), np.zeros((0, 2, 3, 3)),
                              np.zeros((0, 2, 3)), np.zeros(0), np.zeros(0))
    T_mid = np.asarray(forward_kinematics_np(robot, pl.q_mid), np.float64)[list(hulls.link_index)][:, :3, :]
    R, tr = _ends(T_a, T_b, hulls.link_index)
    return SweptPlacement(g_cap, R_cap, t_cap, e_cap, T_mid, R, tr,
                          motion_radii(np.asarray(hulls.motion_a, np.float64), pl.h_cov, speed),
                          swept_radii(hulls.motion_a, np.asarray(tables.part_before), b - a, tau, speed, accel))


def swept_capsule_clearance_np(capsules: CapsuleModel, capsule: int, R_ends, t_ends, item, swept_e: float,
                               margin: float) -> float:
    """NumPy float64 twin of :func:`swept_capsule_clearance`."""
    ends = np.asarray(capsule_ends(capsules), np.float64)[capsule]
    return polytope_clearance_np(ends, ends.mean(axis=0), float(capsules.radius[capsule]), R_ends, t_ends, item,
                                 swept_e, margin)


def swept_part_clearance_np(hulls: HullModel, part: int, T_mid, R_ends, t_ends, item, motion_b: float,
                            swept_e: float, margin: float) -> float:
    """NumPy float64 twin of :func:`swept_part_clearance`."""
    V, centre, r = hulls.vertices[part], hulls.centre[part], float(hulls.radius[part])
    T_mid = np.asarray(T_mid, np.float64)
    mid = polytope_clearance_np(V, centre, r, T_mid[:, :3], T_mid[:, 3], item, motion_b, margin)
    return float(_best(np.float64(mid), np.float64(polytope_clearance_np(V, centre, r, R_ends, t_ends, item, swept_e,
                                                                          margin))))


def swept_record(links: Links, g_capsule, guard_capsule, has_parts: bool, clear_capsules, clear_parts):
    """Steps 1b and 3-5 on F intervals (host side, NumPy). Step 1b: ``clear_capsules(triples)``
    gives the swept clearance of the (interval, capsule, item) triples whose midpoint clearance
    ``g_capsule`` (F, C, B) does not pass its guard (F, C) (a NaN stays NaN); the better of the two
    is the capsule's. Then the cascade's pair selection and composition
    (:func:`~larc_jax.leaf.cascade.select_pairs`, :func:`~larc_jax.leaf.cascade.combine`):
    ``clear_parts(triples) -> (g, guard)`` computes the parts' step 2 on the (interval, part, item)
    triples of the links whose capsules fail an item (no parts: none). Returns ``(g, guard,
    capsule, box, passed)`` per interval."""
    g_capsule = np.array(g_capsule, np.float64, copy=True)
    excess = g_capsule - guard_capsule[:, :, None]
    open_ = np.argwhere(~(excess > 0) & ~np.isnan(excess))  # (interval, capsule, item), sorted
    if len(open_):
        i, c, k = open_.T
        g_capsule[i, c, k] = _best(g_capsule[i, c, k], np.asarray(clear_capsules(open_), np.float64))
    cap_excess = g_capsule - guard_capsule[:, :, None]
    upper = np.full((len(g_capsule), len(links.of_part), g_capsule.shape[2]), np.inf)  # no pair is skipped
    tried, triples = select_pairs(links, cap_excess, upper)
    if not has_parts:
        tried = np.zeros_like(tried)  # no part to try: the capsules decide
        triples = triples[:0]
    g_part, guard_part = clear_parts(triples) if len(triples) else (np.zeros(0), np.zeros(0))
    return combine(links, g_capsule, guard_capsule, tried, triples, g_part, guard_part)


def swept_stage_np(robot: Robot, capsules: CapsuleModel, hulls: HullModel | None, tables: SweptTables, links: Links,
                   traj, obstacles, t0: float, t1: float, margin: float, bounds):
    """The whole swept stage on the leaf ``[t0, t1]`` (the trajectory's own time axis) with the NumPy
    twins, composed as the batched scheduler composes it: ``(g, guard, capsule, box)``."""
    obstacles = scene_obstacles(obstacles)
    a, b = (float(x) for x in rebase_ends(t0, t1, float(bounds.offset_s)))
    d = swept_placement_np(robot, capsules, hulls, tables, traj, obstacles, a, b, margin, bounds)
    G_c = np.asarray(bounds.guard_m, np.float64)
    G_p = np.asarray(bounds.hull_guard_m, np.float64)

    def clear_capsules(triples):
        return np.array([swept_capsule_clearance_np(capsules, c, d.R_capsule[c], d.t_capsule[c], obstacles.take(k),
                                                    float(d.e_capsule[c]), margin) for _, c, k in triples])

    def clear_parts(triples):
        g = np.array([swept_part_clearance_np(hulls, p, d.T_mid[p], d.R_ends[p], d.t_ends[p], obstacles.take(k),
                                              float(d.motion_b[p]), float(d.swept_e[p]), margin) for _, p, k in triples])
        return g, G_p[triples[:, 1]]

    g, guard, c, k, _ = swept_record(links, d.g_capsule[None], G_c[None], hulls is not None, clear_capsules,
                                     clear_parts)
    return float(g[0]), float(guard[0]), int(c[0]), int(k[0])
