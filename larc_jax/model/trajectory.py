"""Joint trajectories: the :class:`Trajectory` record, its validation against a robot, and
finite-difference velocities.

A trajectory is reconstructed by piecewise-cubic Hermite interpolation of the positions and
velocities (:mod:`larc_jax.model.hermite`). Files are read and written by
:mod:`larc_jax.model.trajectory_files`. A file without velocities is refused unless
``velocities="finite-difference"`` (CLI ``--velocities finite-difference``), which computes them
from the positions (:func:`finite_difference_velocities`). The certificate then covers the
Hermite curve through those velocities, which is a different curve from the one the
controller that executes the waypoints may follow.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from ..defaults import POSITION_TOLERANCE, VELOCITY_MODES
from ..errors import LarcInputError
from ..io import real_array, short_repr
from .robot import JointType, Robot

__all__ = [
    "Trajectory",
    "Locator",
    "msg_locator",
    "check_times",
    "check_joint_names",
    "validate_trajectory",
    "finite_difference_velocities",
    "VELOCITY_MODES",
    "MAX_WAYPOINTS",
    "POSITION_TOLERANCE",
]

MAX_WAYPOINTS = 100_000
"""Refuse larger trajectories: a recorded arm motion has hundreds of points, not millions."""




@dataclasses.dataclass(frozen=True)
class Trajectory:
    """One recorded trajectory (at least 2 waypoints).

    The constructor accepts array-likes (lists, NumPy or JAX arrays) and stores read-only
    float64 copies; wrong types or shapes raise :class:`LarcInputError` naming the field.
    Values (finite, increasing times, joint names and limits of a robot) are checked by
    :func:`validate_trajectory`, which :func:`~larc_jax.engine.certify.certify` calls.
    """

    t: np.ndarray
    """(K+1,) waypoint times, s, strictly increasing, t[0] is the start of the horizon."""
    q: np.ndarray
    """(K+1, n) positions, rad / m."""
    qd: np.ndarray
    """(K+1, n) velocities, rad/s / m/s."""
    joint_names: tuple[str, ...]
    """n joint names, one per column of q and qd."""
    id: str = ""
    source: str = ""

    def __post_init__(self):
        for field in ("id", "source"):
            if not isinstance(getattr(self, field), str):
                raise LarcInputError(f"Trajectory.{field} must be a string, got {short_repr(getattr(self, field))}")
        src = self.source or self.id or "Trajectory"
        t = real_array(self.t, f"{src}: Trajectory.t (waypoint times)", 1)
        if len(t) < 2:
            raise LarcInputError(f"{src}: Trajectory.t has {len(t)} waypoint{'s' if len(t) != 1 else ''}; "
                                 "a trajectory needs at least 2")
        q = real_array(self.q, f"{src}: Trajectory.q (positions)", 2)
        qd = real_array(self.qd, f"{src}: Trajectory.qd (velocities)", 2)
        if q.shape[0] != len(t):
            raise LarcInputError(f"{src}: Trajectory.q has {q.shape[0]} rows, but t has {len(t)} waypoints")
        if qd.shape != q.shape:
            raise LarcInputError(f"{src}: Trajectory.qd has shape {qd.shape}, but q has shape {q.shape}")
        names = self.joint_names
        if isinstance(names, str) or not isinstance(names, (list, tuple)) or not all(isinstance(n, str) for n in names):
            raise LarcInputError(f"{src}: Trajectory.joint_names must be a list of joint names, got {short_repr(names)}")
        if len(names) != q.shape[1]:
            raise LarcInputError(f"{src}: Trajectory.joint_names has {len(names)} names, but q has {q.shape[1]} "
                                 "columns (one per joint)")
        for field, value in (("t", t), ("q", q), ("qd", qd), ("joint_names", tuple(names))):
            object.__setattr__(self, field, value)

    @property
    def duration(self) -> float:
        return float(self.t[-1] - self.t[0])

    @property
    def n_waypoints(self) -> int:
        return len(self.t)


Locator = Callable[[int, str, "int | None"], str]
"""(waypoint index, field, joint index or None) -> where it is in the file, for error messages."""


def msg_locator(prefix: str = "") -> Locator:
    return lambda k, field, j: f"{prefix}points[{k}].{field}" + ("" if j is None else f"[{j}]")



def check_times(t: np.ndarray, src: str, loc: Locator) -> None:
    if not np.isfinite(t).all():
        k = int(np.flatnonzero(~np.isfinite(t))[0])
        raise LarcInputError(f"{src}: {loc(k, 'time_from_start', None)} is not finite")
    dt = np.diff(t)
    if (dt <= 0).any():
        k = int(np.flatnonzero(dt <= 0)[0]) + 1
        raise LarcInputError(
            f"{src}: {loc(k, 'time_from_start', None)} ({float(t[k])!r} s) is not after "
            f"{loc(k - 1, 'time_from_start', None)} ({float(t[k - 1])!r} s): times must be strictly increasing"
        )


def finite_difference_velocities(
    t, q, *, source: str = "<trajectory>", where: Locator | None = None
) -> np.ndarray:
    """Velocities at the waypoints from positions alone (``(K+1,)`` times, ``(K+1, n)`` positions).

    Interior waypoints: the three-point central difference on the non-uniform grid
    (``numpy.gradient``), ``qd_k = [h1² (q_{k+1} − q_k) + h2² (q_k − q_{k−1})] / (h1 h2 (h1 + h2))``
    with ``h1 = t_k − t_{k−1}``, ``h2 = t_{k+1} − t_k``; the end points: the three-point one-sided
    difference (``edge_order=2``). Both are exact for quadratic motions, uniform grid or not.
    With only two waypoints both velocities are the secant slope. Times must be finite and
    strictly increasing (refused otherwise, naming the waypoint).

    The result is a modelling choice, not a measurement: a certificate built on these
    velocities covers the Hermite curve through them, not necessarily the motion a controller
    produces from the positions.
    """
    t = np.asarray(t, dtype=np.float64)
    q = np.asarray(q, dtype=np.float64)
    loc = where or msg_locator()
    if len(t) < 2 or q.shape[0] != len(t):
        raise LarcInputError(f"{source}: finite differences need at least 2 waypoints with one time each")
    check_times(t, source, loc)
    bad = ~np.isfinite(q)
    if bad.any():
        k, j = map(int, np.argwhere(bad)[0])
        raise LarcInputError(f"{source}: {loc(k, 'positions', j)} is not finite ({float(q[k, j])!r})")
    if len(t) == 2:
        slope = (q[1] - q[0]) / (t[1] - t[0])
        return np.stack([slope, slope])
    return np.gradient(q, t, axis=0, edge_order=2)


def check_joint_names(names: list, want: list, src: str, prefix: str = "") -> None:
    """``names`` must be the robot's active joints ``want`` (any order, each once)."""
    if len(set(names)) != len(names):
        i = next(i for i, n in enumerate(names) if n in names[:i])
        raise LarcInputError(
            f"{src}: {prefix}joint_names has duplicates: {prefix}joint_names[{i}] '{names[i]}' repeats "
            f"{prefix}joint_names[{names.index(names[i])}]")
    if set(names) != set(want):
        missing = [n for n in want if n not in names]
        extra = [n for n in names if n not in want]
        raise LarcInputError(
            f"{src}: {prefix}joint_names {short_repr(names)} do not match the robot's active joints {want}"
            + (f"; missing {missing}" if missing else "") + (f"; unknown {short_repr(extra)}" if extra else "")
        )



