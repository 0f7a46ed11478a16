"""Every reader refuses a field it does not know (issue 18): scene (YAML, MoveIt ``.scene``
shapes), trajectory (YAML and JSON messages, CSV columns), robot file, manifest and certificate,
each with an extra key at each level; the one-line message names the key and the file. Fields
documented as ignored (ROS headers, accelerations, ...) are still read."""

from __future__ import annotations

import copy
import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from larc_jax.products.certificate_fields import CERTIFICATE_FIELDS
from larc_jax.enclosure import default_capsule_path
from larc_jax.enclosure.robot_file import load_capsules, load_robot_file
from larc_jax.errors import LarcInputError
from larc_jax.drivers.manifest import iter_manifest
from larc_jax.model.scene import read_scene
from larc_jax.model.trajectory_files import read_trajectory
from larc_jax.products.verify import verify_certificate

ROOT = Path(__file__).resolve().parent.parent
EX = ROOT / "configs" / "examples"
CELL, REACH, SWEEP = EX / "cell.yaml", EX / "reach_left.yaml", EX / "sweep_front.yaml"
TYPO = "frame: base_link\nboxes: []\nobstacle:\n  - {name: post, min: [0.30, -0.04, 0.0], max: [0.38, 0.04, 0.45]}\n"


def _refused(call, path, key):
    with pytest.raises(LarcInputError) as err:
        call(path)
    msg = str(err.value)
    assert str(path) in msg and repr(key) in msg and "unknown" in msg and len(msg.splitlines()) == 1, msg
    return msg


# ---------------------------------------------------------------------------------------------- scenes

@pytest.mark.parametrize("text,key", [
    (TYPO, "obstacle"),
    ("frame: base_link\nobstacles:\n  - {name: post, type: box, size: [1, 1, 1], min: [0, 0, 0]}\n", "min"),
    ("frame: base_link\nobstacles:\n  - {name: p, type: sphere, radius: 1, pose: {position: [0, 0, 0], "
     "rotation: [0, 0, 0, 1]}}\n", "rotation"),
    ("frame: base_link\nbox:\n  - {name: post, min: [0, 0, 0], max: [1, 1, 1]}\n", "box"),
    ("frame: base_link\nboxes:\n  - {name: post, min: [0, 0, 0], max: [1, 1, 1], rotation: [0, 0, 1]}\n",
     "rotation"),
])
def test_scene_yaml_refuses_an_unknown_field(tmp_path, text, key):
    path = tmp_path / "scene.yaml"
    path.write_text(text)
    _refused(lambda p: read_scene(p, frame="base_link"), path, key)


def test_scene_yaml_known_fields_are_read(tmp_path):
    path = tmp_path / "scene.yaml"
    path.write_text("frame: base_link\nunits: m\nname: cell\nboxes:\n  - {name: a, min: [0, 0, 0], max: [1, 1, 1]}\n")
    assert read_scene(path, frame="base_link").n_boxes == 1


def test_moveit_scene_refuses_an_unknown_shape(tmp_path):
    path = tmp_path / "cell.scene"
    path.write_text((EX / "pick.scene").read_text().replace("box", "capsule", 1))
    with pytest.raises(LarcInputError, match="unknown shape type 'capsule'") as err:
        read_scene(path)
    assert str(path) in str(err.value)


