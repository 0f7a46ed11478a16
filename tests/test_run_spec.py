"""The run spec (larc_jax.run_spec): validated once, exact JSON round trip, the same run through
``certify(spec=...)`` and keyword arguments, and in the manifest (self-collision and tracking
tolerance included; a resume with another spec refused). Cheap: the reference method (NumPy) only."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import larc_jax as lj
from larc_jax.drivers.cli import main as larc_main
from larc_jax.errors import LarcInputError
from larc_jax.run_spec import RunSpec

from .test_certify import random_scene, random_trajectory
from .test_stream import write_manifest

SPECS = [
    RunSpec(),
    RunSpec(method="fine", margin_m=0.0125, max_depth=7, coarse_depth=2, enclosure="capsules", dtype="float32",
            velocities="finite-difference"),
    RunSpec(tracking_tolerance=0.1 + 0.2, self_collision=True, self_margin_m=1e-3, self_skip=("link1:link6",)),
    RunSpec(tracking_tolerance=(0.001, 0.0, 0.0, 0.0, 0.0, 1 / 3)),
    RunSpec(tracking_tolerance={"joint2": 0.002, "joint1": 0.0}, hold={"joint8": -0.0, "joint7": 0.035},
            joints=("joint1", "joint2"), ignore_links=("base_link",)),
]


@pytest.mark.parametrize("spec", SPECS)
def test_json_round_trip_is_exact(spec):
    text = spec.to_json()
    back = RunSpec.from_json(text)
    assert back == spec and back.to_json() == text
    assert RunSpec.from_dict(json.loads(text)) == spec


@pytest.mark.parametrize("doc,field", [
    ({"margin": 0.01}, "unknown field 'margin'"),
    ({"margin_m": 0}, "margin_m"),
    ({"margin_m": float("nan")}, "margin_m"),
    ({"max_depth": 99}, "max_depth"),
    ({"max_depth": 2.5}, "max_depth"),
    ({"method": "exact"}, "method"),
    ({"enclosure": "spheres"}, "enclosure"),
    ({"dtype": "float16"}, "dtype float16"),
    ({"velocities": "guess"}, "velocities"),
    ({"tracking_tolerance": -0.1}, "tracking_tolerance"),
    ({"tracking_tolerance": {"joint1": "x"}}, r"tracking_tolerance\[joint1\]"),
    ({"self_collision": 1}, "self_collision"),
    ({"self_collision": True, "self_margin_m": -1}, "self_margin_m"),
    ({"self_margin_m": 0.01}, "need self_collision"),
    ({"hold": {"joint7": "open"}}, r"hold\[joint7\]"),
    ({"joints": "joint1"}, "joints"),
])
def test_bad_values_are_refused_naming_the_field(doc, field):
    with pytest.raises(LarcInputError, match=field) as err:
        RunSpec.from_json(json.dumps(doc), "state.json")
    assert str(err.value).startswith("state.json: ") and "\n" not in str(err.value)
    with pytest.raises(LarcInputError, match="not valid JSON"):
        RunSpec.from_json("{", "state.json")


def test_validation_does_not_load_jax():
    code = ("import sys\nfrom larc_jax.run_spec import RunSpec\nRunSpec.from_json(RunSpec(margin_m=0.02).to_json())\n"
            "try:\n    RunSpec(margin_m=-1)\nexcept Exception as e:\n    print(type(e).__name__)\n"
            "assert 'jax' not in sys.modules, 'jax imported'\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                       cwd=Path(__file__).resolve().parent.parent)
    assert p.returncode == 0 and p.stdout.strip() == "LarcInputError", p.stdout + p.stderr


@pytest.fixture(scope="module")
def few(robot):
    rng = np.random.default_rng(19)
    return [random_trajectory(rng, robot, k, max_waypoints=5) for k in range(3)], \
        [random_scene(rng, k % 5) for k in range(3)]


KWARGS = dict(method="reference", max_depth=3, margin=0.012, tracking_tolerance={"joint2": 0.001},
              self_collision=True, self_margin=0.0005)


def test_certify_spec_equals_keyword_arguments(robot, capsules, few):
    trajs, scenes = few
    spec = RunSpec(method="reference", max_depth=3, margin_m=0.012, tracking_tolerance={"joint2": 0.001},
                   self_collision=True, self_margin_m=0.0005)
    a = lj.certify(trajs, scenes, robot, capsules, spec=spec)
    b = lj.certify(trajs, scenes, robot, capsules, **KWARGS)
    pd.testing.assert_frame_equal(a.leaves_dataframe(), b.leaves_dataframe())
    assert list(a.certified) == list(b.certified) and a.spec == b.spec
    assert a.spec.joints == tuple(robot.active_joint_names) and a.spec.margin_m == a.margin_m == 0.012
    assert a.self_margin_m == 0.0005 and dict(a.tracking_tolerance)["joint2"] == 0.001
    with pytest.raises(LarcInputError, match="not both"):
        lj.certify(trajs, scenes, robot, capsules, spec=spec, max_depth=3)
    with pytest.raises(LarcInputError, match="spec must be a RunSpec"):
        lj.certify(trajs, scenes, robot, capsules, spec=spec.to_dict())
    with pytest.raises(LarcInputError, match="spec.joints"):
        lj.certify(trajs, scenes, robot, capsules, spec=RunSpec(method="reference", joints=("joint1",)))


def test_manifest_with_self_collision_and_tolerance_resumes_only_the_same_spec(tmp_path, robot, capsules, few, capsys):
    trajs, scenes = few
    manifest = write_manifest(tmp_path, trajs, scenes)
    out = tmp_path / "r.parquet"
    argv = ["certify", "--manifest", str(manifest), "--out", str(out), "--chunk-size", "2", "--method", "reference",
            "--max-depth", "3", "--margin", "0.012", "--self-collision", "--self-margin", "0.0005",
            "--tracking-tolerance", "joint2=0.001", "--no-fail-on-uncertified"]
    assert larc_main(argv) == 0
    got = pd.read_parquet(out)
    direct = lj.certify([lj.read_trajectory(tmp_path / "data" / f"{t.id}.csv", robot) for t in trajs],
                        [lj.read_scene(tmp_path / "data" / f"scene{k}.yaml") for k in range(len(trajs))],
                        robot, capsules, **KWARGS)
    assert list(got.certified) == list(direct.certified) and list(got.evaluations) == list(direct.evaluations)
    state = json.loads((out / "_larc_manifest.json").read_text())
    spec = RunSpec.from_dict(state["spec"])
    assert spec.self_collision and spec.tracking_tolerance == (("joint2", 0.001),)
    capsys.readouterr()
    assert larc_main(argv) == 0 and "0 chunks now, 2 already done" in capsys.readouterr().out
    changed = [a if a != "0.0005" else "0.001" for a in argv]
    assert larc_main(changed) == 2
    assert "different spec.self_margin_m" in capsys.readouterr().err


@pytest.fixture(scope="module")
def explained(robot, capsules):
    """reach_left in the cell, certified with the hull cascade, a tracking tolerance and the self
    test: its leaves are decided by the capsule test, the hull test and self pairs."""
    from .test_cli import CELL, OK

    scene, traj = lj.read_scene(CELL), lj.read_trajectory(OK, robot)
    spec = RunSpec(method="reference", max_depth=4, tracking_tolerance=0.0005, self_collision=True)
    return scene, traj, spec, lj.certify([traj], scene, robot, capsules, spec=spec)[0]


def test_explain_decides_a_leaf_with_the_results_spec(robot, capsules, explained):
    """explain re-evaluates a leaf with the result's enclosure, tolerance and self test: a leaf the
    hull stage passed is explained as passed by it, with the recorded clearance and guard."""
    from larc_jax.products.explain import explain

    scene, traj, spec, result = explained
    assert result.spec == lj.certify([traj], scene, robot, capsules, spec=spec).spec
    stages = {leaf.stage for leaf in result.leaves}
    assert "hull" in stages or "capsule" in stages
    for leaf in result.leaves[:: max(1, len(result.leaves) // 6)]:
        ex = explain(robot, capsules, traj, scene, result, leaf=leaf)
        assert ex.decided_clearance_m == leaf.clearance_m and ex.guard_m == leaf.guard_m
        assert (ex.stage != "") == leaf.certified
        assert ex.stage == ("self" if leaf.other_capsule else leaf.stage or "")


def _red_shapes(ax):
    """The red boxes and the red polygons without a gid (capsules, shells) of one view."""
    from matplotlib.colors import to_rgb
    from matplotlib.patches import Polygon, Rectangle

    red = to_rgb("#c62828")
    shade = [p for p in ax.patches if tuple(p.get_facecolor()[:3]) == red]
    return ([p for p in shade if isinstance(p, Rectangle)],
            [p for p in shade if isinstance(p, Polygon) and not p.get_gid()])


def test_explain_draws_the_hull_part_or_self_pair_that_decided_the_leaf(robot, capsules, explained):
    """A leaf the hull test decided is drawn with its hull part (the projection of its placed
    vertices), its shell and its box in red, no capsule red; a leaf a self pair decided with both
    capsules of the pair and their shells red, and no box red. Figures are built, not rasterised."""
    from larc_jax.products.explain import explain
    from larc_jax.products.explain_draw import convex_hull_2d, figure

    scene, traj, _, result = explained
    views = ((0, 1), (0, 2), (1, 2))
    ex = explain(robot, capsules, traj, scene, result, next(lf for lf in result.leaves if lf.stage == "hull"))
    part = ex.part
    assert part is not None and ex.pair is None and ex.stage == "hull"
    assert part.lower_bound_m - part.reach_m == pytest.approx(ex.decided_clearance_m, abs=1e-12)
    d = float(np.linalg.norm(part.closest[0] - part.closest[1]))
    # The recorded bound is below; the full GJK search (which the first axis may have spared) is below and near.
    from larc_jax.obstacles import scene_obstacles

    full = scene_obstacles(scene).take(ex.box).polytope_lower_bound_np(part.vertices_m, part.vertices_m.mean(0),
                                                                       np.eye(3), np.zeros(3))
    assert part.lower_bound_m <= full + 1e-9 and full <= d <= full + 1e-4
    fig = figure(ex, robot, capsules, traj, scene, result)
    grow = part.reach_m + ex.guard_m
    for ax, (i, j) in zip(fig.axes, views):
        drawn = {p.get_gid(): p for p in ax.patches if p.get_gid()}
        flat = part.vertices_m[:, [i, j]]
        np.testing.assert_allclose(drawn["hull_part"].get_xy()[:-1], convex_hull_2d(flat))
        shell = drawn["hull_shell"].get_xy()
        np.testing.assert_allclose(shell.max(axis=0), flat.max(axis=0) + grow, rtol=0, atol=3e-3 * grow)
        np.testing.assert_allclose(shell.min(axis=0), flat.min(axis=0) - grow, rtol=0, atol=3e-3 * grow)
        boxes, polygons = _red_shapes(ax)
        assert [tuple(b.get_xy()) for b in boxes] == [tuple(scene.lo[ex.box, [i, j]])] and not polygons

    ex = explain(robot, capsules, traj, scene, result, next(lf for lf in result.leaves if lf.other_capsule))
    pair = [ex.capsule, ex.other_capsule]
    assert ex.pair is not None and ex.part is None and ex.box == -1 and min(pair) >= 0
    radii = np.r_[ex.radius[pair], ex.pair_shell_radius]
    fig = figure(ex, robot, capsules, traj, scene, result)
    for ax, (i, j) in zip(fig.axes, views):
        boxes, polygons = _red_shapes(ax)
        assert not boxes and len(polygons) == 4
        found = []
        for poly in polygons:  # each red polygon: the points at one distance from one pair axis
            xy = poly.get_xy()
            for c, r in zip(pair + pair, radii):
                a, b = ex.seg_a[c, [i, j]], ex.seg_b[c, [i, j]]
                s = np.clip((xy - a) @ (b - a) / max(float((b - a) @ (b - a)), 1e-300), 0, 1)
                if np.allclose(np.linalg.norm(xy - a - s[:, None] * (b - a), axis=1), r, rtol=1e-9, atol=1e-12):
                    found.append((c, r))
        assert sorted(found) == sorted(zip(pair + pair, radii))


def test_stream_takes_one_spec(robot, capsules, few):
    trajs, scenes = few
    spec = RunSpec(method="reference", max_depth=2)
    parts = list(lj.certify_stream(zip(trajs, scenes), robot, capsules, chunk_size=2, spec=spec))
    kw = list(lj.certify_stream(zip(trajs, scenes), robot, capsules, chunk_size=2, method="reference", max_depth=2))
    assert [len(p) for p in parts] == [2, 1] and all(p.spec == parts[0].spec == q.spec for p, q in zip(parts, kw))
    assert [list(p.certified) for p in parts] == [list(q.certified) for q in kw]
    with pytest.raises(LarcInputError, match="margin_m"):
        next(lj.certify_stream(iter(()), robot, capsules, margin=-1.0))
    with pytest.raises(LarcInputError, match="not both"):
        next(lj.certify_stream(iter(()), robot, capsules, spec=spec, margin=0.02))


def test_dask_runs_the_same_manifest_loop(tmp_path, few):
    """Dask (an in-process cluster) and this process run one loop: same rows, same state."""
    pytest.importorskip("dask.distributed")
    from dask.distributed import Client, LocalCluster

    from larc_jax.drivers.distributed import certify_manifest_dask
    from larc_jax.drivers.manifest import ManifestJob, certify_manifest

    trajs, scenes = few
    manifest = write_manifest(tmp_path, trajs, scenes)
    spec = RunSpec(method="reference", max_depth=2, self_collision=True, tracking_tolerance=0.001, padding_m=0.0015)
    jobs = [ManifestJob(out=str(tmp_path / name), leaves=None, robot_file=None, spec=spec, chunk_size=2)
            for name in ("dask.parquet", "local.parquet")]
    seen = []
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cluster, \
            Client(cluster) as client:
        total = certify_manifest_dask(manifest, jobs[0], client, on_chunk=seen.append)
    assert total["rows"] == 3 and total["chunks_done"] == 2 and len(seen) == 2
    certify_manifest(manifest, jobs[1])
    pd.testing.assert_frame_equal(pd.read_parquet(jobs[0].out), pd.read_parquet(jobs[1].out))
    assert (pd.read_parquet(jobs[0].out)["padding_m"] == 0.0015).all()  # the padding reached the workers
    with pytest.raises(LarcInputError, match="spec.max_depth"):  # refused before reaching any cluster
        certify_manifest_dask(manifest, dataclasses.replace(jobs[0], spec=RunSpec(max_depth=3)), "tcp://0.0.0.0:1")