def validate_trajectory(
    traj: Trajectory, robot: Robot, *, where: Locator | None = None,
) -> Trajectory:
    """Check a trajectory against the robot and return it with joints in the robot's order.

    Raises :class:`LarcInputError` naming the file, field and index of the first problem:
    too many waypoints, non-finite or non-increasing times, non-finite positions/velocities,
    joint names that are not exactly the robot's active joints, positions outside the URDF
    limits, and (for active prismatic joints, whose travel the motion constants of the joints
    above them assume) a Hermite curve that leaves the limits between waypoints. ``where(k,
    field, j)`` names waypoint ``k``'s field in the file (default
    ``points[k].field[j]``).
    """
    src = traj.source or traj.id or "<trajectory>"
    loc = where or msg_locator()
    if traj.n_waypoints > MAX_WAYPOINTS:
        raise LarcInputError(f"{src}: {traj.n_waypoints} waypoints (limit {MAX_WAYPOINTS})")
    check_times(traj.t, src, loc)
    for field, arr in (("positions", traj.q), ("velocities", traj.qd)):
        bad = ~np.isfinite(arr)
        if bad.any():
            k, j = map(int, np.argwhere(bad)[0])
            raise LarcInputError(f"{src}: {loc(k, field, j)} is not finite ({float(arr[k, j])!r})")
    names = list(traj.joint_names)
    want = list(robot.active_joint_names)
    check_joint_names(names, want, src)
    order = [names.index(n) for n in want]
    q, qd = traj.q[:, order], traj.qd[:, order]
    lo = np.asarray(robot.q_lower) - POSITION_TOLERANCE
    hi = np.asarray(robot.q_upper) + POSITION_TOLERANCE
    bad = (q < lo) | (q > hi)
    if bad.any():
        k, j = map(int, np.argwhere(bad)[0])
        raise LarcInputError(
            f"{src}: {loc(k, 'positions', order[j])} = {float(q[k, j])!r} for {want[j]} is outside its "
            f"limits [{robot.q_lower[j]}, {robot.q_upper[j]}]"
        )
    for i, jtype in zip(robot.q_index, robot.joint_type):
        if i >= 0 and jtype == JointType.PRISMATIC:
            _check_prismatic_curve(traj.t, q[:, i], qd[:, i], float(lo[i]), float(hi[i]), src, loc, want[i], order[i])
    return dataclasses.replace(traj, q=q, qd=qd, joint_names=tuple(want))


