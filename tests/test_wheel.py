"""A real install: build the wheel, install it into a fresh virtual environment, and run
``larc certify`` from an unrelated folder (the default robot data must come from the package,
not from a checkout).

Fast and offline beyond the registry: the wheel is built from a copy of the sources without
build isolation (setuptools and wheel are in the ``dev`` extra), and installed with ``--no-deps``
into a venv without pip whose ``.pth`` file makes this environment's dependencies visible (not
this environment's editable larc_jax: paths added by a ``.pth`` file are not site folders, so
their own ``.pth`` files are not read).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = ROOT / "configs" / "examples"

pytestmark = pytest.mark.slow


def _run(*cmd, **kw):
    p = subprocess.run([str(c) for c in cmd], capture_output=True, text=True, timeout=600, **kw)
    assert p.returncode == 0, f"{cmd}: exit {p.returncode}\n{p.stdout}\n{p.stderr}"
    return p


def test_wheel_installs_and_certifies_from_any_folder(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    shutil.copytree(ROOT / "larc_jax", src / "larc_jax", ignore=shutil.ignore_patterns("__pycache__"))
    _run(sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w", tmp_path / "dist", src)
    (wheel,) = (tmp_path / "dist").glob("larc_jax-*.whl")

    venv = tmp_path / "venv"
    _run(sys.executable, "-m", "venv", "--without-pip", venv)
    py = venv / "bin" / "python"
    site = _run(py, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])").stdout.strip()
    (Path(site) / "_test_dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    _run(sys.executable, "-m", "pip", "--python", py, "install", "-q", "--no-deps", "--no-index", wheel)

    work = tmp_path / "elsewhere"
    work.mkdir()
    for name in ("reach_left.yaml", "cell.yaml"):
        shutil.copy2(EXAMPLES / name, work / name)
    where = _run(py, "-c", "import larc_jax, larc_jax.data as d; print(larc_jax.__file__)", cwd=work).stdout
    assert where.startswith(str(venv)), where  # the installed copy, not the checkout
    p = _run(venv / "bin" / "larc", "certify", "reach_left.yaml", "--scene", "cell.yaml", "--json", "r.json",
             cwd=work, env=dict(os.environ))
    assert "reach_left  CERTIFIED" in p.stdout
    assert (work / "r.json").is_file()
