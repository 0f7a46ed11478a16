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
* With the cache on, the kernels (the interval kernels, the spline tables' level 0 and the
  device tree's program) are also kept *compiled*: the first call of each kernel shape serializes
  its XLA executable (:mod:`jax.experimental.serialize_executable`) into the cache folder, and
  later processes load that instead of tracing, lowering and compiling again
  (:func:`cached_kernel_call`; JAX's own cache still traces and lowers, which computes its key,
  and that costs about as much as loading). An executable is keyed by the SHA-256 of every source
  file of ``larc_jax`` and the versions of the packages it uses (:func:`library_hash`), the
  backend, device and CPU features (:func:`machine_key`), the x64 mode, and the call's static
  arguments, structure and argument shapes, so a changed library, JAX, machine or argument never
  meets a stale kernel; one that fails its first run is dropped and compiled again.
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

import collections
import functools
import hashlib
import os
import threading
from pathlib import Path

__all__ = ["CACHE_ENV", "default_cache_dir", "cache_dir_from_env", "enable_compile_cache", "keep_builds_in", "cached_kernel_call",
           "cached_kernel", "tracked_call",
           "release_kernels", "machine_key", "kernel_name", "KEPT_IN_MEMORY", "CompileClock"]

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
    """Keep the compiled kernels (:func:`cached_kernel_call`) and what the loaders build from the
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
"""Where compiled kernels are kept (set by :func:`enable_compile_cache`; None: not kept)."""
KEPT_IN_MEMORY = 48
"""At most this many kernel executables are held by :func:`cached_kernel_call` in a process, the
least recently used dropped first (it stays in the cache folder, and is loaded again in a fraction
of a second when met again): each compiled CPU executable holds hundreds of memory mappings (about
800 for an interval kernel, 1,500 for the device tree's program, measured), and a long-lived
process meeting many kernel shapes would otherwise reach the system's limit
(``vm.max_map_count``, 65,530 by default), where XLA aborts."""
_LOADED: collections.OrderedDict = collections.OrderedDict()
"""Kernel key → its executable (:class:`_Kept`), for this process, least recently used first
(:data:`KEPT_IN_MEMORY`, :func:`release_kernels`)."""
_LOADED_LOCK = threading.Lock()


def export_dir() -> Path | None:
    """The folder where compiled kernels are kept, or None when the cache is off."""
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


@functools.lru_cache(maxsize=1)
def machine_key() -> str:
    """What a compiled executable is valid for besides the library: JAX's default backend, its
    platform version and device kind, and (on Linux) the host CPU's feature flags, since XLA's CPU
    backend compiles for the features of the machine it runs on; a kept executable never meets
    another machine's (a cache folder shared over a network, a container moved between hosts).

    Also the compiler's own options, as JAX's cache key has them: ``XLA_FLAGS`` and
    ``LIBTPU_INIT_ARGS`` (e.g. ``--xla_cpu_enable_fast_math=true`` changes rounding, and the
    guards assume IEEE arithmetic as compiled by default), and the trace-time matmul precision; a
    process started with other options never loads an executable compiled under these."""
    import jax

    device = jax.devices()[0]
    flags = ""
    try:
        with open("/proc/cpuinfo") as f:
            flags = next((line for line in f if line.startswith(("flags", "Features"))), "")
    except OSError:
        pass
    compiler = [os.environ.get(name, "") for name in ("XLA_FLAGS", "LIBTPU_INIT_ARGS")]
    return "\0".join([jax.default_backend(), getattr(device.client, "platform_version", ""), device.device_kind, flags,
                      *compiler, str(jax.config.jax_default_matmul_precision)])


def kernel_name(fn) -> tuple[str, str]:
    """A kernel's name and the static arguments a :func:`functools.partial` binds (keywords of
    plain values, e.g. the device tree's step widths), as they enter its cache key."""
    if isinstance(fn, functools.partial):
        name, _ = kernel_name(fn.func)
        return name, repr((fn.args, sorted(fn.keywords.items())))
    return fn.__name__, ""


def cached_kernel_call(fn, args: tuple):
    """``fn(*args)`` for a jitted ``fn`` (or a :func:`functools.partial` of a jittable function
    binding static keywords) returning a tuple of arrays; with the cache on
    (:func:`enable_compile_cache`), through its compiled executable kept in the cache folder, so
    a process that finds it skips tracing, lowering and compiling ``fn``. Same computation, same
    results.

    An executable is keyed by :func:`library_hash`, :func:`machine_key`, the x64 mode, the
    kernel's name and static arguments (:func:`kernel_name`), and the arguments' structure,
    shapes and dtypes. It is a pickle (:mod:`jax.experimental.serialize_executable`): the cache
    folder is trusted like the code itself, as JAX's own cache is."""
    if _EXPORT_DIR is None:
        return fn(*args)
    import jax
    import numpy as np

    leaves, treedef = jax.tree.flatten(args)
    avals = [jax.ShapeDtypeStruct(np.shape(x), np.result_type(getattr(x, "dtype", x))) for x in leaves]
    name, static = kernel_name(fn)
    key = hashlib.sha256("\0".join([library_hash(), machine_key(), name, static, str(jax.config.jax_enable_x64),
                                     str(treedef),
                                     repr([(a.shape, str(a.dtype)) for a in avals])]).encode()).hexdigest()
    with _LOADED_LOCK:
        call = _LOADED.get(key)
        if call is not None:
            _LOADED.move_to_end(key)
    if call is None:  # loaded or compiled outside the lock: threads running other kernels go on
        call = _Kept(fn, treedef, avals, _EXPORT_DIR / f"{name}-{key[:40]}.xlaexe")
        with _LOADED_LOCK:
            _LOADED[key] = call
            while len(_LOADED) > KEPT_IN_MEMORY:
                _LOADED.popitem(last=False)
    return call(leaves)


def release_kernels() -> None:
    """Drop the executables this process loaded or compiled through :func:`cached_kernel_call`
    (they stay in the cache folder). Each compiled CPU executable holds hundreds of memory
    mappings: a long-lived process that meets many kernel shapes (a test suite, a Dask worker)
    calls this with :func:`jax.clear_caches` to stay under the system's mapping limit
    (:data:`KEPT_IN_MEMORY` bounds what this module holds)."""
    with _LOADED_LOCK:
        _LOADED.clear()


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


class _Kept:
    """One kernel shape's executable: loaded from ``path``, or compiled and written there."""

    def __init__(self, fn, treedef, avals, path: Path):
        self.fn, self.treedef, self.avals, self.path = fn, treedef, avals, path
        self.compiled, self.checked = self._load(), False
        if self.compiled is None:
            self.compiled, self.checked = self._compile(), True

    def __call__(self, leaves):
        import numpy as np

        leaves = [x if hasattr(x, "dtype") else np.asarray(x, a.dtype) for x, a in zip(leaves, self.avals)]
        if self.checked:
            return self.compiled(*leaves)
        # A loaded executable's first run is waited for: one that cannot run (a file from a
        # broken write, an XLA that cannot link what it kept) is dropped and compiled again.
        import jax

        try:
            out = jax.block_until_ready(self.compiled(*leaves))
        except jax.errors.JaxRuntimeError:
            self.path.unlink(missing_ok=True)
            self.compiled = self._compile()
            out = self.compiled(*leaves)
        self.checked = True
        return out

    def _load(self):
        import pickle
        import time

        import jax
        from jax.experimental.serialize_executable import deserialize_and_load

        start = time.perf_counter()
        try:
            payload, in_tree, out_tree = pickle.loads(self.path.read_bytes())
            compiled = deserialize_and_load(payload, in_tree, out_tree, execution_devices=jax.devices()[:1])
        except Exception:  # noqa: BLE001 - missing, unreadable or from another version: compile again
            return None
        CompileClock.count_load(time.perf_counter() - start)
        return compiled

    def _compile(self):
        import pickle
        import secrets

        import jax
        from jax.experimental.serialize_executable import serialize

        from .io import atomic_write_bytes

        fn, treedef = self.fn, self.treedef

        def flat(*leaves):
            return fn(*jax.tree.unflatten(treedef, leaves))

        # JAX's persistent cache keys a module by its name too: named after this file, a miss here
        # is a miss there. An executable JAX's cache loaded cannot be serialized again (it runs,
        # but a second load fails: "Function ... not found"), so a hit there compiles once more
        # under a fresh name.
        for salt in ("", "_" + secrets.token_hex(8)):
            flat.__name__ = flat.__qualname__ = "larc_" + self.path.stem.replace("-", "_") + salt
            with CompileClock() as clock:
                compiled = jax.jit(flat).lower(*self.avals).compile()
            if not clock.cache_hits:
                break
        try:
            payload, in_tree, out_tree = serialize(compiled)
            atomic_write_bytes(self.path, pickle.dumps((payload, in_tree, out_tree)))
        except (ValueError, NotImplementedError, OSError, pickle.PicklingError):
            pass  # not serializable, or an unwritable cache: the next process compiles again
        return compiled


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

    @classmethod
    def count_load(cls, seconds: float) -> None:
        """Count an executable :func:`cached_kernel_call` loaded itself (JAX sends no event for
        it) as a compile that hit the cache."""
        with cls._lock:
            for clock in list(cls._active):
                clock.compiles += 1
                clock.cache_hits += 1
                clock.compile_s += float(seconds)

    def __enter__(self) -> "CompileClock":
        self._install()
        with self._lock:
            self._active.append(self)
        return self

    def __exit__(self, *exc) -> bool:
        with self._lock:
            self._active.remove(self)
        return False
