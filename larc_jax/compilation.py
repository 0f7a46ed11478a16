"""JAX compilation: the persistent compilation cache, and how long compiling took.

Every ``certify`` call runs jitted kernels whose shapes depend on the dataset (waypoint, box and
frontier size classes, :mod:`larc_jax.engine.batch`); each new shape is traced, lowered and compiled by
XLA, seconds each on a CPU. JAX's *persistent compilation cache* keeps the compiled executables
on disk, so a later process loads them instead of compiling again (it still traces and lowers,
which computes the cache key).

* The ``larc`` command line turns the cache on by default in :func:`default_cache_dir`
  (``$XDG_CACHE_HOME/larc_jax/jax`` or ``~/.cache/larc_jax/jax``); ``--no-compile-cache`` or
  ``LARC_COMPILE_CACHE=0`` turn it off, ``LARC_COMPILE_CACHE=/some/dir`` moves it.
* The library never changes ``jax.config`` by itself (importing it flips nothing): Python
  users opt in with :func:`enable_compile_cache`, which sets JAX's global cache options (the
  cache directory, and thresholds of zero so that even small kernels are kept).
* With the cache on, the interval kernel is also kept *traced*: the first call of each kernel
  shape exports it (:mod:`jax.export`, the traced and lowered StableHLO) into the cache folder,
  and later processes load that instead of tracing the Python code again
  (:func:`cached_kernel_call`; tracing costs about as much as loading the compiled kernel).
  An export is keyed by the SHA-256 of every source file of ``larc_jax``, the JAX and jaxlib
  versions (:func:`library_hash`), the backend, the x64 mode, and the call's static structure and argument shapes, so a
  changed library, JAX or argument never meets a stale kernel.
* With the cache on, the loaders also keep what they build from the robot's files
  (:mod:`larc_jax.model.robot_cache`): the robot model, the URDF's parse and the hull parts,
  keyed by the same library hash (:func:`library_hash`) and the SHA-256 of the files: a later
  process skips parsing the URDF, reading the meshes and importing yourdfpy, trimesh and SciPy.
  :func:`keep_builds_in` turns this on without importing JAX, so the command line reads and
  checks every input before it pays for JAX's import.
* :class:`CompileClock` measures, while active, the seconds JAX spends tracing, lowering and
  compiling (or loading from the cache), from :mod:`jax.monitoring` events; ``certify`` reports
  them as :attr:`larc_jax.engine.results.DatasetResult.compile_time_s`, separately from the run time.
"""

from __future__ import annotations

import functools
import hashlib
import os
import threading
from pathlib import Path

__all__ = ["CACHE_ENV", "default_cache_dir", "cache_dir_from_env", "enable_compile_cache", "keep_builds_in", "cached_kernel_call",
           "cached_kernel", "tracked_call",
           "CompileClock"]

CACHE_ENV = "LARC_COMPILE_CACHE"
"""Environment variable: ``0`` / ``false`` / ``off`` / ``no`` turn the command line's cache off; a
path puts it there."""

_OFF = {"0", "false", "off", "no"}


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/larc_jax/jax``, else ``~/.cache/larc_jax/jax``."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "larc_jax" / "jax"


def cache_dir_from_env() -> Path | None:
    """The cache folder ``LARC_COMPILE_CACHE`` asks for: ``None`` when it turns the cache off,
    the path it names, or :func:`default_cache_dir` when it is unset or empty."""
    value = os.environ.get(CACHE_ENV, "").strip()
    if value.lower() in _OFF:
        return None
    return Path(value).expanduser() if value else default_cache_dir()


def enable_compile_cache(path: str | os.PathLike | None = None) -> Path:
    """Turn on JAX's persistent compilation cache in ``path`` (default
    :func:`default_cache_dir`) for this process, keeping every compiled kernel however small or
    quick to compile, and :func:`keep_builds_in` that folder. This changes JAX's global
    configuration (it is an explicit opt-in; the library never calls it by itself). Returns the
    folder."""
    import jax

    folder = keep_builds_in(path)
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)  # no size threshold
    jax.config.update("jax_enable_compilation_cache", True)
    return folder


