"""The per-kind tightness driver (experiments.tightness_kinds): its windows are what larc reads,
its truth's pruning bounds hold against FCL for every kind, and end to end (--quick) no path
certified comes within rho of its obstacles by FCL's measure."""

from __future__ import annotations

import json

import numpy as np
import pytest

from experiments import tightness_kinds as tk


@pytest.fixture(scope="module")
def windows(tmp_path_factory):
    return tk.write_scenes(tmp_path_factory.mktemp("windows"), tk.KINDS)


def test_every_window_is_read_as_written(windows):
    import larc_jax as lj

    for kind, path in windows.items():
        scene = lj.read_scene(path)
        groups = tk.fcl_groups(tk.scene_entries(path), path.parent)
        objects = sum(len(g.objects) for g in groups)
        if kind in ("box", "sphere", "cylinder"):
            assert scene.shapes.kinds == (kind,) * objects and objects == len(groups) and not scene.point_sets.count
            R = tk.quaternion_matrix(tk.scene_entries(path)[0]["pose"]["orientation"])
            np.testing.assert_allclose(scene.shapes.R_world_shape[0], R, atol=1e-15)
        elif kind == "mesh":
            assert scene.point_sets.kinds == ("mesh",) and scene.point_sets.solid == (False,)  # a surface
            lo, hi = np.min([g.lo for g in groups], 0), np.max([g.hi for g in groups], 0)
            pts = np.concatenate(scene.point_sets.pieces)
            assert (pts >= lo - 1e-12).all() and (pts <= hi + 1e-12).all()  # larc's pieces where FCL's triangles are
            np.testing.assert_allclose(pts.min(0), lo, atol=1e-12)
            np.testing.assert_allclose(pts.max(0), hi, atol=1e-12)
        else:
            assert scene.point_sets.radius == (tk.POINT_RADIUS_M,) and objects == len(np.load(path.parent / tk.CLOUD_NAME))
            assert len(scene.point_sets.pieces) >= 256  # a scene the engine culls
    with pytest.raises(ValueError, match="unknown kind"):
        tk.kind_entries("octomap")


def test_the_truths_pruning_bounds_hold_for_every_kind(windows, robot):
    """Capsule distance to a group's box <= FCL's mesh distance to the group, for every link and
    group (framed boxes and cylinders included); the vertex bound >= FCL's least distance."""
    import fcl

    from experiments.mesh_truth import MeshTruth

    truth = MeshTruth()
    rng = np.random.default_rng(5)
    lo, hi = np.array([-1.0, 0.2, -1.5, -1.0, -1.0, -1.0]), np.array([1.0, 2.0, 0.0, 1.0, 1.0, 1.0])
    for kind in ("box", "cylinder", "mesh", "points"):
        path = windows[kind]
        ob = tk.truth_obstacles(tk.fcl_groups(tk.scene_entries(path), path.parent))
        Q = rng.uniform(lo, hi, (2, truth.robot.n_joints))
        lb = truth.capsule_lower_bounds(Q, ob)
        for i, q in enumerate(Q):
            near = lb[i] < lb[i].min() + 0.05  # FCL on the nearest groups (the rest: a bounded cost)
            d, _ = truth.distance(q, ob, near)
            assert (lb[i][near] <= d[near] + 1e-9).all(), kind
            if kind == "box":
                every, _ = truth.distance(q, ob)
                assert truth.vertex_upper_bound(Q[i:i + 1], ob) >= every.min() - 1e-9
        assert ob.framed().any() == (kind in ("box", "cylinder"))
    del fcl


@pytest.mark.slow
def test_quick_run_certifies_only_what_fcl_clears(tmp_path):
    import pandas as pd

    assert tk.main(["--quick", "--out", str(tmp_path), "--workers", "1"]) == 0
    truth = pd.read_csv(tmp_path / "truth.csv").set_index("traj_id")
    cert = pd.read_csv(tmp_path / "certification.csv")
    assert set(truth["kind"]) == {"box", "points"} and len(cert) == len(truth) * len(tk.CONFIGS)
    for _, r in cert[cert["certified"]].iterrows():  # soundness, by FCL's measure on the meshes
        assert truth.loc[r["traj_id"], "truth_m"] > tk.MARGIN_M, r["traj_id"]
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["within_rho_certified_any"] == 0 and set(summary["kinds"]) == {"box", "points"}
    goal = (tmp_path / "goal.md").read_text()
    assert "| box |" in goal and "| points |" in goal and "| all |" in goal
    # A second run redoes nothing.
    stamps = {f: f.stat().st_mtime_ns for f in tmp_path.rglob("*") if f.is_file()}
    assert tk.main(["--quick", "--out", str(tmp_path), "--workers", "1"]) == 0
    assert {f: f.stat().st_mtime_ns for f in tmp_path.rglob("*") if f.is_file()} == stamps
