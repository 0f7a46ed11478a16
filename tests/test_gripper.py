"""The gripper state: stated openings (held joints placed by FK), the whole stroke otherwise,
active fingers; API, robot file and command line."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

import larc_jax as lj
from larc_jax import LarcInputError
from larc_jax.drivers.cli import main
from larc_jax.enclosure import link_elements
from larc_jax.enclosure.fit import point_segment_distance
from larc_jax.enclosure.hull import hull_model
from larc_jax.enclosure.meshes import held_joint_states, stroke_shifts
from larc_jax.enclosure.robot_file import load_robot_file
from larc_jax.model.robot import forward_kinematics_np
from larc_jax.model.urdf import load_robot

HOLD = {"joint7": 0.0, "joint8": 0.0}


@pytest.fixture(scope="module")
def stated():
    return load_robot_file(None, hold=HOLD)


def _finger_world(robot, q_arm, link, opening_robot):
    """The finger's own mesh vertices in the world at the opening of ``opening_robot``."""
    i = robot.link_index(link)
    own = link_elements(opening_robot, link)[:, :3].reshape(-1, 3)
    T = forward_kinematics_np(opening_robot, q_arm)[i]
    return own @ T[:3, :3].T + T[:3, 3]


def test_stroke_enclosures_hold_every_sampled_opening(robot, capsules):
    """Without a stated opening the finger capsules and hulls, placed by FK at the recorded
    value, contain the finger mesh at 40 sampled openings of its stroke."""
    hulls = hull_model(robot, capsules.hull_parts, capsules.padding_m)
    q = np.array([0.3, 1.0, -1.2, 0.2, 0.5, 0.4])
    rng = np.random.default_rng(0)
    for link, joint in (("link7", "joint7"), ("link8", "joint8")):
        c = capsules.names.index(link)
        p = hulls.names.index(link)
        T = forward_kinematics_np(robot, q)[robot.link_index(link)]
        for value in np.r_[rng.uniform(-0.038, 0.0, 38), -0.038, 0.0] * (1 if joint == "joint7" else -1):
            at = load_robot(held_joint_values={joint: float(value)}, stated_joints=[joint])
            X = _finger_world(robot, q, link, at)
            local = (X - T[:3, 3]) @ T[:3, :3]  # in the link frame at the recorded value
            d = point_segment_distance(local, np.asarray(capsules.p_link_a[c]), np.asarray(capsules.p_link_b[c]))
            assert d.max() <= capsules.radius[c] - capsules.padding_m + 1e-12
            from larc_jax.enclosure.hull import verify_support

            V = np.asarray(hulls.vertices[p])[: hulls.n_vertices[p]]
            assert verify_support(local, V, float(hulls.radius[p]) - hulls.padding_m, n_dirs=512) <= 1e-12


def test_widened_fit_beats_mid_stroke_plus_half_stroke(robot, capsules, stated):
    """The stroke capsule (fitted to the widened finger) is smaller than the alternative
    construction: the finger's own capsule at mid-stroke inflated by half the stroke (19 mm)."""
    _, caps = stated
    for link in ("link7", "link8"):
        stroke_c, own_c = capsules.names.index(link), caps.names.index(link)
        assert capsules.radius[stroke_c] < caps.radius[own_c] + 0.019
        length = lambda m, k: np.linalg.norm(np.asarray(m.p_link_b[k]) - np.asarray(m.p_link_a[k]))  # noqa: E731
        vol = lambda r, l: np.pi * r * r * l + 4 / 3 * np.pi * r**3  # noqa: E731
        assert vol(capsules.radius[stroke_c], length(capsules, stroke_c)) < vol(caps.radius[own_c] + 0.019,
                                                                                length(caps, own_c))


def test_stated_opening_uses_the_fingers_own_capsules(robot, capsules, stated):
    robot_s, caps_s = stated
    assert robot_s.stated_joints == ("joint7", "joint8") and robot_s.stroke_joints == ()
    assert len(stroke_shifts(robot, "link7")) == 3 and len(stroke_shifts(robot_s, "link7")) == 1
    for link in ("link7", "link8"):
        assert caps_s.radius[caps_s.names.index(link)] < capsules.radius[capsules.names.index(link)] - 0.008
    lj.verify_containment(robot_s, caps_s)  # the stated capsules hold the fingers alone
    assert held_joint_states(robot_s) == (("joint7", "stated", 0.0, 0.0), ("joint8", "stated", 0.0, 0.0))
    assert held_joint_states(robot) == (("joint7", "stroke", -0.038, 0.0), ("joint8", "stroke", 0.0, 0.038))
    # An open gripper: the fingers move 15 mm apart each, FK places them there.
    r_open, c_open = load_robot_file(None, hold={"joint7": -0.015, "joint8": 0.015})
    q = np.array([0.0, 1.0, -1.0, 0.0, 0.3, 0.0])
    i7 = robot.link_index("link7")
    moved = forward_kinematics_np(r_open, q)[i7][:3, 3] - forward_kinematics_np(robot_s, q)[i7][:3, 3]
    assert np.linalg.norm(moved) == pytest.approx(0.015)
    lj.verify_containment(r_open, c_open)


