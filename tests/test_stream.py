"""Streaming certification, manifests (resumable Parquet datasets), several devices, Dask."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import larc_jax as lj
from larc_jax.drivers.cli import main as larc_main
from larc_jax.drivers.manifest import ManifestJob, certify_manifest
from larc_jax.model.trajectory_files import write_trajectory

from .test_certify import random_scene, random_trajectory

ROOT = Path(__file__).resolve().parent.parent


def same_results(a, b):
    """Same decisions, evaluations and leaf cover; clearances equal to rounding (XLA may fuse
    differently for different batch shapes)."""
    da, db = a.to_dataframe(), b.to_dataframe()
    assert list(da.id) == list(db.id)
    assert (da.certified.values == db.certified.values).all()
    assert (da.evaluations.values == db.evaluations.values).all()
    la, lb = a.leaves_dataframe(), b.leaves_dataframe()
    cols = ["id", "depth", "index", "t0", "t1", "certified", "capsule", "box"]
    pd.testing.assert_frame_equal(la[cols], lb[cols])
    np.testing.assert_allclose(la.clearance_m, lb.clearance_m, rtol=0, atol=1e-12)


@pytest.fixture(scope="module")
def small_dataset(robot):
    rng = np.random.default_rng(77)
    trajs = [random_trajectory(rng, robot, k, max_waypoints=6) for k in range(24)]
    scenes = [random_scene(rng, k % 5) for k in range(24)]
    return trajs, scenes


@pytest.mark.slow
def test_stream_equals_one_call(small_dataset, robot, capsules):
    trajs, scenes = small_dataset
    whole = lj.certify(trajs, scenes, robot, capsules, max_depth=6)
    seen = 0
    parts = []
    for chunk in lj.certify_stream(((t, s) for t, s in zip(trajs, scenes)), robot, capsules,
                                   chunk_size=7, max_depth=6):
        assert len(chunk) <= 7
        parts.append(chunk)
        seen += len(chunk)
    assert seen == len(trajs) and [len(p) for p in parts] == [7, 7, 7, 3]
    for k, part in enumerate(parts):
        ref = lj.certify(trajs[7 * k: 7 * k + 7], scenes[7 * k: 7 * k + 7], robot, capsules, max_depth=6)
        same_results(part, ref)
    assert [r.certified for p in parts for r in p] == [r.certified for r in whole]
    assert 0 < sum(r.certified for r in whole) < len(trajs)


def test_stream_bad_items(robot, capsules, small_dataset):
    trajs, scenes = small_dataset
    with pytest.raises(lj.LarcInputError, match="chunk_size"):
        next(lj.certify_stream([(trajs[0], scenes[0])], robot, capsules, chunk_size=0))
    with pytest.raises(lj.LarcInputError, match="item 2 is not a"):
        list(lj.certify_stream([(trajs[0], scenes[0]), (trajs[1], scenes[1]), trajs[2]], robot, capsules))


def write_manifest(tmp: Path, trajs, scenes, bad_rows=()) -> Path:
    (tmp / "data").mkdir()
    lines = ["trajectory,scene,id"]
    for k, (t, s) in enumerate(zip(trajs, scenes)):
        write_trajectory(tmp / "data" / f"{t.id}.csv", t)
        boxes = ", ".join(f"{{name: {n}, min: {lo.tolist()}, max: {hi.tolist()}}}"
                          for n, lo, hi in zip(s.box_names, s.lo, s.hi))
        (tmp / "data" / f"scene{k}.yaml").write_text(f"frame: base_link\nboxes: [{boxes}]\n")
        traj = f"data/{t.id}.csv" if k not in bad_rows else f"data/missing{k}.csv"
        lines.append(f"{traj},data/scene{k}.yaml,{t.id}")
    (tmp / "m.csv").write_text("\n".join(lines) + "\n")
    return tmp / "m.csv"


@pytest.mark.slow
def test_manifest_cli_matches_certify_and_resumes(tmp_path, small_dataset, robot, capsules, capsys, monkeypatch):
    trajs, scenes = small_dataset
    manifest = write_manifest(tmp_path, trajs, scenes)
    out, leaves = tmp_path / "r.parquet", tmp_path / "l.parquet"
    argv = ["certify", "--manifest", str(manifest), "--out", str(out), "--leaves", str(leaves),
            "--chunk-size", "5", "--max-depth", "6", "--no-fail-on-uncertified"]
    assert larc_main(argv) == 0
    first = capsys.readouterr().out
    assert "5 chunks now, 0 already done" in first
    got = pd.read_parquet(out)
    assert list(got.row) == list(range(len(trajs))) and (got.error == "").all()
    # The rows equal one certify() call on the same (re-read) files.
    direct = lj.certify([lj.read_trajectory(tmp_path / "data" / f"{t.id}.csv", robot) for t in trajs],
                        [lj.read_scene(tmp_path / "data" / f"scene{k}.yaml") for k in range(len(trajs))],
                        robot, capsules, max_depth=6)
    want = direct.to_dataframe()
    assert list(got.certified) == list(want.certified)
    assert list(got.evaluations) == list(want.evaluations)
    np.testing.assert_allclose(got.min_clearance_m, want.min_clearance_m, atol=1e-12, rtol=0)
    lv = pd.read_parquet(leaves)
    assert len(lv) == len(direct.leaves_dataframe())
    for row, g in lv.groupby("row"):  # each trajectory's leaves tile its horizon
        g = g.sort_values("t0")
        assert g.t0.iloc[0] == trajs[row].t[0] and g.t1.iloc[-1] == trajs[row].t[-1]
        assert (g.t0.values[1:] == g.t1.values[:-1]).all()

    # Resume: a rerun skips everything; a lost part is recomputed, nothing duplicated.
    assert larc_main(argv) == 0
    assert "0 chunks now, 5 already done" in capsys.readouterr().out
    (out / "part-000002.parquet").unlink()
    assert larc_main(argv) == 0
    assert "1 chunks now, 4 already done" in capsys.readouterr().out
    again = pd.read_parquet(out)
    pd.testing.assert_frame_equal(again, got)

    # A run killed after two chunks loses nothing and duplicates nothing when resumed.
    import larc_jax.drivers.manifest as mf

    out2 = tmp_path / "r2.parquet"
    calls = {"n": 0}
    real = mf.certify_chunk

    def dies_after_two(*args, **kwargs):
        if calls["n"] == 2:
            raise KeyboardInterrupt
        calls["n"] += 1
        return real(*args, **kwargs)

    monkeypatch.setattr(mf, "certify_chunk", dies_after_two)
    with pytest.raises(KeyboardInterrupt):
        larc_main(["certify", "--manifest", str(manifest), "--out", str(out2), "--chunk-size", "5",
                   "--max-depth", "6", "--no-fail-on-uncertified"])
    assert len(list(out2.glob("part-*.parquet"))) == 2
    monkeypatch.setattr(mf, "certify_chunk", real)
    assert larc_main(["certify", "--manifest", str(manifest), "--out", str(out2), "--chunk-size", "5",
                      "--max-depth", "6", "--no-fail-on-uncertified"]) == 0
    assert "3 chunks now, 2 already done" in capsys.readouterr().out
    pd.testing.assert_frame_equal(pd.read_parquet(out2), got)

    # Another parameter set is refused rather than mixed in.
    assert larc_main(argv + ["--margin", "0.02"]) == 2
    assert "another run" in capsys.readouterr().err


@pytest.mark.slow
def test_manifest_bad_rows_and_bad_manifests(tmp_path, small_dataset, capsys):
    trajs, scenes = small_dataset
    manifest = write_manifest(tmp_path, trajs[:4], scenes[:4], bad_rows=(2,))
    out = tmp_path / "r.parquet"
    rc = larc_main(["certify", "--manifest", str(manifest), "--out", str(out), "--max-depth", "4"])
    assert rc == 2
    got = pd.read_parquet(out)
    assert list(got.row) == [0, 1, 2, 3]
    assert "missing2.csv" in got.error[2] and "does not exist" in got.error[2] and not got.certified[2]
    assert (got.error.drop(index=2) == "").all()
    assert "1 manifest rows are bad input" in capsys.readouterr().err
    for text, needle in [("", "empty"), ("trajectory,scenes\na,b\n", "scene"), ("trajectory,scene\na\n", "cells"),
                         ("trajectory,scene\n,b\n", "empty")]:
        bad = tmp_path / "bad.csv"
        bad.write_text(text)
        assert larc_main(["certify", "--manifest", str(bad), "--out", str(tmp_path / "x.parquet")]) == 2
        err = capsys.readouterr().err
        assert "bad.csv" in err and needle in err, err
    assert larc_main(["certify", "--manifest", str(manifest)]) == 2
    assert "--out" in capsys.readouterr().err
    assert larc_main(["certify", "--manifest", str(manifest), "--out", str(out), "--scene", "s.yaml"]) == 2
    assert larc_main(["certify", str(manifest), "--scene", "s.yaml", "--out", str(out)]) == 2
    assert "--out needs --manifest" in capsys.readouterr().err


SHARDED = textwrap.dedent("""
    import os, sys
    os.environ["XLA_FLAGS"] = "--xla_force_host_platform_device_count=2"
    import jax, numpy as np
    import larc_jax as lj
    sys.path.insert(0, {root!r})
    from tests.test_certify import random_scene, random_trajectory
    from tests.test_stream import same_results
    assert len(jax.devices()) == 2, jax.devices()
    robot = lj.load_robot(); caps = lj.load_capsules(lj.default_capsule_path(), robot)
    rng = np.random.default_rng(3)
    trajs = [random_trajectory(rng, robot, k) for k in range(30)]
    scenes = [random_scene(rng, k) for k in range(30)]
    two = lj.certify(trajs, scenes, robot, caps, devices=jax.devices(), enclosure="capsules")
    one = lj.certify(trajs, scenes, robot, caps, devices=jax.devices()[:1], enclosure="capsules")
    same_results(two, one)
    assert 0 < sum(two.certified) < 30
    print("ok", sum(two.certified))
