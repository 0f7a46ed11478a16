"""Certificate files and the independent checker: a real certificate verifies (CLI and API);
edited ones (a leaf removed, a clearance edited, a time shifted, a false claim, a changed scene,
robot file or mesh hash) are refuted; bad input exits 2; the checker never loads JAX."""

from __future__ import annotations

import copy
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from larc_jax.products.certificate import hexf, unhexf
from larc_jax.drivers.cli import EXIT_BAD_INPUT, EXIT_OK, EXIT_REFUTED, main
from larc_jax.errors import LarcInputError
from larc_jax.leaf.record import CULL_SLACK_M

ROOT = Path(__file__).resolve().parent.parent
EX = ROOT / "configs" / "examples"
REACH, SWEEP, CELL = (str(EX / n) for n in ("reach_left.yaml", "sweep_front.yaml", "cell.yaml"))
DEPTH = "6"


@pytest.fixture(scope="module")
def cli_cert(tmp_path_factory):
    """A certificate written by `larc certify` for reach_left (certified) and sweep_front (not)."""
    path = tmp_path_factory.mktemp("cert") / "cert.json"
    rc = main(["certify", REACH, SWEEP, "--scene", CELL, "--max-depth", DEPTH, "--certificate", str(path),
               "--no-fail-on-uncertified", "-q"])
    assert rc == EXIT_OK
    doc = json.loads(path.read_text())
    assert [t["certified"] for t in doc["trajectories"]] == [True, False]
    return path, doc


def _edited(tmp_path, doc, edit) -> Path:
    doc = copy.deepcopy(doc)
    edit(doc)
    out = tmp_path / "edited.json"
    out.write_text(json.dumps(doc))
    return out


def _verify(path, *extra):
    return main(["verify", str(path), *extra])


def test_cli_certificate_verifies(cli_cert, capsys):
    path, doc = cli_cert
    assert _verify(path) == EXIT_OK
    out = capsys.readouterr().out
    assert "VERIFIED: 1 of 2 trajectories" in out
    reach = doc["trajectories"][0]
    assert reach["file"] == REACH and reach["scene"] == 0 and doc["scenes"][0]["file"] == CELL
    assert doc["parameters"]["max_depth"] == int(DEPTH) and doc["parameters"]["dtype"] == "float64"
    assert doc["parameters"]["margin_m"] == 0.01 and doc["version"] == 4 and doc["parameters"]["padding_m"] == 0.0
    assert doc["robot"]["geometry"] and all("sha256" in e for link in doc["robot"]["geometry"].values()
                                            for e in link if "mesh" in e)


def test_float_hex_is_exact():
    for x in (0.1, 1.0 / 3.0, 2.0**-1074, 1e308, np.nextafter(1.0, 2.0), float("inf"), -0.0):
        assert unhexf(hexf(x)) == x and str(unhexf(hexf(x))) == str(x)
    assert np.isnan(unhexf(hexf(float("nan"))))


def test_api_certificate_verifies(tmp_path, robot, capsules):
    import larc_jax as lj

    traj = lj.read_trajectory(REACH, robot)
    scene = lj.read_scene(CELL)
    result = lj.certify([traj], scene, robot, capsules, max_depth=int(DEPTH))
    assert result.certified[0]
    path = lj.write_certificate(tmp_path / "api.json", result, [traj], scene, robot, capsules)
    doc = json.loads(path.read_text())
    leaves = result.leaves
    assert [unhexf(x) for x in doc["trajectories"][0]["leaves"]["t0"]] == leaves.t0.tolist()  # bit for bit
    assert [unhexf(x) for x in doc["trajectories"][0]["leaves"]["clearance_m"]] == leaves.clearance_m.tolist()
    assert doc["trajectories"][0]["file"] is None and doc["trajectories"][0]["sha256"] is None  # arrays only
    with pytest.raises(LarcInputError, match=r"from arrays .*--scene"):
        lj.verify_certificate(path)  # no file recorded: the checker must be given them
    with pytest.raises(LarcInputError, match=r"from arrays .*--trajectory"):
        lj.verify_certificate(path, scenes=[CELL])
    report = lj.verify_certificate(path, trajectories=[REACH], scenes=[CELL])
    assert report.checked == 1 and report.leaves == len(leaves) and report.min_excess_m > 0
    assert report.max_clearance_diff_m < 1e-12  # JAX kernel vs NumPy reference, float64
    _certificate_uses_the_results_hulls(result, traj, scene, robot, capsules, doc)


