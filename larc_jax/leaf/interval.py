"""The interval test (paper eqs. 4-7): one interval of one trajectory, its NumPy reference,
and the whole floating-point error budget of a certificate.

For a leaf ``I = [t0, t1]`` of one trajectory, every capsule ``l`` is placed at the computed
midpoint configuration ``q(t_m)`` and inflated by the motion radius ``b_l = h_cov * sum_j a_lj *
(omega_j + slack_j)`` (eq. 6, exact Hermite speed maxima ``omega``, eq. 5). For every capsule
``l`` and box ``k`` the certificate clearance is::

    g_lk = dist(segment_l(q(t_m)), box_k) * (1 - K_DIST_REL * eps_g) - (r_l + b_l + rho) * (1 + 2 eps)

and the interval passes iff ``g_lk > G_l`` for every pair, ``G_l`` the rounding guard of
capsule ``l`` on this trajectory (below). If it passes, every point of every link stays more
than ``rho`` from every box at every real time of ``I`` (Theorem 1 for the numbers *as
computed*; the chain of inclusions is in ``../shared/notes/architecture.md``). The leaf records
the pair minimising ``g_lk - G_l``, its ``g`` and its ``G``: it passed iff ``g > G``.

:func:`evaluate_interval` is the JAX kernel for one interval; it returns an
:class:`IntervalEval` record of every intermediate. :func:`evaluate_interval_np` is its NumPy
float64 reference, written with the references of every kernel it calls and the same bounds.

Floating-point error budget
---------------------------
``u = eps / 2`` is the unit roundoff of float64, ``u_g`` that of the *geometry* dtype ``g``
(float64, or float32 with ``certify(dtype=np.float32)``). Times, the Hermite curve, speed maxima
and the final sums are always float64 (a float32 time has a 128 s spacing at epoch times, and
float32 knots would describe another curve); forward kinematics and distances run in ``g``.
Every bound below is first order in ``u`` with its constant at least doubled; the tests compare
each with the measured error (``tests/test_rounding.py``). ``T = max(|t'_0|, |t'_K|)`` is the
time magnitude of the rebased knots, ``H_k`` the segment durations.

T. Time (handled by the covering radius, not the guard).
  T1. Rebase (:func:`time_offset`): the knots are shifted by ``o = t_0`` when every ``t_k - t_0``
      is exact (checked with TwoSum; Sterbenz makes it exact whenever ``t_K <= 2 t_0``, e.g.
      epoch times), else ``o = 0``. The shifted curve is then exactly the user's curve. A
      leaf's ends are shifted with outward rounding (:func:`rebase_ends`): the real interval
      ``[a, b]`` evaluated contains ``[t0 - o, t1 - o]``; leaves are reported unshifted.
  T2. ``t_m = fl((a + b) / 2)`` lies in ``[a, b]``, but need not be its midpoint (at 2^40 s,
      an interval of one spacing has ``t_m = a``).
  T3. ``evaluate`` computes ``s = fl(fl(t_m - t_k) / fl(t_{k+1} - t_k)) = s_exact (1 + th)``,
      ``|th| <= 3u``: it returns the curve at ``t' = t_k + s H_k``, ``|t' - t_m| <= 3u H_k <= 6u T``.
  T4. Covering radius ``h_cov = fl(max(fl(t_m - a), fl(b - t_m)) + tau) * (1 + 2 eps)`` with
      ``tau = K_TIME u T``: ``h_cov >= |t - t'|`` for every real ``t`` in ``[a, b]``.
  T5. Speeds are maximised over ``[max(fl(a - tau), t'_0), min(fl(b + tau), t'_K)]``. Its ends
      are off by at most ``u (T + tau)`` and their ``s`` by ``3u H_k``; as ``tau >= 16u T`` the
      range whose speeds enter ``omega`` contains ``[a, b]`` and ``t'``.

P. Curve values (float64).
  P1. Position: the basis form returns ``q^_j`` with ``|q^_j - q_j(t')| <= K_POS u Q_j``,
      ``Q_j = max_k (|q_kj| + |q_k+1,j| + H_k |v_kj| + H_k |v_k+1,j|)`` (basis functions to 6u,
      ``|H00|, |H01| <= 1``, ``|H10|, |H11| <= 4/27``, ``H_k`` to u, 4 products, 3 sums: 12u; the
      reference's power form: ~40u). Float32 geometry rounds ``q^`` once more: ``+ 2 u_g Q_j``.
      Sum: ``E_j``. ``Q_j`` also bounds ``|q_j(t)|`` on the whole curve.
  P2. Speed: each candidate of eq. 5 is the quadratic (*) of :mod:`larc_jax.model.hermite`, whose
      coefficients have ``|(1-s)(1-3s)|, |s(3s-2)| <= 1``, ``6s(1-s) <= 1.5`` on ``[0, 1]``: error
      ``<= 16u V_kj``, ``V_kj = |v_kj| + |v_k+1,j| + 1.5 |d_kj|``. A vertex found off by ``ds``
      changes the value by ``c2 ds^2 <= u V`` (or ``|c2| <= u V`` and the quadratic is linear to
      ``u V``). Hence the true maximum is ``<= omega_j + slack_j``, ``slack_j = K_SPEED u V_j``.
  P2'. Acceleration (the swept test, :mod:`larc_jax.leaf.swept`): (**) of
      :mod:`larc_jax.model.hermite` has coefficients ``<= 4, 4, 6`` on ``[0, 1]``, so each end value
      is off by ``<= 16u A_kj``, ``A_kj = (4 |v_kj| + 4 |v_k+1,j| + 6 |d_kj|) / H_k``, and an end
      found off by ``ds`` changes it by ``<= 12 ds A_kj``: the true maximum is ``<= alpha_j +
      accel_slack_j``, ``accel_slack_j = K_SPEED u A_j``.
  P3. Motion radius: ``b_l = fl(h_cov * sum_j a_lj (omega_j + slack_j)) * (1 + (n + 64) eps)``:
      n non-negative products and sums (``(n + 2) u``), and the ``a_lj`` themselves, computed in
      float64 by :func:`~larc_jax.enclosure.motion.motion_constants` (``<= 64 u`` relative).
      With T3-T5: every point of capsule ``l`` at any ``t`` in ``[a, b]`` lies within ``b_l`` of
      the same point at ``q(t')``, and (P1, the motion-constant argument along the straight
      joint-space path) within ``b_l + sum_j a_lj E_j`` of that point at ``q^``.

G. Geometry (dtype g).
  G1. Placement: FK chains ``L_l`` joint transforms (:mod:`larc_jax.model.kinematics`: 3x4 affine
      products, the entries of 4x4 ones with a ``[0, 0, 0, 1]`` row, each an inner product of <= 4
      terms, in any order within ``gamma_4 |A||B|`` (the constant column counted); rotations stay of
      norm ``1 + O(L u_g)``; XLA's ``sin``/``cos`` are accurate to 2 ulp for every finite argument:
      measured on CPU for ``|x| <= 1e9``, documented for CUDA's libdevice); inputs rounded to g (joint
      origins, axes, segment ends) count as one more rounding per link. The computed segment ends are
      within ``K_FK (L_l + 1) u_g R_l`` of the exact ones at ``q^``, where ``R_l`` bounds every
      coordinate along the chain: the joint offsets' norms, prismatic travel (held ``|q|``, active
      ``Q_j``) and the farthest segment end. Products use ``Precision.HIGHEST`` (on a GPU, not TF32).
  G2. Distance (:mod:`larc_jax.obstacles.geometry`): the computed distance is at most ``(1 + 16 u_g)
      dist + 32 u_g (|p0| + |p1|)``: gaps ``lo - x`` are single subtractions (relative error),
      the squares, sum and square root add ``4 u_g``, the points ``x`` are off the segment by
      ``3 u_g (|p0| + |p1|)``, and a breakpoint or stationary point found off by ``dt`` costs
      ``|d| dt <= 7 u_g (dist + |d|)`` (a breakpoint inside ``[0, 1]`` has ``|lo_i - p0_i| <=
      |d_i|``; an active target has ``|e| <= dist + |d|``). A box's size or distance never
      enters except relative to the distance itself, so a far or huge box costs nothing
      elsewhere. The relative part is removed by ``(1 - K_DIST_REL eps_g)``, the rest is in G.
  G3. Boxes: float64 boxes are exact; float32 corners are rounded outwards (lo down, hi up),
      so the box tested contains the user's box.
  G4. Sums: ``(r + b + rho) (1 + 2 eps)`` is an upper bound (``r`` is the capsule radius the
      kernel is given: with a tracking tolerance, :mod:`larc_jax.enclosure.tracking` has grown it by
      ``Delta_l = fl(sum_j a_lj delta_j) (1 + (n + 4) eps)`` and rounded the sum up, so it is
      at least the real ``r_l + sum_j a_lj delta_j``); ``fl(x - y) > G`` implies
      ``x - y > G (1 - u)``, covered by the factor ``(1 + 8u)`` of G.

Guard of capsule ``l`` on one trajectory (:func:`trajectory_rounding`), metres::

    G_l = (1 + 8u) * ( sum_j a_lj E_j  +  (K_FK (L_l + 1) + 2 K_DIST_ABS) u_g R_l )

It depends only on what that trajectory's test touches: its own curve (``Q``), the capsule's
chain, and the geometry dtype; never on other trajectories or scenes, nor on box coordinates.
NaN or infinite intermediate values (or an infinite guard) always fail the test.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..enclosure.capsule import CapsuleModel
from ..errors import LarcInputError
from .clearance import min_clearance
from ..model.hermite import HermiteSpline
from ..lazy_jax import jax, jnp, pytree_dataclass
from ..obstacles import scene_obstacles
from .placement import Placement, motion_radii, place, place_np
from ..model.robot import Robot, chain_terms

__all__ = [
    "IntervalEval",
    "RoundingBounds",
    "evaluate_interval",
    "evaluate_interval_np",
    "evaluate_placed",
    "evaluate_placed_np",
    "motion_radii",
    "interval_clearance",
    "interval_clearance_np",
    "trajectory_rounding",
    "trajectory_roundings",
    "time_offset",
    "time_offsets",
    "capsule_offsets",
    "rebase_ends",
    "dyadic_ends",
    "geometry_dtype",
    "K_TIME", "K_POS", "K_SPEED", "K_FK", "K_DIST_REL", "K_DIST_ABS",
]

K_TIME = 32
"""tau = K_TIME u T (T3-T5)."""
K_POS = 128
"""Position evaluation error, in u per unit of Q_j (P1)."""
K_SPEED = 128
"""Speed evaluation error, in u per unit of V_j (P2)."""
K_FK = 64
"""Placement error per joint of the chain, in u_g per metre of R_l (G1)."""
K_DIST_REL = 32
"""Relative distance error removed in the kernel, in eps_g (G2)."""
K_DIST_ABS = 64
"""Absolute distance error, in u_g per metre of R_l (G2)."""

_U64 = float(np.finfo(np.float64).eps) / 2
_EPS64 = float(np.finfo(np.float64).eps)


def geometry_dtype(dtype) -> np.dtype:
    """The geometry dtype of ``certify(dtype=...)``: float64 or float32, else LarcInputError."""
    try:
        dt = np.dtype(dtype)
    except TypeError:
        raise LarcInputError(f"certify: dtype {dtype!r} is not supported (np.float64 or np.float32)") from None
    if dt not in (np.dtype(np.float64), np.dtype(np.float32)):
        raise LarcInputError(f"certify: dtype {dt} is not supported (np.float64 or np.float32)")
    return dt


# ----------------------------------------------------------------------------------------------
# Time (T1): the rebase offset and outward-rounded interval ends
# ----------------------------------------------------------------------------------------------


def _two_diff(x, y):
    """``(s, e)`` with ``s = fl(x - y)`` and ``x - y = s + e`` exactly (Knuth's TwoSum)."""
    x = np.asarray(x, np.float64)
    y = -np.asarray(y, np.float64)
    s = x + y
    bp = s - x
    ap = s - bp
    return s, (x - ap) + (y - bp)


def time_offset(t) -> float:
    """The rebase offset of knot times ``t`` (T1): ``t[0]`` if every ``t_k - t[0]`` is exact in
    float64, else 0 (then the times are used as given)."""
    return float(time_offsets(np.asarray(t, np.float64)[None])[0])


def time_offsets(t) -> np.ndarray:
    """:func:`time_offset` of every row of ``t`` (..., N): one rule for one trajectory and a batch."""
    t = np.asarray(t, np.float64)
    _, err = _two_diff(t, t[..., :1])
    return np.where(np.all(err == 0.0, axis=-1), t[..., 0], 0.0)


def rebase_ends(a, b, offset):
    """``(a - offset, b - offset)`` rounded outwards (down for ``a``, up for ``b``), so the
    float interval contains the exact shifted one (elementwise, NumPy float64)."""
    sa, ea = _two_diff(a, offset)
    sb, eb = _two_diff(b, offset)
    return np.where(ea < 0, np.nextafter(sa, -np.inf), sa), np.where(eb > 0, np.nextafter(sb, np.inf), sb)


def dyadic_ends(t_start, t_end, depth, index):
    """Ends of interval ``index`` of the ``2**depth`` equal parts of ``[t_start, t_end]``
    (NumPy, elementwise). The fractions are exact; the horizon ends are taken verbatim."""
    n = np.ldexp(1.0, depth)
    f0, f1 = index / n, (index + 1) / n
    a = np.where(f0 == 0.0, t_start, t_start + (t_end - t_start) * f0)
    b = np.where(f1 == 1.0, t_end, t_start + (t_end - t_start) * f1)
    return a, b


# ----------------------------------------------------------------------------------------------
# Per-trajectory bounds (the guard and the slacks of the budget)
# ----------------------------------------------------------------------------------------------


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class RoundingBounds:
    """What the error budget gives one trajectory (arrays; a batch adds a leading axis)."""

    offset_s: jax.Array
    """Rebase offset o (T1), s: the kernel sees times ``t - o``."""
    t_start: jax.Array
    """Rebased horizon start ``t'_0``, s."""
    t_end: jax.Array
    """Rebased horizon end ``t'_K``, s."""
    tau_s: jax.Array
    """Time slack tau (T4, T5), s."""
    omega_slack: jax.Array
    """(n,) speed slack (P2), rad/s or m/s."""
    accel_slack: jax.Array
    """(n,) acceleration slack (P2'), rad/s^2 or m/s^2."""
    guard_m: jax.Array
    """(C,) rounding guard ``G_l`` of each capsule, m."""
    hull_guard_m: jax.Array
    """(P,) rounding guard of each hull part of the cascade (:mod:`larc_jax.leaf.cascade`; the same
    formula with the part's chain, vertices and motion constants), m; (0,) without hulls."""


def _guard_terms(robot: Robot, link_index, end_norms, motion_a):
    """What ``G_e`` needs of the model (the same for every trajectory): ``(a, lengths, fixed,
    prismatic)``, `chain_terms` (:mod:`larc_jax.model.robot`) with the motion constants."""
    return (np.asarray(motion_a, np.float64).reshape(len(link_index), -1),) + chain_terms(robot, link_index, end_norms)


def _guards(terms, E, Q, ug: float) -> np.ndarray:
    """``G_e`` of the module docstring for enclosures with :func:`_guard_terms` ``terms`` (per-joint
    position error ``E``, curve bound ``Q``, geometry roundoff ``ug``); ``E`` and ``Q`` (..., n),
    the result (..., C): each trajectory's guards, the same arithmetic whatever the leading axes."""
    u = _U64
    a, lengths, fixed, prismatic = terms
    with np.errstate(over="ignore", invalid="ignore"):
        placed = np.where(a > 0, a * E[..., None, :], 0.0).sum(axis=-1)  # sum_j a_lj E_j (a_lj = 0: no effect)
        travel = []
        for js in prismatic:  # sum_j Q_j over the active prismatic joints of the chain, in order
            acc = np.zeros(Q.shape[:-1])
            for j in js:
                acc = acc + Q[..., j]
            travel.append(acc)
        reach = fixed + (np.stack(travel, axis=-1) if travel else np.zeros(Q.shape[:-1] + (0,)))
        return (1 + 8 * u) * (placed + (K_FK * (lengths + 1) + 2 * K_DIST_ABS) * ug * reach)


def trajectory_rounding(traj, robot: Robot, capsules: CapsuleModel, dtype=np.float64, hulls=None) -> RoundingBounds:
    """The bounds of the module docstring's budget for one validated trajectory (NumPy float64):
    its rebase offset, rebased horizon, tau, the speed slack and the guard of every capsule (and
    of every part of ``hulls``, a :class:`~larc_jax.enclosure.hull.HullModel`, if given)."""
    return trajectory_roundings([traj], robot, capsules, dtype, hulls)[0]


def trajectory_roundings(trajs, robot: Robot, capsules: CapsuleModel, dtype=np.float64,
                         hulls=None) -> list[RoundingBounds]:
    """:func:`trajectory_rounding` of every trajectory of ``trajs``, the model's terms computed once."""
    ends = np.maximum(np.linalg.norm(np.asarray(capsules.p_link_a, np.float64), axis=1),
                      np.linalg.norm(np.asarray(capsules.p_link_b, np.float64), axis=1))
    capsule_terms = _guard_terms(robot, capsules.link_index, ends, capsules.motion_a)
    hull_terms = None
    if hulls is not None:
        v_max = np.linalg.norm(np.asarray(hulls.vertices, np.float64), axis=-1).max(axis=1)
        hull_terms = _guard_terms(robot, hulls.link_index, v_max, hulls.motion_a)
    for k, traj in enumerate(trajs):  # no segment: the maxima would be -inf and the guards negative
        if len(traj.t) < 2:
            raise LarcInputError(f"rounding bounds: trajectory {k} has {len(traj.t)} knot(s); need at least 2")
    return [b for lo in range(0, len(trajs), ROUNDING_CHUNK)
            for b in _roundings(trajs[lo:lo + ROUNDING_CHUNK], capsule_terms, hull_terms, dtype)]


ROUNDING_CHUNK = 16
"""Trajectories whose bounds :func:`trajectory_roundings` computes together."""


def _roundings(trajs, capsule_terms, hull_terms, dtype) -> list[RoundingBounds]:
    """:func:`trajectory_roundings` given the model's :func:`_guard_terms`: every trajectory at once,
    padded to the longest with its last knot repeated and the padding masked out of the maxima
    (each element is computed as for the trajectory alone, and a maximum has no rounding)."""
    ug = float(np.finfo(geometry_dtype(dtype)).eps) / 2
    u = _U64
    n_knots = np.array([len(tr.t) for tr in trajs])
    B, N, n = len(trajs), int(n_knots.max()), np.shape(trajs[0].q)[1]
    t, q, v = np.empty((B, N)), np.empty((B, N, n)), np.empty((B, N, n))
    for k, tr in enumerate(trajs):
        m = len(tr.t)
        t[k, :m], t[k, m:] = tr.t, tr.t[-1]
        q[k, :m], q[k, m:] = tr.q, tr.q[-1]
        v[k, :m], v[k, m:] = np.abs(tr.qd), np.abs(tr.qd[-1])
    offset = time_offsets(t)  # T1; the padding repeats t_K, exact when every real step is
    tr = t - offset[:, None]  # exact (T1)
    rows = np.arange(B)
    t_mag = np.maximum(np.abs(tr[:, 0]), np.abs(tr[rows, n_knots - 1]))
    real = (np.arange(N - 1) < (n_knots - 1)[:, None])[..., None]  # (B, N-1, 1): a real segment
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        H = np.diff(tr, axis=1)[..., None]
        seg_max = lambda x: np.max(x, axis=1, where=real, initial=-np.inf)  # noqa: E731 - over real segments
        v_sum = v[:, :-1] + v[:, 1:]
        Q = seg_max(np.abs(q[:, :-1]) + np.abs(q[:, 1:]) + H * v_sum)  # P1
        d = np.abs(np.diff(q, axis=1)) / H
        V = seg_max(v_sum + 1.5 * d)  # P2
        A = seg_max((4 * v[:, :-1] + 4 * v[:, 1:] + 6 * d) / H)  # P2'
        E = K_POS * u * Q + (2.0 * ug * Q if ug > u else 0.0)
    guard = _guards(capsule_terms, E, Q, ug)
    hull_guard = np.zeros((B, 0)) if hull_terms is None else _guards(hull_terms, E, Q, ug)
    tau = K_TIME * u * t_mag
    return [RoundingBounds(
        offset_s=np.float64(offset[k]), t_start=np.float64(tr[k, 0]), t_end=np.float64(tr[k, n_knots[k] - 1]),
        tau_s=np.float64(tau[k]), omega_slack=K_SPEED * u * V[k], accel_slack=K_SPEED * u * A[k],
        guard_m=guard[k], hull_guard_m=hull_guard[k],
    ) for k in range(B)]


# ----------------------------------------------------------------------------------------------
# The interval test
# ----------------------------------------------------------------------------------------------


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class IntervalEval:
    """Everything the interval test computed on one interval (JAX or NumPy arrays)."""

    g: jax.Array
    """Certificate clearance g of the recorded pair, m (+inf without boxes, NaN on non-finite values)."""
    guard: jax.Array
    """Rounding guard of the recorded pair, m: the interval passed iff ``g > guard``."""
    capsule: jax.Array
    """Index of the recorded capsule: the pair minimising ``g - guard`` (0 without boxes)."""
    box: jax.Array
    """Index of the recorded box (0 without boxes)."""
    t_mid: jax.Array
    """Midpoint t_m, s, in the rebased time axis (add ``RoundingBounds.offset_s``)."""
    h: jax.Array
    """Nominal half-width (b - a) / 2, s."""
    h_cov: jax.Array
    """Covering radius (T4), s: what the motion radius uses."""
    q_mid: jax.Array
    """(n,) configuration q(t_m)."""
    omega_max: jax.Array
    """(n,) speed maxima (eq. 5) over the widened interval (T5), without the slack."""
    motion_b: jax.Array
    """(C,) motion radii b_l (eq. 6, P3), m."""
    p_world_a: jax.Array
    """(C, 3) capsule segment starts at q(t_m), base frame, m."""
    p_world_b: jax.Array
    """(C, 3) capsule segment ends at q(t_m), base frame, m."""
    g_pairs: jax.Array
    """(C, B) certificate clearance ``g_lk`` of every capsule and box, m (+inf for padding boxes)."""
    speed: jax.Array
    """(n,) speed bound ``omega_max + slack`` (P2) that the motion radii use."""
    exact: jax.Array
    """Whether (g, guard, capsule, box) are certainly those of the all-pairs test (always True
    unless a broad phase was asked for, :mod:`larc_jax.leaf.clearance`; if False, evaluate again
    with ``k=None``)."""


def evaluate_interval(robot: Robot, capsules: CapsuleModel, spline: HermiteSpline, obstacles,
                      a: jax.Array, b: jax.Array, margin: jax.Array, bounds: RoundingBounds,
                      k: int | None = None) -> IntervalEval:
    """The interval test on one interval ``[a, b]`` (rebased, T1) of one trajectory (eq. 4).

    Args:
      robot, capsules: geometry arrays in the geometry dtype, except ``capsules.radius`` and
        ``capsules.motion_a`` (float64).
      spline: one trajectory's Hermite curve on rebased knots (float64).
      obstacles: one scene's obstacle set (:class:`~larc_jax.obstacles.ObstacleSet`, B items) in
        the geometry dtype.
      a, b: interval ends, s (``a <= b``); margin: rho, m; bounds: :func:`trajectory_rounding`.
      k: static; ``None``: every capsule-box pair gets the exact distance; an int: a sound
        broad phase picks the ``k`` most threatening pairs (:func:`~larc_jax.leaf.clearance.min_clearance`)
        and ``exact`` says whether the result is certainly the all-pairs one.
    """
    return evaluate_placed(place(robot, capsules, spline, a, b, bounds), capsules, obstacles, margin, bounds, k)


def capsule_offsets(pl: Placement, capsules: CapsuleModel, margin):
    """``(shell (C,), dist_scale)`` of the capsule test on an interval placed as ``pl``: a capsule's
    clearance is ``dist * dist_scale - shell``, with ``shell = (r + b + rho)(1 + 2 eps)`` (G4) and
    ``dist_scale = 1 - K_DIST_REL eps_g`` deflating the computed distance (G2)."""
    eps = float(jnp.finfo(pl.q_mid.dtype).eps)
    eps_g = float(jnp.finfo(pl.p_world_a.dtype).eps)
    return (capsules.radius + pl.motion_b + margin) * (1 + 2 * eps), 1 - K_DIST_REL * eps_g


def evaluate_placed(pl: Placement, capsules: CapsuleModel, obstacles, margin, bounds,
                    k: int | None = None) -> IntervalEval:
    """The capsule-box test (eq. 7) of :func:`evaluate_interval` on an interval already placed
    (:func:`~larc_jax.leaf.placement.place`): the capsule stage of the leaf test."""
    p_world_a, p_world_b, motion_b = pl.p_world_a, pl.p_world_b, pl.motion_b
    shell, dist_scale = capsule_offsets(pl, capsules, margin)
    dist = obstacles.segment_distances(p_world_a, p_world_b)
    dist = dist.astype(pl.q_mid.dtype) * dist_scale  # G2
    g_cb = jnp.where(obstacles.mask[None, :], dist - shell[:, None], jnp.inf)  # eq. 7 (unused outputs cost nothing)
    n_boxes = obstacles.n_items
    if k is None:
        flat = jnp.argmin(g_cb - bounds.guard_m[:, None])
        capsule, box = flat // n_boxes, flat % n_boxes
        g_pick, exact = g_cb[capsule, box], jnp.asarray(True)
    else:
        # The same g_lk (eq. 7, G2, G4) for the chosen pair; the bounds of the others are
        # monotone images of a distance lower bound (larc_jax.leaf.clearance).
        g_pick, capsule, box, exact = min_clearance(
            p_world_a, p_world_b, shell, obstacles, jnp.zeros(n_boxes, shell.dtype), k,
            dist_scale=dist_scale, guard_seg=bounds.guard_m)
    g = jnp.where(pl.finite, g_pick, jnp.nan)  # NaN never certifies
    return IntervalEval(g=g, guard=bounds.guard_m[capsule], capsule=capsule, box=box, t_mid=pl.t_mid, h=pl.h,
                        h_cov=pl.h_cov, q_mid=pl.q_mid, omega_max=pl.omega_max, motion_b=motion_b,
                        p_world_a=p_world_a, p_world_b=p_world_b, g_pairs=g_cb, speed=pl.speed, exact=exact)


def interval_clearance(robot, capsules, spline, obstacles, a, b, margin, bounds):
    """``(g, guard, capsule, box)`` of :func:`evaluate_interval`."""
    ev = evaluate_interval(robot, capsules, spline, obstacles, a, b, margin, bounds)
    return ev.g, ev.guard, ev.capsule, ev.box


def evaluate_interval_np(robot: Robot, capsules: CapsuleModel, traj, obstacles, t0: float, t1: float,
                         margin: float, bounds: RoundingBounds | None = None) -> IntervalEval:
    """NumPy float64 reference of :func:`evaluate_interval` on the leaf ``[t0, t1]`` given in the
    trajectory's own time axis (``traj``: a :class:`~larc_jax.model.trajectory.Trajectory`,
    ``obstacles``: an obstacle set or a :class:`~larc_jax.model.scene.Scene`, :func:`~larc_jax.obstacles.scene_obstacles`;
    ``bounds``: :func:`trajectory_rounding`, computed if None)."""
    if bounds is None:
        bounds = trajectory_rounding(traj, robot, capsules)
    a, b = (float(x) for x in rebase_ends(t0, t1, float(bounds.offset_s)))
    return evaluate_placed_np(place_np(robot, capsules, traj, a, b, bounds), capsules, obstacles, margin, bounds)


def evaluate_placed_np(pl: Placement, capsules: CapsuleModel, obstacles, margin: float, bounds) -> IntervalEval:
    """NumPy float64 twin of :func:`evaluate_placed` (``obstacles``: an obstacle set, or a
    :class:`~larc_jax.model.scene.Scene`, :func:`~larc_jax.obstacles.scene_obstacles`)."""
    obstacles = scene_obstacles(obstacles)
    p_a, p_b, motion_b = pl.p_world_a, pl.p_world_b, pl.motion_b
    radius = np.asarray(capsules.radius, np.float64)
    guard = np.asarray(bounds.guard_m, np.float64)
    best, pair, g = math.inf, (0, 0), math.inf
    g_pairs = np.full((capsules.n_capsules, max(obstacles.n_items, 1)), np.inf)
    for c in range(capsules.n_capsules):
        shell = (radius[c] + motion_b[c] + margin) * (1 + 2 * _EPS64)
        for k in (k for k in range(obstacles.n_items) if obstacles.mask[k]):
            dist = obstacles.take(k).segment_distance_np(p_a[c], p_b[c]) * (1 - K_DIST_REL * _EPS64)
            g_pairs[c, k] = dist - shell
            excess = (dist - shell) - guard[c]
            if excess < best or (math.isnan(excess) and not math.isnan(best)):
                best, pair, g = excess, (c, k), dist - shell
    g = g if pl.finite else math.nan
    return IntervalEval(g=g, guard=float(guard[pair[0]]), capsule=pair[0], box=pair[1], t_mid=pl.t_mid, h=pl.h,
                        h_cov=pl.h_cov, q_mid=pl.q_mid, omega_max=pl.omega_max, motion_b=motion_b,
                        p_world_a=p_a, p_world_b=p_b, g_pairs=g_pairs, speed=pl.speed, exact=True)


def interval_clearance_np(robot, capsules, traj, obstacles, t0: float, t1: float, margin: float, bounds=None):
    """``(g, guard, capsule, box)`` of :func:`evaluate_interval_np`."""
    ev = evaluate_interval_np(robot, capsules, traj, obstacles, t0, t1, margin, bounds)
    return ev.g, ev.guard, ev.capsule, ev.box
