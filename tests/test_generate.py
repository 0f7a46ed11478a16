"""Stage B generation (OMPL + TOPP-RA + FCL recheck), the direct control, and the FCL audit."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("fcl")
pytest.importorskip("ompl")
pytest.importorskip("toppra")

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def config():
    from experiments.common import load_config

    return load_config(ROOT / "configs" / "stageB.yaml")


@pytest.fixture(scope="module")
def generated(config, tmp_path_factory):
    from experiments.generate import generate_scene, write_combined_attempts

    out = tmp_path_factory.mktemp("gen")
    summary = generate_scene("easy_window", config, out, n_pairs=1, max_attempts=6, progress=False)
    write_combined_attempts(out, ["easy_window"])
    return out, summary


def test_protocol_file(config):
    for key, value in dict(pairs_per_scene=20, margin_m=0.01, max_depth=9, coarse_depth=4,
                           audit_hz=250, recheck_hz=50, timing_seed=20270824, timing_repeats=3,
                           workspace_seed=20270823, workspace_samples=6000,
                           velocity_scaling=0.1, acceleration_scaling=0.1).items():
        assert config[key] == value, key
    assert list(config["scenes"]) == ["open", "easy_window", "medium_window", "easy_shelf"]
    seeds = [s["seed"] for s in config["scenes"].values()]
    assert len(set(seeds)) == len(seeds)
    for s in config["scenes"].values():
        assert (ROOT / s["file"]).is_file()
    g = config["generation"]
    # The planner's only limit is a count (no wall-clock limit: the dataset must not depend on load).
    assert "planner_time_limit_s" not in g and g["planner_max_validity_checks"] > 0
    assert g["max_attempts_per_scene"] >= 20


def test_generation_writes_valid_files(generated, robot, config):
    from larc_jax.model.trajectory_files import read_trajectory

    out, summary = generated
    assert summary["n_pairs_accepted"] == 1
    folder = out / "trajectories" / "easy_window"
    planned = read_trajectory(folder / "easy_window_p00_ompl_planned.yaml", robot)
    direct = read_trajectory(folder / "easy_window_p00_direct_smoothstep.yaml", robot)
    rows = list(csv.DictReader((out / "attempts.csv").open()))
    assert len(rows) == summary["attempts"]
    acc = [r for r in rows if r["outcome"] == "accepted"]
    assert len(acc) == 1 and acc[0]["pair"] == "easy_window_p00"
    assert {r["outcome"] for r in rows} <= {"accepted", "invalid_start", "invalid_goal",
                                            "planning_failure", "hermite_recheck_failure"}
    assert float(acc[0]["duration_s"]) == pytest.approx(planned.duration, abs=1e-8)
    assert int(acc[0]["n_waypoints"]) == planned.n_waypoints
    # Recorded endpoints are the attempt's start and goal, at rest; within the MoveIt limits.
    start = np.array([float(x) for x in acc[0]["start"].split()])
    goal = np.array([float(x) for x in acc[0]["goal"].split()])
    np.testing.assert_allclose(planned.q[0], start, atol=1e-12)
    np.testing.assert_allclose(planned.q[-1], goal, atol=1e-12)
    assert np.abs(planned.qd[[0, -1]]).max() == 0.0
    # Velocity limits (0.1 x yaml) hold at the recorded waypoints (small TOPP-RA tolerance).
    assert np.abs(planned.qd).max() <= 0.5 * 1.02
    # Start and goal are on opposite sides of the wall (gripper-base point).
    from larc_jax.model.robot import forward_kinematics_np

    xs = sorted(forward_kinematics_np(robot, q)[robot.link_index("link7")][0, 3] for q in (start, goal))
    assert xs[0] <= 0.15 and xs[1] >= 0.29
    # The control: same endpoints, duration and waypoint count; zero end velocities.
    assert direct.duration == pytest.approx(planned.duration, abs=1e-9)
    assert direct.n_waypoints == planned.n_waypoints
    np.testing.assert_allclose(direct.q[0], planned.q[0], atol=1e-12)
    np.testing.assert_allclose(direct.q[-1], planned.q[-1], atol=1e-12)
    assert np.abs(direct.qd[[0, -1]]).max() == 0.0
    np.testing.assert_allclose(np.diff(direct.t), direct.duration / (direct.n_waypoints - 1), atol=2e-9)


def test_accepted_trajectory_passes_audit(generated, robot, config):
    from experiments.audit import audit_trajectory
    from experiments.collision import CollisionModel, SceneBoxes
    from experiments.self_collision import load_allowed_pairs
    from larc_jax.model.trajectory_files import read_trajectory

    out, _ = generated
    model = CollisionModel(robot)
    boxes = SceneBoxes.from_file(ROOT / config["scenes"]["easy_window"]["file"])
    allowed = load_allowed_pairs(ROOT / config["allowed_collisions"], robot)
    traj = read_trajectory(out / "trajectories" / "easy_window" / "easy_window_p00_ompl_planned.yaml", robot)
    res = audit_trajectory(traj, boxes, model, hz=250, allowed_pairs=allowed)
    assert res["audit_states"] >= int(traj.duration * 250)
    assert res["audit_collision"] is False and res["first_collision_t"] is None
    assert res["self_collision"] is False
    # The same trajectory against a box around the start pose collides at t = 0.
    from larc_jax.model.robot import forward_kinematics_np

    p = forward_kinematics_np(robot, traj.q[0])[robot.link_index("link6")][:3, 3]
    hit = audit_trajectory(traj, (p[None] - 0.03, p[None] + 0.03), model, hz=250, allowed_pairs=allowed)
    assert hit["audit_collision"] is True and hit["first_collision_t"] == 0.0


def test_resume_skips_finished_scene(generated, config):
    from experiments.generate import generate_scene

    out, summary = generated
    again = generate_scene("easy_window", config, out, n_pairs=1, max_attempts=6, progress=False)
    assert again.get("skipped") is True and again["fingerprint"] == summary["fingerprint"]


def test_attempts_are_reproducible(config):
    from experiments.generate import SceneContext, attempt_endpoints

    ctx = SceneContext("medium_window", config)
    seed = config["scenes"]["medium_window"]["seed"]
    a = attempt_endpoints(ctx, seed, 5)
    b = attempt_endpoints(ctx, seed, 5)
    c = attempt_endpoints(ctx, seed, 6)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    assert a[2] == b[2] and not np.array_equal(a[0], c[0])
    lo, hi = ctx.limits["lo"], ctx.limits["hi"]
    assert ((a[0] >= lo) & (a[0] <= hi)).all()


def test_smoothstep_and_hermite_helpers():
    from experiments.generate import hermite_states, smoothstep_trajectory

    q0, q1 = np.zeros(6), np.linspace(0.1, 0.6, 6)
    tr = smoothstep_trajectory(q0, q1, 4.0, 41, [f"joint{i}" for i in range(1, 7)])
    u = tr.t / 4.0
    np.testing.assert_allclose(tr.q, np.outer(3 * u**2 - 2 * u**3, q1), atol=1e-12)
    np.testing.assert_allclose(tr.qd, np.outer((6 * u - 6 * u**2) / 4.0, q1), atol=1e-12)
    ts, Q = hermite_states(tr.t, tr.q, tr.qd, 50)
    assert ts[0] == 0.0 and ts[-1] == 4.0 and len(ts) == 201
    # Cubic Hermite reproduces a cubic exactly.
    uu = ts / 4.0
    np.testing.assert_allclose(Q, np.outer(3 * uu**2 - 2 * uu**3, q1), atol=1e-12)
