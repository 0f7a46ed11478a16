"""Shared fixtures and the test session's environment.

* The PIPER description comes from ``LARC_PIPER_DESCRIPTION``; tests fall back to
  ``../shared/robots/piper_description`` beside the checkout. A *relative* value (the README's
  commands give ``../shared/...``) is made absolute here, once, against the folder pytest was
  started from: tests that run ``larc`` in temporary folders inherit the environment and must
  still find PIPER.
* Tests share a persistent compilation cache (:mod:`larc_jax.compilation`), in this process
  and in the ``larc`` processes they start (``LARC_COMPILE_CACHE``): by default
  ``$XDG_CACHE_HOME/larc_jax/tests`` (``~/.cache/...``), so a second test session compiles
  little; ``LARC_TEST_COMPILE_CACHE=DIR`` moves it, ``LARC_TEST_COMPILE_CACHE=tmp`` uses a fresh
  temporary folder (a cold, hermetic session). Entries are keyed by the compiled program (and
  kept executables by the library's sources and the machine), so a code change never meets a stale entry.
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

_WHERE = os.environ.get("LARC_TEST_COMPILE_CACHE", "")
if _WHERE == "tmp":
    _TMP = tempfile.TemporaryDirectory(prefix="larc-test-compile-cache-")
    _WHERE = _TMP.name
if not _WHERE:
    from larc_jax.compilation import default_cache_dir

    _WHERE = str(default_cache_dir().parent / "tests")
os.environ["LARC_COMPILE_CACHE"] = _WHERE


def pytest_configure(config):
    from larc_jax.compilation import enable_compile_cache

    enable_compile_cache(os.environ["LARC_COMPILE_CACHE"])


@pytest.fixture(scope="session")
def piper_dir() -> Path:
    from larc_jax.model.urdf import piper_description_dir

    return piper_description_dir()


@pytest.fixture(scope="session")
def robot():
    from larc_jax.model.urdf import load_robot

    return load_robot()


@pytest.fixture(scope="session")
def capsules(robot):
    from larc_jax.enclosure import default_capsule_path, load_capsules

    return load_capsules(default_capsule_path(), robot)


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_kernels():
    """Drop JAX's in-memory executables after each test module: every compiled CPU executable
    holds memory mappings, and one long pytest process compiling hundreds of kernel shapes
    (interval, broad phase, cascade, self test, per bucket) can reach the kernel's
    vm.max_map_count (65530), where XLA aborts. Later modules reload from the persistent
    compilation cache the tests share. The kernels :func:`larc_jax.compilation.cached_kernel_call`
    keeps (with the cache on) are JAX's cache's reach too: released with it."""
    yield
    import gc

    import jax

    from larc_jax.compilation import release_kernels
    from larc_jax.engine.tree_pool import small_batches_on_tree

    jax.clear_caches()
    release_kernels()
    small_batches_on_tree(False)  # a module that warmed the tree up leaves the next on the host frontier
    gc.collect()
