"""The README's examples run as written.

* Every ```` ```python ```` block is executed in-process.
* Every ```` ```sh ```` block is run by ``bash -e -o pipefail`` in a fresh temporary folder that
  holds a copy of ``configs/``, with this interpreter's ``bin`` folder (``larc``, ``python``)
  first on PATH and the environment (``LARC_PIPER_DESCRIPTION``) passed through. A block whose
  command is expected to fail says so itself (``larc certify ... || echo "exit status $?"``).
  ```` ```bash ```` blocks (set-up from the repository root) and ```` ```text ```` /
  ```` ```yaml ```` blocks are not run.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = (ROOT / "README.md").read_text()


def _blocks(lang: str) -> list[tuple[int, str]]:
    """(line number, text) of every ```lang block that starts a line."""
    return [(README.count("\n", 0, m.start()) + 1, m.group(1))
            for m in re.finditer(rf"^```{lang}\n(.*?)^```", README, re.S | re.M)]


def test_readme_python_example_runs():
    blocks = _blocks("python")
    assert blocks, "README has no python example"
    for _, block in blocks:
        exec(compile(block, "README.md", "exec"), {})


SH_BLOCKS = _blocks("sh")


def test_readme_has_command_line_examples():
    assert len(SH_BLOCKS) >= 4
    text = "\n".join(b for _, b in SH_BLOCKS)
    for needle in ("larc certify", "--leaves", "--json", "--quiet", "larc explain", "larc fit-capsules",
                   "larc verify-capsules", "--certificate", "larc verify cert.json"):
        assert needle in text, needle


@pytest.mark.slow
@pytest.mark.parametrize("line,block", SH_BLOCKS, ids=[f"README.md:{n}" for n, _ in SH_BLOCKS])
def test_readme_sh_example_runs(tmp_path, line, block):
    shutil.copytree(ROOT / "configs", tmp_path / "configs")
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    p = subprocess.run(["bash", "-e", "-o", "pipefail", "-c", block], cwd=tmp_path, env=env,
                       capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, (
        f"README.md line {line}: exit status {p.returncode}\n{block}\n"
        f"--- stdout:\n{p.stdout}\n--- stderr:\n{p.stderr}"
    )
    assert "Traceback" not in p.stderr, p.stderr


# ----------------------------------------------------------------------------------------------
# The Quick start commands, .ci/run, and the generated Stage B summary
# ----------------------------------------------------------------------------------------------


def _ci_command(name: str) -> str:
    p = subprocess.run([sys.executable, str(ROOT / ".ci" / "readme_command.py"), name], capture_output=True,
                       text=True)
    assert p.returncode == 0, p.stderr
    return p.stdout.rstrip("\n")


def test_ci_runs_the_readme_quick_start_verbatim():
    """.ci/run takes its commands from README.md (so they cannot drift apart): the test command
    and the main job, with the relative LARC_PIPER_DESCRIPTION a new user types."""
    ci = (ROOT / ".ci" / "run").read_text()
    assert "run_readme_command tests" in ci and "run_readme_command main-job" in ci
    assert "git status --porcelain" in ci
    bash = [b.strip() for _, b in _blocks("bash")]
    for name in ("main-job", "tests", "fast-tests"):
        cmd = _ci_command(name)
        assert cmd in bash and cmd.startswith("python3 -m venv .venv && .venv/bin/pip install -q -e '.[dev]' && ")
        assert "LARC_PIPER_DESCRIPTION=../shared/robots/piper_description " in cmd
    assert _ci_command("tests").endswith("-m pytest -q")
    assert _ci_command("fast-tests").endswith('-m pytest -q -m "not slow"')
    assert _ci_command("main-job").endswith("-m experiments.stageB")


def test_relative_piper_path_works_from_any_folder(tmp_path):
    """conftest made a relative LARC_PIPER_DESCRIPTION absolute, so larc in another folder finds PIPER."""
    assert Path(os.environ["LARC_PIPER_DESCRIPTION"]).is_absolute()
    env = dict(os.environ, LARC_PIPER_DESCRIPTION=os.path.relpath(os.environ["LARC_PIPER_DESCRIPTION"], ROOT))
    code = ("import os, sys; sys.path.insert(0, 'tests'); import conftest; "
            "print(os.environ['LARC_PIPER_DESCRIPTION'])")
    p = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip() == os.environ["LARC_PIPER_DESCRIPTION"]


def test_stageB_summary_is_the_generated_one():
    """The README's Stage B section is results/stageB/summary.md, which the tables stage writes
    (every number in it comes from the committed results)."""
    from experiments.stageB_report import SUMMARY_BEGIN, SUMMARY_END

    summary = (ROOT / "results" / "stageB" / "summary.md").read_text()
    i, j = README.index(SUMMARY_BEGIN) + len(SUMMARY_BEGIN), README.index(SUMMARY_END)
    assert README[i:j].strip() == summary.strip()


def test_cold_start_figures_are_the_generated_ones():
    """The README's cold-start table quotes the coldstart section of results/bench/bench_cpu.json."""
    import json

    doc = json.loads((ROOT / "results" / "bench" / "bench_cpu.json").read_text())["coldstart"]
    section = README[README.index("### Cold start"):README.index("## Code map")]
    for key, label in (("first_ever", "first ever"), ("warm_cache", "second and later"),
                       ("no_cache", "`--no-compile-cache`")):
        row = next(line for line in section.splitlines() if line.startswith(f"| {label}"))
        r = doc[key]
        cells = [f"{r[k]:.2f} s" for k in ("wall_s", "robot_s", "compile_s", "run_s")]
        assert row.split(" | ")[1:] == cells[:-1] + [cells[-1] + " |"], row
    assert f"{doc['import_s']:.2f} s" in section and f"{doc['bad_option_s']:.2f} s for a wrong" in section
    assert f"load average {doc['machine']['load_average_before'][0]:.2f}" in section
    from experiments.bench import tree_sentence

    assert tree_sentence(doc["tree"]) in " ".join(section.split())


def test_tightness_table_is_the_generated_one():
    """The README's tightness table is results/tightness/table.md and goal.md (experiments.tightness)."""
    gen = ROOT / "results" / "tightness"
    begin = "<!-- tightness table: results/tightness/table.md and goal.md, written by experiments.tightness -->"
    i, j = README.index(begin) + len(begin), README.index("<!-- end of tightness table -->")
    want = "\n\n".join(_demote((gen / name).read_text()) for name in ("table.md", "goal.md"))
    assert README[i:j].strip() == want.strip()


def test_kinds_tightness_table_is_the_generated_one():
    """The README's per-kind tightness table is results/tightness_kinds/goal.md and table.md
    (experiments.tightness_kinds)."""
    gen = ROOT / "results" / "tightness_kinds"
    begin = ("<!-- kinds tightness table: results/tightness_kinds/goal.md and table.md, written by "
             "experiments.tightness_kinds -->")
    i, j = README.index(begin) + len(begin), README.index("<!-- end of kinds tightness table -->")
    want = "\n\n".join(_demote((gen / name).read_text()) for name in ("goal.md", "table.md"))
    assert README[i:j].strip() == want.strip()


def test_readme_quotes_the_boundary_table():
    """The README's per-kind boundary table is results/boundary_kinds/table.md (experiments.boundary_kinds)."""
    begin = "<!-- kinds boundary table: results/boundary_kinds/table.md, written by experiments.boundary_kinds -->"
    i, j = README.index(begin) + len(begin), README.index("<!-- end of kinds boundary table -->")
    assert README[i:j].strip() == (ROOT / "results" / "boundary_kinds" / "table.md").read_text().strip()


def _demote(text: str) -> str:
    """A generated Markdown file as the README quotes it: its '# ' title as bold text."""
    lines = text.strip().splitlines()
    if lines and lines[0].startswith("# "):
        lines[0] = f"**{lines[0][2:]}**"
    return "\n".join(lines)


@pytest.mark.parametrize("name", ["bench_cpu", "bench_gpu", "bench_gpu_hull"])
def test_benchmark_table_is_the_generated_one(name):
    """The README's benchmark tables are results/bench/NAME.md (experiments.bench --json)."""
    begin = f"<!-- bench table: results/bench/{name}.md, written by experiments.bench -->"
    i = README.index(begin) + len(begin)
    j = README.index("<!-- end of bench table -->", i)
    assert README[i:j].strip() == (ROOT / "results" / "bench" / f"{name}.md").read_text().strip()


@pytest.mark.parametrize("name", ["tree_cpu", "tree_cpu1"])
def test_tree_table_is_the_generated_one(name):
    """The README's device-tree tables are results/bench/NAME.md (experiments.bench_tree)."""
    begin = f"<!-- tree table: results/bench/{name}.md, written by experiments.bench_tree -->"
    i = README.index(begin) + len(begin)
    j = README.index("<!-- end of tree table -->", i)
    assert README[i:j].strip() == (ROOT / "results" / "bench" / f"{name}.md").read_text().strip()


def test_obstacles_table_is_the_generated_one():
    """The README's obstacle-kind cost table is results/bench/obstacles_cpu.md (experiments.bench_obstacles)."""
    begin = "<!-- obstacles table: results/bench/obstacles_cpu.md, written by experiments.bench_obstacles -->"
    i, j = README.index(begin) + len(begin), README.index("<!-- end of obstacles table -->")
    assert README[i:j].strip() == (ROOT / "results" / "bench" / "obstacles_cpu.md").read_text().strip()