def _certificate_uses_the_results_hulls(result, traj, scene, robot, capsules, doc):
    """hulls= (what certify was given): the robot file's parts give the same certificate; other
    parts, which larc verify would not prove, are refused; so is a result without its run spec."""
    import dataclasses

    from larc_jax.products.certificate import certificate
    from larc_jax.enclosure.hull import hull_model

    own = hull_model(robot, capsules.hull_parts, result.padding_m)
    assert certificate(result, [traj], scene, robot, capsules, hulls=own) == doc
    thinner = dataclasses.replace(own, radius=np.asarray(own.radius) * 0.5)
    with pytest.raises(LarcInputError, match=r"hull parts \(hulls=\) other than .*hull_parts"):
        certificate(result, [traj], scene, robot, capsules, hulls=thinner)
    with pytest.raises(LarcInputError, match=r"no run spec"):
        certificate(dataclasses.replace(result, spec=None), [traj], scene, robot, capsules)
    with pytest.raises(LarcInputError, match=r"the result's margin_m 0.02 is not its spec's 0.01"):
        certificate(dataclasses.replace(result, margin_m=0.02), [traj], scene, robot, capsules)


def _drop_leaf(k):
    def edit(doc):
        for col in doc["trajectories"][0]["leaves"].values():
            del col[k]
    return edit


def _set_leaf(key, k, f):
    def edit(doc):
        col = doc["trajectories"][0]["leaves"][key]
        col[k] = f(col[k])
    return edit


@pytest.mark.parametrize("name,edit,why", [
    ("leaf removed", _drop_leaf(1), "do not tile"),
    ("last leaf removed", _drop_leaf(-1), "do not tile"),
    ("clearance edited", _set_leaf("clearance_m", 0, lambda s: hexf(unhexf(s) + 1e-4)), "stored clearance"),
    ("time shifted", _set_leaf("t1", 0, lambda s: hexf(unhexf(s) + 1e-3)), "dyadic piece"),
    ("time shifted by one ulp", _set_leaf("t0", 1, lambda s: hexf(np.nextafter(unhexf(s), 0.0))), "dyadic piece"),
    ("depth edited", _set_leaf("depth", 0, lambda d: d + 1), "dyadic piece"),
    ("guard input edited", lambda doc: doc["trajectories"][0]["rounding"].update(tau_s=hexf(0.0)), "rounding input"),
    ("margin raised", lambda doc: doc["parameters"].update(margin_m=0.0105), "stored clearance"),
    ("margin lowered", lambda doc: doc["parameters"].update(margin_m=0.0095), "stored clearance"),
    ("clearance lowered", _set_leaf("clearance_m", 0, lambda s: hexf(unhexf(s) - 1e-4)), "is below the recomputed"),
    ("margin raised a lot", lambda doc: doc["parameters"].update(margin_m=0.5), "fails the reference test"),
    ("false claim", lambda doc: doc["trajectories"][1].update(certified=True), "sweep_front"),
    ("mesh hash edited", lambda doc: doc["robot"]["geometry"]["link6"][0].update(sha256="0" * 64), "collision geometry"),
    ("urdf hash edited", lambda doc: doc["robot"].update(urdf_sha256="0" * 64), "URDF"),
    ("enclosures hash edited", lambda doc: doc["robot"].update(enclosures_sha256="0" * 64), "robot.enclosures_sha256"),
    ("padding forged", lambda doc: doc["parameters"].update(padding_m=0.001), "robot.enclosures_sha256"),
    ("trajectory file hash edited", lambda doc: doc["trajectories"][0].update(sha256="0" * 64), "trajectory file"),
])
def test_edited_certificate_is_refuted(cli_cert, tmp_path, capsys, name, edit, why):
    path, doc = cli_cert
    rc = _verify(_edited(tmp_path, doc, edit))
    err = capsys.readouterr().err
    assert rc == EXIT_REFUTED, err
    assert "REFUTED" in err and why in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1


