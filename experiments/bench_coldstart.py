"""Benchmark: the cold start of ``larc certify`` on one file, as a fresh process.

    python -m experiments.bench_coldstart [--repeats 3] [--json FILE]

(``python -m experiments.bench`` runs it too: its ``coldstart`` section, which the README quotes.)

Runs ``larc -v certify configs/examples/reach_left.yaml --scene configs/examples/cell.yaml`` as a
new process, each time timing the whole process (wall clock, from ``subprocess`` start to exit):

* **first ever**: with an empty compilation cache (a fresh ``XDG_CACHE_HOME``), ``repeats``
  times, each with its own empty cache;
* **warm cache**: ``repeats`` more runs sharing the cache the first run filled;
* **no cache**: ``repeats`` runs with ``--no-compile-cache`` (what every run cost before the
  cache);
* **bad option**: ``repeats`` runs with a wrong ``--hold`` (a joint the robot does not have),
  which must be refused (exit 2) before anything compiles;
* **device tree**: the first 32 Stage B trajectories of ``medium_window`` in one ``larc certify``
  (:data:`TREE_COMMAND`: enough that LARC runs the device tree,
  :data:`larc_jax.engine.tree_pool.TREE_FROM_TRAJECTORIES`), once with an empty cache and
  ``repeats`` times with the cache that run filled.

The phases come from ``larc -v``'s ``time:`` line (loading the robot: URDF parse, capsule file
and motion constants; reading the trajectory; certifying, split into compiling — tracing,
lowering, XLA compilation or cache load — and running); ``import`` is the wall time of a fresh
``python -c "import larc_jax.drivers.cli, larc_jax.engine.certify"`` (interpreter start and imports; the
remainder of a run's wall time is the interpreter exit and argument parsing). Medians are
reported; the machine's load average is recorded because the figures depend on it.
"""

from __future__ import annotations

import argparse
import os
import platform
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = ROOT / "configs" / "examples"
COMMAND = ["certify", str(EXAMPLES / "reach_left.yaml"), "--scene", str(EXAMPLES / "cell.yaml")]
STAGEB_SET = ROOT / "results" / "stageB" / "dataset" / "trajectories" / "medium_window"
TREE_FILES = [str(p) for p in sorted(STAGEB_SET.glob("*.yaml"))[:32]]
TREE_COMMAND = ["certify", *TREE_FILES, "--scene",
                str(ROOT / "configs" / "scenes" / "medium_window.yaml"), "--no-fail-on-uncertified"]
TIME_LINE = re.compile(r"time: (?P<laps>.*) \(of which compiling (?P<compile>[\d.]+) s, running (?P<run>[\d.]+) s\)")

__all__ = ["run_once", "refusal_once", "measure", "main"]


def _larc() -> list[str]:
    return [sys.executable, "-m", "larc_jax.drivers.cli"]


def run_once(cache_home: str | None, *extra: str, command: list[str] = COMMAND) -> dict:
    """One fresh ``larc -v`` process of ``command``: wall seconds and the phases it logs."""
    env = dict(os.environ)
    if cache_home is not None:
        env["XDG_CACHE_HOME"] = cache_home
    env.pop("LARC_COMPILE_CACHE", None)
    t0 = time.perf_counter()
    p = subprocess.run(_larc() + ["-v", *extra, *command], env=env, capture_output=True, text=True, cwd=ROOT)
    wall = time.perf_counter() - t0
    if p.returncode != 0:
        raise RuntimeError(f"larc exited {p.returncode}:\n{p.stderr}")
    m = TIME_LINE.search(p.stderr)
    if not m:
        raise RuntimeError(f"no time: line in larc -v output:\n{p.stderr}")
    laps = {k: float(v) for k, v in re.findall(r"(\w+) ([\d.]+) s", m["laps"])}
    return dict(wall_s=wall, robot_s=laps.get("robot", 0.0), read_s=laps.get("read", 0.0),
                certify_s=laps.get("certify", 0.0), compile_s=float(m["compile"]), run_s=float(m["run"]))


