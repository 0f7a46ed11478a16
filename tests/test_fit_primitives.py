"""`larc fit-capsules` on links made of primitives: a part that cannot be split keeps one capsule
(main crashed with AttributeError in _fit_one for --n-capsules and --capsules-per-link LINK=2)."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

from larc_jax import LarcInputError
from larc_jax.drivers.cli import main as larc_main
from larc_jax.enclosure import fit_capsules, load_robot_file, verify_containment
from larc_jax.model.urdf import load_robot

URDF = """<?xml version="1.0"?>
<robot name="primitives">
  <link name="base"><collision><geometry><box size="0.3 0.3 0.05"/></geometry></collision></link>
  <link name="post">
    <collision><origin xyz="0 0 0.15"/><geometry><cylinder radius="0.04" length="0.3"/></geometry></collision>
  </link>
  <link name="block"><collision><geometry><box size="0.1 0.06 0.2"/></geometry></collision></link>
  <link name="arm">
    <collision><origin xyz="0.1 0 0"/><geometry><box size="0.2 0.05 0.05"/></geometry></collision>
    <collision><origin xyz="0.3 0 0" rpy="0 1.5708 0"/><geometry><cylinder radius="0.03" length="0.2"/></geometry></collision>
  </link>
  <link name="tip"><collision><geometry><sphere radius="0.03"/></geometry></collision></link>
  <joint name="j1" type="revolute"><parent link="base"/><child link="post"/><origin xyz="0 0 0.025"/>
    <axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="j2" type="revolute"><parent link="post"/><child link="block"/><origin xyz="0 0 0.3"/>
    <axis xyz="0 1 0"/><limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
  <joint name="j3" type="revolute"><parent link="block"/><child link="arm"/><origin xyz="0 0 0.1"/>
    <axis xyz="0 1 0"/><limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
  <joint name="j4" type="revolute"><parent link="arm"/><child link="tip"/><origin xyz="0.4 0 0"/>
    <axis xyz="1 0 0"/><limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
</robot>
"""


def write_primitive_urdf(folder: Path) -> Path:
    """A 4-joint arm made of primitives only (no mesh files): one box, cylinder or sphere per
    link, and one link ('arm') of two primitives, the only one that can be split."""
    path = folder / "primitives.urdf"
    path.write_text(URDF)
    return path


def test_n_capsules_splits_only_what_can_be_split(tmp_path):
    robot = load_robot(write_primitive_urdf(tmp_path))
    fitted = fit_capsules(robot, n_capsules=6)
    assert sorted(f.name for f in fitted) == ["arm_a", "arm_b", "base", "block", "post", "tip"]
    with pytest.raises(LarcInputError, match=r"cannot fit 7 capsules .* between 5 and 6 .*cannot be split: base, "
                                             r"block, post, tip"):
        fit_capsules(robot, n_capsules=7)
    with pytest.raises(LarcInputError, match="cannot fit 4 capsules"):
        fit_capsules(robot, n_capsules=4)


def test_forced_split_of_one_primitive_keeps_one_capsule(tmp_path, caplog):
    robot = load_robot(write_primitive_urdf(tmp_path))
    with caplog.at_level(logging.WARNING, logger="larc_jax"):
        fitted = fit_capsules(robot, capsules_per_link={"post": 2, "tip": 2, "arm": 2})
    assert sorted(f.name for f in fitted) == ["arm_a", "arm_b", "base", "block", "post", "tip"]
    assert "link 'post' has 1 collision element that cannot be split in two: it keeps one capsule" in caplog.text
    with pytest.raises(LarcInputError, match="capsules_per_link: link 'nowhere' is not a link with collision"):
        fit_capsules(robot, capsules_per_link={"nowhere": 2})


@pytest.mark.parametrize("args", [["--n-capsules", "6"], ["--capsules-per-link", "post=2"],
                                  ["--n-capsules", "5", "--capsules-per-link", "block=2"]])
def test_fit_capsules_command_on_primitives(tmp_path, capsys, args):
    urdf = write_primitive_urdf(tmp_path)
    out = tmp_path / "robot.yaml"
    rc = larc_main(["fit-capsules", str(urdf), "-o", str(out), *args])
    _, err = capsys.readouterr()
    assert rc == 0, err
    robot, capsules = load_robot_file(out)
    assert verify_containment(robot, capsules) and set(capsules.link_names) == {"base", "post", "block", "arm", "tip"}
    assert larc_main(["-q", "verify-capsules", str(out)]) == 0


def test_fit_capsules_command_bad_requests(tmp_path, capsys):
    urdf = write_primitive_urdf(tmp_path)
    out = tmp_path / "robot.yaml"
    assert larc_main(["fit-capsules", str(urdf), "-o", str(out), "--n-capsules", "9"]) == 2
    assert "cannot fit 9 capsules" in capsys.readouterr().err
    assert larc_main(["fit-capsules", str(urdf), "-o", str(out), "--capsules-per-link", "link6=2"]) == 2
    assert "link 'link6' is not a link with collision geometry" in capsys.readouterr().err
    for bad, message in ((["--padding", "nan"], "--padding nan: must be a finite number >= 0 m"),  # was exit 3
                         (["--capsules-per-link", "post=\u00b2"], "--capsules-per-link 'post=\u00b2'"),  # was exit 3
                         (["--hold", "j4"], "--hold 'j4': expected JOINT=VALUE"),
                         (["--package-dir", "nothing"], "--package-dir 'nothing': expected NAME=PATH")):
        assert larc_main(["fit-capsules", str(urdf), "-o", str(out), *bad]) == 2
        assert f"larc: error: {message}" in capsys.readouterr().err
    assert larc_main(["fit-capsules", str(urdf), "-o", str(tmp_path)]) == 2
    assert "is a directory" in capsys.readouterr().err
    assert not out.exists()


SLIDER = """<?xml version="1.0"?>
<robot name="slider">
  <link name="base"><collision><geometry><box size="0.1 0.1 0.05"/></geometry></collision></link>
  <link name="turn"><collision><geometry><cylinder radius="0.03" length="0.1"/></geometry></collision></link>
  <link name="carriage"><collision><geometry><box size="0.05 0.05 0.05"/></geometry></collision></link>
  <joint name="spin" type="revolute"><parent link="base"/><child link="turn"/><origin xyz="0 0 0.05"/>
    <axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="slide" type="prismatic"><parent link="turn"/><child link="carriage"/><origin xyz="0 0 0.1"/>
    <axis xyz="1 0 0"/><limit lower="0" upper="0.2" effort="1" velocity="1"/></joint>
