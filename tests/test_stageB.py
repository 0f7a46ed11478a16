"""End-to-end Stage B in quick mode: ``python -m experiments.stageB --quick --out <tmp>``.

Runs the whole pipeline (generation with OMPL + TOPP-RA, FCL audit, batched certification,
paired timing, tables, figures) on 2 pairs per scene, then runs it again and checks that every
stage is reused.
"""

from __future__ import annotations

import csv
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
REQUIRED_COLUMNS = [
    "traj_id", "scene", "pair_id", "variant", "duration_s", "n_waypoints", "certified_larc", "certified_fine",
    "certified_coarse", "evals_larc", "evals_fine", "evals_coarse", "audit_states", "audit_collision",
    "min_clearance_m", "time_larc_ms", "time_fine_ms", "time_coarse_ms",
]
SCENES = ("open", "easy_window", "medium_window", "easy_shelf")
FIGURES = ("outcomes_vs_audit", "eval_ratio", "runtime_ratio", "results", "frontier_levels", "scene_replay",
           "workspace")

pytestmark = pytest.mark.slow


def _run(out: Path, timeout: int = 900) -> tuple[subprocess.CompletedProcess, float]:
    env = dict(os.environ)
    env.setdefault("LARC_PIPER_DESCRIPTION", str(ROOT.parent / "shared" / "robots" / "piper_description"))
    env["MPLBACKEND"] = "Agg"
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "experiments.stageB", "--quick", "--out", str(out)],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout,
    )
    return proc, time.perf_counter() - t0


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("stageB_quick")
    proc, secs = _run(out)
    if proc.returncode != 0:
        pytest.fail(f"stageB --quick exited {proc.returncode}\nSTDOUT:\n{proc.stdout[-6000:]}\n"
                    f"STDERR:\n{proc.stderr[-6000:]}")
    return out, proc, secs


def _rows(path: Path) -> list[dict]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def test_quick_run_tables(quick_run):
    out, proc, _ = quick_run
    rows = _rows(out / "trajectories.csv")
    assert len(rows) == 4 * 2 * 2, f"expected 16 trajectories, got {len(rows)}"
    missing = [c for c in REQUIRED_COLUMNS if c not in rows[0]]
    assert not missing, f"trajectories.csv lacks {missing}"
    assert {r["scene"] for r in rows} == set(SCENES)
    assert {r["variant"] for r in rows} == {"ompl_planned", "direct_smoothstep"}
    for s in SCENES:
        assert sum(r["scene"] == s for r in rows) == 4
    assert all(int(r["evals_fine"]) == 512 for r in rows)
    assert all(int(r["evals_coarse"]) == 16 for r in rows)
    false_safe = [r["traj_id"] for r in rows if r["certified_larc"] == "True" and r["audit_collision"] == "True"]
    assert not false_safe, f"certified by LARC despite an audit collision: {false_safe}"
    for r in rows:
        assert int(r["audit_states"]) > 0
        assert float(r["time_larc_ms"]) > 0 and float(r["time_fine_ms"]) > 0
    for name in ("overall", "per_scene", "rejection_by_variant", "frontier_levels", "batch_timing", "generation",
                 "checks"):
        assert (out / f"{name}.md").is_file() and (out / f"{name}.csv").is_file(), name
    readme = (out / "README.md").read_text()
    assert "## Why they differ" in readme and "Quick run" in readme
    assert "[check]" in proc.stdout


def test_quick_run_figures(quick_run):
    out, _, _ = quick_run
    for f in FIGURES:
        p = out / "figures" / f"{f}.png"
        assert p.is_file() and p.stat().st_size > 5000, f"missing or empty figure {p}"
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_second_run_reuses_stages(quick_run):
    out, _, first_secs = quick_run
    proc, secs = _run(out, timeout=300)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-4000:]
    for stage in ("generate", "audit", "certify", "timing", "tables", "figures"):
        assert f"[stageB] {stage}: skipped" in proc.stdout, f"stage {stage} was not reused:\n{proc.stdout}"
    assert secs < max(10.0, 0.5 * first_secs), f"second run took {secs:.1f} s (first {first_secs:.1f} s)"


def test_forced_generation_is_byte_identical(quick_run, tmp_path):
    """Generation is deterministic (planner limited by a count of validity checks, never by wall
    time; no wall times in the outputs): regenerating with --force writes the same bytes."""
    out, _, _ = quick_run
    env = dict(os.environ)
    env.setdefault("LARC_PIPER_DESCRIPTION", str(ROOT.parent / "shared" / "robots" / "piper_description"))
    again = tmp_path / "dataset"
    proc = subprocess.run([sys.executable, "-m", "experiments.generate", "--quick", "--force", "--out", str(again)],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-4000:]
    first = {p.relative_to(out / "dataset"): p.read_bytes() for p in (out / "dataset").rglob("*") if p.is_file()}
    second = {p.relative_to(again): p.read_bytes() for p in again.rglob("*") if p.is_file()}
    assert sorted(first) == sorted(second)
    assert sum(str(k).endswith(".yaml") for k in first) == 16
    differ = [str(k) for k in first if first[k] != second[k]]
    assert not differ, f"regenerated files differ: {differ}"


def test_check_reports_nothing_out_of_date(quick_run):
    out, _, _ = quick_run
    env = dict(os.environ)
    env.setdefault("LARC_PIPER_DESCRIPTION", str(ROOT.parent / "shared" / "robots" / "piper_description"))
    proc = subprocess.run([sys.executable, "-m", "experiments.stageB", "--quick", "--out", str(out), "--check"],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0 and "up to date" in proc.stdout, proc.stdout + proc.stderr