def keep_builds_in(path: str | os.PathLike | None = None) -> Path:
    """Keep the traced kernels (:func:`cached_kernel_call`) and what the loaders build from the
    robot's files (:mod:`larc_jax.model.robot_cache`) in ``path`` (default
    :func:`default_cache_dir`), without importing JAX or changing its configuration: the command
    line calls this first, reads and checks every input (a robot kept here loads without
    yourdfpy), and only then imports JAX and calls :func:`enable_compile_cache`. Returns the
    folder."""
    folder = Path(path).expanduser() if path is not None else default_cache_dir()
    folder.mkdir(parents=True, exist_ok=True)
    global _EXPORT_DIR
    _EXPORT_DIR = folder / "exported"
    return folder


_EXPORT_DIR: Path | None = None
"""Where traced kernels are kept (set by :func:`enable_compile_cache`; None: not kept)."""
_LOADED: dict = {}
"""Kernel key → jitted call of its export, for this process."""


def export_dir() -> Path | None:
    """The folder where traced kernels are kept, or None when the cache is off."""
    return _EXPORT_DIR


@functools.lru_cache(maxsize=1)
def library_hash() -> str:
    """SHA-256 of every source file of the package and of the versions of the packages whose
    results the caches keep (JAX, jaxlib, yourdfpy, trimesh, SciPy, NumPy): any change gives new
    keys. Read without importing them (:mod:`importlib.metadata`)."""
    from importlib import metadata

    versions = []
    for name in ("jax", "jaxlib", "yourdfpy", "trimesh", "scipy", "numpy"):
        try:
            versions.append(f"{name}={metadata.version(name)}")
        except metadata.PackageNotFoundError:
            versions.append(f"{name}=none")
    h = hashlib.sha256(" ".join(versions).encode())
    root = Path(__file__).resolve().parent
    for p in sorted(root.rglob("*.py")):
        h.update(str(p.relative_to(root)).encode() + b"\0" + p.read_bytes() + b"\0")
    return h.hexdigest()


def cached_kernel_call(fn, args: tuple):
    """``fn(*args)`` for a jitted ``fn`` returning a tuple of arrays; with the cache on
    (:func:`enable_compile_cache`), through its :mod:`jax.export` kept in the cache folder, so a
    process that finds the export skips tracing ``fn``. Same computation, same results."""
    if _EXPORT_DIR is None:
        return fn(*args)
    import jax
    import numpy as np

    leaves, treedef = jax.tree.flatten(args)
    avals = [jax.ShapeDtypeStruct(np.shape(x), np.result_type(getattr(x, "dtype", x))) for x in leaves]
    key = hashlib.sha256("\0".join([library_hash(), jax.default_backend(), fn.__name__, str(jax.config.jax_enable_x64),
                                     str(treedef),
                                     repr([(a.shape, str(a.dtype)) for a in avals])]).encode()).hexdigest()
    call = _LOADED.get(key)
    if call is None:
        call = _LOADED[key] = _load_or_export(fn, treedef, avals, _EXPORT_DIR / f"{fn.__name__}-{key[:40]}.jaxexport")
    return call(*leaves)


_SEEN: set = set()
"""Call signatures (function, shapes, dtypes, static structure) seen by :func:`tracked_call` with
an ``on_compile`` listener: a call with a new one compiles first (or loads from the persistent
cache). Tracked only when someone listens, so the default path pays nothing."""