""")


@pytest.mark.slow
def test_two_devices_give_identical_results(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    p = subprocess.run([sys.executable, "-c", SHARDED.format(root=str(ROOT))], env=env, capture_output=True,
                       text=True, timeout=600, cwd=tmp_path)
    assert p.returncode == 0 and "ok" in p.stdout, p.stdout + p.stderr


DASK = textwrap.dedent("""
    import sys
    sys.path.insert(0, {root!r})
    if __name__ == "__main__":
        import pandas as pd
        from dask.distributed import Client, LocalCluster
        from larc_jax.drivers.distributed import certify_manifest_dask
        from larc_jax.drivers.manifest import ManifestJob, certify_manifest
        from larc_jax.run_spec import RunSpec
        with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, \\
                Client(cluster) as client:
            job = ManifestJob(out="dask.parquet", leaves="dask_leaves.parquet", robot_file=None, chunk_size=3,
                              spec=RunSpec(max_depth=5))
            total = certify_manifest_dask("m.csv", job, client)
            assert total["rows"] == 8 and total["chunks_done"] == 3, total
            assert len(client.scheduler_info()["workers"]) == 2
        local = ManifestJob(out="local.parquet", leaves="local_leaves.parquet", robot_file=None, chunk_size=3,
                            spec=RunSpec(max_depth=5))
        certify_manifest("m.csv", local)
        pd.testing.assert_frame_equal(pd.read_parquet("dask.parquet"), pd.read_parquet("local.parquet"))
        pd.testing.assert_frame_equal(pd.read_parquet("dask_leaves.parquet"), pd.read_parquet("local_leaves.parquet"))
        print("ok")
