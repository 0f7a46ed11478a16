"""Attacks on ``larc verify`` by someone who writes the certificate and the files (issue 18,
red team): each test is a hole that was found, now closed.

* A certificate whose ``excluded_links`` or self-collision ``skip`` list holds a non-name reached
  the pins' report join as a traceback (exit 3): it is bad input (exit 2).
* A robot file that holds a *revolute* joint (the arm with joint6 held at 0): the report said its
  links were "enclosed over the stroke", which only a held prismatic finger is; the claim in fact
  assumes the joint never moves, and the report must say so.
* A claimed trajectory's ``scene`` of JSON ``false`` / ``true`` was taken as index 0 / 1 and
  printed as "scene False": a scene index is an integer, not a boolean.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from larc_jax.products.certificate import CERTIFICATE_FORMAT, CERTIFICATE_VERSION
from larc_jax.enclosure.robot_file import default_capsule_path
from larc_jax.errors import LarcInputError
from larc_jax.run_spec import RunSpec
from larc_jax.products.verify import Refuted, verify_certificate
from larc_jax.products.verify_report import report_lines


def _bare_certificate(tmp_path: Path, **parameters) -> Path:
    doc = {"format": CERTIFICATE_FORMAT, "version": CERTIFICATE_VERSION, "trajectories": [],
           "parameters": {**RunSpec(max_depth=4, enclosure="capsules").to_dict(), **parameters}}
    path = tmp_path / "bare.json"
    path.write_text(json.dumps(doc))
    return path


@pytest.mark.parametrize("parameters,pin,where", [
    ({"ignore_links": [1]}, {"no_excluded_links": True}, r"parameters: ignore_links\[0\] 1: expected a non-empty name"),
    ({"self_collision": True, "self_skip": [{"a": 1}]}, {"no_self_skip": True}, r"parameters: self_skip\[0\]"),
    ({"self_collision": "yes"}, {"self_collision": True}, r"parameters: self_collision 'yes': must be true or false"),
])
def test_a_list_of_names_holding_a_non_name_is_bad_input(tmp_path, parameters, pin, where):
    with pytest.raises(LarcInputError, match=where):
        verify_certificate(_bare_certificate(tmp_path, **parameters), **pin)


@pytest.fixture(scope="module")
def arm5(tmp_path_factory, piper_dir) -> Path:
    """A certificate (NumPy reference) made with a robot file that holds joint6 at 0: a still
    5-joint trajectory in an empty scene."""
    import larc_jax as lj
    from larc_jax.enclosure.robot_file import load_robot_file

    tmp = tmp_path_factory.mktemp("arm5")
    doc = yaml.safe_load(default_capsule_path().read_text())
    doc = {"urdf": str(piper_dir / "urdf" / "piper_description.urdf"),
           "package_dirs": {"piper_description": str(piper_dir)}, **doc}
    doc["active_joints"] = [f"joint{j}" for j in range(1, 6)]
    doc["held_joints"] = {"joint6": 0.0, **doc["held_joints"]}
    robot_file = tmp / "arm5.yaml"
    robot_file.write_text(yaml.safe_dump(doc, sort_keys=False))
    traj_file, scene_file = tmp / "still.yaml", tmp / "empty.yaml"
    traj_file.write_text(yaml.safe_dump({"joint_names": doc["active_joints"], "points": [
        {"positions": [0.5, 1.0, -1.0, 0.0, 0.5], "velocities": [0.0] * 5, "time_from_start": {"sec": k, "nanosec": 0}}
        for k in range(2)]}))
    scene_file.write_text("frame: base_link\nboxes: []\n")
    robot, capsules = load_robot_file(robot_file)
    traj, scene = lj.read_trajectory(traj_file, robot), lj.read_scene(scene_file)
    result = lj.certify([traj], scene, robot, capsules, max_depth=2, method="reference")
    return lj.write_certificate(tmp / "arm5.json", result, [traj], scene, robot, capsules,
                                robot_file=str(robot_file), trajectory_files=[traj_file], scene_files=[scene_file])


def test_a_held_revolute_joint_is_reported_as_assumed_fixed(arm5):
    """The robot file makes joint6 a held joint: the certificate is true only while joint6 stays
    at 0, and the VERIFIED report must say that rather than call it enclosed over a stroke."""
    report = verify_certificate(arm5)
    assert report.refuted is None and report.robot.fixed_joints == ("joint6",)
    held = next(line for line in report_lines(report) if "held joints:" in line)
    assert "joint6 = 0.0 (held by the robot file: its links placed at this value alone, assumed never to move)" in held
    assert "joint7 = 0.0 (not stated: its links enclosed over the stroke)" in held


def test_a_boolean_scene_index_is_bad_input(arm5, tmp_path):
    """JSON false indexed scene 0 (true: scene 1) and the report printed "scene False"."""
    doc = json.loads(arm5.read_text())
    doc["trajectories"][0]["scene"] = False
    path = tmp_path / "bool_scene.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(LarcInputError, match=r"trajectories\[0\]\.scene: expected a scene index"):
        verify_certificate(path)


def test_a_newline_in_an_id_or_the_method_cannot_add_report_lines(arm5, tmp_path):
    """The trajectory id is the certificate's text: it verifies (labels are not trusted), but
    must not print lines of its own, such as a pin "held". The method is a run-spec field: any
    text but a method is bad input, in one line."""
    doc = json.loads(arm5.read_text())
    doc["trajectories"][0]["id"] = "still'\n  pins: --robot-sha256 " + "0" * 64 + " (held)"
    path = tmp_path / "injected.json"
    path.write_text(json.dumps(doc))
    lines = report_lines(verify_certificate(path))
    assert all("\n" not in line for line in lines)
    assert [line for line in lines if line.lstrip().startswith("pins:")] == ["  pins: none"]
    assert any("trajectory \"still'\\n  pins: --robot-sha256" in line for line in lines)
    doc["parameters"]["method"] = "larc\n  pins: --no-stated-joints (held)"
    path.write_text(json.dumps(doc))
    with pytest.raises(LarcInputError, match=r"parameters: method 'larc\\n  pins.*': one of larc") as err:
        verify_certificate(path)
    assert "\n" not in str(err.value)


def test_a_trajectory_not_claimed_certified_can_be_pinned(arm5, tmp_path):
    """A certificate that marks its trajectory not certified verifies (it claims nothing, exit 0)
    even with the file supplied, which is then not even read: --all-certified refuses it."""
    doc = json.loads(arm5.read_text())
    doc["trajectories"][0]["certified"] = False
    path = tmp_path / "unclaimed.json"
    path.write_text(json.dumps(doc))
    assert verify_certificate(path).checked == 0
    with pytest.raises(Refuted, match="pin --all-certified: trajectory 'still' is not claimed certified"):
        verify_certificate(path, all_certified=True)
    assert verify_certificate(arm5, all_certified=True).checked == 1


def test_a_certificate_states_its_whole_run_spec(tmp_path):
    """A run-spec field left out is refused, not read as its default (the claim would then be one
    the certificate never stated)."""
    path = _bare_certificate(tmp_path)
    doc = json.loads(path.read_text())
    del doc["parameters"]["margin_m"]
    path.write_text(json.dumps(doc))
    with pytest.raises(LarcInputError, match=r"parameters: missing field 'margin_m'"):
        verify_certificate(path)
