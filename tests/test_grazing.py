"""The committed grazing corpus (``python -m experiments.grazing``): every trajectory comes within
rho of its thin box only between 250 Hz samples. The sampled FCL audit calls each one clear,
FCL at the recorded witness time shows the meshes within rho, and LARC refuses every one."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
CORPUS = ROOT / "results" / "grazing"


@pytest.fixture(scope="module")
def corpus(robot):
    import larc_jax as lj

    summary = json.loads((CORPUS / "summary.json").read_text())
    cases = summary["trajectories"]
    trajs = [lj.read_trajectory(CORPUS / c["trajectory"], robot) for c in cases]
    scenes = [lj.read_scene(CORPUS / c["scene"], frame=robot.link_names[0]) for c in cases]
    return summary, cases, trajs, scenes


@pytest.fixture(scope="module")
def fcl_model(robot):
    pytest.importorskip("fcl")
    from experiments.collision import CollisionModel

    return CollisionModel(robot)


def test_summary_counts(corpus):
    summary, cases, _, _ = corpus
    assert summary["cases"] == len(cases) >= 20
    for key in ("sampled_clear", "within_margin_between_samples", "larc_refused"):
        assert summary[key] == len(cases), key
    assert summary["collide_between_samples"] == sum(c["witness_collision"] for c in cases)


def test_sampled_audit_calls_each_clear(corpus, fcl_model):
    from experiments.audit import audit_times, audit_trajectory
    from experiments.collision import SceneBoxes
    from experiments.grazing import sampled_min_distance

    summary, cases, trajs, scenes = corpus
    rho, hz = summary["margin_m"], summary["audit_hz"]
    assert hz == 250.0
    for c, traj, scene in zip(cases, trajs, scenes):
        boxes = SceneBoxes.from_scene(scene)
        audit = audit_trajectory(traj, boxes, fcl_model, hz)
        assert not audit["audit_collision"], c["id"]
        d, _ = sampled_min_distance(fcl_model, traj, boxes, audit_times(traj.t, hz))
        assert d > rho, c["id"]  # no audit sample even within rho


def test_each_case_comes_within_rho_between_samples(corpus, fcl_model):
    from scipy.interpolate import CubicHermiteSpline

    from experiments.audit import audit_times
    from experiments.collision import SceneBoxes

    summary, cases, trajs, scenes = corpus
    rho = summary["margin_m"]
    for c, traj, scene in zip(cases, trajs, scenes):
        t = c["witness_t"]
        samples = audit_times(traj.t, summary["audit_hz"])
        assert np.min(np.abs(samples - t)) > 1e-4, c["id"]  # strictly between two audit samples
        q = CubicHermiteSpline(traj.t, traj.q, traj.qd, axis=0)(t)
        d = fcl_model.min_distance(q, SceneBoxes.from_scene(scene))
        assert d < rho, c["id"]
        assert np.isclose(d, c["witness_distance_m"], atol=1e-9) or d < 0, c["id"]
        assert fcl_model.scene_collision(q, SceneBoxes.from_scene(scene)) == c["witness_collision"], c["id"]


def test_larc_refuses_every_case(corpus, robot, capsules):
    import larc_jax as lj

    summary, cases, trajs, scenes = corpus
    result = lj.certify(trajs, scenes, robot, capsules, margin=summary["margin_m"])
    assert not result.certified.any(), [c["id"] for c, ok in zip(cases, result.certified) if ok]
    for i, c in enumerate(cases):  # the refused leaf holds the witness time
        rows = result.leaves
        sl = result.leaf_slice(i)
        bad = ~rows.certified[sl]
        t0, t1 = rows.t0[sl][bad], rows.t1[sl][bad]
        assert np.any((t0 <= c["witness_t"]) & (c["witness_t"] <= t1)), c["id"]


def test_readme_states_the_generated_counts(corpus):
    summary, cases, _, _ = corpus
    readme = (ROOT / "README.md").read_text()
    for phrase in (f"holds {summary['cases']} PIPER trajectories",
                   f"audit calls {summary['sampled_clear']} of {summary['cases']} clear",
                   f"finds all {summary['within_margin_between_samples']} within",
                   f"({summary['collide_between_samples']} of them in collision)",
                   f"LARC refuses {summary['larc_refused']} of {summary['cases']}",
                   f"ρ = {summary['margin_m'] * 1000:g} mm"):
        assert phrase in " ".join(readme.split()), phrase
    speeds = [c["speed_at_witness_m_s"] for c in cases]
    assert 5 <= min(speeds) and max(speeds) <= 13  # "tip speeds of 5–13 m/s"
