"""The committed Stage B results are what HEAD's code writes, and the fingerprints that decide it.

``test_committed_results_are_up_to_date`` fails when code (or data) a stage depends on changed
without the stage's results being regenerated: rerun ``python -m experiments.stageB`` (it
redoes exactly the out-of-date stages) and commit the results.
"""

from __future__ import annotations

import re
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def test_committed_results_are_up_to_date():
    from experiments.common import CONFIG_PATH, Layout, load_config
    from experiments.stageB import out_of_date

    stale = out_of_date(Layout(ROOT / "results" / "stageB"), load_config(CONFIG_PATH), CONFIG_PATH)
    assert not stale, (f"committed Stage B results are out of date with HEAD: {stale}; run "
                       "`python -m experiments.stageB` and commit results/stageB (and README.md)")


def test_stage_code_closures():
    """Each stage depends on the modules it imports, and only those."""
    from experiments.fingerprints import code_closure

    cert = code_closure(["experiments.timing"])
    for m in ("larc_jax.engine.certify", "larc_jax.engine.batch", "larc_jax.leaf.interval", "larc_jax.obstacles.geometry", "larc_jax.model.hermite",
              "larc_jax.model.robot", "larc_jax.enclosure.robot_file", "larc_jax.model.trajectory_files", "experiments.common"):
        assert m in cert, m
    for m in ("larc_jax.drivers.cli", "larc_jax.products.explain", "larc_jax.products.report", "larc_jax", "experiments.tables",
              "experiments.fingerprints"):
        assert m not in cert, m
    gen = code_closure(["experiments.generate"])
    assert "larc_jax.engine.certify" not in gen and "experiments.collision" in gen and "larc_jax.enclosure.meshes" in gen
    assert not any(m.startswith("larc_jax") for m in code_closure(["experiments.stageB_report"])
                   if m not in ("larc_jax.io", "larc_jax.errors", "larc_jax.plain_yaml"))


def test_normalised_source_ignores_comments_and_docstrings(tmp_path):
    from experiments.fingerprints import normalised_source

    a = tmp_path / "a.py"
    b = tmp_path / "b.py"
    c = tmp_path / "c.py"
    a.write_text('"""Doc."""\nX = 1  # one\n\n\ndef f(y):\n    """Doc."""\n    return y + X\n')
    b.write_text('"""Other doc."""\n# a comment\nX = 1\nY_DOC = 2\n"""Attribute doc."""\n\ndef f(y):\n    return (y +\n X)\n')
    c.write_text('X = 1\n\ndef f(y):\n    return y - X\n')
    na, nb, nc = (normalised_source(p) for p in (a, b, c))
    assert na.replace("Y_DOC = 2\n", "") == nb.replace("Y_DOC = 2\n", "") and na != nc


def test_fingerprint_changes_with_data_params_and_code(tmp_path):
    from experiments.fingerprints import fingerprint

    f = tmp_path / "data.txt"
    f.write_text("a")
    base = fingerprint([f], {"k": 1}, code=["experiments.tables"])
    assert base == fingerprint([f], {"k": 1}, code=["experiments.tables"])
    assert base != fingerprint([f], {"k": 2}, code=["experiments.tables"])
    assert base != fingerprint([f], {"k": 1}, code=["experiments.figures"])
    f.write_text("b")
    assert base != fingerprint([f], {"k": 1}, code=["experiments.tables"])


def test_source_fingerprint_is_the_code_and_constants_not_the_clone(tmp_path, monkeypatch):
    """A driver stage's own code (experiments.tightness_kinds, boundary_kinds): the same in a
    clone elsewhere (paths are written relative to the repository), blind to docstrings and to
    private names (a worker's cache), changed by a constant or by what a function does."""
    from experiments import fingerprints as fp

    here = {"ROOT": fp.ROOT, "SOURCE": fp.ROOT / "results" / "x", "PAIRS": 6, "_WORKER": {}}
    clone = tmp_path / "elsewhere"
    clone.mkdir()
    funcs = {}
    for name, text in (("a", 'def stage(x):\n    """Doc."""\n    return x + 1\n'),
                       ("b", "def stage(x):\n    # a comment\n    return (x +\n            1)\n"),
                       ("c", "def stage(x):\n    return x + 2\n")):
        path = tmp_path / f"{name}.py"
        path.write_text(text)
        scope = {}
        exec(compile(text, str(path), "exec"), scope)
        funcs[name] = scope["stage"]
    base = fp.source_fingerprint(here, funcs["a"])
    assert base == fp.source_fingerprint(here, funcs["b"]) != fp.source_fingerprint(here, funcs["c"])
    assert base == fp.source_fingerprint(dict(here, _WORKER={"truth": object()}), funcs["a"])
    assert base != fp.source_fingerprint(dict(here, PAIRS=7), funcs["a"])
    monkeypatch.setattr(fp, "ROOT", clone)
    assert base == fp.source_fingerprint(dict(here, ROOT=clone, SOURCE=clone / "results" / "x"), funcs["a"])
    assert base != fp.source_fingerprint(dict(here, ROOT=clone, SOURCE=clone / "results" / "y"), funcs["a"])


def test_discussion_quotes_numbers_only_through_placeholders():
    """Every number in the hand-written discussion is a {{placeholder}} filled in from the
    tables; a rerun rewrites them all."""
    from experiments.stageB_report import DISCUSSION, PLACEHOLDER

    text = PLACEHOLDER.sub("", DISCUSSION.read_text())
    text = re.sub(r"`[^`]*`", "", text)                 # file names, options
    text = re.sub(r"\b(link|joint)\d\b", "", text)        # link names
    text = re.sub(r"\b(Table|eq\.|eqs\.)\s+[IVX\d]+", "", text)
    numbers = re.findall(r"\d", text)
    assert not numbers, "\n".join(textwrap.wrap(f"digits outside placeholders in {DISCUSSION.name}: {text}", 100))


def test_discussion_and_summary_fill_from_the_committed_tables():
    import pandas as pd

    from experiments.common import CONFIG_PATH, load_config
    from experiments.stageB_report import DISCUSSION, discussion_values, fill_template, summary_markdown

    out = ROOT / "results" / "stageB"
    df = pd.read_csv(out / "trajectories.csv")
    for c in ("certified_larc", "certified_fine", "certified_coarse", "audit_collision", "self_collision"):
        df[c] = df[c].astype(str).str.lower().eq("true")
    values = discussion_values(df, pd.read_csv(out / "batch_timing.csv"), pd.read_csv(out / "generation.csv"),
                               load_config(CONFIG_PATH))
    filled = fill_template(DISCUSSION.read_text(), values)
    assert "{{" not in filled and filled.strip() in (out / "README.md").read_text()
    assert summary_markdown(values) == (out / "summary.md").read_text()
    with pytest.raises(KeyError, match="no_such_value"):
        fill_template("{{no_such_value}}", values)
