"""The padding is a parameter of the run (RunSpec.padding_m, --padding, certify(padding=)).

Every enclosure is its proven containment of the meshes plus the run's padding: the capsules'
cores are kept (CapsuleModel.with_padding, exact in rational arithmetic), the hull parts are
built with it; the result, the table, the JSON, the manifest's results and the certificate record
it, and ``larc verify`` re-checks with it (a forged padding is refuted; --padding-at-least pins it).
"""

from __future__ import annotations

import json
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest

import larc_jax as lj
from larc_jax.defaults import DEFAULT_RUN_PADDING_M
from larc_jax.drivers.cli import EXIT_BAD_INPUT, EXIT_OK, EXIT_REFUTED, main
from larc_jax.engine.results import STAGES
from larc_jax.errors import LarcInputError

ROOT = Path(__file__).resolve().parent.parent
EX = ROOT / "configs" / "examples"
REACH, SWEEP, CELL = (str(EX / n) for n in ("reach_left.yaml", "sweep_front.yaml", "cell.yaml"))
DEPTH = 5


def test_spec_default_is_the_enclosures_and_a_bad_padding_is_refused():
    assert lj.RunSpec(enclosure="capsules").padding_m == DEFAULT_RUN_PADDING_M["capsules"] == 0.001
    assert lj.RunSpec(enclosure="hull").padding_m == DEFAULT_RUN_PADDING_M["hull"] == 0.0
    spec = lj.RunSpec(enclosure="capsules", padding_m=0.0025)
    assert lj.RunSpec.from_json(spec.to_json()) == spec and spec.padding_m == 0.0025
    for bad in (-1e-3, float("nan"), float("inf"), True, "1mm"):
        with pytest.raises(LarcInputError, match=r"^padding_m .*must be a finite number >= 0 m"):
            lj.RunSpec(padding_m=bad)


def test_with_padding_keeps_every_core_exactly(capsules):
    """radius' - padding' >= radius - padding in exact arithmetic, and >= the float64 core the robot
    file's proof computed, for paddings around and far from the file's; the same padding is the
    same model; the motion constants are kept (they bound the mesh points, which lie in the core)."""
    assert capsules.with_padding(capsules.padding_m) is capsules
    rng = np.random.default_rng(3)
    for padding in [0.0, 1e-12, 0.000999999, 0.0010000001, 0.002, 0.05, *rng.uniform(0, 0.01, 20)]:
        padded = capsules.with_padding(float(padding))
        assert padded.padding_m == float(padding)
        np.testing.assert_array_equal(np.asarray(padded.motion_a), np.asarray(capsules.motion_a))
        for r_new, r_old in zip(np.asarray(padded.radius), np.asarray(capsules.radius)):
            exact = Fraction(float(r_new)) - Fraction(float(padding))
            assert exact >= Fraction(float(r_old)) - Fraction(capsules.padding_m)
            assert exact >= Fraction(float(r_old - capsules.padding_m))
            assert float(r_new) - float(padding) >= r_old - capsules.padding_m
            assert abs(float(r_new) - (r_old - capsules.padding_m + padding)) < 1e-15  # rounded up by ulps only


def test_the_padding_shifts_the_capsule_test_and_is_recorded(robot, capsules, tmp_path):
    """Fixed-fine leaves (the same intervals): every capsule-stage clearance moves by exactly the
    padding difference (up to float64 rounding), decisions are monotone in the padding, and the
    result, the table and the JSON say which padding was used."""
    from larc_jax.products.report import result_json, table_lines

    trajs = [lj.read_trajectory(p, robot) for p in (REACH, SWEEP)]
    scene = lj.read_scene(CELL)
    runs = {p: lj.certify(trajs, scene, robot, capsules, method="fine", max_depth=DEPTH, enclosure="capsules",
                          padding=p) for p in (0.0, 0.001, 0.004)}
    assert [runs[p].padding_m for p in runs] == [0.0, 0.001, 0.004]
    assert [runs[p].spec.padding_m for p in runs] == [0.0, 0.001, 0.004]
    base = runs[0.001].leaves
    for p, res in runs.items():
        lv = res.leaves
        assert np.array_equal(lv.t0, base.t0) and np.array_equal(lv.capsule, base.capsule)
        same = np.isfinite(lv.clearance_m) & (lv.stage == STAGES.index("capsule"))
        np.testing.assert_allclose(lv.clearance_m[same] - base.clearance_m[same], 0.001 - p, atol=1e-12)
    # A larger padding never certifies a leaf a smaller one does not.
    assert not np.any(runs[0.004].leaves.certified & ~runs[0.001].leaves.certified)
    assert not np.any(runs[0.001].leaves.certified & ~runs[0.0].leaves.certified)
    assert "padding 4 mm" in table_lines(runs[0.004])[len(trajs) + 1]
    assert result_json(runs[0.004], CELL)["padding_m"] == 0.004


