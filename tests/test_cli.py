"""The `larc` command line: certify with hand-written files, exit codes, JSON, bad input."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

TRAJ = """joint_names: [joint1, joint2, joint3, joint4, joint5, joint6]
points:
  - positions: [0.0, 0.5, -0.8, 0.0, 0.3, 0.0]
    velocities: [0, 0, 0, 0, 0, 0]
    time_from_start: {sec: 0, nanosec: 0}
  - positions: [0.6, 0.9, -1.1, 0.2, 0.4, 0.5]
    velocities: [0.1, 0, 0, 0, 0, 0]
    time_from_start: {sec: 1, nanosec: 500000000}
  - positions: [1.2, 0.9, -1.1, 0.2, 0.4, 0.5]
    velocities: [0, 0, 0, 0, 0, 0]
    time_from_start: {sec: 3, nanosec: 0}
"""
FAR_SCENE = """frame: base_link
boxes:
  - {name: crate, min: [-0.8, -0.8, 0.0], max: [-0.6, -0.6, 0.2]}
"""
NEAR_SCENE = """frame: base_link
boxes:
  - {name: pillar, min: [0.25, -0.05, 0.0], max: [0.35, 0.05, 0.5]}
"""


def run_larc(*args, cwd):
    env = dict(os.environ)
    return subprocess.run([sys.executable, "-m", "larc_jax.drivers.cli", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=300)


@pytest.fixture()
def files(tmp_path):
    (tmp_path / "reach.yaml").write_text(TRAJ)
    (tmp_path / "far.yaml").write_text(FAR_SCENE)
    (tmp_path / "near.yaml").write_text(NEAR_SCENE)
    return tmp_path


def test_certified_exit_0_and_json(files):
    p = run_larc("certify", "reach.yaml", "--scene", "far.yaml", "--json", "out.json", cwd=files)
    assert p.returncode == 0, p.stderr
    assert "CERTIFIED" in p.stdout
    doc = json.loads((files / "out.json").read_text())
    (t,) = doc["trajectories"]
    assert t["id"] == "reach" and t["certified"] is True
    assert t["evaluations"] >= 1 and len(t["frontier_sizes"]) == 10
    assert t["min_clearance_m"] > 0


@pytest.mark.slow
def test_uncertified_exit_1_names_blocking_pair(files):
    p = run_larc("certify", "reach.yaml", "--scene", "near.yaml", "--json", "out.json", cwd=files)
    assert p.returncode == 1, p.stderr
    assert "UNCERTIFIED" in p.stdout and "pillar" in p.stdout
    t = json.loads((files / "out.json").read_text())["trajectories"][0]
    assert t["certified"] is False and t["evaluations"] > 1 and t["min_clearance_m"] <= 0
    assert t["first_inconclusive"]["box"] == "pillar"


@pytest.mark.parametrize("method,evals", [("fine", 512), ("coarse", 16)])
def test_fixed_methods(files, method, evals):
    p = run_larc("certify", "reach.yaml", "--scene", "far.yaml", "--method", method, "--json", "o.json", cwd=files)
    assert p.returncode == 0, p.stderr
    assert json.loads((files / "o.json").read_text())["trajectories"][0]["evaluations"] == evals


@pytest.mark.parametrize("mutate,needle", [
    (lambda t: t.replace("joint6]", "joint7]"), "joint_names"),
    (lambda t: t.replace("sec: 3,", "sec: 1,"), "points[2].time_from_start"),
    (lambda t: t.replace("[1.2, 0.9", "[.nan, 0.9"), "points[2].positions[0]"),
    (lambda t: t.replace("[1.2, 0.9", "[9.0, 0.9"), "points[2].positions[0]"),
    (lambda t: "", "empty"),
])
def test_bad_trajectory_exit_2(files, mutate, needle):
    (files / "bad.yaml").write_text(mutate(TRAJ))
    p = run_larc("certify", "bad.yaml", "--scene", "far.yaml", "--json", "out.json", cwd=files)
    assert p.returncode == 2
    assert needle in p.stderr and "bad.yaml" in p.stderr
    assert "Traceback" not in p.stderr
    assert not (files / "out.json").exists()


def test_bad_scene_exit_2(files):
    (files / "inverted.yaml").write_text("boxes:\n  - {name: b, min: [0, 0, 1], max: [1, 1, 0]}\n")
    p = run_larc("certify", "reach.yaml", "--scene", "inverted.yaml", cwd=files)
    assert p.returncode == 2 and "boxes[0].min[2]" in p.stderr and "Traceback" not in p.stderr


# ----------------------------------------------------------------------------------------------
# In-process tests (larc_jax.drivers.cli.main with capsys: no new process, JAX compiled once)
# ----------------------------------------------------------------------------------------------

from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from larc_jax.drivers import cli  # noqa: E402

EXAMPLES = Path(__file__).resolve().parent.parent / "configs" / "examples"
OK = str(EXAMPLES / "reach_left.yaml")       # certified in cell.yaml
BLOCKED = str(EXAMPLES / "sweep_front.yaml")  # not certified in cell.yaml (passes through the post)
CELL = str(EXAMPLES / "cell.yaml")


def larc(capsys, *args):
    """Run `larc ARGS` in-process; returns (exit status, stdout, stderr)."""
    capsys.readouterr()
    rc = cli.main([str(a) for a in args])
    out, err = capsys.readouterr()
    return rc, out, err


def check_cover(leaves: pd.DataFrame, horizon: dict[str, tuple[float, float]]):
    """Per trajectory, the leaves tile [t_start, t_end] exactly (no gap, no overlap) and each is
    the dyadic interval its (depth, index) names."""
    assert set(leaves["id"]) == set(horizon)
    for tid, (ts, te) in horizon.items():
        lv = leaves[leaves["id"] == tid].sort_values("t0")
        t0, t1 = lv["t0"].to_numpy(), lv["t1"].to_numpy()
        assert t0[0] == ts and t1[-1] == te
        assert np.array_equal(t1[:-1], t0[1:])
        assert (t1 > t0).all()
        frac = lv["index"].to_numpy() / np.ldexp(1.0, lv["depth"].to_numpy())
        np.testing.assert_allclose(t0, ts + (te - ts) * frac, rtol=0, atol=1e-12)
        assert (lv["depth"] <= 9).all()


@pytest.mark.slow
def test_leaves_parquet_and_csv_cover_the_horizon(tmp_path, capsys):
    rc, out, _ = larc(capsys, "certify", OK, BLOCKED, "--scene", CELL, "--json", tmp_path / "r.json",
                      "--leaves", tmp_path / "leaves.parquet")
    assert rc == 1
    leaves = pd.read_parquet(tmp_path / "leaves.parquet")
    assert {"id", "depth", "index", "t0", "t1", "clearance_m", "capsule", "box"} <= set(leaves.columns)
    ok = "passed" if "passed" in leaves.columns else "certified"  # did this leaf pass the test
    check_cover(leaves, {"reach_left": (0.0, 3.0), "sweep_front": (0.0, 3.0)})
    doc = json.loads((tmp_path / "r.json").read_text())
    for t in doc["trajectories"]:
        lv = leaves[leaves["id"] == t["id"]]
        assert bool(lv[ok].all()) == t["certified"]
        assert lv["clearance_m"].min() == t["min_clearance_m"]
        assert t["evaluations"] >= len(lv)
    bad = leaves[~leaves[ok]]
    assert len(bad) and set(bad["id"]) == {"sweep_front"} and (bad["box"] == "post").all()
    assert (bad["clearance_m"] <= 0).all() and (leaves[leaves[ok]]["clearance_m"] > 0).all()
    # Same cover as CSV (floats written as round-trip decimals).
    rc, _, _ = larc(capsys, "certify", OK, BLOCKED, "--scene", CELL, "--leaves", tmp_path / "leaves.csv")
    assert rc == 1
    floats = ["t0", "t1", "clearance_m"]  # parsed by Python's float(): exact round trip
    csv = pd.read_csv(tmp_path / "leaves.csv", keep_default_na=False, dtype={c: str for c in floats})
    csv[floats] = csv[floats].map(float)
    pd.testing.assert_frame_equal(csv, leaves, check_dtype=False)
    assert not [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")]  # atomic writes


def test_leaves_bad_suffix_or_no_pyarrow_is_bad_input(tmp_path, capsys, monkeypatch):
    rc, out, err = larc(capsys, "certify", OK, "--scene", CELL, "--leaves", tmp_path / "leaves.xlsx")
    assert rc == 2 and "--leaves" in err and ".parquet or .csv" in err and out == ""
    monkeypatch.setitem(sys.modules, "pyarrow", None)  # import pyarrow -> ImportError
    rc, out, err = larc(capsys, "certify", OK, "--scene", CELL, "--leaves", tmp_path / "l.parquet")
    assert rc == 2 and "pyarrow" in err and ".csv" in err and "Traceback" not in err
    assert not (tmp_path / "l.parquet").exists()


@pytest.mark.slow
def test_exit_codes_and_fail_on_uncertified(tmp_path, capsys):
    assert larc(capsys, "certify", OK, "--scene", CELL)[0] == 0
    assert larc(capsys, "certify", OK, BLOCKED, "--scene", CELL)[0] == 1
    assert larc(capsys, "certify", OK, BLOCKED, "--scene", CELL, "--fail-on-uncertified")[0] == 1
    rc, out, err = larc(capsys, "certify", OK, BLOCKED, "--scene", CELL, "--no-fail-on-uncertified",
                        "--json", tmp_path / "r.json")
    assert rc == 0 and "UNCERTIFIED" in out and "--no-fail-on-uncertified" in err
    assert [t["certified"] for t in json.loads((tmp_path / "r.json").read_text())["trajectories"]] == [True, False]
    rc, _, err = larc(capsys, "certify", tmp_path / "missing.yaml", "--scene", CELL, "--no-fail-on-uncertified")
    assert rc == 2 and "missing.yaml" in err
    rc, _, err = larc(capsys, "certify", OK)  # usage errors are bad input too
    assert rc == 2 and "--scene" in err


def test_internal_error_is_exit_3_not_1(capsys, monkeypatch):
    def boom(*args, **kwargs):
        raise RuntimeError("simulated bug")

    monkeypatch.setattr(sys.modules["larc_jax.engine.certify"], "certify", boom)
    rc, _, err = larc(capsys, "certify", OK, "--scene", CELL)
    assert rc == 3 and "simulated bug" in err and "internal error" in err


@pytest.mark.slow
def test_table_is_aligned(capsys):
    rc, out, _ = larc(capsys, "certify", OK, BLOCKED, "--scene", CELL)
    head, ok, blocked, summary, *assumptions = out.splitlines()
    end = head.index("evals") + len("evals")
    assert ok[end - 1].isdigit() and blocked[end - 1].isdigit()  # evaluations right-aligned
    assert ok[end] == " " and blocked[end] == " "
    g_end = head.index("min clearance") + len("min clearance")
    assert ok[:g_end].endswith(" mm") and blocked[:g_end].endswith(" mm")
    assert ok.split()[:2] == ["reach_left", "CERTIFIED"] and blocked.split()[:2] == ["sweep_front", "UNCERTIFIED"]
    assert "t=[" in blocked and "/ post" in blocked and "t=[" not in ok
    assert summary.startswith("1 of 2 certified (larc, capsules then hulls, margin 10 mm")
    assert assumptions and assumptions[0].startswith("gripper:")


@pytest.mark.parametrize("where", ["before", "after"])
def test_quiet_prints_nothing(tmp_path, capsys, where):
    import logging

    def quiet(*args):
        return ["-q", *args] if where == "before" else [*args, "-q"]

    opts = ["--scene", CELL, "--json", tmp_path / "r.json", "--leaves", tmp_path / "l.csv",
            "--progress"]  # --quiet wins over --progress
    rc, out, err = larc(capsys, *quiet("certify", OK, *opts))
    assert (rc, out, err) == (0, "", "")
    assert (tmp_path / "r.json").exists() and (tmp_path / "l.csv").exists()
    rc, out, err = larc(capsys, *quiet("certify", OK, BLOCKED, *opts))
    assert rc == 1 and out == "" and err == ""
    assert logging.getLogger("larc").propagate  # main restores the logging configuration


def test_quiet_in_a_real_process(files):
    """Nothing at all from a whole process (JAX start-up warnings included)."""
    p = run_larc("certify", "reach.yaml", "--scene", "far.yaml", "--json", "out.json", "--quiet", cwd=files)
    assert (p.returncode, p.stdout, p.stderr) == (0, "", "")
    assert (files / "out.json").exists()


def test_progress_and_log_messages_go_to_stderr(tmp_path, capsys):
    rc, out, err = larc(capsys, "certify", OK, BLOCKED, "--scene", CELL, "--progress",
                        "--leaves", tmp_path / "l.parquet")
    assert rc == 1
    assert "certifying (larc)" in err and "intervals" in err and "reading" in err
    assert "larc: wrote" in err and "leaves" in err
    assert "certifying" not in out and "wrote" not in out
    # Not a terminal and no --progress: no bar, log messages only; -v adds debug lines.
    rc, out, err = larc(capsys, "-v", "certify", OK, "--scene", CELL)
    assert rc == 0 and "certifying" not in err and "larc: debug [larc]" in err
    rc, out, err = larc(capsys, "certify", OK, "--scene", CELL, "--no-progress")
    assert rc == 0 and err == ""


def test_fit_capsules_progress(tmp_path, capsys, piper_dir):
    urdf = piper_dir / "urdf" / "piper_description.urdf"
    rc, out, err = larc(capsys, "fit-capsules", urdf, "--package-dir", f"piper_description={piper_dir}",
                        "-o", tmp_path / "robot.yaml", "--progress")
    assert rc == 0 and "fitting capsules" in err and "links" in err and "link6" in err
    assert "containment proven" in out and (tmp_path / "robot.yaml").exists()


@pytest.mark.slow
def test_explain_writes_png_of_the_blocking_interval(tmp_path, capsys):
    rc, out, err = larc(capsys, "explain", BLOCKED, "--scene", CELL, "-o", tmp_path / "why.png")
    assert rc == 0, err
    assert (tmp_path / "why.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    rc2, table, _ = larc(capsys, "certify", BLOCKED, "--scene", CELL, "--enclosure", "capsules")  # as explain
    blocked = table.splitlines()[1].split("t=")[1]  # "[a, b] s  capsule / box", as certify names it
    assert "UNCERTIFIED" in out and "first inconclusive" in out
    assert "t=" + blocked.split(" s ")[0] in out and "box post" in out
    rc, out, err = larc(capsys, "explain", OK, "--scene", CELL, "-o", tmp_path / "ok.svg", "-q")
    assert (rc, out, err) == (0, "", "") and (tmp_path / "ok.svg").read_text().lstrip().startswith("<?xml")
    rc, out, err = larc(capsys, "explain", OK, "--scene", CELL, "--leaf", "worst", "-o", tmp_path / "w.png")
    assert rc == 0 and "CERTIFIED" in out and "tightest" in out


def test_explain_takes_every_run_spec_option():
    """explain's options build the same RunSpec as certify's (its certify run and re-evaluation use it)."""
    from larc_jax.drivers.cli import _certificate_options
    from larc_jax.drivers.cli_parser import build_parser

    opts = ["--scene", CELL, "--margin", "0.02", "--max-depth", "5", "--dtype", "float32", "--enclosure", "hull",
            "--self-collision", "--self-margin", "0.003", "--self-skip", "link1:link4", "--tracking-tolerance",
            "joint2=0.001", "--velocities", "finite-difference", "--ignore-link", "base_link", "--hold", "joint7=0"]
    parser = build_parser()
    spec = _certificate_options(parser.parse_args(["explain", OK, *opts]))
    assert spec == _certificate_options(parser.parse_args(["certify", OK, *opts]))
    assert (spec.dtype, spec.self_collision, spec.self_margin_m, spec.self_skip, spec.tracking_tolerance) == \
        ("float32", True, 0.003, ("link1:link4",), (("joint2", 0.001),))
    assert (spec.margin_m, spec.max_depth, spec.enclosure, spec.velocities, spec.ignore_links, spec.hold) == \
        (0.02, 5, "hull", "finite-difference", ("base_link",), (("joint7", 0.0),))


def test_explain_bad_input(tmp_path, capsys):
    # explain takes certify's run-spec options, checked on the same path before anything is loaded
    for args, why in ((["--self-margin", "0.01"], "--self-margin and --self-skip need --self-collision"),
                      (["--tracking-tolerance", "abc"], "--tracking-tolerance 'abc'"),
                      (["--tracking-tolerance", "-1"], "--tracking-tolerance -1.0: must be a finite number >= 0"),
                      (["--self-collision", "--self-margin", "nan"], "--self-margin nan"),
                      (["--dtype", "float16"], "argument --dtype: invalid choice")):
        rc, _, err = larc(capsys, "explain", OK, "--scene", CELL, *args, "-o", tmp_path / "x.png")
        assert rc == 2 and why in err and len(err.strip().splitlines()) == 1, (args, err)
    rc, _, err = larc(capsys, "explain", OK, "--scene", CELL, "-o", tmp_path / "x.pngx")
    assert rc == 2 and "unknown image type" in err
    rc, _, err = larc(capsys, "explain", OK, "--scene", CELL, "--at", "7.5", "-o", tmp_path / "x.png")
    assert rc == 2 and "outside the horizon" in err and not (tmp_path / "x.png").exists()


@pytest.mark.slow
def test_explain_recomputes_the_interval_test(robot, capsules):
    """The picture's numbers are the certificate's: same g(I), and g = d - (r + rho + b)."""
    import larc_jax as lj
    from larc_jax.products.explain import choose_leaf, explain

    scene = lj.read_scene(CELL)
    for path in (OK, BLOCKED):
        traj = lj.read_trajectory(path, robot)
        result = lj.certify([traj], scene, robot, capsules, margin=0.01, enclosure="capsules")[0]  # as larc explain
        for which in ("first", "worst"):
            leaf = choose_leaf(result, which)
            ex = explain(robot, capsules, traj, scene, result, leaf=leaf)
            assert ex.clearance_m == pytest.approx(leaf.clearance_m, abs=1e-12)
            assert capsules.names[ex.capsule] == leaf.capsule and scene.box_names[ex.box] == leaf.box
            assert ex.distance_m - ex.shell_radius[ex.capsule] == pytest.approx(ex.clearance_m, abs=1e-9)
            assert (ex.motion_b >= 0).all()
        if not result.certified:
            assert choose_leaf(result) == result.first_inconclusive
            assert choose_leaf(result, "worst").clearance_m == result.min_clearance_m
        mid = choose_leaf(result, at=1.5)
        assert mid.t0 <= 1.5 <= mid.t1
