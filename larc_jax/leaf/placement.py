"""Placing the enclosures on one interval: the step every stage of the leaf test shares.

An interval ``[a, b]`` (rebased, budget T1 of :mod:`larc_jax.leaf.interval`) is placed once: its
midpoint ``t_m``, covering radius ``h_cov`` (T4), speed maxima (eq. 5, T5) and speed bound
(P2), the capsules' motion radii (eq. 6, P3) and the capsule segments at ``q(t_m)`` in the
base frame. The stages of :mod:`larc_jax.leaf.record` (capsule, hull, self) read these instead of
computing them again. :func:`motion_radii` is the one place the motion-radius formula lives:
the capsules', the hull parts' (:mod:`larc_jax.leaf.cascade`) and the self pairs'
(:mod:`larc_jax.leaf.self_collision`) use it.

:func:`place` is the one-item JAX kernel, :func:`place_np` its NumPy float64 twin. Nothing
here imports JAX (:mod:`larc_jax.lazy_jax`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..enclosure.capsule import CapsuleModel, capsule_segments, capsule_segments_np
from ..model.hermite import HermiteSpline, evaluate, evaluate_np, speed_max, speed_max_np
from ..lazy_jax import jax, jnp, pytree_dataclass
from ..model.robot import Robot

__all__ = ["Placement", "place", "place_np", "motion_radii"]

EPS64 = float(np.finfo(np.float64).eps)


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class Placement:
    """The enclosures placed on one interval (JAX or NumPy arrays)."""

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
    speed: jax.Array
    """(n,) speed bound ``omega_max + slack`` (P2) that the motion radii use."""
    motion_b: jax.Array
    """(C,) capsule motion radii b_l (eq. 6, P3), m."""
    p_world_a: jax.Array
    """(C, 3) capsule segment starts at q(t_m), base frame, m (geometry dtype)."""
    p_world_b: jax.Array
    """(C, 3) capsule segment ends at q(t_m), base frame, m."""
    finite: jax.Array
    """Whether all of the above is finite: a stage's clearance is NaN (never certifies) if not."""


def motion_radii(motion_a, h_cov, speed):
    """Motion radii ``b_e = h_cov * sum_j a_ej speed_j`` (eq. 6) of enclosures with motion
    constants ``motion_a`` (E, n), float64 and rounded up (P3): (E,), m. JAX or NumPy arrays."""
    n = speed.shape[-1]
    if isinstance(speed, np.ndarray):
        return h_cov * (np.asarray(motion_a, np.float64) @ speed) * (1 + (n + 64) * EPS64)
    return h_cov * jnp.matmul(motion_a, speed, precision=jax.lax.Precision.HIGHEST) * (1 + (n + 64) * EPS64)


def place(robot: Robot, capsules: CapsuleModel, spline: HermiteSpline, a, b, bounds) -> Placement:
    """The placement of one interval ``[a, b]`` (rebased, ``a <= b``) of one trajectory
    (``spline``, float64, rebased knots; ``bounds``: :func:`~larc_jax.leaf.interval.trajectory_rounding`);
    ``robot`` and the capsule segments in the geometry dtype, radii and motion constants float64."""
    eps = float(jnp.finfo(spline.knots().dtype).eps)
    gdtype = robot.T_parent_joint.dtype
    t_mid = 0.5 * (a + b)
    h = 0.5 * (b - a)
    h_cov = (jnp.maximum(t_mid - a, b - t_mid) + bounds.tau_s) * (1 + 2 * eps)  # T4
    q_mid, _ = evaluate(spline, t_mid)
    lo = jnp.maximum(a - bounds.tau_s, bounds.t_start)  # T5
    hi = jnp.minimum(b + bounds.tau_s, bounds.t_end)
    omega_max = speed_max(spline, lo, hi)  # eq. 5
    speed = omega_max + bounds.omega_slack  # P2
    motion_b = motion_radii(capsules.motion_a, h_cov, speed)  # eq. 6, P3
    p_world_a, p_world_b = capsule_segments(robot, capsules, q_mid.astype(gdtype))
    finite = (
        jnp.isfinite(q_mid).all() & jnp.isfinite(omega_max).all() & jnp.isfinite(motion_b).all()
        & jnp.isfinite(p_world_a).all() & jnp.isfinite(p_world_b).all()
    )
    return Placement(t_mid=t_mid, h=h, h_cov=h_cov, q_mid=q_mid, omega_max=omega_max, speed=speed,
                     motion_b=motion_b, p_world_a=p_world_a, p_world_b=p_world_b, finite=finite)


def place_np(robot: Robot, capsules: CapsuleModel, traj, a: float, b: float, bounds) -> Placement:
    """NumPy float64 twin of :func:`place`: ``traj`` a :class:`~larc_jax.model.trajectory.Trajectory`,
    ``[a, b]`` already rebased by ``bounds.offset_s`` (:func:`~larc_jax.leaf.interval.rebase_ends`)."""
    offset, tau = float(bounds.offset_s), float(bounds.tau_s)
    t = np.asarray(traj.t, np.float64) - offset  # exact (T1)
    t_mid = 0.5 * (a + b)
    h = 0.5 * (b - a)
    h_cov = (max(t_mid - a, b - t_mid) + tau) * (1 + 2 * EPS64)
    q_mid, _ = evaluate_np(t, traj.q, traj.qd, t_mid)
    omega_max = speed_max_np(t, traj.q, traj.qd, max(a - tau, t[0]), min(b + tau, t[-1]))
    speed = omega_max + np.asarray(bounds.omega_slack, np.float64)
    motion_b = motion_radii(capsules.motion_a, h_cov, speed)
    p_a, p_b = capsule_segments_np(robot, capsules, q_mid)
    finite = all(np.isfinite(x).all() for x in (q_mid, omega_max, motion_b, p_a, p_b))
    return Placement(t_mid=t_mid, h=h, h_cov=h_cov, q_mid=q_mid, omega_max=omega_max, speed=speed,
                     motion_b=motion_b, p_world_a=p_a, p_world_b=p_b, finite=finite)