def test_hull_parts_take_the_runs_padding(robot, capsules):
    """The cascade builds its hull parts with the run's padding; parts built with another one
    (certify(hulls=...)) are refused, naming both."""
    from larc_jax.enclosure.hull import PROOF_ALLOWANCE_M, hull_model

    traj = lj.read_trajectory(REACH, robot)
    scene = lj.read_scene(CELL)
    h0 = hull_model(robot, capsules.hull_parts, 0.0)
    h1 = hull_model(robot, capsules.hull_parts, 0.001)
    np.testing.assert_allclose(np.asarray(h1.radius) - np.asarray(h0.radius), 0.001, atol=1e-15)
    assert (np.asarray(h0.radius) >= PROOF_ALLOWANCE_M).all()
    with pytest.raises(LarcInputError, match=r"hulls were built with padding_m 0.001, but the run's padding_m is 0.0"):
        lj.certify([traj], scene, robot, capsules, max_depth=DEPTH, hulls=h1)
    res = lj.certify([traj], scene, robot, capsules, max_depth=DEPTH, hulls=h0)
    assert res.padding_m == 0.0 and res.enclosure == "hull"


def test_cli_padding_is_certified_verified_and_pinned(tmp_path, capsys):
    """--padding reaches the certificate; larc verify re-checks with it, refutes a forged one, and
    --padding-at-least pins it; a bad --padding is refused naming the option, before any file."""
    path = tmp_path / "c.json"
    rc = main(["certify", REACH, "--scene", CELL, "--max-depth", str(DEPTH), "--enclosure", "capsules",
               "--padding", "0.003", "--certificate", str(path), "-q"])
    assert rc == EXIT_OK
    doc = json.loads(path.read_text())
    assert doc["parameters"]["padding_m"] == 0.003 and doc["version"] == 4
    assert main(["verify", str(path)]) == EXIT_OK
    assert "padding 0.003 m" in capsys.readouterr().out
    assert main(["verify", str(path), "--padding-at-least", "0.003"]) == EXIT_OK
    capsys.readouterr()
    assert main(["verify", str(path), "--padding-at-least", "0.004"]) == EXIT_REFUTED
    assert "pin --padding-at-least 0.004: the certificate's padding is 0.003 m" in capsys.readouterr().err
    for forged in (0.0, 0.005):
        doc2 = dict(doc, parameters=dict(doc["parameters"], padding_m=forged))
        p2 = tmp_path / f"forged_{forged}.json"
        p2.write_text(json.dumps(doc2))
        assert main(["verify", str(p2)]) == EXIT_REFUTED  # the enclosures it names are not those rebuilt
        assert "robot.enclosures_sha256" in capsys.readouterr().err
        # With the hash brought along (a forger who recomputed it), the leaves themselves refute a
        # larger padding (their stored clearances exceed the recomputed ones); a smaller one is a
        # weaker claim, true wherever the larger one was proven, and verifies.
        doc3 = dict(doc2, robot=dict(doc["robot"], enclosures_sha256=_enclosures_sha256(forged)))
        p2.write_text(json.dumps(doc3))
        if forged > 0.003:
            assert main(["verify", str(p2)]) == EXIT_REFUTED
            assert "exceeds the recomputed" in capsys.readouterr().err
        else:
            assert main(["verify", str(p2)]) == EXIT_OK
            assert "padding 0.0 m" in capsys.readouterr().out
    assert main(["certify", REACH, "--scene", str(tmp_path / "missing.yaml"), "--padding", "-0.001"]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert "--padding -0.001: must be a finite number >= 0 m" in err and "missing.yaml" not in err


def _enclosures_sha256(padding_m: float) -> str:
    """The enclosures hash of PIPER's capsule test with ``padding_m`` (the certificate's field)."""
    from larc_jax.enclosure.robot_file import load_robot_file
    from larc_jax.leaf.reference import leaf_enclosures
    from larc_jax.products.certificate import enclosures_sha256

    robot, capsules = load_robot_file(None)
    return enclosures_sha256(leaf_enclosures(robot, capsules.with_padding(padding_m), "capsules"))


def test_manifest_results_record_the_padding(tmp_path):
    import pandas as pd

    from larc_jax.drivers.manifest import MANIFEST_RESULT_COLUMNS, ManifestJob, certify_manifest

    manifest = tmp_path / "m.csv"
    manifest.write_text(f"trajectory,scene\n{REACH},{CELL}\n")
    spec = lj.RunSpec(enclosure="capsules", max_depth=DEPTH, padding_m=0.002)
    job = ManifestJob(out=str(tmp_path / "out.parquet"), leaves=None, robot_file=None, spec=spec)
    certify_manifest(manifest, job)
    df = pd.read_parquet(job.out)
    assert "padding_m" in MANIFEST_RESULT_COLUMNS
    assert len(df) == 1 and (df["padding_m"] == 0.002).all() and (df["enclosure"] == "capsules").all()
