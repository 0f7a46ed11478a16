"""The interval test (paper eqs. 4-7): one interval of one trajectory, its NumPy reference,
and the floating-point rounding guard.

For ``I = [t_m - h, t_m + h]`` of one trajectory, every capsule ``l`` is placed at the midpoint
configuration ``q(t_m)`` and inflated by the motion radius ``b_l(I) = h * sum_j a_lj *
omega_max_j(I)`` (eq. 6) with exact Hermite speed maxima (eq. 5). The certificate clearance is::

    g(I) = min_{l, box} dist(segment_l(q(t_m)), box) - (r_l + b_l(I) + rho)

and the interval passes iff ``g(I) > guard`` where ``guard >= 0`` is the rounding guard below.
If it passes, every point of every link stays more than ``rho`` from every box on ``I``
(Theorem 1; see ``../shared/notes/architecture.md`` for the chain of inclusions).

:func:`evaluate_interval` is the JAX kernel for one interval; it returns an
:class:`IntervalEval` record of every intermediate (``q_mid``, speed maxima, motion radii,
placed segments, the clearance and the pair attaining it) so the schedulers, ``explain`` and
the tests share one computation (a jitted caller that keeps only ``g`` pays for nothing else).
:func:`evaluate_interval_np` is its NumPy float64 reference, written with the references of
every kernel it calls.

Rounding guard. Every quantity in ``g`` is computed in floating point. ``guard`` is an
absolute bound, in metres, on how far the computed ``g`` can exceed the exact one:
``guard = ulps * eps(dtype) * (1 + scale)`` with ``scale`` the largest coordinate magnitude
involved (box corners and the arm's reach, in metres) and ``ulps`` 256 for float64 and 4096
for float32 (measured errors are far below; see tests/test_certify.py). In float32 mode each
interval's endpoints are also rounded *outwards* so that the float32 intervals still cover the
float64 horizon. NaN or infinite intermediate values always fail the test.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from .enclosure.capsule import CapsuleModel, capsule_segments, capsule_segments_np
from .errors import LarcInputError
from .geometry import segment_box_distance, segment_box_distance_np
from .hermite import HermiteSpline, evaluate, evaluate_np, speed_max, speed_max_np
from .robot import JointType, Robot

__all__ = [
    "IntervalEval",
    "evaluate_interval",
    "evaluate_interval_np",
    "interval_clearance",
    "interval_clearance_np",
    "rounding_guard",
    "coordinate_scale",
    "GUARD_ULPS",
]

GUARD_ULPS = {np.dtype(np.float64): 256, np.dtype(np.float32): 4096}


def rounding_guard(dtype, scale: float) -> float:
    """Absolute bound (m) on the rounding error of a computed clearance ``g`` (module doc)."""
    dtype = np.dtype(dtype)
    if dtype not in GUARD_ULPS:
        raise LarcInputError(f"dtype {dtype} is not supported (float64 or float32)")
    return float(GUARD_ULPS[dtype] * np.finfo(dtype).eps * (1.0 + scale))


def coordinate_scale(scenes, robot: Robot, capsules: CapsuleModel) -> float:
    """Bound on every coordinate magnitude (m) in the clearance: box corners, and any capsule
    point (sum of joint-origin offsets, held/active prismatic travel, farthest capsule point)."""
    corners = [np.abs(s.lo).max() for s in scenes if s.n_boxes] + [np.abs(s.hi).max() for s in scenes if s.n_boxes]
    offsets = float(np.linalg.norm(np.asarray(robot.T_parent_joint)[:, :3, 3], axis=1).sum())
    travel = float(np.abs(np.asarray(robot.q_held)).sum())
    for k, jtype in zip(robot.q_index, robot.joint_type):
        if k >= 0 and jtype == JointType.PRISMATIC:
            travel += max(abs(float(robot.q_lower[k])), abs(float(robot.q_upper[k])))
    ends = np.concatenate([np.asarray(capsules.p_link_a), np.asarray(capsules.p_link_b)])
    far = float(np.linalg.norm(ends, axis=1).max() + np.asarray(capsules.radius).max())
    return max(float(max(corners, default=0.0)), offsets + travel + far)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class IntervalEval:
    """Everything the interval test computed on one interval (JAX or NumPy arrays)."""

    g: jax.Array
    """Certificate clearance g(I), m (+inf without boxes, NaN on non-finite values)."""
    capsule: jax.Array
    """Index of the capsule attaining g (0 without boxes)."""
    box: jax.Array
    """Index of the box attaining g (0 without boxes)."""
    t_mid: jax.Array
    """Midpoint t_m, s."""
    h: jax.Array
    """Half-width h, s."""
    q_mid: jax.Array
    """(n,) configuration q(t_m)."""
    omega_max: jax.Array
    """(n,) exact speed maxima over I (eq. 5), rad/s or m/s."""
    motion_b: jax.Array
    """(C,) motion radii b_l(I) (eq. 6), m."""
    p_world_a: jax.Array
    """(C, 3) capsule segment starts at q(t_m), base frame, m."""
    p_world_b: jax.Array
    """(C, 3) capsule segment ends at q(t_m), base frame, m."""


def evaluate_interval(robot: Robot, capsules: CapsuleModel, spline: HermiteSpline,
                      box_lo: jax.Array, box_hi: jax.Array, box_mask: jax.Array,
                      a: jax.Array, b: jax.Array, margin: jax.Array) -> IntervalEval:
    """The interval test on one interval ``[a, b]`` of one trajectory (paper eq. 4).

    Args:
      spline: one trajectory's Hermite curve.
      box_lo, box_hi: (B, 3) obstacle boxes, m; box_mask: (B,) which boxes are real.
      a, b: interval ends, s (``a <= b``); margin: rho, m.
    """
    t_mid = 0.5 * (a + b)
    h = 0.5 * (b - a)
    q_mid, _ = evaluate(spline, t_mid)
    omega_max = speed_max(spline, a, b)  # eq. 5
    motion_b = h * (capsules.motion_a @ omega_max)  # eq. 6
    p_world_a, p_world_b = capsule_segments(robot, capsules, q_mid)
    per_box = jax.vmap(segment_box_distance, in_axes=(None, None, 0, 0))
    dist = jax.vmap(per_box, in_axes=(0, 0, None, None))(p_world_a, p_world_b, box_lo, box_hi)
    g_cb = dist - (capsules.radius + motion_b + margin)[:, None]  # eq. 7
    g_cb = jnp.where(box_mask[None, :], g_cb, jnp.inf)
    flat = jnp.argmin(g_cb)
    g = jnp.min(g_cb)
    finite = (
        jnp.isfinite(q_mid).all() & jnp.isfinite(omega_max).all() & jnp.isfinite(motion_b).all()
        & jnp.isfinite(p_world_a).all() & jnp.isfinite(p_world_b).all()
    )
    g = jnp.where(finite, g, jnp.nan)  # NaN never certifies
    n_boxes = box_lo.shape[0]
    return IntervalEval(g=g, capsule=flat // n_boxes, box=flat % n_boxes, t_mid=t_mid, h=h, q_mid=q_mid,
                        omega_max=omega_max, motion_b=motion_b, p_world_a=p_world_a, p_world_b=p_world_b)


def interval_clearance(robot, capsules, spline, box_lo, box_hi, box_mask, a, b, margin):
    """``(g, capsule, box)`` of :func:`evaluate_interval`."""
    ev = evaluate_interval(robot, capsules, spline, box_lo, box_hi, box_mask, a, b, margin)
    return ev.g, ev.capsule, ev.box


def evaluate_interval_np(robot: Robot, capsules: CapsuleModel, traj, scene, a: float, b: float,
                         margin: float) -> IntervalEval:
    """NumPy float64 reference of :func:`evaluate_interval` (``traj``: a
    :class:`~larc_jax.trajectory.Trajectory`, ``scene``: a :class:`~larc_jax.scene.Scene`)."""
    t_mid = 0.5 * (a + b)
    h = 0.5 * (b - a)
    q_mid, _ = evaluate_np(traj.t, traj.q, traj.qd, t_mid)
    omega_max = speed_max_np(traj.t, traj.q, traj.qd, a, b)
    motion_b = h * (np.asarray(capsules.motion_a, np.float64) @ omega_max)
    p_a, p_b = capsule_segments_np(robot, capsules, q_mid)
    finite = all(np.isfinite(x).all() for x in (q_mid, omega_max, motion_b, p_a, p_b))
    g_best, best = math.inf, (0, 0)
    radius = np.asarray(capsules.radius, np.float64)
    for c in range(capsules.n_capsules):
        for k in range(scene.n_boxes):
            g = segment_box_distance_np(p_a[c], p_b[c], scene.lo[k], scene.hi[k]) - (
                radius[c] + motion_b[c] + margin
            )
            if g < g_best or (math.isnan(g) and not math.isnan(g_best)):
                g_best, best = g, (c, k)
    return IntervalEval(g=g_best if finite else math.nan, capsule=best[0], box=best[1], t_mid=t_mid, h=h,
                        q_mid=q_mid, omega_max=omega_max, motion_b=motion_b, p_world_a=p_a, p_world_b=p_b)


def interval_clearance_np(robot, capsules, traj, scene, a: float, b: float, margin: float):
    """``(g, capsule, box)`` of :func:`evaluate_interval_np`."""
    ev = evaluate_interval_np(robot, capsules, traj, scene, a, b, margin)
    return ev.g, ev.capsule, ev.box
