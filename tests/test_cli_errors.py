"""Errors that help (issue 5 item 6): every malformed input to ``larc certify`` gives exactly one
line ``larc: error: ...`` on stderr naming the file, the field and the index, exit status 2, no
traceback, and no (partial) output file.

Three parts: a table of hand-written bad inputs (in-process ``main`` plus a few real
subprocesses), the atomic-output checks, and property-based fuzzing (hypothesis) that mutates a
valid trajectory / scene / command line and requires exit 0/1/2 with the same contract.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import os
import re
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from larc_jax.drivers.cli import build_parser, main
from larc_jax.model.trajectory import MAX_WAYPOINTS

ROOT = Path(__file__).resolve().parent.parent
JOINTS = [f"joint{i}" for i in range(1, 7)]


def valid_traj() -> dict:
    return {
        "joint_names": list(JOINTS),
        "points": [
            {"positions": [0.0, 0.5, -0.8, 0.0, 0.3, 0.0], "velocities": [0.0] * 6,
             "time_from_start": {"sec": 0, "nanosec": 0}},
            {"positions": [0.6, 0.9, -1.1, 0.2, 0.4, 0.5], "velocities": [0.1, 0.0, 0.0, 0.0, 0.0, 0.0],
             "time_from_start": {"sec": 1, "nanosec": 500000000}},
            {"positions": [1.2, 0.9, -1.1, 0.2, 0.4, 0.5], "velocities": [0.0] * 6,
             "time_from_start": {"sec": 3, "nanosec": 0}},
        ],
    }


def valid_scene() -> dict:
    return {"frame": "base_link",
            "boxes": [{"name": "crate", "min": [-0.8, -0.8, 0.0], "max": [-0.6, -0.6, 0.2]}]}


def _certify_parser():
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    return sub.choices["certify"]


HAS_LEAVES = any("--leaves" in a.option_strings for a in _certify_parser()._actions)


# ------------------------------------------------------------------------------------------------
# document edits
# ------------------------------------------------------------------------------------------------


def _parent(doc, path):
    for key in path[:-1]:
        doc = doc[key]
    return doc


def put(path, value):
    def edit(doc):
        _parent(doc, path)[path[-1]] = value
    return edit


def drop(path):
    def edit(doc):
        del _parent(doc, path)[path[-1]]
    return edit


def T(*edits) -> dict:
    doc = valid_traj()
    for e in edits:
        e(doc)
    return doc


def S(*edits) -> dict:
    doc = valid_scene()
    for e in edits:
        e(doc)
    return doc


MISSING = object()  # the file is not created
DIRECTORY = object()  # a directory stands where the file should be


def write(path: Path, content) -> None:
    if content is MISSING:
        return
    if content is DIRECTORY:
        path.mkdir()
    elif isinstance(content, bytes):
        path.write_bytes(content)
    elif isinstance(content, str):
        path.write_text(content)
    elif path.suffix == ".json":
        path.write_text(json.dumps(content))
    else:
        path.write_text(yaml.safe_dump(content, sort_keys=False))


def robot_doc(**changes) -> dict:
    from larc_jax.model.urdf import piper_urdf_path

    doc = yaml.safe_load((ROOT / "larc_jax" / "data" / "piper_capsules.yaml").read_text())
    doc = {"urdf": str(piper_urdf_path()), **doc}
    for k, v in changes.items():
        if v is MISSING:
            del doc[k]
        else:
            doc[k] = v
    return doc


@dataclasses.dataclass
class Case:
    id: str
    needles: tuple[str, ...]
    traj: Any = None  # None: the valid trajectory
    scene: Any = None
    args: tuple[str, ...] = ()
    traj_name: str = "t.yaml"
    scene_name: str = "s.yaml"
    robot: Any = None  # content of r.yaml, passed as --robot r.yaml

    def setup(self, tmp: Path) -> list[str]:
        write(tmp / self.traj_name, valid_traj() if self.traj is None else self.traj)
        write(tmp / self.scene_name, valid_scene() if self.scene is None else self.scene)
        argv = ["certify", str(tmp / self.traj_name), "--scene", str(tmp / self.scene_name), *self.args]
        if self.robot is not None:  # a callable builds it now (the PIPER path is known at run time)
            write(tmp / "r.yaml", self.robot() if callable(self.robot) else self.robot)
            argv += ["--robot", str(tmp / "r.yaml")]
        return argv


P1 = ("points", 1)
BIG = 10**400  # an integer too large for a float


CASES = [
    # --- the trajectory file as a whole
    Case("empty", ("t.yaml", "empty"), traj=""),
    Case("whitespace", ("t.yaml", "empty"), traj="  \n\n  \t\n"),
    Case("yaml-comment-only", ("t.yaml",), traj="# nothing here\n"),
    Case("not-yaml", ("t.yaml", "YAML"), traj="joint_names: [joint1, joint2\npoints: {\n"),
    Case("not-json", ("t.json", "JSON"), traj="{joint_names: [", traj_name="t.json"),
    Case("json-trailing", ("t.json", "JSON"), traj=json.dumps(valid_traj()) + "}", traj_name="t.json"),
    Case("yaml-scalar", ("t.yaml", "mapping"), traj="hello world\n"),
    Case("yaml-list", ("t.yaml", "mapping"), traj="- 1\n- 2\n"),
    Case("yaml-python-tag", ("t.yaml", "YAML"), traj="!!python/object/apply:os.system ['true']\n"),
    Case("binary", ("t.yaml",), traj=bytes(range(256)) * 4),
    Case("binary-json", ("t.json",), traj=b"\x00\x01\x02\xff\xfe{}", traj_name="t.json"),
    Case("nul-in-utf8", ("t.yaml",), traj="joint_names: [joint1\x00]\n"),
    Case("deeply-nested-json", ("t.json", "nested"), traj="[" * 200_000 + "]" * 200_000, traj_name="t.json"),
    Case("deeply-nested-yaml", ("t.yaml", "nested"), traj="[" * 200_000 + "]" * 200_000),
    Case("directory", ("t.yaml", "directory"), traj=DIRECTORY),
    Case("missing", ("t.yaml", "does not exist"), traj=MISSING),
    # --- joint names
    Case("unknown-joint", ("t.yaml", "joint_names", "joint7"), traj=T(put(("joint_names", 5), "joint7"))),
    Case("five-joints", ("t.yaml", "joint_names", "joint6"), traj=T(drop(("joint_names", 5)))),
    Case("seven-joints", ("t.yaml", "joint_names", "joint7"), traj=T(lambda d: d["joint_names"].append("joint7"))),
    Case("duplicate-joints", ("t.yaml", "joint_names", "duplicate"), traj=T(put(("joint_names", 5), "joint1"))),
    Case("joint-names-missing", ("t.yaml", "joint_names"), traj=T(drop(("joint_names",)))),
    Case("joint-names-string", ("t.yaml", "joint_names"), traj=T(put(("joint_names",), "joint1"))),
    Case("joint-names-empty", ("t.yaml", "joint_names"), traj=T(put(("joint_names",), []))),
    Case("joint-name-number", ("t.yaml", "joint_names[2]"), traj=T(put(("joint_names", 2), 3))),
    # --- points
    Case("points-missing", ("t.yaml", "points"), traj=T(drop(("points",)))),
    Case("points-mapping", ("t.yaml", "points"), traj=T(put(("points",), {"a": 1}))),
    Case("one-point", ("t.yaml", "points", "2"), traj=T(lambda d: d["points"].__delitem__(slice(1, None)))),
    Case("point-not-mapping", ("t.yaml", "points[1]"), traj=T(put(P1, [1, 2, 3]))),
    Case("positions-missing", ("t.yaml", "points[1].positions"), traj=T(drop(P1 + ("positions",)))),
    Case("velocities-missing", ("t.yaml", "points[2].velocities"), traj=T(drop(("points", 2, "velocities")))),
    Case("velocities-null", ("t.yaml", "points[1].velocities"), traj=T(put(P1 + ("velocities",), None))),
    Case("time-missing", ("t.yaml", "points[0].time_from_start"), traj=T(drop(("points", 0, "time_from_start")))),
    Case("position-string", ("t.yaml", "points[1].positions[2]"), traj=T(put(P1 + ("positions", 2), "abc"))),
    Case("position-numeric-string", ("t.yaml", "points[1].positions[2]"), traj=T(put(P1 + ("positions", 2), "0.5"))),
    Case("position-bool", ("t.yaml", "points[1].positions[2]"), traj=T(put(P1 + ("positions", 2), True))),
    Case("position-null", ("t.yaml", "points[1].positions[2]"), traj=T(put(P1 + ("positions", 2), None))),
    Case("position-nested", ("t.yaml", "points[1].positions[3]"), traj=T(put(P1 + ("positions", 3), [0.1, 0.2]))),
    Case("positions-nested-rows", ("t.yaml", "points[1].positions"), traj=T(put(P1 + ("positions",), [[0.0] * 6]))),
    Case("positions-string", ("t.yaml", "points[1].positions"), traj=T(put(P1 + ("positions",), "0 0 0 0 0 0"))),
    Case("positions-mapping", ("t.yaml", "points[1].positions"), traj=T(put(P1 + ("positions",), {"joint1": 0}))),
    Case("position-huge-int", ("t.yaml", "points[1].positions[0]"), traj=T(put(P1 + ("positions", 0), BIG))),
    Case("velocity-huge-int-json", ("t.json", "points[1].velocities[0]"), traj=T(put(P1 + ("velocities", 0), BIG)),
         traj_name="t.json"),
    Case("int-too-many-digits-yaml", ("t.yaml",), traj=yaml.safe_dump(T()).replace("sec: 3", "sec: " + "9" * 5000)),
    Case("int-too-many-digits-json", ("t.json",), traj=json.dumps(T()).replace('"sec": 3', '"sec": ' + "9" * 5000),
         traj_name="t.json"),
    Case("ragged-short", ("t.yaml", "points[1].positions", "5"), traj=T(lambda d: d["points"][1]["positions"].pop())),
    Case("ragged-long", ("t.yaml", "points[2].velocities", "7"),
         traj=T(lambda d: d["points"][2]["velocities"].append(0.0))),
    # --- times
    Case("time-string", ("t.yaml", "points[1].time_from_start"), traj=T(put(P1 + ("time_from_start",), "1.5 s"))),
    Case("time-list", ("t.yaml", "points[1].time_from_start"), traj=T(put(P1 + ("time_from_start",), [1, 0]))),
    Case("sec-string", ("t.yaml", "points[1].time_from_start.sec"), traj=T(put(P1 + ("time_from_start", "sec"), "1"))),
    Case("sec-missing", ("t.yaml", "points[1].time_from_start.sec"), traj=T(drop(P1 + ("time_from_start", "sec")))),
    Case("time-unknown-field", ("t.yaml", "points[1].time_from_start"),
         traj=T(put(P1 + ("time_from_start",), {"secs": 1, "nsecs": 0, "extra": 3}))),
    Case("nanosec-negative", ("t.yaml", "points[1].time_from_start.nanosec"),
         traj=T(put(P1 + ("time_from_start", "nanosec"), -5))),
    Case("nanosec-too-big", ("t.yaml", "points[1].time_from_start.nanosec"),
         traj=T(put(P1 + ("time_from_start", "nanosec"), 1_000_000_000))),
    Case("sec-huge-int", ("t.yaml", "points[1].time_from_start"), traj=T(put(P1 + ("time_from_start", "sec"), BIG))),
    Case("time-decreasing", ("t.yaml", "points[2].time_from_start", "increasing"),
         traj=T(put(("points", 2, "time_from_start"), {"sec": 1, "nanosec": 0}))),
    Case("time-equal", ("t.yaml", "points[1].time_from_start", "increasing"),
         traj=T(put(P1 + ("time_from_start",), {"sec": 0, "nanosec": 0}))),
    Case("time-nan", ("t.yaml", "points[1].time_from_start", "finite"),
         traj=T(put(P1 + ("time_from_start",), math.nan))),
    Case("time-sec-inf", ("t.yaml", "points[2].time_from_start", "finite"),
         traj=T(put(("points", 2, "time_from_start", "sec"), math.inf))),
    Case("time-nan-json", ("t.json", "points[1].time_from_start", "finite"),
         traj=T(put(P1 + ("time_from_start",), math.nan)), traj_name="t.json"),
    # --- values
    Case("position-nan", ("t.yaml", "points[1].positions[2]", "finite"), traj=T(put(P1 + ("positions", 2), math.nan))),
    Case("position-minus-inf", ("t.yaml", "points[0].positions[5]", "finite"),
         traj=T(put(("points", 0, "positions", 5), -math.inf))),
    Case("velocity-inf", ("t.yaml", "points[2].velocities[4]", "finite"),
         traj=T(put(("points", 2, "velocities", 4), math.inf))),
    Case("velocity-nan-json", ("t.json", "points[1].velocities[0]", "finite"),
         traj=T(put(P1 + ("velocities", 0), math.nan)), traj_name="t.json"),
    Case("position-over-limit", ("t.yaml", "points[1].positions[1]", "joint2", "limits"),
         traj=T(put(P1 + ("positions", 1), 9.0))),
    Case("position-under-limit-reordered", ("t.yaml", "points[2].positions[0]", "joint6", "limits"),
         traj=T(put(("joint_names",), JOINTS[::-1]), lambda d: [p["positions"].reverse() for p in d["points"]],
                put(("points", 2, "positions", 0), -50.0))),
    # --- enormous
    Case("too-many-points-json", ("t.json", "points", str(MAX_WAYPOINTS)), traj_name="t.json",
         traj='{"joint_names": ["joint1","joint2","joint3","joint4","joint5","joint6"], "points": ['
              + ",".join(['{"positions":[0,0,0,0,0,0],"velocities":[0,0,0,0,0,0],'
                          '"time_from_start":{"sec":0,"nanosec":0}}'] * (MAX_WAYPOINTS + 1)) + "]}"),
    Case("too-many-points-yaml", ("t.yaml", "points", str(MAX_WAYPOINTS)),
         traj="joint_names: [joint1, joint2, joint3, joint4, joint5, joint6]\npoints:\n"
              + "- positions: [0, 0, 0, 0, 0, 0]\n  velocities: [0, 0, 0, 0, 0, 0]\n"
                "  time_from_start: {sec: 0, nanosec: 0}\n" * (MAX_WAYPOINTS + 1)),
    Case("huge-joint-list", ("t.yaml", "joint_names"),
         traj=T(put(("joint_names",), [f"j{i}" for i in range(2_000)]))),
    # --- scene
    Case("scene-empty", ("s.yaml", "empty"), scene=""),
    Case("scene-not-yaml", ("s.yaml", "YAML"), scene="boxes: [\n"),
    Case("scene-list", ("s.yaml", "mapping"), scene=[1, 2]),
    Case("scene-binary", ("s.yaml",), scene=bytes(range(256))),
    Case("scene-directory", ("s.yaml", "directory"), scene=DIRECTORY),
    Case("scene-missing", ("s.yaml", "does not exist"), scene=MISSING),
    Case("scene-boxes-missing", ("s.yaml", "boxes"), scene=S(drop(("boxes",)))),
    Case("scene-boxes-typo", ("s.yaml", "box"), scene={"frame": "base_link", "box": valid_scene()["boxes"]}),
    Case("scene-boxes-mapping", ("s.yaml", "boxes"), scene=S(put(("boxes",), {"crate": 1}))),
    Case("scene-box-not-mapping", ("s.yaml", "boxes[0]"), scene=S(put(("boxes", 0), [0, 0, 0]))),
    Case("scene-box-max-missing", ("s.yaml", "boxes[0].max"), scene=S(drop(("boxes", 0, "max")))),
    Case("scene-box-min-short", ("s.yaml", "boxes[0].min"), scene=S(put(("boxes", 0, "min"), [0, 0]))),
    Case("scene-box-min-string", ("s.yaml", "boxes[0].min[1]"), scene=S(put(("boxes", 0, "min", 1), "x"))),
    Case("scene-box-min-nested", ("s.yaml", "boxes[0].min[1]"), scene=S(put(("boxes", 0, "min", 1), [0]))),
    Case("scene-box-inverted", ("s.yaml", "boxes[0].min[2]", "boxes[0].max[2]"),
         scene=S(put(("boxes", 0, "min", 2), 0.5))),
    Case("scene-box-nan", ("s.yaml", "boxes[0].max[1]", "finite"), scene=S(put(("boxes", 0, "max", 1), math.nan))),
    Case("scene-box-inf", ("s.yaml", "boxes[0].min[0]", "finite"), scene=S(put(("boxes", 0, "min", 0), -math.inf))),
    Case("scene-box-huge-int", ("s.yaml", "boxes[0].min[0]"), scene=S(put(("boxes", 0, "min", 0), -BIG))),
    Case("scene-units-mm", ("s.yaml", "units", "mm"), scene=S(put(("units",), "mm"))),
    Case("scene-units-list", ("s.yaml", "units"), scene=S(put(("units",), ["m"]))),
    Case("scene-frame", ("s.yaml", "frame", "world"), scene=S(put(("frame",), "world"))),
    # --- other formats and --velocities finite-difference go through the same checks
    Case("csv-binary", ("t.csv", "not a text file"), traj=bytes(range(256)), traj_name="t.csv"),
    Case("csv-directory", ("t.csv", "directory"), traj=DIRECTORY, traj_name="t.csv"),
    Case("csv-ragged", ("t.csv:3",), traj_name="t.csv", args=("--velocities", "finite-difference"),
         traj="t,joint1,joint2,joint3,joint4,joint5,joint6\n0,0,0.5,-0.8,0,0.3,0\n1,0,0.5,-0.8,0\n"),
    Case("fd-equal-times", ("t.yaml", "points[1].time_from_start"), args=("--velocities", "finite-difference"),
         traj=T(put(P1 + ("time_from_start",), {"sec": 0, "nanosec": 0}))),
    Case("fd-nan-position", ("t.yaml", "points[2].positions[3]"), args=("--velocities", "finite-difference"),
         traj=T(put(("points", 2, "positions", 3), math.nan))),
    Case("moveit-scene-binary", ("s.scene", "not a text file"), scene=bytes(range(256)), scene_name="s.scene"),
    Case("moveit-scene-directory", ("s.scene", "directory"), scene=DIRECTORY, scene_name="s.scene"),
    # --- command-line values
    Case("margin-negative", ("--margin", "-0.01"), args=("--margin", "-0.01")),
    Case("margin-zero", ("--margin",), args=("--margin", "0")),
    Case("margin-nan", ("--margin", "nan"), args=("--margin", "nan")),
    Case("margin-inf", ("--margin", "inf"), args=("--margin", "inf")),
    Case("margin-not-number", ("--margin", "abc"), args=("--margin", "abc")),
    Case("max-depth-negative", ("--max-depth", "-1"), args=("--max-depth", "-1")),
    Case("max-depth-huge", ("--max-depth", "99"), args=("--max-depth", "99")),
    Case("max-depth-float", ("--max-depth", "2.5"), args=("--max-depth", "2.5")),
    Case("method-unknown", ("--method", "magic"), args=("--method", "magic")),
    Case("json-is-directory", ("out_dir",), args=("--json", "DIR:out_dir")),
    # --- --robot file
    Case("robot-missing", ("r.yaml", "does not exist"), robot=MISSING),
    Case("robot-directory", ("r.yaml", "directory"), robot=DIRECTORY),
    Case("robot-empty", ("r.yaml", "empty"), robot=""),
    Case("robot-binary", ("r.yaml",), robot=bytes(range(256))),
    Case("robot-not-yaml", ("r.yaml", "YAML"), robot="urdf: [\n"),
    Case("robot-no-urdf", ("r.yaml", "urdf"), robot={"capsules": []}),
    Case("robot-urdf-number", ("r.yaml", "urdf"), robot=lambda: robot_doc(urdf=5)),
    Case("robot-urdf-missing-file", ("nowhere.urdf",), robot=lambda: robot_doc(urdf="nowhere.urdf")),
    Case("robot-package-dirs-list", ("r.yaml", "package_dirs"), robot=lambda: robot_doc(package_dirs=["a"])),
    Case("robot-active-joints-string", ("r.yaml", "active_joints"), robot=lambda: robot_doc(active_joints="joint1")),
    Case("robot-held-joints-list", ("r.yaml", "held_joints"), robot=lambda: robot_doc(held_joints=[1, 2])),
    Case("robot-held-joint-string", ("r.yaml", "held_joints", "joint7"), robot=lambda: robot_doc(held_joints={"joint7": "x"})),
    Case("robot-padding-string", ("r.yaml", "padding_m"), robot=lambda: robot_doc(padding_m="abc")),
    Case("robot-capsules-missing", ("r.yaml", "capsules"), robot=lambda: robot_doc(capsules=MISSING)),
    Case("robot-capsule-radius-string", ("r.yaml", "capsules[0].radius"),
         robot=lambda: robot_doc(capsules=[{"link": "base_link", "a": [0, 0, 0], "b": [0, 0, 0.1], "radius": "big"}])),
    Case("robot-capsule-a-huge", ("r.yaml", "capsules[0].a"),
         robot=lambda: robot_doc(capsules=[{"link": "base_link", "a": [BIG, 0, 0], "b": [0, 0, 0.1], "radius": 0.1}])),
    Case("robot-capsule-link-list", ("r.yaml", "capsules[0].link"),
         robot=lambda: robot_doc(capsules=[{"link": ["base_link"], "a": [0, 0, 0], "b": [0, 0, 0.1], "radius": 0.1}])),
]


def check_one_error_line(rc: int, err: str, needles) -> str:
    assert rc == 2, err
    assert "Traceback" not in err
    lines = err.splitlines()
    assert len(lines) == 1, f"expected one stderr line, got:\n{err}"
    (line,) = lines
    assert line.startswith("larc: error: "), line
    for needle in needles:
        assert needle in line, f"{needle!r} not in {line!r}"
    return line


def no_outputs(tmp: Path) -> None:
    assert not (tmp / "out.json").exists()
    assert not (tmp / "leaves.csv").exists()
    assert not [p.name for p in tmp.iterdir() if p.name.endswith(".tmp")]


def _argv(case: Case, tmp: Path) -> list[str]:
    argv = case.setup(tmp)
    argv = [f"{tmp / a[4:]}" if a.startswith("DIR:") else a for a in argv]
    for a in case.args:
        if a.startswith("DIR:"):
            (tmp / a[4:]).mkdir()
    if "--json" not in case.args:
        argv += ["--json", str(tmp / "out.json")]
    if HAS_LEAVES:
        argv += ["--leaves", str(tmp / "leaves.csv")]
    return argv


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input_one_line_exit_2(case, tmp_path, capsys):
    argv = _argv(case, tmp_path)
    start = time.perf_counter()
    rc = main(argv)
    elapsed = time.perf_counter() - start
    out, err = capsys.readouterr()
    check_one_error_line(rc, err, case.needles)
    no_outputs(tmp_path)
    if case.id.startswith("too-many-points"):
        assert elapsed < 10.0, f"refusing an enormous trajectory took {elapsed:.1f} s"


def test_unreadable_file(tmp_path, capsys, monkeypatch):
    """Permission denied (simulated: the tests may run as root, which reads anything)."""
    argv = _argv(Case("perm", ()), tmp_path)
    real_open = os.open

    def deny(path, *a, **k):  # every user file is opened by larc_jax.io.read_input_bytes
        if Path(path).name == "t.yaml":
            raise PermissionError(13, "Permission denied", str(path))
        return real_open(path, *a, **k)

    monkeypatch.setattr(os, "open", deny)
    rc = main(argv)
    check_one_error_line(rc, capsys.readouterr().err, ("t.yaml", "ermission"))
    no_outputs(tmp_path)


@pytest.mark.skipif(os.geteuid() == 0 if hasattr(os, "geteuid") else True, reason="root reads any file")
def test_unreadable_file_chmod(tmp_path, capsys):
    argv = _argv(Case("perm", ()), tmp_path)
    (tmp_path / "t.yaml").chmod(0)
    rc = main(argv)
    check_one_error_line(rc, capsys.readouterr().err, ("t.yaml", "ermission"))


def test_existing_outputs_untouched(tmp_path, capsys):
    """A failed run leaves a pre-existing --json (and --leaves) file exactly as it was."""
    argv = Case("x", (), traj=T(put(P1 + ("positions", 2), math.nan))).setup(tmp_path)
    (tmp_path / "out.json").write_text("old results\n")
    argv += ["--json", str(tmp_path / "out.json")]
    if HAS_LEAVES:
        (tmp_path / "leaves.csv").write_text("old leaves\n")
        argv += ["--leaves", str(tmp_path / "leaves.csv")]
    rc = main(argv)
    check_one_error_line(rc, capsys.readouterr().err, ("points[1].positions[2]",))
    assert (tmp_path / "out.json").read_text() == "old results\n"
    if HAS_LEAVES:
        assert (tmp_path / "leaves.csv").read_text() == "old leaves\n"
    assert not [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


def test_no_subcommand_is_one_line(capsys):
    rc = main([])
    check_one_error_line(rc, capsys.readouterr().err, ())


def test_missing_scene_option_is_one_line(tmp_path, capsys):
    write(tmp_path / "t.yaml", valid_traj())
    rc = main(["certify", str(tmp_path / "t.yaml")])
    check_one_error_line(rc, capsys.readouterr().err, ("--scene",))


def test_help_still_exits_0(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["certify", "--help"])
    assert exc.value.code == 0
    assert "--scene" in capsys.readouterr().out


# ------------------------------------------------------------------------------------------------
# real processes: nothing but the one line reaches stderr (no traceback, no logging noise)
# ------------------------------------------------------------------------------------------------

SUBPROCESS_CASES = ["position-nan", "directory", "margin-nan", "scene-box-inverted", "binary", "robot-urdf-number"]


@pytest.mark.slow
def test_subprocess_bad_inputs_one_line(tmp_path):
    env = dict(os.environ)
    env.setdefault("LARC_PIPER_DESCRIPTION", str(ROOT.parent / "shared" / "robots" / "piper_description"))
    by_id = {c.id: c for c in CASES}
    for name in SUBPROCESS_CASES:
        case = by_id[name]
        tmp = tmp_path / name
        tmp.mkdir()
        argv = _argv(case, tmp)
        p = subprocess.run([sys.executable, "-m", "larc_jax.drivers.cli", *argv], cwd=ROOT, env=env,
                           capture_output=True, text=True, timeout=300)
        check_one_error_line(p.returncode, p.stderr, case.needles)
        assert p.stdout == ""
        no_outputs(tmp)


# ------------------------------------------------------------------------------------------------
# outputs are written atomically
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("module", ["cli.py", "explain.py", "explain_draw.py"])
def test_cli_writes_outputs_atomically(module):
    """Every file the CLI writes goes through larc_jax.io's atomic writers (temp file + rename):
    no direct write_text / write_bytes / json.dump / open(..., "w") in the command-line modules."""
    import ast

    path = ROOT / "larc_jax" / module
    if not path.exists():
        pytest.skip(f"{module} not in this revision")
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            f = node.func
            name = f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", "")
            assert name not in {"write_text", "write_bytes", "dump"}, ast.unparse(node)
            if name == "open" and len(node.args) > 1:
                mode = node.args[1]
                assert not (isinstance(mode, ast.Constant) and set(str(mode.value)) & set("wax")), ast.unparse(node)


def test_atomic_write_killed_midway_leaves_old_file(tmp_path):
    """A writer killed (SIGKILL) after writing part of the temp file leaves the target untouched."""
    target = tmp_path / "out.json"
    target.write_text("old\n")
    code = (
        "import os, signal, sys\n"
        "import larc_jax.io as io\n"
        "real = os.fsync\n"
        "def die(fd):\n"
        "    os.kill(os.getpid(), signal.SIGKILL)\n"
        "os.fsync = die\n"
        f"io.atomic_write_text({str(target)!r}, 'x' * 10_000_000)\n"
    )
    p = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, timeout=120)
    assert p.returncode == -9
    assert target.read_text() == "old\n"
    # the killed writer may leave its hidden temp file behind, never a partial target
    assert {q.name for q in tmp_path.iterdir()} - {"out.json"} <= {
        q.name for q in tmp_path.iterdir() if q.name.startswith(".out.json.") and q.name.endswith(".tmp")}


# ------------------------------------------------------------------------------------------------
# odd but valid inputs: certified or not (exit 0/1), never a crash
# ------------------------------------------------------------------------------------------------

ODD_VALID = {
    "huge-velocities": T(put(P1 + ("velocities",), [1e300] * 6)),
    "tiny-time-step": T(put(P1 + ("time_from_start",), {"sec": 0, "nanosec": 1})),
    "long-horizon": T(put(("points", 2, "time_from_start"), {"sec": 10**15, "nanosec": 0})),
    "time-as-seconds": T(*[put(("points", k, "time_from_start"), t) for k, t in enumerate([0.0, 1.5, 3])]),
    "two-points": T(lambda d: d["points"].pop(1)),
    "joints-reordered": T(put(("joint_names",), JOINTS[::-1]),
                          lambda d: [p[f].reverse() for p in d["points"] for f in ("positions", "velocities")]),
    "no-boxes": None,
    "huge-margin": None,
    "tiny-margin": None,
}


@pytest.mark.parametrize("name", list(ODD_VALID))
def test_odd_but_valid_inputs(name, tmp_path, capsys):
    traj = ODD_VALID[name] or valid_traj()
    write(tmp_path / "t.yaml", traj)
    write(tmp_path / "s.yaml", S(put(("boxes",), [])) if name == "no-boxes" else valid_scene())
    args = {"huge-margin": ["--margin", "1e300"], "tiny-margin": ["--margin", "1e-300"]}.get(name, [])
    rc = _run_and_check(tmp_path, ["certify", str(tmp_path / "t.yaml"), "--scene", str(tmp_path / "s.yaml"),
                                   "--max-depth", "3", *args], capsys, fuzzing=False)
    assert rc in (0, 1)
    if name in ("huge-velocities", "huge-margin"):
        assert rc == 1


# ------------------------------------------------------------------------------------------------
# property-based: random mutations of valid inputs never crash and never leave output behind
# ------------------------------------------------------------------------------------------------

_TEXT = st.text(alphabet=st.characters(blacklist_categories=("Cs",)), max_size=8)
_KEYS = st.sampled_from(["sec", "nanosec", "nsecs", "positions", "velocities", "time_from_start",
                         "joint_names", "points", "min", "max", "name", "boxes", "frame", "units"]) | _TEXT
SPECIAL = [math.nan, math.inf, -math.inf, BIG, -BIG, 1e308, -1e308, 5e-324, 0, -1, 1e9, 999_999_999,
           1_000_000_000, -0.0, 1e-300, True, False, None, "", "1.5", "joint1", "base_link", [], {}, [[]]]
_LEAF = st.one_of(st.none(), st.booleans(), st.integers(-10**30, 10**30), st.floats(), _TEXT,
                  st.sampled_from(SPECIAL))
JSON_VALUE = st.recursive(_LEAF, lambda c: st.lists(c, max_size=7) | st.dictionaries(_KEYS, c, max_size=4),
                          max_leaves=12)
NUMBER_SWAPS = st.sampled_from([math.nan, math.inf, -math.inf, BIG, 1e308, -1e308, 5e-324, 1e-300, -1e-9])

FUZZ = settings(max_examples=int(os.environ.get("LARC_FUZZ_EXAMPLES", "800")), deadline=None,
                derandomize=True, database=None, print_blob=True,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow,
                                       HealthCheck.data_too_large])


def _paths(doc, prefix=()):
    items = doc.items() if isinstance(doc, dict) else enumerate(doc) if isinstance(doc, list) else ()
    out = []
    for k, v in items:
        out.append(prefix + (k,))
        out.extend(_paths(v, prefix + (k,)))
    return out


def _mutate(doc, data) -> None:
    """One random edit of a parsed document, in place."""
    paths = _paths(doc)
    numbers = [q for q in paths if isinstance(_parent(doc, q)[q[-1]], (int, float))]
    if numbers and data.draw(st.booleans(), label="number only"):
        paths = numbers  # half the edits hit a number: inputs that stay valid but odd
    if not paths:
        return
    path = data.draw(st.sampled_from(paths), label="path")
    parent, key = _parent(doc, path), path[-1]
    value = parent[key]
    numeric = isinstance(value, (int, float)) and not isinstance(value, bool)
    kinds = ["delete", "replace", "retype", "duplicate", "swap"] + ["perturb", "nonfinite"] * numeric
    kind = data.draw(st.sampled_from(kinds), label="edit")
    if kind == "delete":
        del parent[key]
    elif kind == "replace":
        parent[key] = copy.deepcopy(data.draw(JSON_VALUE, label="value"))  # SPECIAL holds shared lists
    elif kind == "retype":
        parent[key] = data.draw(st.sampled_from([str(value), [value], {"value": value}, None]), label="retyped")
        parent[key] = copy.deepcopy(parent[key])
    elif kind == "duplicate":
        if isinstance(parent, list):
            parent.insert(key, copy.deepcopy(value))
        else:
            parent[key] = [value, copy.deepcopy(value)]
    elif kind == "swap":  # exchange with a sibling: reorders points, joints, times, corners
        siblings = list(parent.keys()) if isinstance(parent, dict) else list(range(len(parent)))
        other = data.draw(st.sampled_from(siblings), label="sibling")
        parent[key], parent[other] = parent[other], parent[key]
    elif kind == "perturb":
        scale, shift = data.draw(st.floats(-3, 3), label="scale"), data.draw(st.floats(-2, 2), label="shift")
        try:
            parent[key] = value * scale + shift
        except OverflowError:  # an integer beyond the float range (BIG) stays as it is
            pass
    else:
        parent[key] = data.draw(NUMBER_SWAPS, label="number")


def _serialise(doc, fmt: str) -> bytes:
    if fmt == "json":
        return json.dumps(doc).encode()
    return yaml.safe_dump(doc, sort_keys=False).encode()


def _corrupt(raw: bytes, data) -> bytes:
    op = data.draw(st.sampled_from(["none"] * 6 + ["truncate", "insert", "flip"]), label="bytes")
    if op == "none" or not raw:
        return raw
    at = data.draw(st.integers(0, len(raw)), label="at")
    if op == "truncate":
        return raw[:at]
    if op == "insert":
        return raw[:at] + data.draw(st.binary(min_size=1, max_size=6), label="inserted") + raw[at:]
    at = min(at, len(raw) - 1)
    return raw[:at] + bytes([raw[at] ^ data.draw(st.integers(1, 255), label="xor")]) + raw[at + 1:]


def _run_and_check(tmp: Path, argv: list[str], capsys, fuzzing: bool = True) -> int:
    out = tmp / "out.json"
    leaves = tmp / "leaves.csv"
    argv = argv + ["--json", str(out)] + (["--leaves", str(leaves)] if HAS_LEAVES else [])
    rc = main(argv)  # an exception escaping main fails the test
    stdout, err = capsys.readouterr()
    if fuzzing:  # hypothesis statistics (pytest --hypothesis-show-statistics)
        event(f"exit {rc}")
    if fuzzing and rc == 2:
        event("error: " + re.sub(r"\[\d+\]", "[i]", err.split(": ", 3)[-1])[:50])
    assert rc in (0, 1, 2), f"exit status {rc}:\n{err}"
    if rc == 2:
        check_one_error_line(rc, err, ())
        assert not out.exists() and not leaves.exists()
    else:
        assert "Traceback" not in err and "error" not in err, err
        doc = json.loads(out.read_text())
        assert len(doc["trajectories"]) == 1
        assert doc["trajectories"][0]["certified"] is (rc == 0)
    assert not [p.name for p in tmp.iterdir() if p.name.endswith(".tmp")]
    return rc


@pytest.mark.slow
@FUZZ
@given(data=st.data())
def test_fuzz_trajectory_and_scene(data, capsys):
    """Mutated trajectory and scene documents: exit 0/1/2, one error line, no output on error."""
    import tempfile

    traj = valid_traj()
    scene = valid_scene() if data.draw(st.booleans(), label="far box") else S(
        put(("boxes", 0), {"name": "pillar", "min": [0.25, -0.05, 0.0], "max": [0.35, 0.05, 0.5]}))
    for _ in range(data.draw(st.sampled_from([0, 1, 1, 2, 3]), label="trajectory edits")):
        _mutate(traj, data)
    for _ in range(data.draw(st.sampled_from([0, 0, 0, 1, 2]), label="scene edits")):
        _mutate(scene, data)
    t_fmt = data.draw(st.sampled_from(["yaml", "json"]), label="trajectory format")
    t_suffix = data.draw(st.sampled_from([t_fmt] * 5 + ["yaml" if t_fmt == "json" else "json"]), label="suffix")
    t_raw = _corrupt(_serialise(traj, t_fmt), data)
    s_raw = _serialise(scene, "yaml")
    if data.draw(st.sampled_from([False, False, False, True]), label="corrupt scene"):
        s_raw = _corrupt(s_raw, data)
    args = []
    if data.draw(st.integers(0, 9), label="odd options") == 7:
        args = ["--margin", repr(data.draw(st.sampled_from([0.0, -0.01, 1e-9, 0.5, 1e300, math.nan, math.inf]))),
                "--max-depth", str(data.draw(st.sampled_from([-1, 0, 1, 3, 21])))]
    args += ["--method", data.draw(st.sampled_from(["larc"] * 5 + ["reference", "fine", "coarse"]), label="method")]
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        (tmp / f"t.{t_suffix}").write_bytes(t_raw)
        (tmp / "s.yaml").write_bytes(s_raw)
        _run_and_check(tmp, ["certify", str(tmp / f"t.{t_suffix}"), "--scene", str(tmp / "s.yaml"),
                             "--max-depth", "3", *args], capsys)


@pytest.mark.slow
@settings(FUZZ, max_examples=max(10, FUZZ.max_examples // 5))
@given(data=st.data())
def test_fuzz_robot_file(data, capsys):
    """Mutated --robot files (URDF path + capsules): exit 0/1/2 with the same contract."""
    import tempfile

    doc = robot_doc()
    doc["capsules"] = doc["capsules"][:3]  # keep the paths few; mutations hit the top-level fields too
    for _ in range(data.draw(st.integers(1, 2), label="robot edits")):
        _mutate(doc, data)
    raw = _corrupt(yaml.safe_dump(doc, sort_keys=False).encode(), data)
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        write(tmp / "t.yaml", valid_traj())
        write(tmp / "s.yaml", valid_scene())
        (tmp / "r.yaml").write_bytes(raw)
        _run_and_check(tmp, ["certify", str(tmp / "t.yaml"), "--scene", str(tmp / "s.yaml"), "--max-depth", "3",
                             "--robot", str(tmp / "r.yaml")], capsys)
