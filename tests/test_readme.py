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
                   "larc verify-capsules"):
        assert needle in text, needle


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
