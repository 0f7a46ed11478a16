"""What `larc verify` prints, pins and refuses (issue 18, items 2 and 3): the velocity-mode forgery
(a file whose recorded velocity swings the gripper through the post, certified by its
finite-difference reading) is refuted by default; files swapped under a label are named in the
report (an id on another file, an empty scene) or refused (one id twice); every pin holds the
certificate to it (match: verified, mismatch: refuted naming it); --json reports every verdict.

One library certification (three trajectories, two scenes, depth 6) makes every certificate here."""

from __future__ import annotations

import copy
import json
import logging
from pathlib import Path

import numpy as np
import pytest
import yaml

from larc_jax.products.certificate import certificate, hexf, scene_sha256
from larc_jax.drivers.cli import EXIT_BAD_INPUT, EXIT_OK, EXIT_REFUTED, main
from larc_jax.errors import LarcInputError
from larc_jax.model.urdf import file_sha256
from larc_jax.products.verify import Refuted, VerifyPins, verify_certificate
from larc_jax.run_spec import RunSpec
from larc_jax.products.verify_report import report_lines

ROOT = Path(__file__).resolve().parent.parent
EX = ROOT / "configs" / "examples"
REACH, SWEEP, CELL = (str(EX / n) for n in ("reach_left.yaml", "sweep_front.yaml", "cell.yaml"))
POSE = [0.5, 1.0, -1.0, 0.0, 0.5, 0.0]
"""The forged trajectory's three equal waypoints: the gripper beside the post."""
POST = (np.array([0.30, -0.04, 0.0]), np.array([0.38, 0.04, 0.45]))


def _overshoot_msg(with_velocities: bool) -> dict:
    points = []
    for k in range(3):
        p = {"positions": list(POSE), "time_from_start": {"sec": k, "nanosec": 0}}
        if with_velocities:
            p["velocities"] = [-4.0 if k == 1 else 0.0] + [0.0] * 5  # joint1 at -4 rad/s in the middle
        points.append(p)
    return {"joint_names": [f"joint{j}" for j in range(1, 7)], "points": points}


@pytest.fixture(scope="module")
def made(tmp_path_factory, robot, capsules):
    """The files and one certificate document: reach_left (cell), the forged overshoot read with
    finite-difference velocities (cell), sweep_front in an empty scene."""
    import larc_jax as lj

    d = tmp_path_factory.mktemp("assume")
    overshoot, empty = d / "overshoot.yaml", d / "empty.yaml"
    overshoot.write_text(yaml.safe_dump(_overshoot_msg(True)))
    empty.write_text("frame: base_link\nboxes: []\n")
    cell, no_boxes = lj.read_scene(CELL), lj.read_scene(empty)
    trajs = [lj.read_trajectory(REACH, robot), lj.read_trajectory(overshoot, robot, velocities="finite-difference"),
             lj.read_trajectory(SWEEP, robot)]
    result = lj.certify(trajs, [cell, cell, no_boxes], robot, capsules, max_depth=6)
    assert result.certified.tolist() == [True, True, True]
    doc = certificate(result, trajs, [cell, cell, no_boxes], robot, capsules, velocities="recorded",
                         trajectory_files=[REACH, overshoot, SWEEP], scene_files=[CELL, empty])
    doc["trajectories"][1]["velocities"] = "finite-difference"  # the mode it was read with
    return {"dir": d, "doc": doc, "overshoot": overshoot, "empty": empty, "result": result, "trajs": trajs,
            "scenes": [cell, no_boxes]}


def _cert(made, tmp_path, keep, edit=None) -> Path:
    """A certificate of the trajectories ``keep`` (indices into the made document)."""
    doc = copy.deepcopy(made["doc"])
    doc["trajectories"] = [copy.deepcopy(doc["trajectories"][k]) for k in keep]
    if edit:
        edit(doc)
    path = tmp_path / "cert.json"
    path.write_text(json.dumps(doc))
    return path


