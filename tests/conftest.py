"""Shared fixtures and the test session's environment.

* The PIPER description comes from ``LARC_PIPER_DESCRIPTION``; tests fall back to
  ``../shared/robots/piper_description`` beside the checkout. A *relative* value (the README's
  commands give ``../shared/...``) is made absolute here, once, against the folder pytest was
  started from: tests that run ``larc`` in temporary folders inherit the environment and must
  still find PIPER.
* ``larc`` processes started by tests share one compilation cache for the session
  (``LARC_COMPILE_CACHE`` in a temporary folder): hermetic, and later runs skip compiling.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
_SHARED = ROOT.parent / "shared" / "robots" / "piper_description"
_ENV = "LARC_PIPER_DESCRIPTION"
if os.environ.get(_ENV):
    os.environ[_ENV] = str(Path(os.environ[_ENV]).expanduser().resolve())
elif _SHARED.is_dir():
    os.environ[_ENV] = str(_SHARED)

_CACHE = tempfile.TemporaryDirectory(prefix="larc-test-compile-cache-")
os.environ["LARC_COMPILE_CACHE"] = str(Path(_CACHE.name) / "jax")


@pytest.fixture(scope="session")
def piper_dir() -> Path:
    from larc_jax.urdf import piper_description_dir

    return piper_description_dir()


@pytest.fixture(scope="session")
def robot():
    from larc_jax.urdf import load_robot

    return load_robot()


@pytest.fixture(scope="session")
def capsules(robot):
    from larc_jax.enclosure import default_capsule_path, load_capsules

    return load_capsules(default_capsule_path(), robot)
