"""Joint tracking-error tolerance: a certificate for every executed trajectory near the plan.

A controller does not follow the planned curve ``q(t)`` exactly. With a tolerance ``delta_j``
per active joint (rad for a revolute joint, m for a prismatic one), the certificate made with
``certify(..., tracking_tolerance=delta)`` holds for every executed trajectory ``q_e(t)`` with
``|q_e,j(t) - q_j(t)| <= delta_j`` at every instant ``t`` of the horizon (no smoothness asked
of the error; the executed configurations of active prismatic joints must stay within their
validated stroke, the limits widened by :data:`~larc_jax.defaults.POSITION_TOLERANCE`, for which
the motion constants were derived; with the self-collision test, a link pair proven apart over a
box of joint values is skipped only if the planned curve's enclosure widened by ``delta`` lies
in that box, :func:`larc_jax.leaf.self_collision.curve_ranges`, so the executions are covered too).

Why growing every capsule radius by ``Delta_l = sum_j a_lj delta_j`` is enough. Fix ``t`` and
walk the straight joint-space path ``s -> q(t) + s e``, ``s in [0, 1]``, ``e = q_e(t) - q(t)``
(inside the limits: they are a box, hence convex). A point ``p`` of capsule ``l`` rigid in its
link moves with velocity ``sum_j e_j v_j(p)``: ``v_j = axis_j x (p - o_j)`` for a revolute
joint, so ``|v_j| = dist(p, axis_j) <= a_lj`` (the arc it sweeps is at most radius x angle),
and ``v_j = axis_j``, ``|v_j| = 1 = a_lj``, for a prismatic one
(:func:`~larc_jax.enclosure.motion.motion_constants`, valid at every configuration within the
limits). Integrating over ``s``, the point at ``q_e(t)`` lies within ``sum_j a_lj |e_j| <=
Delta_l`` of the same point at ``q(t)``. So the link, inside its capsule at ``q_e(t)``, lies
inside the capsule at ``q(t)`` with radius ``r_l + Delta_l``. The interval test then runs
unchanged on the planned curve with these radii: the motion radius ``b_l`` bounds how far
the grown capsule moves over an interval, since the grown capsule is the original one plus a
ball that moves with it (the ``a_lj`` need not grow with the radius).

Rounding. ``Delta_l`` is ``n`` non-negative products and sums: ``fl(sum) * (1 + (n + 4) eps)``
bounds it from above; the grown radius ``fl(r_l + Delta_l)`` is moved up by one ulp unless the
sum is exact (checked with TwoSum), so the radius the kernel uses is at least the real one.
A zero tolerance leaves every radius bit-identical (the certificate is then the plain one).
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from typing import Mapping

import numpy as np

from .capsule import CapsuleModel
from ..errors import LarcInputError
from ..model.robot import JointType, Robot
from ..option_values import parse_tracking_tolerance  # the command-line form (no JAX: the CLI checks it first)

__all__ = ["check_tracking_tolerance", "parse_tracking_tolerance", "tracked_capsules", "tracking_radius", "joint_units"]

_EPS64 = float(np.finfo(np.float64).eps)


def _value(x, what: str) -> float:
    if isinstance(x, bool) or not isinstance(x, numbers.Real) or not (math.isfinite(x) and x >= 0):
        raise LarcInputError(f"{what} {x!r}: must be a finite number >= 0 (rad for a revolute joint, m for a "
                             "prismatic one)")
    return float(x)


def check_tracking_tolerance(value, robot: Robot, what: str = "certify: tracking_tolerance") -> np.ndarray | None:
    """The tolerance as an (n,) float64 array over the robot's active joints, or None.

    ``value``: None (no tolerance), one number for every joint, a sequence of ``n`` numbers in
    the order of ``robot.active_joint_names``, or a mapping from active joint names to numbers
    (joints not named get 0). Negative, NaN, infinite, a wrong length or an unknown joint name
    raise :class:`LarcInputError` naming it."""
    n = robot.n_joints
    names = tuple(robot.active_joint_names)
    if value is None:
        return None
    if isinstance(value, Mapping):
        out = np.zeros(n)
        for name, x in value.items():
            if name not in names:
                raise LarcInputError(f"{what}: '{name}' is not an active joint of the robot ({', '.join(names)})")
            out[names.index(name)] = _value(x, f"{what}[{name}]")
        return out
    if isinstance(value, numbers.Real) or (isinstance(value, np.ndarray) and value.ndim == 0):
        return np.full(n, _value(value.item() if isinstance(value, np.ndarray) else value, what))
    if isinstance(value, (str, bytes)) or not hasattr(value, "__len__"):
        raise LarcInputError(f"{what}: expected a number, {n} numbers or a mapping joint -> number, got "
                             f"{type(value).__name__}")
    items = list(value)
    if len(items) != n:
        raise LarcInputError(f"{what}: {len(items)} values for {n} active joints ({', '.join(names)})")
    return np.array([_value(x.item() if isinstance(x, np.generic) else x, f"{what}[{i}] ({names[i]})")
                     for i, x in enumerate(items)], np.float64)


def tracking_radius(capsules: CapsuleModel, delta: np.ndarray) -> np.ndarray:
    """(C,) ``Delta_l >= sum_j a_lj delta_j``, m, rounded up (module docstring)."""
    a = np.asarray(capsules.motion_a, np.float64)
    n = a.shape[1]
    return (a @ np.asarray(delta, np.float64)) * (1 + (n + 4) * _EPS64)


def tracked_capsules(capsules: CapsuleModel, delta: np.ndarray | None) -> CapsuleModel:
    """``capsules`` with every radius grown by :func:`tracking_radius` (upper bound; the same model
    when ``delta`` is None). The motion constants stay those of the original capsules."""
    if delta is None:
        return capsules
    r = np.asarray(capsules.radius, np.float64)
    grow = tracking_radius(capsules, delta)
    s = r + grow
    bp = s - r  # TwoSum (Knuth): r + grow = s + err exactly
    err = (r - (s - bp)) + (grow - bp)
    radius = np.where(err == 0, s, np.nextafter(s, np.inf))
    return dataclasses.replace(capsules, radius=radius)


def joint_units(robot: Robot) -> tuple[str, ...]:
    """'rad' or 'm' per active joint, for printing a tolerance."""
    units = ["rad"] * robot.n_joints
    for i, j in enumerate(robot.q_index):
        if j >= 0 and robot.joint_type[i] == JointType.PRISMATIC:
            units[j] = "m"
    return tuple(units)