def test_certificate_at_a_stated_opening_is_sound(stated):
    """A box at least 15 mm from the open finger's mesh (5 mm beyond rho): certified with the
    opening stated, and the mesh really clears rho at every sampled time."""
    r_open, c_open = load_robot_file(None, hold={"joint7": -0.03, "joint8": 0.03})
    q0 = np.array([0.0, 1.2, -1.1, 0.0, 0.4, 0.0])
    traj = lj.Trajectory(t=np.array([0.0, 1.0]), q=np.stack([q0, q0 + 0.002]), qd=np.zeros((2, 6)),
                         joint_names=r_open.active_joint_names, id="still")
    X = _finger_world(r_open, q0, "link7", r_open)
    T6 = forward_kinematics_np(r_open, q0)[r_open.link_index("link6")]
    side = T6[:3, :3] @ np.array([0.0, -1.0, 0.0])  # joint7 opens along -y of link6 here ...
    side = side if (X - T6[:3, 3]) @ side @ np.ones(len(X)) > 0 else -side  # ... whichever way the finger is
    reach = float((X @ side).max())
    # An axis-aligned box of half-size 50 mm whose support toward the finger is 15 mm beyond it.
    centre = side * (reach + 0.015 + 0.05 * np.abs(side).sum()) + (np.eye(3) - np.outer(side, side)) @ X.mean(0)
    scene = lj.Scene(lo=(centre - 0.05)[None], hi=(centre + 0.05)[None], box_names=("post",))
    res = lj.certify(traj, scene, r_open, c_open, max_depth=12)[0]
    assert res.certified
    from scipy.interpolate import CubicHermiteSpline

    spline = CubicHermiteSpline(traj.t, traj.q, traj.qd)
    for t in np.linspace(0, 1, 200):
        W = _finger_world(r_open, spline(t), "link7", r_open)
        gap = np.maximum(np.maximum(scene.lo[0] - W, W - scene.hi[0]), 0)
        assert np.sqrt((gap * gap).sum(1)).min() > 0.01


def test_active_fingers_are_placed_by_the_trajectory(robot):
    """Finger joints carried by the trajectory: motion constant 1 (prismatic), no stroke copies."""
    r = load_robot(active_joints=[f"joint{i}" for i in range(1, 9)])
    assert r.n_joints == 8 and r.stroke_joints == ()
    assert link_elements(r, "link7").shape[1] == 3
    caps = lj.load_capsules(lj.default_capsule_path(), r)
    a = np.asarray(caps.motion_a)
    k7, k8 = caps.names.index("link7"), caps.names.index("link8")
    assert a[k7, 6] == 1.0 and a[k7, 7] == 0.0 and a[k8, 7] == 1.0 and a[k8, 6] == 0.0
    q = np.zeros((3, 8)) + np.array([0.0, 1.0, -1.0, 0.0, 0.3, 0.0, 0.0, 0.0])
    q[:, 6] = [0.0, -0.02, -0.038]
    q[:, 7] = [0.0, 0.02, 0.038]
    traj = lj.Trajectory(t=np.array([0.0, 1.0, 2.0]), q=q, qd=np.zeros((3, 8)), joint_names=r.active_joint_names)
    res = lj.certify(traj, lj.Scene.empty(), r, caps)
    assert res.certified.all() and res.held_joints == ()


def test_bad_hold_is_named():
    with pytest.raises(LarcInputError, match="joint2"):
        load_robot_file(None, hold={"joint2": 0.1})  # an active joint cannot be held
    with pytest.raises(LarcInputError, match="outside"):
        load_robot_file(None, hold={"joint7": 0.01})  # beyond the stroke
    with pytest.raises(LarcInputError, match="finite"):
        load_robot_file(None, hold={"joint7": float("nan")})


def test_cli_hold_and_enclosure_are_reported(tmp_path, capsys, monkeypatch):
    from pathlib import Path

    ex = Path(__file__).resolve().parent.parent / "configs" / "examples"
    monkeypatch.chdir(tmp_path)
    args = [str(ex / "reach_left.yaml"), "--scene", str(ex / "cell.yaml"), "--json", "out.json", "--leaves", "l.csv"]
    assert main(["certify", *args, "--hold", "joint7=0", "--hold", "joint8=0"]) == 0
    out = capsys.readouterr().out
    assert "gripper: joint7 = 0 (stated), joint8 = 0 (stated)" in out and "capsules then hulls" in out
    doc = json.loads(Path("out.json").read_text())
    assert doc["enclosure"] == "hull" and doc["held_joints"]["joint7"] == {"state": "stated", "value": 0.0}
    import pandas as pd

    assert set(pd.read_csv("l.csv")["stage"].dropna()) <= {"capsule", "hull"}
    assert main(["certify", *args, "--enclosure", "capsules"]) == 0
    out = capsys.readouterr().out
    assert "whole stroke enclosed" in out and "capsules then hulls" not in out
    doc = json.loads(Path("out.json").read_text())
    assert doc["enclosure"] == "capsules" and doc["held_joints"]["joint8"] == {"state": "stroke", "range": [0.0, 0.038]}
    assert main(["certify", *args, "--hold", "joint7"]) == 2
    assert "--hold 'joint7'" in capsys.readouterr().err
    assert main(["certify", *args, "--hold", "joint7=0", "--hold", "joint7=-0.01"]) == 2
    assert "twice" in capsys.readouterr().err


def test_dataclass_replace_keeps_stated(robot):
    r = dataclasses.replace(robot, stated_joints=("joint7",))
    assert r.stroke_joints == ("joint8",)