def _check_prismatic_curve(t, q, v, lo: float, hi: float, src: str, loc: Locator, name: str, j: int) -> None:
    """The Hermite curve of an active prismatic joint must stay within its limits (widened by
    the tolerance) between waypoints too: its extremes on a segment are at the ends or at the
    roots of the quadratic velocity (:mod:`larc_jax.model.hermite`, form (*))."""
    h = np.diff(t)
    q0, q1, v0, v1 = q[:-1], q[1:], v[:-1], v[1:]
    d = (q1 - q0) / h
    c0, c1, c2 = v0, 6 * d - 4 * v0 - 2 * v1, 3 * v0 + 3 * v1 - 6 * d
    with np.errstate(divide="ignore", invalid="ignore"):
        disc = np.sqrt(np.maximum(c1 * c1 - 4 * c2 * c0, 0.0))
        roots = [np.where(c2 != 0, (-c1 + sgn * disc) / (2 * c2), np.where(c1 != 0, -c0 / c1, 0.0)) for sgn in (1, -1)]
    for s in roots:
        s = np.clip(np.nan_to_num(s, nan=0.0), 0.0, 1.0)
        qs = ((1 + 2 * s) * (1 - s) ** 2 * q0 + s * (1 - s) ** 2 * h * v0 + s * s * (3 - 2 * s) * q1
              + s * s * (s - 1) * h * v1)
        bad = (qs < lo) | (qs > hi)
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise LarcInputError(
                f"{src}: between {loc(k, 'positions', j)} and {loc(k + 1, 'positions', j)} the Hermite curve of "
                f"prismatic joint {name} reaches {float(qs[k])!r}, outside its limits (the velocities carry it "
                f"past the limit; the motion constants hold within the limits only)")

