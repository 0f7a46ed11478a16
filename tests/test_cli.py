"""The `larc` command line: certify with hand-written files, exit codes, JSON, bad input."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

TRAJ = """joint_names: [joint1, joint2, joint3, joint4, joint5, joint6]
points:
  - positions: [0.0, 0.5, -0.8, 0.0, 0.3, 0.0]
    velocities: [0, 0, 0, 0, 0, 0]
    time_from_start: {sec: 0, nanosec: 0}
  - positions: [0.6, 0.9, -1.1, 0.2, 0.4, 0.5]
    velocities: [0.1, 0, 0, 0, 0, 0]
    time_from_start: {sec: 1, nanosec: 500000000}
  - positions: [1.2, 0.9, -1.1, 0.2, 0.4, 0.5]
    velocities: [0, 0, 0, 0, 0, 0]
    time_from_start: {sec: 3, nanosec: 0}
"""
FAR_SCENE = """frame: base_link
boxes:
  - {name: crate, min: [-0.8, -0.8, 0.0], max: [-0.6, -0.6, 0.2]}
"""
NEAR_SCENE = """frame: base_link
boxes:
  - {name: pillar, min: [0.25, -0.05, 0.0], max: [0.35, 0.05, 0.5]}
"""


def run_larc(*args, cwd):
    env = dict(os.environ)
    return subprocess.run([sys.executable, "-m", "larc_jax.cli", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=300)


@pytest.fixture()
def files(tmp_path):
    (tmp_path / "reach.yaml").write_text(TRAJ)
    (tmp_path / "far.yaml").write_text(FAR_SCENE)
    (tmp_path / "near.yaml").write_text(NEAR_SCENE)
    return tmp_path


def test_certified_exit_0_and_json(files):
    p = run_larc("certify", "reach.yaml", "--scene", "far.yaml", "--json", "out.json", cwd=files)
    assert p.returncode == 0, p.stderr
    assert "CERTIFIED" in p.stdout
    doc = json.loads((files / "out.json").read_text())
    (t,) = doc["trajectories"]
    assert t["id"] == "reach" and t["certified"] is True
    assert t["evaluations"] >= 1 and len(t["frontier_sizes"]) == 10
    assert t["min_clearance_m"] > 0


def test_uncertified_exit_1_names_blocking_pair(files):
    p = run_larc("certify", "reach.yaml", "--scene", "near.yaml", "--json", "out.json", cwd=files)
    assert p.returncode == 1, p.stderr
    assert "UNCERTIFIED" in p.stdout and "pillar" in p.stdout
    t = json.loads((files / "out.json").read_text())["trajectories"][0]
    assert t["certified"] is False and t["evaluations"] > 1 and t["min_clearance_m"] <= 0
    assert t["first_inconclusive"]["box"] == "pillar"


@pytest.mark.parametrize("method,evals", [("fine", 512), ("coarse", 16)])
def test_fixed_methods(files, method, evals):
    p = run_larc("certify", "reach.yaml", "--scene", "far.yaml", "--method", method, "--json", "o.json", cwd=files)
    assert p.returncode == 0, p.stderr
    assert json.loads((files / "o.json").read_text())["trajectories"][0]["evaluations"] == evals


@pytest.mark.parametrize("mutate,needle", [
    (lambda t: t.replace("joint6]", "joint7]"), "joint_names"),
    (lambda t: t.replace("sec: 3,", "sec: 1,"), "points[2].time_from_start"),
    (lambda t: t.replace("[1.2, 0.9", "[.nan, 0.9"), "points[2].positions[0]"),
    (lambda t: t.replace("[1.2, 0.9", "[9.0, 0.9"), "points[2].positions[0]"),
    (lambda t: "", "empty"),
])
def test_bad_trajectory_exit_2(files, mutate, needle):
    (files / "bad.yaml").write_text(mutate(TRAJ))
    p = run_larc("certify", "bad.yaml", "--scene", "far.yaml", "--json", "out.json", cwd=files)
    assert p.returncode == 2
    assert needle in p.stderr and "bad.yaml" in p.stderr
    assert "Traceback" not in p.stderr
    assert not (files / "out.json").exists()


def test_bad_scene_exit_2(files):
    (files / "inverted.yaml").write_text("boxes:\n  - {name: b, min: [0, 0, 1], max: [1, 1, 0]}\n")
    p = run_larc("certify", "reach.yaml", "--scene", "inverted.yaml", cwd=files)
    assert p.returncode == 2 and "boxes[0].min[2]" in p.stderr and "Traceback" not in p.stderr