def test_the_forged_file_really_swings_through_the_post(made, robot):
    """The claim the forgery would carry is false: the motion the file describes puts the finger
    frames inside the post; its finite-difference reading stands still."""
    from larc_jax.model.hermite import evaluate_np
    from larc_jax.model.robot import forward_kinematics_np
    import larc_jax as lj

    rec = lj.read_trajectory(made["overshoot"], robot)
    fd = made["trajs"][1]
    assert np.all(fd.qd == 0.0) and not np.all(rec.qd == 0.0)
    lo, hi = POST
    inside = []
    for t in np.linspace(0.0, 2.0, 41):
        p = forward_kinematics_np(robot, evaluate_np(rec.t, rec.q, rec.qd, t)[0])[:, :3, 3]
        inside += [robot.link_names[i] for i in range(len(p)) if np.all((lo <= p[i]) & (p[i] <= hi))]
    assert "link7" in inside


def test_finite_difference_certificate_of_a_file_with_velocities_is_refuted(made, tmp_path, capsys):
    path = _cert(made, tmp_path, [1])
    with pytest.raises(Refuted, match=r"overshoot.*finite-difference velocities.*records velocities at 3 waypoints"):
        verify_certificate(path)
    with pytest.raises(Refuted, match="finite-difference"):  # the real file supplied: refuted as well
        verify_certificate(path, trajectories=[made["overshoot"]])
    assert main(["verify", str(path)]) == EXIT_REFUTED
    assert "--allow-finite-difference" in capsys.readouterr().err
    # Accepted only when asked, and the report says what was accepted.
    report = verify_certificate(path, allow_finite_difference=True)
    t = report.trajectory_files[0]
    assert report.checked == 1 and t.velocities == "finite-difference" and t.ignored_velocities == 3
    assert "velocities finite-difference (3 recorded velocities in the file ignored" in "\n".join(report_lines(report))
    with pytest.raises(Refuted, match="pin --velocities recorded"):
        verify_certificate(path, allow_finite_difference=True, velocities="recorded")


def test_finite_difference_of_a_file_without_velocities_verifies(made, tmp_path):
    bare = tmp_path / "overshoot_positions.yaml"  # same arrays once differentiated: zero velocities
    bare.write_text(yaml.safe_dump(_overshoot_msg(False)))
    path = _cert(made, tmp_path, [1], lambda d: d["trajectories"][0].update(file=str(bare), sha256=file_sha256(bare)))
    report = verify_certificate(path)
    assert report.trajectory_files[0].velocities == "finite-difference"
    assert report.trajectory_files[0].ignored_velocities == 0
    assert "velocities finite-difference;" in "\n".join(report_lines(report))


def test_reading_finite_difference_warns_that_verify_refuses(made, robot, caplog):
    from larc_jax.model.trajectory_files import read_trajectory_file

    with caplog.at_level(logging.WARNING):
        traj, ignored = read_trajectory_file(made["overshoot"], robot, velocities="finite-difference")
    assert ignored == 3 and "not the motion the file describes" in caplog.text and "larc verify refuses" in caplog.text


def test_an_id_on_another_file_is_named_in_the_report(made, tmp_path, capsys):
    """reach_left's cover relabelled 'sweep_front': verified, but the report names the file."""
    def relabel(doc):
        doc["trajectories"][1]["id"] = "sweep_front"

    path = _cert(made, tmp_path, [0, 0], relabel)
    assert main(["verify", str(path)]) == EXIT_OK
    out = capsys.readouterr().out
    assert (f"trajectory 'sweep_front': {REACH} (named by the certificate) sha256 {file_sha256(REACH)} (its id is not "
            "the file's name)") in out
    assert f"trajectory 'reach_left': {REACH} (named by the certificate) sha256 {file_sha256(REACH)};" in out


def test_two_trajectories_with_one_id_are_refused(made, tmp_path, robot, capsules):
    import larc_jax as lj

    path = _cert(made, tmp_path, [0, 0])
    with pytest.raises(Refuted, match=r"trajectories\[0\] and trajectories\[1\] have the same id 'reach_left'"):
        verify_certificate(path)
    traj = made["trajs"][0]
    with pytest.raises(LarcInputError, match="two trajectories have the id 'reach_left'"):
        certificate(made["result"], [traj, traj, traj], made["scenes"][0], robot, capsules)


