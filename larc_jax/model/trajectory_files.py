"""Trajectory files: reading (ROS/MoveIt messages as YAML or JSON, CSV) and writing.

Accepted inputs (:func:`read_trajectory`):

* ``trajectory_msgs/JointTrajectory`` as YAML or JSON::

      joint_names: [joint1, ..., joint6]
      points:
        - positions: [...]            # rad (revolute) / m (prismatic)
          velocities: [...]           # rad/s, m/s
          time_from_start: {sec: 0, nanosec: 0}

  This is also what ``ros2 topic echo --once /topic`` prints (``header``, ``accelerations``
  and ``effort`` are ignored; the trailing ``---`` is fine; block lists, flow lists and the
  ``array('d', [...])`` of old ros2cli releases are all read). ROS 1 ``secs``/``nsecs`` work too.
* ``moveit_msgs/RobotTrajectory`` (``joint_trajectory`` is used; a non-empty
  ``multi_dof_joint_trajectory`` is refused) and ``moveit_msgs/DisplayTrajectory`` holding
  exactly one RobotTrajectory in ``trajectory``.
* CSV (``.csv``): a header row, then one row per waypoint. Columns, in any order: the time in
  seconds (``t``, ``time`` or ``time_from_start``), one position column per joint named by the
  joint (``joint1``), and optionally one velocity column per joint named ``<joint>_vel`` or
  ``qd_<joint>``. Blank lines and lines starting with ``#`` are skipped.

One message per file: several ``---``-separated messages are refused (record with
``ros2 topic echo --once`` or split the file).

Fields. A message field the reader does not know is an error naming it (a typo such as
``velocity:`` must not read as a trajectory without velocities). Documented as ignored, since
they do not change the motion that is certified: ``header`` (JointTrajectory and an empty
``multi_dof_joint_trajectory``), ``accelerations`` and ``effort`` (of a point), ``model_id``
and ``trajectory_start`` (DisplayTrajectory). A CSV column that is not the time or a velocity
column is a joint position column; one naming no joint of the robot is refused when the
trajectory is checked against the robot.

A trajectory is reconstructed by piecewise-cubic Hermite interpolation of the positions and
velocities (:mod:`larc_jax.model.hermite`). A file without velocities is refused unless
``velocities="finite-difference"`` (CLI ``--velocities finite-difference``), which computes them
from the positions (:func:`finite_difference_velocities`). The certificate then covers the
Hermite curve through those velocities, which is a different curve from the one the
controller that executes the waypoints may follow. On a file that records velocities the
reader warns that it ignores them (:func:`read_trajectory_file` counts them), and ``larc
verify`` refuses such a certificate unless ``--allow-finite-difference`` (:mod:`larc_jax.products.verify`).
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
import re
from pathlib import Path
from typing import NamedTuple

import numpy as np
import yaml

from ..errors import LarcInputError
from ..io import (atomic_write_text, check_keys, deferred_log, parse_json, parse_number, parse_vector,
                 parse_yaml_documents, read_input_text, short_repr)
from .robot import Robot
from .trajectory import (MAX_WAYPOINTS, VELOCITY_MODES, Locator, Trajectory, check_joint_names, check_times,
                         finite_difference_velocities, msg_locator, validate_trajectory)

__all__ = [
    "read_trajectory",
    "read_trajectory_file",
    "TrajectoryFile",
    "write_trajectory",
    "trajectory_to_msg",
    "trajectory_to_csv",
    "trajectory_from_msg",
]

log = logging.getLogger(__name__)

_PER_JOINT = "one per joint_names entry"


def _time_of(value, source: str, where: str) -> float:
    if isinstance(value, dict):
        if "sec" not in value and "secs" not in value:  # nanosec alone would silently drop seconds
            raise LarcInputError(f"{source}: {where}.sec is missing ({where} must have sec and nanosec)")
        check_keys(value, ("sec", "secs", "nanosec", "nsec", "nsecs"), source, where)
        sec_key = "sec" if "sec" in value else "secs"
        nsec_key = next((k for k in ("nanosec", "nsec", "nsecs") if k in value), "nanosec")
        sec = parse_number(value.get(sec_key, 0), source, f"{where}.{sec_key}")
        nsec = parse_number(value.get(nsec_key, 0), source, f"{where}.{nsec_key}")
        if not 0 <= nsec < 1_000_000_000:
            raise LarcInputError(
                f"{source}: {where}.{nsec_key} = {short_repr(value.get(nsec_key))} is outside 0..999999999 "
                f"(a ROS Duration's nanoseconds; carry whole seconds in {sec_key})")
        return sec + nsec * 1e-9
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return parse_number(value, source, where)
    raise LarcInputError(
        f"{source}: {where} must be {{sec, nanosec}} or a number of seconds, got {short_repr(value)}")


_JOINT_TRAJECTORY = ("joint_names", "points")
_POINT = ("positions", "velocities", "time_from_start")


def _unwrap(doc, source: str):
    """The JointTrajectory mapping inside ``doc`` and its field prefix (``joint_trajectory.``...)."""
    if not isinstance(doc, dict):
        raise LarcInputError(f"{source}: expected a JointTrajectory mapping with joint_names and points")
    if "joint_names" in doc or "points" in doc:
        check_keys(doc, _JOINT_TRAJECTORY, source, ignored=("header",))
        return doc, ""
    if "joint_trajectory" in doc:
        check_keys(doc, ("joint_trajectory", "multi_dof_joint_trajectory"), source)
        multi = doc.get("multi_dof_joint_trajectory")
        if isinstance(multi, dict):
            check_keys(multi, _JOINT_TRAJECTORY, source, "multi_dof_joint_trajectory", ignored=("header",))
        if isinstance(multi, dict) and (multi.get("joint_names") or multi.get("points")):
            n = len(multi.get("points") or [])
            raise LarcInputError(
                f"{source}: multi_dof_joint_trajectory has {n} points for joints "
                f"{multi.get('joint_names') or []}: multi-DOF (floating/planar joint) trajectories "
                f"are not supported; only joint_trajectory is certified")
        return doc["joint_trajectory"], "joint_trajectory."
    if "trajectory" in doc and isinstance(doc["trajectory"], list):
        check_keys(doc, ("trajectory",), source, ignored=("model_id", "trajectory_start"))
        items = doc["trajectory"]
        if len(items) != 1:
            raise LarcInputError(
                f"{source}: trajectory (a DisplayTrajectory) holds {len(items)} RobotTrajectory "
                f"messages; exactly one is supported (split it into one file per trajectory)")
        if not isinstance(items[0], dict) or "joint_trajectory" not in items[0]:
            raise LarcInputError(f"{source}: trajectory[0].joint_trajectory is missing")
        msg, prefix = _unwrap(items[0], source)
        return msg, "trajectory[0]." + prefix
    raise LarcInputError(
        f"{source}: expected a JointTrajectory (joint_names, points), a RobotTrajectory "
        f"(joint_trajectory) or a DisplayTrajectory (trajectory); found fields {short_repr(sorted(map(str, doc)))}")


def _missing_velocities(source: str, what: str) -> LarcInputError:
    return LarcInputError(
        f"{source}: {what}: the trajectory has no recorded velocities; pass "
        f"--velocities finite-difference (Python: velocities='finite-difference') to compute "
        f"them from the positions")


def _check_mode(velocities: str) -> None:
    if velocities not in VELOCITY_MODES:
        raise LarcInputError(f"velocities must be one of {VELOCITY_MODES}, got {velocities!r}")


def trajectory_from_msg(
    msg, *, source: str = "<trajectory>", traj_id: str = "", velocities: str = "recorded"
) -> Trajectory:
    """Parse a JointTrajectory-shaped mapping (no robot checks; see :func:`validate_trajectory`).

    ``msg`` may also be a RobotTrajectory or DisplayTrajectory mapping (module docstring).
    ``velocities`` is one of :data:`VELOCITY_MODES`.
    """
    return _from_msg(msg, source=source, traj_id=traj_id, velocities=velocities)[0]


_IGNORED_VELOCITIES = ("%s: ignoring the recorded velocities of %d waypoints: velocities are computed by finite "
                       "differences, so the result covers the Hermite curve through those, not the motion the file "
                       "describes (larc verify refuses its certificate unless --allow-finite-difference)")


def _from_msg(msg, *, source: str, traj_id: str, velocities: str) -> tuple[Trajectory, Locator, int]:
    _check_mode(velocities)
    msg, prefix = _unwrap(msg, source)
    loc = msg_locator(prefix)
    if not isinstance(msg, dict):
        raise LarcInputError(f"{source}: {prefix.rstrip('.') or 'file'} must be a JointTrajectory mapping with joint_names and points")
    names = msg.get("joint_names")
    if not isinstance(names, list) or not names:
        raise LarcInputError(
            f"{source}: {prefix}joint_names must be a non-empty list of strings, got {short_repr(names)}")
    for i, name in enumerate(names):
        if not isinstance(name, str):
            raise LarcInputError(f"{source}: {prefix}joint_names[{i}] is not a string ({short_repr(name)})")
    if len(names) > 1000:  # no arm has that many joints; keeps the arrays below small
        raise LarcInputError(f"{source}: {prefix}joint_names has {len(names)} entries (limit 1000)")
    points = msg.get("points")
    if not isinstance(points, list) or len(points) < 2:
        raise LarcInputError(f"{source}: {prefix}points must be a list of at least 2 waypoints")
    if len(points) > MAX_WAYPOINTS:
        raise LarcInputError(f"{source}: {prefix}points has {len(points)} waypoints (limit {MAX_WAYPOINTS})")
    n = len(names)
    t = np.empty(len(points))
    q = np.empty((len(points), n))
    qd = np.empty((len(points), n))
    recorded = velocities == "recorded"
    ignored = 0
    for k, p in enumerate(points):
        if not isinstance(p, dict):
            raise LarcInputError(f"{source}: {prefix}points[{k}] must be a mapping")
        check_keys(p, _POINT, source, f"{prefix}points[{k}]", ignored=("accelerations", "effort"))
        for key in ("positions", "time_from_start"):
            if key not in p or p[key] is None:
                raise LarcInputError(f"{source}: {loc(k, key, None)} is missing")
        q[k] = parse_vector(p["positions"], n, source, loc(k, "positions", None), entries=_PER_JOINT)
        has_vel = p.get("velocities") not in (None, [])
        if recorded:
            if not has_vel:
                raise _missing_velocities(source, f"{loc(k, 'velocities', None)} is missing")
            qd[k] = parse_vector(p["velocities"], n, source, loc(k, "velocities", None), entries=_PER_JOINT)
        else:
            ignored += has_vel
        t[k] = _time_of(p["time_from_start"], source, loc(k, "time_from_start", None))
    if not recorded:
        if ignored:
            log.warning(_IGNORED_VELOCITIES, source, ignored)
        qd = finite_difference_velocities(t, q, source=source, where=loc)
    return Trajectory(t=t, q=q, qd=qd, joint_names=tuple(names), id=traj_id, source=source), loc, ignored



def _precheck_joint_names(doc, robot: Robot, source: str) -> None:
    """Check a message's joint_names against the robot before its points are parsed, so a
    missing or extra joint is reported as such (not as rows of the wrong length)."""
    msg, prefix = _unwrap(doc, source)
    names = msg.get("joint_names") if isinstance(msg, dict) else None
    if isinstance(names, list) and names and all(isinstance(n, str) for n in names):
        check_joint_names(names, list(robot.active_joint_names), source, prefix)



_OLD_ROS2_ARRAY = re.compile(r"array\('[a-zA-Z]', (\[[^\]]*\])\)")
"""``array('d', [0.0, 1.0])``: how some ros2cli releases echoed float64[] fields."""

def _read_text(path: Path) -> str:
    text = read_input_text(path)  # missing, directory, permissions, binary, too large
    if not text.strip():
        raise LarcInputError(f"{path}: file is empty")
    return text


def _load_document(path: Path):
    """The one message in a JSON or YAML file (``---`` separators allowed, one document)."""
    text = _read_text(path)
    # Refuse an enormous trajectory before parsing it (parsing 10^5 waypoints takes ~20 s): every
    # waypoint carries one time_from_start key (ROS 1 and 2, YAML and JSON alike).
    stamps = text.count("time_from_start")
    if stamps > MAX_WAYPOINTS:
        raise LarcInputError(
            f"{path}: points has about {stamps} waypoints ({stamps} time_from_start keys), "
            f"more than the limit of {MAX_WAYPOINTS}")
    if path.suffix.lower() == ".json":
        return parse_json(text, str(path))
    text = _OLD_ROS2_ARRAY.sub(r"\1", text)
    docs = [d for d in parse_yaml_documents(text, str(path)) if d is not None]
    if not docs:
        raise LarcInputError(f"{path}: file is empty")
    if len(docs) > 1:
        raise LarcInputError(
            f"{path}: holds {len(docs)} messages separated by '---'; one trajectory per file: "
            f"record with `ros2 topic echo --once TOPIC` or split the file")
    return docs[0]


_TIME_COLUMNS = ("t", "time", "time_from_start")


def _velocity_joint(column: str) -> str | None:
    if column.endswith("_vel") and len(column) > 4:
        return column[:-4]
    if column.startswith("qd_") and len(column) > 3:
        return column[3:]
    return None


def _read_csv(path: Path, *, traj_id: str, velocities: str) -> tuple[Trajectory, Locator, int]:
    """CSV reader (module docstring). Errors are ``file:line: column 'name': problem``."""
    source = str(path)
    text = _read_text(path)
    rows = csv.reader(io.StringIO(text, newline=""), skipinitialspace=True)
    header, header_line = None, 0
    data, lines = [], []
    try:
        for row in rows:
            if not row or all(not c.strip() for c in row) or row[0].lstrip().startswith("#"):
                continue
            if header is None:
                header, header_line = [c.strip() for c in row], rows.line_num
                continue
            if len(data) >= MAX_WAYPOINTS:
                raise LarcInputError(f"{source}:{rows.line_num}: more than {MAX_WAYPOINTS} waypoints")
            data.append(row)
            lines.append(rows.line_num)
    except csv.Error as exc:
        raise LarcInputError(f"{source}:{rows.line_num}: not valid CSV ({exc})") from None
    if header is None:
        raise LarcInputError(f"{source}: file is empty")

    def err(line: int, message: str) -> LarcInputError:
        return LarcInputError(f"{source}:{line}: {message}")

    for i, name in enumerate(header):
        if not name:
            raise err(header_line, f"header column {i + 1} has no name")
        if header.index(name) != i:
            raise err(header_line, f"header names column '{name}' twice")
    time_cols = [i for i, c in enumerate(header) if c in _TIME_COLUMNS]
    if len(time_cols) != 1:
        raise err(header_line, f"header needs exactly one time column named t or time (seconds); "
                               f"found {[header[i] for i in time_cols] or 'none'} in {header}")
    tcol = time_cols[0]
    pos_cols = [i for i, c in enumerate(header) if i != tcol and _velocity_joint(c) is None]
    names = [header[i] for i in pos_cols]
    if not names:
        raise err(header_line, f"header has no joint position columns (one per joint, named by the joint): {header}")
    vel_of = {}
    for i, c in enumerate(header):
        joint = _velocity_joint(c)
        if joint is None or i == tcol:
            continue
        if joint not in names:
            raise err(header_line, f"velocity column '{c}' names joint '{joint}', which has no position column")
        if joint in vel_of:
            raise err(header_line, f"joint '{joint}' has two velocity columns: '{header[vel_of[joint]]}' and '{c}'")
        vel_of[joint] = i
    recorded = velocities == "recorded"
    if recorded:
        if not vel_of:
            raise _missing_velocities(source, f"line {header_line}: no velocity columns (<joint>_vel or qd_<joint>)")
        missing = [n for n in names if n not in vel_of]
        if missing:
            raise err(header_line, f"no velocity column for {missing} (name it <joint>_vel or qd_<joint>)")
    elif vel_of:
        log.warning(_IGNORED_VELOCITIES, source, len(data))
    vel_cols = [vel_of[n] for n in names] if recorded else []
    if len(data) < 2:
        raise LarcInputError(f"{source}: needs at least 2 waypoint rows after the header, found {len(data)}")

    def cell(row, line: int, i: int) -> float:
        raw = row[i].strip()
        try:
            value = float(raw)
        except ValueError:
            raise err(line, f"column '{header[i]}': {raw!r} is not a number") from None
        if not math.isfinite(value):
            raise err(line, f"column '{header[i]}': {raw!r} is not finite")
        return value

    n = len(names)
    t = np.empty(len(data))
    q = np.empty((len(data), n))
    qd = np.empty((len(data), n))
    for k, (row, line) in enumerate(zip(data, lines)):
        if len(row) != len(header):
            raise err(line, f"row has {len(row)} cells, the header has {len(header)}")
        t[k] = cell(row, line, tcol)
        q[k] = [cell(row, line, i) for i in pos_cols]
        if recorded:
            qd[k] = [cell(row, line, i) for i in vel_cols]

    def loc(k: int, field: str, j: int | None) -> str:
        col = {"time_from_start": tcol, "positions": pos_cols[j] if j is not None else None,
               "velocities": vel_cols[j] if (j is not None and vel_cols) else None}[field]
        return f"line {lines[k]}" + ("" if col is None else f" column '{header[col]}'")

    if not recorded:
        qd = finite_difference_velocities(t, q, source=source, where=loc)
    ignored = len(data) if vel_of and not recorded else 0
    return Trajectory(t=t, q=q, qd=qd, joint_names=tuple(names), id=traj_id, source=source), loc, ignored


class TrajectoryFile(NamedTuple):
    """A trajectory as read from its file, and what the reading left out."""

    trajectory: Trajectory
    ignored_velocities: int
    """Waypoints whose recorded velocities were ignored (``velocities="finite-difference"`` on a
    file that carries velocities: the trajectory then differs from the motion the file describes)."""


def read_trajectory(
    path: str | Path, robot: Robot | None = None, *, velocities: str = "recorded"
) -> Trajectory:
    """Read a trajectory file (JointTrajectory / RobotTrajectory / DisplayTrajectory YAML or
    JSON, ``ros2 topic echo`` output, or CSV; see the module docstring).

    ``velocities``: ``"recorded"`` (default) uses the file's velocities and refuses a file
    without them; ``"finite-difference"`` computes them from the positions
    (:func:`finite_difference_velocities`; a warning says so when the file carries velocities).
    Validated against ``robot`` when given.
    """
    return read_trajectory_file(path, robot, velocities=velocities).trajectory


def read_trajectory_file(path: str | Path, robot: Robot | None = None, *, velocities: str = "recorded") -> TrajectoryFile:
    """:func:`read_trajectory`, also counting the waypoints whose recorded velocities were ignored."""
    _check_mode(velocities)
    path = Path(path)
    with deferred_log(log):  # a refused file gives its error line only, not warnings too
        if path.suffix.lower() == ".csv":
            traj, loc, ignored = _read_csv(path, traj_id=path.stem, velocities=velocities)
        else:
            doc = _load_document(path)
            if robot is not None:
                _precheck_joint_names(doc, robot, str(path))
            traj, loc, ignored = _from_msg(doc, source=str(path), traj_id=path.stem, velocities=velocities)
        return TrajectoryFile(validate_trajectory(traj, robot, where=loc) if robot is not None else traj, ignored)


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


def trajectory_to_csv(traj: Trajectory) -> str:
    """CSV text: ``t, <joint>..., <joint>_vel...`` with repr floats (exact round trip)."""
    names = list(traj.joint_names)
    lines = [",".join(["t", *names, *(f"{n}_vel" for n in names)])]
    for k in range(traj.n_waypoints):
        values = [traj.t[k], *traj.q[k], *traj.qd[k]]
        lines.append(",".join(repr(float(v)) for v in values))
    return "\n".join(lines) + "\n"


def write_trajectory(path: str | Path, traj: Trajectory) -> None:
    """Write a trajectory file atomically: CSV if the suffix is .csv, JSON if .json, else YAML.

    Floats are written with repr precision, so positions and velocities round-trip exactly;
    in YAML/JSON times are quantised to 1 ns, as in a ROS message (CSV keeps them exactly).
    """
    path = Path(path)
    if path.suffix.lower() == ".csv":
        atomic_write_text(path, trajectory_to_csv(traj))
        return
    msg = trajectory_to_msg(traj)
    if path.suffix.lower() == ".json":
        atomic_write_text(path, json.dumps(msg) + "\n")
    else:
        atomic_write_text(path, yaml.safe_dump(msg, sort_keys=False, default_flow_style=None, width=200))
