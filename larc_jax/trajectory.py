"""Joint trajectories: reading, validating and writing ``trajectory_msgs/JointTrajectory`` files.

File format (YAML or JSON)::

    joint_names: [joint1, ..., joint6]
    points:
      - positions: [...]            # rad (revolute) / m (prismatic)
        velocities: [...]           # rad/s, m/s
        time_from_start: {sec: 0, nanosec: 0}

A trajectory is reconstructed by piecewise-cubic Hermite interpolation of the recorded
positions and velocities (:mod:`larc_jax.hermite`).
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Sequence

import numpy as np
import yaml

from .errors import LarcInputError
from .io import atomic_write_text
from .robot import Robot

__all__ = [
    "Trajectory",
    "read_trajectory",
    "write_trajectory",
    "trajectory_to_msg",
    "trajectory_from_msg",
    "validate_trajectory",
    "MAX_WAYPOINTS",
    "POSITION_TOLERANCE",
]

MAX_WAYPOINTS = 100_000
"""Refuse larger trajectories: a recorded arm motion has hundreds of points, not millions."""

POSITION_TOLERANCE = 1e-6
"""Positions may exceed a joint limit by at most this much (rad or m): recorders round.
The motion constants are derived for the URDF limits, so larger excursions are refused."""


@dataclasses.dataclass(frozen=True)
class Trajectory:
    """One recorded trajectory, joints in the robot's active-joint order."""

    t: np.ndarray
    """(K+1,) waypoint times, s, strictly increasing, t[0] is the start of the horizon."""
    q: np.ndarray
    """(K+1, n) positions, rad / m."""
    qd: np.ndarray
    """(K+1, n) velocities, rad/s / m/s."""
    joint_names: tuple[str, ...]
    id: str = ""
    source: str = ""

    @property
    def duration(self) -> float:
        return float(self.t[-1] - self.t[0])

    @property
    def n_waypoints(self) -> int:
        return len(self.t)


def _time_of(value, source: str, where: str) -> float:
    if isinstance(value, dict):
        sec, nsec = value.get("sec", 0), value.get("nanosec", value.get("nsec", 0))
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (sec, nsec)):
            raise LarcInputError(f"{source}: {where} must have numeric sec and nanosec")
        return float(sec) + float(nsec) * 1e-9
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    raise LarcInputError(f"{source}: {where} must be {{sec, nanosec}} or a number of seconds")


def _vector(value, n: int, source: str, where: str) -> np.ndarray:
    if not isinstance(value, (list, tuple)):
        raise LarcInputError(f"{source}: {where} must be a list of {n} numbers")
    if len(value) != n:
        raise LarcInputError(f"{source}: {where} has {len(value)} entries, expected {n}")
    out = np.empty(n)
    for i, v in enumerate(value):
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise LarcInputError(f"{source}: {where}[{i}] is not a number ({v!r})")
        out[i] = float(v)
    return out


def trajectory_from_msg(msg, *, source: str = "<trajectory>", traj_id: str = "") -> Trajectory:
    """Parse a JointTrajectory-shaped mapping (no robot checks; see :func:`validate_trajectory`)."""
    if not isinstance(msg, dict):
        raise LarcInputError(f"{source}: expected a JointTrajectory mapping with joint_names and points")
    names = msg.get("joint_names")
    if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
        raise LarcInputError(f"{source}: joint_names must be a non-empty list of strings")
    points = msg.get("points")
    if not isinstance(points, list) or len(points) < 2:
        raise LarcInputError(f"{source}: points must be a list of at least 2 waypoints")
    if len(points) > MAX_WAYPOINTS:
        raise LarcInputError(f"{source}: points has {len(points)} waypoints (limit {MAX_WAYPOINTS})")
    n = len(names)
    t = np.empty(len(points))
    q = np.empty((len(points), n))
    qd = np.empty((len(points), n))
    for k, p in enumerate(points):
        where = f"points[{k}]"
        if not isinstance(p, dict):
            raise LarcInputError(f"{source}: {where} must be a mapping")
        for key in ("positions", "velocities", "time_from_start"):
            if key not in p or p[key] is None or (key == "velocities" and p[key] == []):
                raise LarcInputError(f"{source}: {where}.{key} is missing")
        q[k] = _vector(p["positions"], n, source, f"{where}.positions")
        qd[k] = _vector(p["velocities"], n, source, f"{where}.velocities")
        t[k] = _time_of(p["time_from_start"], source, f"{where}.time_from_start")
    return Trajectory(t=t, q=q, qd=qd, joint_names=tuple(names), id=traj_id, source=source)