""")


@pytest.mark.slow
def test_dask_local_cluster_equals_single_process(tmp_path, small_dataset):
    pytest.importorskip("dask.distributed")
    trajs, scenes = small_dataset
    write_manifest(tmp_path, trajs[:8], scenes[:8])
    script = tmp_path / "run_dask.py"
    script.write_text(DASK.format(root=str(ROOT)))
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    p = subprocess.run([sys.executable, str(script)], env=env, capture_output=True, text=True, timeout=900,
                       cwd=tmp_path)
    assert p.returncode == 0 and "ok" in p.stdout, p.stdout[-3000:] + p.stderr[-3000:]


def test_certify_in_batches_equals_one_batch(monkeypatch):
    """A dataset larger than MAX_BATCH_TRAJECTORIES runs batch after batch (bounded memory): the
    same leaves, frontier and per-trajectory results as one batch."""
    import importlib

    import larc_jax as lj

    from .test_certify import random_scene, random_trajectory

    C = importlib.import_module("larc_jax.engine.certify")  # the module (larc_jax.engine.certify is the function)
    robot = lj.load_robot()
    capsules = lj.load_capsules(lj.default_capsule_path(), robot)
    rng = np.random.default_rng(11)
    trajs = [random_trajectory(rng, robot, k) for k in range(13)]
    scenes = [random_scene(rng, k % 4) for k in range(13)]
    kw = dict(margin=0.01, max_depth=4, enclosure="capsules")
    one = lj.certify(trajs, scenes, robot, capsules, **kw)
    monkeypatch.setattr(C, "MAX_BATCH_TRAJECTORIES", 5)
    many = lj.certify(trajs, scenes, robot, capsules, **kw)
    np.testing.assert_array_equal(one.frontier, many.frontier)
    np.testing.assert_array_equal(one.certified, many.certified)
    a, b = one.leaves_dataframe(), many.leaves_dataframe()
    assert a.drop(columns=["clearance_m"]).equals(b.drop(columns=["clearance_m"]))
    np.testing.assert_allclose(a.clearance_m, b.clearance_m, rtol=0, atol=1e-12)
