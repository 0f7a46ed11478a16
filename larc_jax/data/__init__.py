"""Robot data shipped inside the package (PIPER): the capsule file written by ``larc
fit-capsules`` and the allowed self-collision pairs (MoveIt's ``disable_collisions``), read with
:mod:`importlib.resources` so an installed ``larc`` finds them without a source checkout."""

from __future__ import annotations

import atexit
import contextlib
from importlib import resources
from pathlib import Path

__all__ = ["data_path", "PIPER_CAPSULES", "PIPER_ALLOWED_COLLISIONS", "PIPER_SELF_SEPARATION"]

PIPER_CAPSULES = "piper_capsules.yaml"
"""PIPER's capsule file (11 capsules, ``larc fit-capsules``)."""
PIPER_ALLOWED_COLLISIONS = "piper_allowed_collisions.yaml"
"""PIPER's allowed self-collision pairs (``python -m experiments.self_collision``)."""
PIPER_SELF_SEPARATION = "piper_self_separation.yaml"
"""PIPER link pairs proven never to touch (``python -m experiments.self_separation``)."""

_extracted = contextlib.ExitStack()  # files extracted from a zipped install, removed at exit
atexit.register(_extracted.close)


def data_path(name: str) -> Path:
    """A file on disk holding the package data file ``name``."""
    ref = resources.files(__name__) / name
    if not ref.is_file():
        raise FileNotFoundError(f"larc_jax/data/{name}: not in this installation of larc_jax")
    if isinstance(ref, Path):
        return ref
    return _extracted.enter_context(resources.as_file(ref))