</robot>
"""


def test_prismatic_curve_beyond_its_limits_is_refused(tmp_path):
    """The motion constant of 'spin' assumes the carriage within its stroke [0, 0.2] m; waypoints
    within it whose velocities carry the Hermite curve beyond 0.2 m would be under-inflated (main
    accepted them). Refused, naming the segment and joint; a curve inside the stroke is fine."""
    import numpy as np

    from larc_jax import Scene, Trajectory, certify

    (tmp_path / "slider.urdf").write_text(SLIDER)
    out = tmp_path / "slider.yaml"
    assert larc_main(["-q", "fit-capsules", str(tmp_path / "slider.urdf"), "-o", str(out)]) == 0
    robot, capsules = load_robot_file(out)
    over = Trajectory(t=[0.0, 1.0], q=[[0.0, 0.1], [0.0, 0.2]], qd=[[0.0, 1.0], [0.0, 1.0]],
                      joint_names=["spin", "slide"])
    with pytest.raises(LarcInputError, match=r"between points\[0\].positions\[1\] and points\[1\].positions\[1\] the "
                                             r"Hermite curve of prismatic joint slide reaches 0.2\d+, outside its limits"):
        certify(over, Scene.empty(), robot, capsules)
    inside = Trajectory(t=[0.0, 1.0], q=[[0.0, 0.0], [1.0, 0.2]], qd=[[0.0, 0.0], [0.0, 0.0]],
                        joint_names=["spin", "slide"])
    assert certify(inside, Scene.empty(), robot, capsules)[0].certified
    assert np.asarray(capsules.motion_a)[list(capsules.names).index("carriage"), 0] > 0.2



def test_fit_robot_file_from_python(tmp_path):
    """fit_robot_file (what `larc fit-capsules` runs) from Python: a held finger-like prismatic
    joint gives stated capsules, paths are relative to the file's folder, and the file passes
    `larc verify-capsules`'s proof of every enclosure it gives."""
    from larc_jax import fit_robot_file
    from larc_jax.enclosure.proof import prove_robot_file

    (tmp_path / "slider.urdf").write_text(SLIDER)
    out = tmp_path / "robots" / "slider.yaml"
    steps = []
    fit = fit_robot_file(tmp_path / "slider.urdf", out, active_joints=["spin"], held_joint_values={"slide": 0.1},
                         progress=steps.append)
    assert fit.path == out and [f.name for f in fit.fitted] == ["base", "turn", "carriage"]
    assert {"fitting carriage", "splitting turn", "proving base"} <= set(steps)
    assert "urdf: ../slider.urdf" in out.read_text() and fit.elements_proven > 0
    assert fit.table_lines()[-1] == f"wrote {out}: 3 capsules; containment proven for {fit.elements_proven} mesh elements"
    proof = prove_robot_file(out)
    assert (proof.capsules, proof.stated_capsules, proof.links) == (3, 1, 3)
    robot, capsules = load_robot_file(out)
    assert robot.active_joint_names == fit.robot.active_joint_names == ("spin",)
    assert capsules.names == fit.capsules.names


def test_fit_robot_file_refuses_before_the_work_and_never_leaves_an_unproven_file(tmp_path, monkeypatch):
    from larc_jax import fit_robot_file
    from larc_jax.enclosure import fit_robot

    urdf = tmp_path / "slider.urdf"
    urdf.write_text(SLIDER)
    out = tmp_path / "robot.yaml"
    for padding in (float("nan"), -0.001, True):
        with pytest.raises(LarcInputError, match=r"^padding_m .*: must be a finite number >= 0 m"):
            fit_robot_file(urdf, out, padding_m=padding)
    with pytest.raises(LarcInputError, match="is a directory"):
        fit_robot_file(urdf, tmp_path)

    def not_contained(robot, capsules, **kwargs):
        raise LarcInputError("link 'carriage' element 0 is not inside any of its capsules")

    out.write_text("an older robot file\n")
    monkeypatch.setattr(fit_robot, "verify_containment", not_contained)
    with pytest.raises(LarcInputError, match="not inside"):
        fit_robot_file(urdf, out)
    assert not out.exists()
