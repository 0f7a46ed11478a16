"""The committed results of the tightness drivers (``experiments.tightness``,
``experiments.tightness_kinds``, ``experiments.boundary_kinds``) are what HEAD's code writes: each
driver runs with its stages replaced by a comparison of the fingerprint it would record against
the one its ``_stages/<stage>.json`` holds, and ``tightness_kinds``' planning (per (kind, padding),
by its ``done.json`` markers) by a record of the jobs it would run (Stage B's:
tests/test_stageB_fingerprints.py).

A stage is stale when its code or its inputs changed since it ran: ``boundary_kinds`` reads
``tightness_kinds``' certification, so running the two at once records the certification as it
was before ``tightness_kinds`` rewrote it (run it after)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest


@pytest.mark.parametrize("driver", ["tightness", "tightness_kinds", "boundary_kinds"])
def test_committed_results_are_up_to_date(driver, monkeypatch):
    import importlib

    module = importlib.import_module(f"experiments.{driver}")
    checked, stale = [], []

    def compare(out, name, fp, outputs, fn, force, tag="tightness"):
        recorded = json.loads((Path(out) / "_stages" / f"{name}.json").read_text())["fingerprint"]
        checked.append(name)
        if recorded != fp or not all(Path(o).exists() for o in outputs):
            stale.append(name)

    monkeypatch.setattr(module, "run_stage", compare)
    if driver == "tightness_kinds":  # it plans (kind, padding) datasets whose done.json marker is stale

        def planned(fn, jobs, workers):
            checked.append("generate")
            stale.extend(f"generate: {j['kind']}, padding {j['padding_mm']} mm" for j in jobs)
            return iter(())

        monkeypatch.setattr(module, "pool_map", planned)
    assert module.main([]) in (0, None)
    assert checked, "the driver ran no stage"
    assert not stale, (f"committed results/{driver} stages {stale} are out of date with HEAD: run "
                       f"`python -m experiments.{driver}` and commit results/{driver} (and README.md)")
