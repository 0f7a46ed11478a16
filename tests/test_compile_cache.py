"""Compilation: the persistent cache of the command line (on by default, off by flag or
environment), compile time reported as such, and a library that flips no global JAX option."""

from __future__ import annotations

import collections
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parent.parent / "configs" / "examples"
ARGS = ["certify", str(EXAMPLES / "reach_left.yaml"), "--scene", str(EXAMPLES / "cell.yaml"), "--max-depth", "4"]


def run(tmp_path, *args, **env):
    e = dict(os.environ, **env)
    return subprocess.run([sys.executable, "-m", "larc_jax.drivers.cli", *args], cwd=tmp_path, env=e, capture_output=True,
                          text=True, timeout=300)


def test_help_has_no_raw_rest_markup():
    for sub in ([], ["certify"], ["explain"], ["fit-capsules"], ["verify"]):
        p = subprocess.run([sys.executable, "-m", "larc_jax.drivers.cli", *sub, "--help"], capture_output=True, text=True)
        assert p.returncode == 0 and "`" not in p.stdout, p.stdout


@pytest.mark.slow
def test_cache_is_filled_then_used_and_compiling_is_shown(tmp_path):
    cache = tmp_path / "cache"
    p = run(tmp_path, "-v", "--progress", *ARGS, "--json", "first.json", LARC_COMPILE_CACHE=str(cache))
    assert p.returncode == 0, p.stderr
    assert "compiling kernels" in p.stderr  # the progress bar says so while JAX compiles
    assert f"compilation cache: {cache}" in p.stderr
    entries = list(cache.iterdir())
    assert entries, "nothing was written to the compilation cache"
    first = json.loads((tmp_path / "first.json").read_text())
    assert 0 < first["compile_time_s"] <= first["wall_time_s"]
    assert "compiling" in p.stdout  # the summary line separates compile time
    p = run(tmp_path, "-v", *ARGS, "--leaves", "warm.csv", LARC_COMPILE_CACHE=str(cache))
    assert p.returncode == 0, p.stderr
    line = next(x for x in p.stderr.splitlines() if "kernels:" in x)
    n, hits = (int(w) for w in line.split("kernels: ")[1].replace(",", "").split()[:5:4])
    assert n > 0 and hits == n, line  # every kernel came from the cache
    assert sorted(cache.iterdir()) == sorted(entries)
    assert list((cache / "exported").glob("*.xlaexe")) and list((cache / "robots").glob("*.npz"))
    # Loaded kernels compute exactly what freshly traced ones do.
    p = run(tmp_path, "--no-compile-cache", *ARGS, "--leaves", "cold.csv", LARC_COMPILE_CACHE="")
    assert p.returncode == 0, p.stderr
    assert (tmp_path / "warm.csv").read_bytes() == (tmp_path / "cold.csv").read_bytes()


@pytest.mark.slow
@pytest.mark.parametrize("how", ["env", "flag"])
def test_cache_can_be_turned_off(tmp_path, how):
    xdg = tmp_path / "xdg"
    if how == "env":
        p = run(tmp_path, "-v", *ARGS, LARC_COMPILE_CACHE="0", XDG_CACHE_HOME=str(xdg))
    else:
        p = run(tmp_path, "-v", "--no-compile-cache", *ARGS, LARC_COMPILE_CACHE="", XDG_CACHE_HOME=str(xdg))
    assert p.returncode == 0, p.stderr
    assert "compilation cache: off" in p.stderr and not xdg.exists()


def test_default_cache_folder_follows_xdg(tmp_path, monkeypatch):
    from larc_jax.compilation import cache_dir_from_env, default_cache_dir

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.delenv("LARC_COMPILE_CACHE", raising=False)
    assert default_cache_dir() == tmp_path / "larc_jax" / "jax" == cache_dir_from_env()
    for off in ("0", "off", "False", "no"):
        monkeypatch.setenv("LARC_COMPILE_CACHE", off)
        assert cache_dir_from_env() is None
    monkeypatch.setenv("LARC_COMPILE_CACHE", str(tmp_path / "c"))
    assert cache_dir_from_env() == tmp_path / "c"