def validate_trajectory(
    traj: Trajectory, robot: Robot, *, position_tolerance: float = POSITION_TOLERANCE
) -> Trajectory:
    """Check a trajectory against the robot and return it with joints in the robot's order.

    Raises :class:`LarcInputError` naming the file, field and index of the first problem:
    non-finite or non-increasing times, non-finite positions/velocities, joint names that are
    not exactly the robot's active joints, positions outside the URDF limits.
    """
    src = traj.source or traj.id or "<trajectory>"
    if not np.isfinite(traj.t).all():
        k = int(np.flatnonzero(~np.isfinite(traj.t))[0])
        raise LarcInputError(f"{src}: points[{k}].time_from_start is not finite")
    dt = np.diff(traj.t)
    if (dt <= 0).any():
        k = int(np.flatnonzero(dt <= 0)[0]) + 1
        raise LarcInputError(
            f"{src}: points[{k}].time_from_start ({traj.t[k]!r} s) is not after points[{k - 1}] "
            f"({traj.t[k - 1]!r} s): times must be strictly increasing"
        )
    for field, arr in (("positions", traj.q), ("velocities", traj.qd)):
        bad = ~np.isfinite(arr)
        if bad.any():
            k, j = map(int, np.argwhere(bad)[0])
            raise LarcInputError(f"{src}: points[{k}].{field}[{j}] is not finite ({arr[k, j]!r})")
    names = list(traj.joint_names)
    want = list(robot.active_joint_names)
    if len(set(names)) != len(names):
        raise LarcInputError(f"{src}: joint_names has duplicates: {names}")
    if set(names) != set(want):
        missing = [n for n in want if n not in names]
        extra = [n for n in names if n not in want]
        raise LarcInputError(
            f"{src}: joint_names {names} do not match the robot's active joints {want}"
            + (f"; missing {missing}" if missing else "") + (f"; unknown {extra}" if extra else "")
        )
    order = [names.index(n) for n in want]
    q, qd = traj.q[:, order], traj.qd[:, order]
    lo = np.asarray(robot.q_lower) - position_tolerance
    hi = np.asarray(robot.q_upper) + position_tolerance
    bad = (q < lo) | (q > hi)
    if bad.any():
        k, j = map(int, np.argwhere(bad)[0])
        raise LarcInputError(
            f"{src}: points[{k}].positions[{order[j]}] = {q[k, j]!r} for {want[j]} is outside its "
            f"limits [{robot.q_lower[j]}, {robot.q_upper[j]}]"
        )
    return dataclasses.replace(traj, q=q, qd=qd, joint_names=tuple(want))


def _load_document(path: Path):
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise LarcInputError(f"{path}: file does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise LarcInputError(f"{path}: cannot read ({exc})") from None
    if not text.strip():
        raise LarcInputError(f"{path}: file is empty")
    try:
        if path.suffix.lower() == ".json":
            return json.loads(text)
        return yaml.safe_load(text)
    except (json.JSONDecodeError, yaml.YAMLError) as exc:
        raise LarcInputError(f"{path}: not valid {'JSON' if path.suffix.lower() == '.json' else 'YAML'} ({exc})".replace("\n", " ")) from None


def read_trajectory(path: str | Path, robot: Robot | None = None) -> Trajectory:
    """Read a JointTrajectory YAML/JSON file; validate against ``robot`` when given."""
    path = Path(path)
    traj = trajectory_from_msg(_load_document(path), source=str(path), traj_id=path.stem)
    return validate_trajectory(traj, robot) if robot is not None else traj


def _stamp(t: float) -> dict:
    sec = math.floor(t)
    nsec = int(round((t - sec) * 1e9))
    if nsec >= 1_000_000_000:
        sec, nsec = sec + 1, nsec - 1_000_000_000
    return {"sec": int(sec), "nanosec": nsec}


def trajectory_to_msg(traj: Trajectory) -> dict:
    """JointTrajectory mapping. Times are written as {sec, nanosec} (1 ns resolution)."""
    return {
        "joint_names": list(traj.joint_names),
        "points": [
            {
                "positions": [float(x) for x in traj.q[k]],
                "velocities": [float(x) for x in traj.qd[k]],
                "time_from_start": _stamp(float(traj.t[k])),
            }
            for k in range(traj.n_waypoints)
        ],
    }


def write_trajectory(path: str | Path, traj: Trajectory) -> None:
    """Write a JointTrajectory file atomically (JSON if the suffix is .json, else YAML).

    Floats are written with repr precision, so positions and velocities round-trip exactly;
    times are quantised to 1 ns, as in a ROS message.
    """
    path = Path(path)
    msg = trajectory_to_msg(traj)
    if path.suffix.lower() == ".json":
        atomic_write_text(path, json.dumps(msg) + "\n")
    else:
        atomic_write_text(path, yaml.safe_dump(msg, sort_keys=False, default_flow_style=None, width=200))