def test_typo_scene_is_refused_by_larc_certify(tmp_path):
    """The issue's case: with the typo read as an empty scene, sweep_front (through the post)
    was CERTIFIED. Now exit 2, one line, naming the key and the file; before any JAX work."""
    path = tmp_path / "typo.yaml"
    path.write_text(TYPO)
    proc = subprocess.run([sys.executable, "-m", "larc_jax.drivers.cli", "certify", str(SWEEP), "--scene", str(path)],
                          capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert "CERTIFIED" not in proc.stdout
    err = proc.stderr.strip().splitlines()
    assert len(err) == 1 and "'obstacle'" in err[0] and str(path) in err[0], proc.stderr


# ---------------------------------------------------------------------------------------------- trajectories

def _reach_msg() -> dict:
    return yaml.safe_load(REACH.read_text())


def _robot_trajectory(msg):
    return {"joint_trajectory": msg, "multi_dof_joint_trajectory": {"header": {}, "joint_names": [], "points": []}}


TRAJECTORY_EXTRAS = {
    "top": lambda m: {**m, "joint_name": ["joint1"]},
    "point": lambda m: {**m, "points": [{**m["points"][0], "velocity": [0] * 6}] + m["points"][1:]},
    "time": lambda m: {**m, "points": [{**m["points"][0], "time_from_start": {"sec": 0, "nanosec": 0, "msec": 5}}]
                       + m["points"][1:]},
    "robot_trajectory": lambda m: {**_robot_trajectory(m), "joint_trajectories": []},
    "multi_dof": lambda m: {"joint_trajectory": m, "multi_dof_joint_trajectory": {"joint_name": []}},
    "display_trajectory": lambda m: {"trajectory": [_robot_trajectory(m)], "model": "piper"},
}
TRAJECTORY_KEYS = {"top": "joint_name", "point": "velocity", "time": "msec", "robot_trajectory": "joint_trajectories",
                   "multi_dof": "joint_name", "display_trajectory": "model"}


@pytest.mark.parametrize("suffix", [".yaml", ".json"])
@pytest.mark.parametrize("level", sorted(TRAJECTORY_EXTRAS))
def test_trajectory_message_refuses_an_unknown_field(tmp_path, level, suffix):
    path = tmp_path / f"traj{suffix}"
    doc = TRAJECTORY_EXTRAS[level](_reach_msg())
    path.write_text(json.dumps(doc) if suffix == ".json" else yaml.safe_dump(doc))
    _refused(read_trajectory, path, TRAJECTORY_KEYS[level])


def test_trajectory_ignored_fields_are_documented_and_read(tmp_path):
    msg = _reach_msg()
    msg["header"] = {"stamp": {"sec": 1, "nanosec": 0}, "frame_id": "base_link"}
    msg["points"] = [{**p, "accelerations": [], "effort": []} for p in msg["points"]]
    doc = {"model_id": "piper", "trajectory": [_robot_trajectory(msg)], "trajectory_start": {}}
    path = tmp_path / "display.yaml"
    path.write_text(yaml.safe_dump(doc))
    assert read_trajectory(path).n_waypoints == 3
    import larc_jax.model.trajectory_files as tf

    for key in ("header", "accelerations", "effort", "model_id", "trajectory_start"):
        assert f"``{key}``" in tf.__doc__


def test_trajectory_csv_refuses_an_unknown_column(tmp_path, robot):
    path = tmp_path / "traj.csv"
    lines = (EX / "traj.csv").read_text().splitlines()
    path.write_text("\n".join([lines[0] + ",jonit7"] + [line + ",0" for line in lines[1:] if line]) + "\n")
    with pytest.raises(LarcInputError, match="jonit7") as err:
        read_trajectory(path, robot)
    assert str(path) in str(err.value)


# ---------------------------------------------------------------------------------------------- robot file

def _robot_doc() -> dict:
    return yaml.safe_load(default_capsule_path().read_text())


ROBOT_EXTRAS = {
    "top": (lambda d: d.update(padding=0.0), "padding"),
    "capsule": (lambda d: d["capsules"][0].update(radius_m=1.0), "radius_m"),
    "stated_capsule": (lambda d: d["stated_capsules"][0].update(offset=[0, 0, 0]), "offset"),
    "hull_part": (lambda d: next(iter(d["hull_parts"].values())).update(normals=[1, 0, 0]), "normals"),
}


@pytest.mark.parametrize("level", sorted(ROBOT_EXTRAS))
def test_robot_file_refuses_an_unknown_field(tmp_path, robot, level):
    edit, key = ROBOT_EXTRAS[level]
    doc = _robot_doc()
    edit(doc)
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    _refused(lambda p: load_capsules(p, robot), path, key)


def test_robot_file_top_level_is_checked_before_the_urdf_is_read(tmp_path):
    doc = {"urdf": "missing.urdf", "urdf_sha": "0" * 64, **_robot_doc()}
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    _refused(load_robot_file, path, "urdf_sha")


def test_shipped_robot_file_reads_with_its_documented_ignored_fields(robot):
    doc = _robot_doc()
    assert {"revision", "gripper_opening_m", "held_prismatic_stroke_enclosed"} <= set(doc)
    assert load_capsules(default_capsule_path(), robot).names


# ---------------------------------------------------------------------------------------------- manifest

def test_manifest_refuses_an_unknown_column(tmp_path):
    path = tmp_path / "m.csv"
    path.write_text("trajectory,scene,scenes\na.yaml,b.yaml,c.yaml\n")
    with pytest.raises(LarcInputError) as err:
        list(iter_manifest(path))
    msg = str(err.value)
    assert f"{path}:1:" in msg and "unknown column 'scenes'" in msg
    path.write_text("id,trajectory,scene\nx,a.yaml,b.yaml\n")
    assert [r.id for r in iter_manifest(path)] == ["x"]


# ---------------------------------------------------------------------------------------------- certificate

def _skeleton() -> dict:
    """A certificate with every level present (values are placeholders: the field check runs
    before any value is read)."""
    doc = {key: None for key in CERTIFICATE_FIELDS[""]}
    doc.update(format="larc-certificate", version=4)
    doc["parameters"] = {key: None for key in CERTIFICATE_FIELDS["parameters"]}
    doc["robot"] = {key: None for key in CERTIFICATE_FIELDS["robot"]}
    doc["scenes"] = [{key: None for key in CERTIFICATE_FIELDS["scenes[]"]}]
    traj = {key: None for key in CERTIFICATE_FIELDS["trajectories[]"]}
    traj["rounding"] = {key: None for key in CERTIFICATE_FIELDS["trajectories[].rounding"]}
    traj["leaves"] = {key: [] for key in CERTIFICATE_FIELDS["trajectories[].leaves"]}
    doc["trajectories"] = [copy.deepcopy(traj), traj]
    return doc


CERT_LEVELS = {
    "": (lambda d: d, ""),
    "parameters": (lambda d: d["parameters"], "parameters: "),
    "robot": (lambda d: d["robot"], "robot: "),
    "scenes[]": (lambda d: d["scenes"][0], "scenes[0]: "),
    "trajectories[]": (lambda d: d["trajectories"][1], "trajectories[1]: "),
    "trajectories[].rounding": (lambda d: d["trajectories"][1]["rounding"], "trajectories[1].rounding: "),
    "trajectories[].leaves": (lambda d: d["trajectories"][0]["leaves"], "trajectories[0].leaves: "),
}


def test_every_certificate_level_is_walked():
    assert set(CERT_LEVELS) == set(CERTIFICATE_FIELDS)


@pytest.mark.parametrize("level", sorted(CERT_LEVELS))
def test_certificate_refuses_an_unknown_field(tmp_path, level):
    pick, where = CERT_LEVELS[level]
    doc = _skeleton()
    pick(doc)["claims"] = True
    path = tmp_path / "cert.json"
    path.write_text(json.dumps(doc))
    msg = _refused(verify_certificate, path, "claims")
    assert f"{path}: {where}unknown field 'claims'" in msg


def test_certificate_skeleton_passes_the_field_check(tmp_path):
    """Control: without the extra key the skeleton gets past the field check (and fails later,
    on its placeholder values, with another message)."""
    path = tmp_path / "cert.json"
    path.write_text(json.dumps(_skeleton()))
    with pytest.raises(LarcInputError) as err:
        verify_certificate(path)
    assert "unknown field" not in str(err.value)