def test_false_claim_names_the_first_failing_leaf(cli_cert, tmp_path, capsys):
    path, doc = cli_cert

    def claim(doc):
        t = doc["trajectories"][1]
        t["certified"] = True
        t["leaves"]["certified"] = [True] * len(t["leaves"]["certified"])

    assert _verify(_edited(tmp_path, doc, claim)) == EXIT_REFUTED
    err = capsys.readouterr().err
    assert "trajectory 'sweep_front' leaf" in err and "fails the reference test" in err


def test_changed_scene_is_refuted(cli_cert, tmp_path, capsys):
    path, _ = cli_cert
    scene = tmp_path / "cell.yaml"
    scene.write_text(Path(CELL).read_text().replace("0.30, -0.04, 0.0", "0.20, -0.04, 0.0"))
    assert _verify(path, "--scene", str(scene)) == EXIT_REFUTED
    assert "scene file" in capsys.readouterr().err
    same = tmp_path / "same.yaml"
    shutil.copy(CELL, same)  # the same bytes elsewhere verify
    assert _verify(path, "--scene", str(same)) == EXIT_OK


def test_changed_trajectory_and_robot_file_are_refuted(cli_cert, tmp_path, capsys):
    from larc_jax.enclosure import default_capsule_path

    path, _ = cli_cert
    traj = tmp_path / "reach.yaml"
    traj.write_text(Path(REACH).read_text() + "\n# edited\n")
    assert _verify(path, "--trajectory", str(traj), SWEEP) == EXIT_REFUTED
    assert "trajectory file" in capsys.readouterr().err
    robot = tmp_path / "robot.yaml"
    robot.write_text(Path(default_capsule_path()).read_text() + "\n# edited\n")
    assert _verify(path, "--robot", str(robot)) == EXIT_REFUTED
    assert "robot file" in capsys.readouterr().err


def test_changed_mesh_on_disk_is_refuted(tmp_path, capsys):
    """A second robot (URDF + one mesh in tmp): after a certificate, one byte of the mesh changes."""
    import trimesh

    mesh = trimesh.creation.box(extents=(0.04, 0.04, 0.2))
    mesh.apply_translation((0, 0, 0.1))
    mesh.export(tmp_path / "arm.stl")
    (tmp_path / "arm.urdf").write_text("""<robot name="mini">
  <link name="base"/>
  <link name="arm"><collision><geometry><mesh filename="arm.stl"/></geometry></collision></link>
  <joint name="j1" type="revolute"><parent link="base"/><child link="arm"/><axis xyz="0 0 1"/>
    <limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
</robot>
""")
    assert main(["fit-capsules", str(tmp_path / "arm.urdf"), "-o", str(tmp_path / "robot.yaml"), "-q"]) == EXIT_OK
    (tmp_path / "t.yaml").write_text("joint_names: [j1]\npoints:\n"
                                     "  - {positions: [0.0], velocities: [0.0], time_from_start: {sec: 0, nanosec: 0}}\n"
                                     "  - {positions: [1.0], velocities: [0.0], time_from_start: {sec: 1, nanosec: 0}}\n")
    (tmp_path / "s.yaml").write_text("frame: base\nboxes:\n  - {name: far, min: [1, 1, 0], max: [1.2, 1.2, 0.2]}\n")
    cert = tmp_path / "c.json"
    assert main(["certify", str(tmp_path / "t.yaml"), "--scene", str(tmp_path / "s.yaml"), "--robot",
                 str(tmp_path / "robot.yaml"), "--max-depth", "3", "--certificate", str(cert), "-q"]) == EXIT_OK
    assert _verify(cert) == EXIT_OK
    data = bytearray((tmp_path / "arm.stl").read_bytes())
    data[-1] ^= 0x01
    (tmp_path / "arm.stl").write_bytes(bytes(data))
    capsys.readouterr()
    assert _verify(cert) == EXIT_REFUTED
    assert "arm.stl" in capsys.readouterr().err