def test_an_empty_scene_is_printed_as_such(made, tmp_path, capsys):
    """sweep_front (through the post of cell.yaml) certified in an empty scene: the claim is true
    of that scene, and the report names it and its zero boxes."""
    path = _cert(made, tmp_path, [2], lambda d: d.update(scenes=d["scenes"][1:]) or
                 d["trajectories"][0].update(scene=0))
    assert main(["verify", str(path)]) == EXIT_OK
    out = capsys.readouterr().out
    assert f"scene 0: {made['empty']} (named by the certificate) sha256 {file_sha256(made['empty'])}" in out
    assert "0 obstacles: the claim says nothing about obstacles" in out
    assert main(["verify", str(path), "--scene", CELL]) == EXIT_REFUTED  # the third party's scene
    assert "scene file" in capsys.readouterr().err


def test_report_names_every_assumption_and_where_it_came_from(made, tmp_path):
    path = _cert(made, tmp_path, [0])
    report = verify_certificate(path, trajectories=[REACH])
    assert report.robot.file.source == "shipped" and report.robot.file.sha256 == made["doc"]["robot"]["sha256"]
    assert report.robot.urdf_sha256 == made["doc"]["robot"]["urdf_sha256"]
    assert {h for _, _, h in report.robot.geometry if h} == {e["sha256"] for es in made["doc"]["robot"]["geometry"]
                                                             .values() for e in es if "sha256" in e}
    assert [(j, s) for j, _, s in report.robot.held_joints] == [("joint7", False), ("joint8", False)]
    assert report.trajectory_files[0].file.source == "supplied" and report.scene_files[0].file.source == "certificate"
    assert report.scene_files[0].arrays_sha256 == scene_sha256(made["scenes"][0])
    p = report.parameters
    assert (p.margin_m, p.max_depth, p.enclosure, p.dtype, p.excluded_links, p.tracking_tolerance,
            p.self_margin_m) == (made["doc"]["parameters"]["margin_m"], 6, "hull", "float64", (), None, None)
    text = "\n".join(report_lines(report))
    for what in ("margin 0.01 m", "maximum depth 6", "enclosure hull", "geometry dtype float64",
                 "tracking tolerance: none", "self-collision: not certified",
                 "excluded links (not checked at all): none",
                 "joint7 = 0.0 (not stated", "given by the caller", "PIPER's shipped file", "URDF: ", "pins: none"):
        assert what in text, what


def test_a_refutation_carries_what_was_established(made, tmp_path):
    def edit(doc):
        doc["trajectories"][0]["leaves"]["clearance_m"][0] = hexf(1.0)

    with pytest.raises(Refuted, match="stored clearance") as exc:
        verify_certificate(_cert(made, tmp_path, [0], edit))
    report = exc.value.report
    assert report.refuted and report.robot is not None and len(report.scene_files) == 2
    assert report.trajectory_files[0].file.path == REACH and report.checked == 0


ALL_MATCHING = ["--margin-at-least", "0.01", "--depth-at-most", "6", "--enclosure", "hull", "--dtype", "float64",
                "--no-excluded-links", "--no-stated-joints", "--tracking-tolerance-at-least", "0",
                "--velocities", "recorded", "--require-files"]


def test_pins_that_hold_verify(made, tmp_path, capsys):
    path = _cert(made, tmp_path, [0])
    sha = made["doc"]["robot"]["sha256"]
    assert main(["verify", str(path), *ALL_MATCHING, "--robot-sha256", sha]) == EXIT_OK
    out = capsys.readouterr().out
    assert "VERIFIED" in out and f"--robot-sha256 {sha}" in out and "--require-files (held)" in out


@pytest.mark.parametrize("args,edit", [
    (["--margin-at-least", "0.02"], None),
    (["--depth-at-most", "5"], None),
    (["--margin-at-least", "0.010000000000000002"], None),  # one ulp above
    (["--enclosure", "capsules"], None),
    (["--dtype", "float32"], None),
    (["--no-excluded-links"], lambda d: d["parameters"].update(ignore_links=["base_link"])),
    (["--tracking-tolerance-at-least", "joint2=0.001"], None),
    (["--self-collision"], None),
    (["--self-margin-at-least", "0"], None),
    (["--no-self-skip"], None),
    (["--robot-sha256", "0" * 64], None),
    (["--no-stated-joints"], lambda d: (d["robot"]["stated_joints"].update(joint7=hexf(0.0)),
                                        d["parameters"].update(hold={"joint7": 0.0}))),
    (["--velocities", "finite-difference"], None),
    (["--require-files"], lambda d: d["trajectories"][0].update(sha256=None)),
])
def test_a_pin_not_met_is_refuted_naming_it(made, tmp_path, capsys, args, edit):
    path = _cert(made, tmp_path, [0], edit)
    assert main(["verify", str(path), *args]) == EXIT_REFUTED
    assert f"REFUTED: {path}: pin {args[0]}" in capsys.readouterr().err
    if args[0] == "--require-files":  # the same certificate without the pin: verified (its arrays bind it)
        assert main(["verify", str(path), "-q"]) == EXIT_OK