def refusal_once(cache_home: str) -> float:
    """Wall seconds of a fresh ``larc certify`` with a wrong ``--hold``, which must exit 2."""
    env = dict(os.environ, XDG_CACHE_HOME=cache_home)
    env.pop("LARC_COMPILE_CACHE", None)
    t0 = time.perf_counter()
    p = subprocess.run(_larc() + [*COMMAND, "--hold", "no_such_joint=0"], env=env, capture_output=True, text=True,
                       cwd=ROOT)
    wall = time.perf_counter() - t0
    if p.returncode != 2 or "no_such_joint" not in p.stderr:
        raise RuntimeError(f"a wrong --hold was not refused (exit {p.returncode}):\n{p.stderr}")
    return wall


def import_time() -> float:
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-c", "import larc_jax.drivers.cli, larc_jax.engine.certify"], check=True, cwd=ROOT)
    return time.perf_counter() - t0


def _median(rows: list[dict]) -> dict:
    return {k: round(statistics.median(r[k] for r in rows), 3) for k in rows[0]}


def measure(repeats: int = 3) -> dict:
    """Every figure of the module docstring, medians of ``repeats`` runs each."""
    load_before = os.getloadavg()
    imports = [import_time() for _ in range(repeats)]
    first, warm, nocache, refused = [], [], [], []
    with tempfile.TemporaryDirectory() as shared:
        for _ in range(repeats):
            with tempfile.TemporaryDirectory() as fresh:
                first.append(run_once(fresh))
        run_once(shared)  # fill the shared cache
        for _ in range(repeats):
            warm.append(run_once(shared))
        for _ in range(repeats):
            nocache.append(run_once(shared, "--no-compile-cache"))
        for _ in range(repeats):
            refused.append(refusal_once(shared))
    with tempfile.TemporaryDirectory() as cache:
        tree_first = run_once(cache, command=TREE_COMMAND)
        tree_warm = [run_once(cache, command=TREE_COMMAND) for _ in range(repeats)]
    out = dict(
        command="larc certify configs/examples/reach_left.yaml --scene configs/examples/cell.yaml",
        repeats=repeats, import_s=round(statistics.median(imports), 3),
        first_ever=_median(first), warm_cache=_median(warm), no_cache=_median(nocache),
        bad_option_s=round(statistics.median(refused), 3),
        tree=dict(trajectories=len(TREE_FILES), scene="medium_window", first_ever=_median([tree_first]),
                  warm_cache=_median(tree_warm)),
        machine=dict(cpus=os.cpu_count(), system=f"{platform.system()} {platform.machine()}",
                     python=platform.python_version(), load_average_before=[round(x, 2) for x in load_before],
                     load_average_after=[round(x, 2) for x in os.getloadavg()]),
    )
    w = out["warm_cache"]
    phases = dict(imports=out["import_s"], robot=w["robot_s"], compile=w["compile_s"], run=w["run_s"])
    out["warm_cache_dominant_phase"] = max(phases, key=phases.get)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", help="write the figures as JSON")
    args = ap.parse_args(argv)

    out = measure(args.repeats)
    w = out["warm_cache"]
    phases = dict(imports=out["import_s"], robot=w["robot_s"], compile=w["compile_s"], run=w["run_s"])
    out["warm_cache_dominant_phase"] = max(phases, key=phases.get)
    for name in ("first_ever", "warm_cache", "no_cache"):
        r = out[name]
        print(f"{name:>10}: {r['wall_s']:.2f} s wall (robot {r['robot_s']:.2f} s, certify {r['certify_s']:.2f} s: "
              f"compile {r['compile_s']:.2f} s, run {r['run_s']:.2f} s)")
    print(f"    import: {out['import_s']:.2f} s (fresh python, import larc_jax.drivers.cli + certify)")
    t = out["tree"]
    print(f"      tree: {t['trajectories']} trajectories, {t['first_ever']['wall_s']:.2f} s wall with an empty cache, "
          f"{t['warm_cache']['wall_s']:.2f} s warm (compiling {t['warm_cache']['compile_s']:.2f} s)")
    print(f"bad option: refused in {out['bad_option_s']:.2f} s")
    print(f"warm cache: dominated by {out['warm_cache_dominant_phase']}; load average "
          f"{out['machine']['load_average_before']} -> {out['machine']['load_average_after']}")
    if args.json:
        from larc_jax.io import atomic_write_json

        atomic_write_json(args.json, out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