@pytest.mark.slow
def test_library_flips_no_global_jax_option():
    code = ("import jax, larc_jax as lj, numpy as np\n"
            "before = (jax.config.jax_compilation_cache_dir, jax.config.jax_enable_x64)\n"
            "r = lj.load_robot(); c = lj.load_capsules(lj.default_capsule_path(), r)\n"
            "t = lj.read_trajectory(%r, r)\n"
            "lj.certify([t], lj.read_scene(%r), r, c, max_depth=2)\n"
            "assert (jax.config.jax_compilation_cache_dir, jax.config.jax_enable_x64) == before == (None, False), before\n"
            "print('ok')\n") % (str(EXAMPLES / "reach_left.yaml"), str(EXAMPLES / "cell.yaml"))
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0 and "ok" in p.stdout, p.stderr


def test_enable_compile_cache_is_an_explicit_opt_in(tmp_path):
    code = ("import jax\nfrom larc_jax.compilation import enable_compile_cache\n"
            "d = enable_compile_cache(%r)\n"
            "assert jax.config.jax_compilation_cache_dir == str(d) and d.is_dir()\n"
            "assert jax.config.jax_persistent_cache_min_compile_time_secs == 0\n"
            "print('ok')\n") % str(tmp_path / "c")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0 and "ok" in p.stdout, p.stderr


def _interval_args(robot, capsules, seed=3):
    import numpy as np

    from larc_jax.engine import batch as B
    from larc_jax.leaf.interval import trajectory_rounding
    from larc_jax.model.scene import read_scene
    from larc_jax.model.trajectory_files import read_trajectory

    traj = read_trajectory(EXAMPLES / "sweep_front.yaml", robot)
    caps = capsules.without_links(robot, ["base_link"])
    b = B.prepare([traj], [read_scene(EXAMPLES / "cell.yaml")], robot, caps, 0.01, np.float64,
                  [trajectory_rounding(traj, robot, caps)], devices=None)
    rng = np.random.default_rng(seed)
    tr = np.zeros(16, np.int64)
    depth = rng.integers(0, 8, 16)
    index = np.array([rng.integers(0, 2**d) for d in depth])
    return b.kernel_args(tr, *b.endpoints(tr, depth, index))


def test_kept_kernel_is_the_same_computation(tmp_path, monkeypatch, robot, capsules):
    """The compiled kernel kept in the cache (a serialized XLA executable) gives bit-identical
    results to the jitted one, when first compiled and when loaded by a later process (simulated:
    in-memory table cleared), and the load is counted as a compile that hit the cache."""
    import jax
    import numpy as np

    from larc_jax import compilation
    from larc_jax.engine import batch as B

    monkeypatch.setattr(compilation, "_EXPORT_DIR", tmp_path / "exported")
    monkeypatch.setattr(compilation, "_LOADED", collections.OrderedDict())
    args = _interval_args(robot, capsules)
    with jax.enable_x64(True):
        ref = [np.asarray(x) for x in B.evaluate_intervals(*args)]
        first = [np.asarray(x) for x in compilation.cached_kernel_call(B.evaluate_intervals, args)]
        compilation.release_kernels()
        with compilation.CompileClock() as clock:
            loaded = [np.asarray(x) for x in compilation.cached_kernel_call(B.evaluate_intervals, args)]
    assert clock.compiles == clock.cache_hits == 1 and clock.compile_s > 0 and clock.trace_s == 0
    for r, f, l in zip(ref, first, loaded):
        np.testing.assert_array_equal(r, f)
        np.testing.assert_array_equal(r, l)
    assert len(list((tmp_path / "exported").glob("evaluate_intervals-*.xlaexe"))) == 1


