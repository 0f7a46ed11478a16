"""Shared fixtures. The PIPER description comes from LARC_PIPER_DESCRIPTION (set by .ci/run);
tests fall back to ../shared/robots/piper_description beside the checkout."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
_SHARED = ROOT.parent / "shared" / "robots" / "piper_description"
if "LARC_PIPER_DESCRIPTION" not in os.environ and _SHARED.is_dir():
    os.environ["LARC_PIPER_DESCRIPTION"] = str(_SHARED)


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