def tracked_call(fn, args: tuple, on_compile):
    """``fn(*args)``, telling ``on_compile`` (True, then False) when the call compiles (a signature
    this process has not called ``fn`` with)."""
    if on_compile is None:
        return fn(*args)
    import jax
    import numpy as np

    leaves = jax.tree.leaves(args)
    sig = (fn, jax.tree.structure(args), tuple((np.shape(x), str(getattr(x, "dtype", type(x)))) for x in leaves),
           jax.config.jax_enable_x64)
    new = sig not in _SEEN
    if new:
        on_compile(True)
    try:
        return fn(*args)
    finally:
        _SEEN.add(sig)
        if new:
            on_compile(False)


_CACHED_KERNELS: dict = {}


def cached_kernel(kernel):
    """``kernel`` (jitted, returning a tuple of arrays) through :func:`cached_kernel_call`: one
    callable per kernel, so that :func:`tracked_call` recognises a shape it has seen."""
    if kernel not in _CACHED_KERNELS:
        _CACHED_KERNELS[kernel] = functools.partial(_kernel_call, kernel)
    return _CACHED_KERNELS[kernel]


def _kernel_call(kernel, *args):
    return cached_kernel_call(kernel, args)


def _load_or_export(fn, treedef, avals, path: Path):
    import jax

    from .io import atomic_write_bytes

    try:
        exported = jax.export.deserialize(bytearray(path.read_bytes()))
    except Exception:  # noqa: BLE001 - missing, unreadable or from another version: export again
        def flat(*leaves):
            return fn(*jax.tree.unflatten(treedef, leaves))

        exported = jax.export.export(jax.jit(flat))(*avals)
        try:
            atomic_write_bytes(path, bytes(exported.serialize()))
        except OSError:  # an unwritable cache only costs the next process a trace
            pass
    return jax.jit(exported.call)


_TRACE = "/jax/core/compile/jaxpr_trace_duration"
_LOWER = "/jax/core/compile/jaxpr_to_mlir_module_duration"
_COMPILE = "/jax/core/compile/backend_compile_duration"  # XLA compile, or load from the cache
_CACHE_HIT = "/jax/compilation_cache/cache_hits"


class CompileClock:
    """While active (``with CompileClock() as clock:``), counts what JAX compiles in this
    process: ``compiles`` (executables compiled or loaded from the persistent cache),
    ``cache_hits`` (of those, loaded), and seconds spent ``trace_s``, ``lower_s`` and
    ``compile_s`` (XLA compilation or cache load); ``seconds`` is their sum.

    One :mod:`jax.monitoring` listener, installed on first use, feeds every active clock (JAX
    cannot remove a listener in every version). Nested and concurrent clocks all count.
    """

    _active: list["CompileClock"] = []
    _lock = threading.Lock()
    _installed = False

    def __init__(self):
        self.compiles = 0
        self.cache_hits = 0
        self.trace_s = 0.0
        self.lower_s = 0.0
        self.compile_s = 0.0

    @property
    def seconds(self) -> float:
        return self.trace_s + self.lower_s + self.compile_s

    @classmethod
    def _install(cls) -> None:
        with cls._lock:
            if cls._installed:
                return
            import jax.monitoring

            def on_duration(event: str, duration: float, **kwargs) -> None:
                field = {_TRACE: "trace_s", _LOWER: "lower_s", _COMPILE: "compile_s"}.get(event)
                if field is None:
                    return
                for clock in list(cls._active):
                    setattr(clock, field, getattr(clock, field) + float(duration))
                    if event == _COMPILE:
                        clock.compiles += 1

            def on_event(event: str, **kwargs) -> None:
                if event == _CACHE_HIT:
                    for clock in list(cls._active):
                        clock.cache_hits += 1

            jax.monitoring.register_event_duration_secs_listener(on_duration)
            jax.monitoring.register_event_listener(on_event)
            cls._installed = True

    def __enter__(self) -> "CompileClock":
        self._install()
        with self._lock:
            self._active.append(self)
        return self

    def __exit__(self, *exc) -> bool:
        with self._lock:
            self._active.remove(self)
        return False