def test_kept_kernel_keys_and_damage(tmp_path, monkeypatch, robot, capsules):
    """Static arguments a partial binds and the machine enter the key (another file each); a
    damaged file is compiled again and rewritten, with the same results."""
    import functools

    import jax
    import numpy as np

    from larc_jax import compilation

    monkeypatch.setattr(compilation, "_EXPORT_DIR", tmp_path)
    monkeypatch.setattr(compilation, "_LOADED", collections.OrderedDict())

    @functools.partial(jax.jit, static_argnames=("power",))
    def scaled(x, *, power):
        return (x**power,)

    x = np.arange(5.0, dtype=np.float32)
    for power in (2, 3):
        (y,) = compilation.cached_kernel_call(functools.partial(scaled, power=power), (x,))
        np.testing.assert_array_equal(np.asarray(y), x**power)
    assert len(list(tmp_path.glob("scaled-*.xlaexe"))) == 2
    monkeypatch.setattr(compilation, "machine_key", lambda: "another machine")
    compilation.cached_kernel_call(functools.partial(scaled, power=2), (x,))
    files = sorted(tmp_path.glob("scaled-*.xlaexe"))
    assert len(files) == 3
    for f in files:
        f.write_bytes(f.read_bytes()[: len(f.read_bytes()) // 2])  # a torn write
    compilation.release_kernels()
    (y,) = compilation.cached_kernel_call(functools.partial(scaled, power=2), (x,))
    np.testing.assert_array_equal(np.asarray(y), x**2)
    compilation.release_kernels()
    with compilation.CompileClock() as clock:  # rewritten whole: loads
        (y,) = compilation.cached_kernel_call(functools.partial(scaled, power=2), (x,))
    assert clock.cache_hits == clock.compiles == 1
    np.testing.assert_array_equal(np.asarray(y), x**2)
    # At most KEPT_IN_MEMORY held, the least recently used dropped first.
    monkeypatch.setattr(compilation, "KEPT_IN_MEMORY", 2)
    for power in (4, 2, 5):
        compilation.cached_kernel_call(functools.partial(scaled, power=power), (x,))
    assert [call.fn.keywords["power"] for call in compilation._LOADED.values()] == [2, 5]


def test_kept_robot_is_the_built_robot(tmp_path, monkeypatch):
    import dataclasses

    import numpy as np

    from larc_jax import compilation
    from larc_jax.model import robot_cache
    from larc_jax.model.urdf import load_robot

    monkeypatch.setattr(compilation, "_EXPORT_DIR", tmp_path / "exported")
    built = load_robot()
    (kept,) = (tmp_path / "robots").glob("*.npz")
    cached = load_robot()
    assert cached is not built
    for f in dataclasses.fields(built):
        x, y = getattr(built, f.name), getattr(cached, f.name)
        if isinstance(x, np.ndarray) or hasattr(x, "shape"):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
            assert np.asarray(x).dtype == np.asarray(y).dtype
        else:
            assert x == y and type(x) is type(y), f.name
    # Other arguments, another entry; a kept robot whose mesh is gone is not used.
    load_robot(held_joint_values={"joint7": -0.01})
    assert len(list((tmp_path / "robots").glob("*.npz"))) == 2
    key = {"any": "thing"}
    robot_cache.keep_robot(key, built, [tmp_path / "gone.stl"])
    assert robot_cache.cached_robot(key) is None


def test_compiler_options_enter_the_kept_kernels_key(tmp_path):
    """A process started with other XLA options (``XLA_FLAGS``; fast math would change rounding)
    compiles and keeps its own executable instead of loading one compiled under the default
    options; a later process with the same options loads its own."""
    code = ("import functools, jax, numpy as np\n"
            "from larc_jax import compilation\n"
            "compilation.enable_compile_cache(%r)\n"
            "f = jax.jit(lambda x: (x * 2.0 + 1.0,))\n"
            "f.__name__ = 'doubled'\n"
            "with compilation.CompileClock() as clock:\n"
            "    (y,) = compilation.cached_kernel_call(f, (np.arange(4.0),))\n"
            "assert np.asarray(y).tolist() == [1.0, 3.0, 5.0, 7.0]\n"
            "print(clock.cache_hits)\n") % str(tmp_path / "c")

    def kept(**env):
        e = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
        p = subprocess.run([sys.executable, "-c", code], env=dict(e, **env), capture_output=True, text=True, timeout=300)
        assert p.returncode == 0, p.stderr
        return int(p.stdout.split()[-1]), len(list((tmp_path / "c").rglob("doubled-*.xlaexe")))

    assert kept() == (0, 1)
    assert kept() == (1, 1)
    assert kept(XLA_FLAGS="--xla_cpu_enable_fast_math=false") == (0, 2)
    assert kept(XLA_FLAGS="--xla_cpu_enable_fast_math=false") == (1, 2)