@pytest.mark.parametrize("content,why", [
    (None, "does not exist"),
    ("{not json", "not valid JSON"),
    ('{"format": "something"}', "not a larc certificate"),
    ('{"format": "larc-certificate", "version": 99}', "unknown certificate version 99"),
    ('{"format": "larc-certificate", "version": 4}', "missing field 'parameters'"),
    ('{"format": "larc-certificate", "version": 2}', "a version-2 certificate"),
    ('{"format": "larc-certificate", "version": 3}', "a version-3 certificate"),
])
def test_bad_input_exits_2(tmp_path, capsys, content, why):
    path = tmp_path / "c.json"
    if content is not None:
        path.write_text(content)
    assert _verify(path) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert why in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_bad_fields_and_files_exit_2(cli_cert, tmp_path, capsys):
    path, doc = cli_cert
    bad = _edited(tmp_path, doc, _set_leaf("t0", 0, lambda s: "zero"))
    assert _verify(bad) == EXIT_BAD_INPUT
    assert "not a float.hex() number" in capsys.readouterr().err
    assert _verify(path, "--scene", str(tmp_path / "missing.yaml")) == EXIT_BAD_INPUT
    assert "scene file does not exist" in capsys.readouterr().err
    assert _verify(path, "--trajectory", REACH) == EXIT_BAD_INPUT  # 1 file for 2 trajectories
    assert "2" in capsys.readouterr().err


def test_checker_process_never_imports_jax(cli_cert):
    path, _ = cli_cert
    code = ("import sys\nfrom larc_jax.drivers.cli import main\nrc = main(['verify', sys.argv[1], '-q'])\n"
            "assert 'jax' not in sys.modules and 'jaxlib' not in sys.modules, 'jax was imported'\nsys.exit(rc)\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True, env=env,
                          timeout=120)
    assert proc.returncode == EXIT_OK, proc.stderr


def test_reference_method_with_an_ignored_link_verifies(tmp_path, capsys):
    path = tmp_path / "ref.json"
    assert main(["certify", REACH, "--scene", CELL, "--method", "reference", "--ignore-link", "base_link",
                 "--certificate", str(path), "-q"]) == EXIT_OK
    doc = json.loads(path.read_text())
    assert doc["parameters"]["method"] == "reference" and doc["parameters"]["ignore_links"] == ["base_link"]
    assert _verify(path) == EXIT_OK
    edited = _edited(tmp_path, doc, lambda d: d["parameters"].update(ignore_links=[]))
    assert _verify(edited) == EXIT_REFUTED  # the capsule list no longer matches
    assert "capsule names" in capsys.readouterr().err


@pytest.mark.slow
def test_float32_certificate_verifies(tmp_path, robot, capsules):
    import larc_jax as lj

    traj = lj.read_trajectory(REACH, robot)
    scene = lj.read_scene(CELL)
    result = lj.certify([traj], scene, robot, capsules, max_depth=int(DEPTH), dtype=np.float32)
    assert result.dtype == "float32" and result.certified[0]
    path = lj.write_certificate(tmp_path / "f32.json", result, [traj], scene, robot, capsules,
                                trajectory_files=[REACH], scene_files=[CELL])
    report = lj.verify_certificate(path)
    assert report.checked == 1 and report.min_excess_m > 0