def test_pins_on_self_collision_and_tracking_tolerance(robot):
    """The pins' comparisons where the made certificate has nothing to compare (unit level)."""
    p = RunSpec(margin_m=0.01, max_depth=6, self_collision=True, self_margin_m=0.002, self_skip=("link1:link4",))
    VerifyPins(self_collision=True, self_margin_at_least_m=0.002).check_parameters(p)
    with pytest.raises(Refuted, match="pin --self-margin-at-least 0.003"):
        VerifyPins(self_margin_at_least_m=0.003).check_parameters(p)
    with pytest.raises(Refuted, match="pin --no-self-skip: .*link1:link4"):
        VerifyPins(no_self_skip=True).check_parameters(p)
    delta = np.full(robot.n_joints, 0.002)
    from larc_jax.products.verify_report import InputFile, RobotFacts

    facts = RobotFacts(file=InputFile("r.yaml", "supplied", "0" * 64, None), urdf="u", urdf_sha256="0", geometry=(),
                       active_joints=(), held_joints=(), capsules=0, excluded_links=())
    VerifyPins(tracking_tolerance_at_least="0.002").check_robot(facts, robot, delta)
    with pytest.raises(Refuted, match="pin --tracking-tolerance-at-least .*joint3 0.002 < 0.003"):
        VerifyPins(tracking_tolerance_at_least={"joint3": 0.003}).check_robot(facts, robot, delta)


@pytest.mark.parametrize("args,why", [
    (["--margin-at-least", "-1"], "--margin-at-least"),
    (["--robot-sha256", "xyz"], "--robot-sha256"),
    (["--tracking-tolerance-at-least", "joint9=0.1"], "joint9"),
])
def test_a_malformed_pin_is_bad_input(made, tmp_path, capsys, args, why):
    path = _cert(made, tmp_path, [0])
    assert main(["verify", str(path), *args]) == EXIT_BAD_INPUT
    assert why in capsys.readouterr().err


def test_json_report_for_every_verdict(made, tmp_path, capsys):
    path = _cert(made, tmp_path, [0, 1])
    assert main(["verify", str(path), "--json", "--allow-finite-difference", "--margin-at-least", "0.01"]) == EXIT_OK
    doc = json.loads(capsys.readouterr().out)
    assert doc["verdict"] == "verified" and doc["exit_status"] == 0 and doc["refuted"] is None
    assert doc["checked"] == 2 and doc["leaves"] > 0 and doc["min_excess_m"] > 0
    assert doc["robot"]["file"]["sha256"] == made["doc"]["robot"]["sha256"] and doc["robot"]["urdf_sha256"]
    assert doc["scene_files"][0]["file"]["path"] == CELL and len(doc["scene_files"][0]["boxes"]) == 3
    assert [(t["id"], t["velocities"], t["file"]["source"]) for t in doc["trajectory_files"]] == [
        ("reach_left", "recorded", "certificate"), ("overshoot", "finite-difference", "certificate")]
    assert doc["parameters"]["margin_m"] == 0.01 and doc["pins"] == ["--margin-at-least 0.01"]
    assert doc["allow_finite_difference"] is True

    assert main(["verify", str(path), "--json"]) == EXIT_REFUTED
    doc = json.loads(capsys.readouterr().out)
    assert doc["verdict"] == "refuted" and doc["exit_status"] == 1 and "finite-difference" in doc["refuted"]
    assert doc["trajectory_files"][0]["leaves"] > 0  # established before the refutation

    assert main(["verify", str(tmp_path / "missing.json"), "--json"]) == EXIT_BAD_INPUT
    doc = json.loads(capsys.readouterr().out)
    assert doc["verdict"] == "bad input" and doc["exit_status"] == 2 and "missing.json" in doc["error"]