def test_deferred_jax_registers_the_pytrees_when_jax_is_used():
    """After the checker deferred JAX, the first JAX module of the library registers the pytrees."""
    code = ("import sys\nimport larc_jax\nassert 'jax' not in sys.modules\nimport larc_jax.products.verify\n"
            "from larc_jax.enclosure.robot_file import load_robot_file\nrobot, caps = load_robot_file()\n"
            "assert 'jax' not in sys.modules\nimport larc_jax.engine.batch\nimport jax\n"
            "assert len(jax.tree.leaves(robot)) == 5 and len(jax.tree.leaves(caps)) == 4\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode == 0, proc.stderr


# ----------------------------------------------------------------------------------------------
# What the run assumed: the hull cascade, the gripper state, tracking tolerance, self-collision
# ----------------------------------------------------------------------------------------------


def test_hull_leaves_are_rechecked_with_the_cascade(cli_cert, tmp_path, capsys):
    """The default certificate (the cascade) has leaves only the hull stage passes: the checker
    re-runs the cascade's reference on them, and an edited hull-leaf clearance is refuted. With 1 mm
    of padding (with the cascade's default, none, the capsule test passes all of reach_left)."""
    path = tmp_path / "padded.json"
    assert main(["certify", REACH, "--scene", CELL, "--max-depth", DEPTH, "--padding", "0.001", "--certificate",
                 str(path), "-q"]) == EXIT_OK
    doc = json.loads(path.read_text())
    assert _verify(path) == EXIT_OK
    capsys.readouterr()
    stages = doc["trajectories"][0]["leaves"]["stage"]
    assert doc["parameters"]["enclosure"] == "hull" and 2 in stages, stages
    j = stages.index(2)
    assert _verify(_edited(tmp_path, doc, _set_leaf("clearance_m", j, lambda s: hexf(unhexf(s) + 1e-4)))) == \
        EXIT_REFUTED
    assert f"leaf {j} " in capsys.readouterr().err
    # Near the guard a hull leaf's stored clearance may be below the reference's (the engine and
    # the reference may pass it at different stages): one claiming less verifies; a capsule leaf
    # there claiming less is refuted.
    lv = doc["trajectories"][0]["leaves"]
    slack = [unhexf(g) - unhexf(gd) for g, gd in zip(lv["clearance_m"], lv["guard_m"])]
    near = [i for i, (st, sl) in enumerate(zip(stages, slack)) if sl < CULL_SLACK_M / 2 - 1e-3]
    hull, caps = [i for i in near if stages[i] == 2], [i for i in near if stages[i] == 1]
    assert hull and caps, (stages, slack)
    assert _verify(_edited(tmp_path, doc, _set_leaf("clearance_m", hull[0], lambda s: hexf(unhexf(s) - 1e-4)))) == \
        EXIT_OK
    assert _verify(_edited(tmp_path, doc, _set_leaf("clearance_m", caps[0], lambda s: hexf(unhexf(s) - 1e-4)))) == \
        EXIT_REFUTED
    assert "is below the recomputed" in capsys.readouterr().err
    # The same certificate claimed with the capsule test alone does not hold (its hull guards and
    # that leaf disagree with the capsule test).
    assert _verify(_edited(tmp_path, doc, lambda d: d["parameters"].update(enclosure="capsules"))) == EXIT_REFUTED


def test_stated_gripper_tolerance_and_self_collision_are_rechecked(tmp_path, capsys):
    """--hold, --tracking-tolerance and --self-collision are recorded and re-checked: the
    certificate verifies, and claiming a looser assumption (the opening, a smaller tolerance, a
    larger self margin) is refuted or rejected."""
    path = tmp_path / "c.json"
    rc = main(["certify", REACH, "--scene", CELL, "--max-depth", DEPTH, "--hold", "joint7=0", "--hold", "joint8=0",
               "--tracking-tolerance", "0.002", "--self-collision", "--certificate", str(path), "-q"])
    assert rc == EXIT_OK
    doc = json.loads(path.read_text())
    assert set(doc["robot"]["stated_joints"]) == {"joint7", "joint8"}
    assert doc["parameters"]["tracking_tolerance"] == 0.002 and doc["parameters"]["self_collision"] is True
    assert _verify(path) == EXIT_OK
    capsys.readouterr()
    edits = [
        lambda d: d["robot"]["stated_joints"].update(joint7=hexf(-0.038)),  # another opening
        lambda d: d["parameters"].update(tracking_tolerance=0.0),
        lambda d: d["parameters"].update(self_margin_m=0.5),
        lambda d: d["parameters"].update(hold={"joint7": 0.0}),  # joint8 no longer stated
    ]
    for edit in edits:
        rc = _verify(_edited(tmp_path, doc, edit))
        err = capsys.readouterr().err
        assert rc in (EXIT_REFUTED, EXIT_BAD_INPUT) and "Traceback" not in err, err
