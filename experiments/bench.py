"""Benchmark: where LARC stands on this machine, every figure measured in one run.

    python -m experiments.bench [--json results/bench/bench_cpu.json] [--quick]

On a GPU set ``XLA_PYTHON_CLIENT_PREALLOCATE=false``: the cold-start, manifest and RSS sections
start fresh processes beside this one, and by default each JAX process takes most of the GPU's
memory. The committed GPU figures (an NVIDIA H200 lent for one session, 15 minutes in all) came
from two runs, each on a freshly started machine::

    python -m experiments.bench --json results/bench/bench_gpu.json --skip-audit --skip-reference \
        --rss-n '' --manifest-n 2000 --peak-gflops 34000   # stopped at its limit after ``capsules``
    python -m experiments.bench --json results/bench/bench_gpu.json --render
    python -m experiments.bench --json results/bench/bench_gpu_hull.json --enclosures hull \
        --skip-paired --stageB-only --peak-gflops 34000

Sections (each printed and written into the JSON):

* ``stageB`` — the 160 committed Stage B trajectories with their scenes, for the paper's capsule
  test and the default hull cascade (``enclosure="hull"``): LARC and fixed-fine whole-dataset
  warm times (:data:`WARM_ROUNDS` rounds after a first call each and :data:`SETTLE_ROUNDS`
  untimed ones, the two methods' order alternating from round to round, so that a slow spell of
  the machine falls on both; each method's median), interval evaluations per second, and *real* capsule–box pairs per second
  (each evaluated interval counts its capsules × the real boxes of its scene; padded or masked
  boxes do not count); compile time (first call − warm call) reported separately; the
  intervals the capsule test leaves open (every evaluated interval it does not pass: the only
  ones the cascade's later stages can cost anything); the paper's paired protocol, one
  trajectory per call (:func:`section_paired`): the median over trajectories of fine / LARC;
  and the floor of such a call (:func:`section_floor`): one interval per trajectory
  (``method="coarse"``, ``coarse_depth=0``), what a call costs whatever it evaluates.
* ``coldstart`` — ``larc certify`` of the README example as a fresh process, with an empty and
  a warm compilation cache, and a wrong option's refusal (:mod:`experiments.bench_coldstart`).
* ``manifest`` — ``larc certify --manifest`` of ``--manifest-n`` rows cycling through the
  tightness set's planned trajectories (``results/tightness``), default cascade, as one fresh
  process with an empty compilation cache: wall time (compiling included) and peak RSS; and,
  measured alone afterwards, the time to read one row's trajectory file, with its share of
  that wall (:func:`_read_ms_per_row`).
* ``kernel`` — XLA's cost analysis of the compiled interval kernel at the largest bucket on the
  Stage B scenes: flops and bytes accessed per interval, against the machine's nominal peak; and
  the kernel alone timed on that bucket (best of :data:`KERNEL_REPEATS`): its real capsule–box
  pairs per second and GFLOP/s, beside the whole-set figures that add the host's work and the
  smaller buckets of a frontier; and where its time goes: its first parts compiled alone
  (:func:`_stage_kernel`), timed in turns with it.
* ``reference`` — the NumPy float64 reference (the paper's Algorithm 1) on the same
  trajectories: ratio reference / LARC (``--skip-reference`` leaves it out).
* ``audit`` — the FCL mesh audit at 250 Hz (``experiments.audit``, 2 worker processes) on the
  same trajectories: ratio audit / LARC (``--skip-audit`` leaves it out).
* ``stream`` — ``certify_stream`` over N Stage B-like trajectories (each a Stage B trajectory
  with a random joint offset and time scale, generated lazily): trajectories and intervals per
  second.
* ``rss`` — peak resident memory of a fresh process that certifies N Stage B-like trajectories,
  for each N of ``--rss-n``, one subprocess per N (``experiments.bench_rss``), streamed, and in
  one ``certify`` call for N up to :data:`MAX_CALL_N` (a call holds all its inputs and leaves).

Every section is written into the JSON as soon as it is measured, so a run stopped part-way keeps
what it finished (the Markdown table is written at the end, or from such a file by ``--render``).
Each Stage B method records ``decisions_sha256`` (:func:`decisions_sha256`): equal hashes from two
machines (a CPU and a GPU) mean the same decision and the same number of evaluations for every
trajectory.

The kernel, reference, audit, stream and RSS sections measure the paper's capsule test
(``enclosure="capsules"``); :mod:`experiments.bench_cascade` breaks the hull cascade's cost down
by stage.

Machine peak: ``cores × clock × flops/cycle`` with flops/cycle = 16 (float64: two 256-bit FMA
pipes, as on AMD Zen 4 and Intel AVX2/AVX-512 server cores) unless ``--peak-gflops`` is given;
it is a nominal figure, stated as such in the output.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
STAGEB_DIR = ROOT / "results" / "stageB" / "dataset" / "trajectories"
SCENES_DIR = ROOT / "configs" / "scenes"

__all__ = ["stageB_dataset", "stageB_like", "decisions_sha256", "tree_sentence", "main"]

ENCLOSURE = "capsules"
"""The interval test of the kernel, reference, audit, stream and RSS sections (module docstring)."""
ENCLOSURES = ("capsules", "hull")
"""The Stage B section's: the paper's capsule test, and the default hull cascade."""
PAIRED_REPEATS = 3
"""Timed calls per trajectory and method in the paired section."""
KERNEL_REPEATS = 20
"""Timed calls of the compiled kernel on one full bucket in the kernel section (the best is kept)."""
WARM_ROUNDS = 5
"""Timed rounds of the whole-set calls (each round one call per method, the order alternating)."""
SETTLE_ROUNDS = 2
"""Untimed rounds before them: on this machine the two or three calls after the first (compiling)
one of a whole-set call ran up to twice as long as later ones (0.13-0.24 s against 0.08-0.09 s
for LARC's capsule test, measured with and without a pause of 8 s after the first call: the count
of calls matters, not the time), and a median of five rounds that start there carries it."""
MAX_CALL_N = 10_000
"""Largest N of the RSS section measured as one ``certify`` call (module docstring)."""


def tree_sentence(tree: dict) -> str:
    """The sentence the README and the bench table say of the command line's device tree
    (:mod:`experiments.bench_coldstart`'s ``tree``)."""
    first, warm = tree["first_ever"], tree["warm_cache"]
    return (f"The device tree from the command line ({tree['trajectories']} Stage B trajectories of "
            f"`{tree['scene']}` in one `larc certify`, default cascade): {first['wall_s']:.2f} s with an empty cache "
            f"and {warm['wall_s']:.2f} s with a warm one, {warm['compile_s']:.2f} s of it loading the compiled kernels.")


def stageB_dataset(robot):
    """The committed Stage B trajectories and their scenes (folder name = scene name)."""
    from larc_jax import read_scene, read_trajectory

    trajs, scenes, cache = [], [], {}
    for folder in sorted(p for p in STAGEB_DIR.iterdir() if p.is_dir()):
        scene = cache.setdefault(folder.name, read_scene(SCENES_DIR / f"{folder.name}.yaml"))
        for f in sorted(folder.glob("*.yaml")):
            trajs.append(read_trajectory(f, robot))
            scenes.append(scene)
    return trajs, scenes


def stageB_like(robot, trajs, scenes, n: int, seed: int = 0):
    """``n`` (trajectory, scene) pairs, generated lazily: a random Stage B trajectory with every
    joint offset by U(-0.05, 0.05) rad (kept within the limits) and its time axis scaled by
    U(0.8, 1.25) (velocities scaled inversely), in its own scene."""
    import dataclasses

    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(robot.q_lower), np.asarray(robot.q_upper)
    for k in range(n):
        i = int(rng.integers(len(trajs)))
        t = trajs[i]
        shift = rng.uniform(-0.05, 0.05, t.q.shape[1])
        shift = np.clip(shift, lo - t.q.min(axis=0), hi - t.q.max(axis=0))
        scale = rng.uniform(0.8, 1.25)
        yield dataclasses.replace(t, t=t.t * scale, q=t.q + shift, qd=t.qd / scale, id=f"like{k:07d}"), scenes[i]


def _timed(fn):
    start = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - start


def _warm_pair(calls: dict, rounds: int = WARM_ROUNDS) -> dict:
    """``{name: (first result, first call s, median warm s, warm s of every round)}`` of the
    zero-argument ``calls``: a first call each, :data:`SETTLE_ROUNDS` untimed rounds, then
    ``rounds`` timed rounds of one call each, the order reversed every other round (the module
    docstring's ``stageB``)."""
    names = list(calls)
    first = {m: _timed(calls[m]) for m in names}
    times = {m: [] for m in names}
    for r in range(SETTLE_ROUNDS + rounds):
        for m in (names if r % 2 == 0 else names[::-1]):
            t = _timed(calls[m])[1]
            if r >= SETTLE_ROUNDS:
                times[m].append(t)
    return {m: (first[m][0], first[m][1], statistics.median(times[m]), times[m]) for m in names}


def real_pairs(result, capsules, scenes) -> int:
    """Capsule–box pairs really evaluated: per interval, capsules × the scene's real boxes."""
    boxes = np.array([s.n_boxes for s in scenes])
    return int((result.evaluations * boxes).sum()) * capsules.n_capsules


def decisions_sha256(result) -> str:
    """SHA-256 of a result's per-trajectory decisions and evaluation counts, in input order: two
    runs (two machines, a CPU and a GPU) with equal hashes certified the same trajectories with the
    same number of interval evaluations each."""
    import hashlib

    h = hashlib.sha256(np.asarray(result.certified, dtype=np.uint8).tobytes())
    h.update(np.asarray(result.evaluations, dtype=np.int64).tobytes())
    return h.hexdigest()


def capsule_open(result) -> int:
    """Evaluated intervals the capsule test leaves open: all but the leaves it passed (an interval
    the capsule test passes is a leaf; every other one went on to the cascade's later stages or
    was bisected or failed)."""
    from larc_jax.leaf.record import Stage

    return int(result.evaluations.sum()) - int((result.leaves.stage == Stage.CAPSULE).sum())


def section_stageB(robot, capsules, trajs, scenes, enclosure: str, paired: bool = True) -> dict:
    from larc_jax import certify

    out = {"n_trajectories": len(trajs), "enclosure": enclosure, "warm_rounds": WARM_ROUNDS}
    timed = _warm_pair({m: (lambda m=m: certify(trajs, scenes, robot, capsules, method=m, enclosure=enclosure))
                        for m in ("larc", "fine")})
    for method, (res, t_first, t_warm, rounds) in timed.items():
        evals = int(res.evaluations.sum())
        pairs = real_pairs(res, capsules, scenes)
        out[method] = {
            "certified": int(res.certified.sum()), "evaluations": evals, "real_pairs": pairs,
            "capsule_open": capsule_open(res),
            "first_call_s": t_first, "warm_s": t_warm, "warm_rounds_s": rounds, "compile_s": max(0.0, t_first - t_warm),
            "intervals_per_s": evals / t_warm, "pairs_per_s": pairs / t_warm,
            "decisions_sha256": decisions_sha256(res),
        }
    out["fine_over_larc_time"] = out["fine"]["warm_s"] / out["larc"]["warm_s"]
    out["fine_over_larc_evaluations"] = out["fine"]["evaluations"] / out["larc"]["evaluations"]
    if paired:
        _release_executables()  # the whole set's programs, before the paired section's 8 shapes x 3 methods
        out["paired"] = section_paired(robot, capsules, trajs, scenes, enclosure)
        out["floor"] = section_floor(robot, capsules, trajs, scenes, enclosure)
    return out


def section_paired(robot, capsules, trajs, scenes, enclosure: str, repeats: int = PAIRED_REPEATS) -> dict:
    """The paper's paired protocol: each trajectory certified alone, by LARC and by fixed-fine,
    after one untimed call each (compiling its shapes), ``repeats`` timed rounds (the order of
    the methods turning every round); per trajectory the median of its rounds per method, and the
    median over trajectories of the ratio fine / LARC. Also LARC on the device tree in the same
    rounds (:func:`_tree_forced`; by default ``certify`` runs a one-trajectory batch on the host
    frontier, after ``warm_up_tree`` on the tree), its median and its median ratio fine / tree."""
    from larc_jax import certify

    names = ("larc", "fine", "tree")
    ms = {m: [] for m in names}
    ratios, tree_ratios = [], []
    for traj, scene in zip(trajs, scenes):
        calls = {m: (lambda m=m: certify([traj], [scene], robot, capsules, method=m, enclosure=enclosure))
                 for m in ("larc", "fine")}
        calls["tree"] = _tree_forced(calls["larc"])
        for call in calls.values():
            call()
        times = {m: [] for m in calls}
        for r in range(repeats):
            for m in names[r % 3:] + names[: r % 3]:
                times[m].append(_timed(calls[m])[1])
        for m in names:
            ms[m].append(1e3 * statistics.median(times[m]))
        ratios.append(ms["fine"][-1] / ms["larc"][-1])
        tree_ratios.append(ms["fine"][-1] / ms["tree"][-1])
    return {"n": len(trajs), "repeats": repeats, "larc_median_ms": statistics.median(ms["larc"]),
            "fine_median_ms": statistics.median(ms["fine"]), "median_fine_over_larc": statistics.median(ratios),
            "tree_median_ms": statistics.median(ms["tree"]), "median_fine_over_tree": statistics.median(tree_ratios)}


def _tree_forced(call):
    """``call`` with ``certify``'s LARC running small batches on the device tree
    (:func:`larc_jax.engine.tree_pool.small_batches_on_tree`, what ``warm_up_tree`` turns on),
    set back after the call: the other columns keep ``certify``'s default."""
    from larc_jax.engine.tree_pool import small_batches_on_tree

    def forced():
        was = small_batches_on_tree(True)
        try:
            return call()
        finally:
            small_batches_on_tree(was)

    return forced


def section_floor(robot, capsules, trajs, scenes, enclosure: str, n: int = 16) -> dict:
    """The fixed cost of a one-trajectory call: each of ``n`` trajectories (every tenth) certified
    alone on one interval (``method="coarse"``, ``coarse_depth=0``: that interval's kernel calls at
    the smallest buckets, and everything ``certify`` does around them), after one untimed call
    each; the median over trajectories of the best of :data:`PAIRED_REPEATS` calls."""
    from larc_jax import certify

    picked = list(zip(trajs, scenes))[:: max(1, len(trajs) // n)][:n]
    ms = []
    for traj, scene in picked:
        call = lambda: certify([traj], [scene], robot, capsules, method="coarse", coarse_depth=0,  # noqa: E731
                               enclosure=enclosure)
        call()
        ms.append(1e3 * min(_timed(call)[1] for _ in range(PAIRED_REPEATS)))
    return {"n": len(picked), "one_interval_median_ms": statistics.median(ms)}


def _release_executables() -> None:
    """Drop JAX's in-memory executables between sections (each section warms its own up first):
    every compiled CPU executable holds ~100 memory mappings, and the Stage B sections' programs
    alone hold ~24,000 (both enclosures, every bucket, one trajectory per call), so one process
    running every section reached ``vm.max_map_count`` (65,530) in the stream section, where LLVM
    fails with "Cannot allocate memory" and the process dies (as ``tests/conftest.py`` and
    ``experiments.timing`` guard against)."""
    import gc

    import jax

    jax.clear_caches()
    gc.collect()


def section_kernel(robot, capsules, trajs, scenes, peak_gflops: float) -> dict:
    """XLA cost analysis of the interval kernel on one full bucket of Stage B intervals."""
    import jax

    from larc_jax.engine.batch import prepare
    from larc_jax.engine.buckets import BUCKETS
    from larc_jax.engine.certify import _check_inputs  # noqa: PLC2701 - the benchmark measures internals
    from larc_jax.engine.kernels import evaluate_intervals, evaluate_intervals_broad
    from larc_jax.leaf.clearance import BROAD_PHASE_K
    from larc_jax.leaf.interval import trajectory_rounding

    trajs, scenes, _ = _check_inputs(trajs, scenes, robot, capsules, np.float64, None)
    bounds = [trajectory_rounding(t, robot, capsules) for t in trajs]
    batch = prepare(trajs, scenes, robot, capsules, 0.01, np.float64, bounds)
    F = BUCKETS[-1]
    rng = np.random.default_rng(0)
    traj = rng.integers(0, len(trajs), F)
    depth, index = np.full(F, 6), rng.integers(0, 64, F)
    out = {"bucket_intervals": F, "peak_gflops_nominal": peak_gflops,
           "boxes_padded_to": batch.obstacles.n_items, "device": str(jax.devices()[0])}
    # The kernel certify runs (broad phase, larc_jax.leaf.clearance) and the all-pairs one it falls
    # back to for intervals the broad phase cannot prove.
    args = batch.kernel_args(traj, *batch.endpoints(traj, depth, index))
    pairs = capsules.n_capsules * int(np.array([s.n_boxes for s in scenes])[traj].sum())  # real pairs (real_pairs)
    kernels = {"broad_phase": evaluate_intervals_broad, "all_pairs": evaluate_intervals,
               "placement": _stage_kernel(pair_bounds=False), "pair_bounds": _stage_kernel(pair_bounds=True)}
    with jax.enable_x64(True):
        compiled = {name: kernel.lower(*args).compile() for name, kernel in kernels.items()}
        for c in compiled.values():
            jax.block_until_ready(c(*args))
        # Each kernel alone on one full bucket, its inputs already prepared: the best of
        # KERNEL_REPEATS calls, the kernels taking turns (a slow spell of the machine falls on all).
        best = dict.fromkeys(compiled, float("inf"))
        for _ in range(KERNEL_REPEATS):
            for name, c in compiled.items():
                t0 = time.perf_counter()
                jax.block_until_ready(c(*args))
                best[name] = min(best[name], time.perf_counter() - t0)
    for name in ("broad_phase", "all_pairs"):
        cost = compiled[name].cost_analysis()
        cost = dict(cost[0] if isinstance(cost, (list, tuple)) else cost)
        flops, nbytes = cost["flops"] / F, cost["bytes accessed"] / F
        out[name] = {"flops_per_interval": flops, "bytes_per_interval": nbytes,
                     "arithmetic_intensity_flops_per_byte": flops / nbytes, "bucket_s": best[name],
                     "repeats": KERNEL_REPEATS, "kernel_pairs_per_s": pairs / best[name],
                     "kernel_gflops": flops * F / best[name] / 1e9}
    # Where the broad-phase kernel's time goes: its first parts compiled alone (_stage_kernel).
    out["stages"] = {"placement_s": best["placement"], "pair_bounds_s": best["pair_bounds"],
                     "exact_pairs": BROAD_PHASE_K, "repeats": KERNEL_REPEATS, "real_pairs": pairs}
    return out


def _stage_kernel(pair_bounds: bool):
    """The broad-phase kernel's first parts on F intervals, jitted alone (the kernel section's
    breakdown): the placement (``larc_jax.leaf.placement.place``: the midpoint configuration, the
    exact speed maxima, the motion radii, forward kinematics and the capsule segments), and with
    ``pair_bounds`` also every capsule–box pair's distance lower bound, the broad phase's cheap
    bound (``larc_jax.leaf.clearance``). One number per interval leaves the call, computed from
    every output of the parts, so XLA drops none of their work."""
    import jax
    import jax.numpy as jnp

    from larc_jax.leaf.placement import place
    from larc_jax.model.spline_batch import SplineRow

    def kernel(robot, capsules, splines, obstacles, bounds, traj, sel, a, b, margin):
        def one(t, s, ai, bi):
            pl = place(robot, capsules, SplineRow(splines, t), ai, bi, jax.tree.map(lambda x: x[t], bounds))
            if not pair_bounds:
                return pl.p_world_a.sum() + pl.p_world_b.sum() + pl.motion_b.sum()
            items = obstacles.take(s)
            lb = items.segment_lower_bounds(pl.p_world_a, pl.p_world_b)
            return jnp.min(jnp.where(items.mask[None, :], lb - pl.motion_b[:, None], jnp.inf))

        return jax.vmap(one)(traj, sel, a, b)

    kernel.__name__ = kernel.__qualname__ = "bench_pair_bounds" if pair_bounds else "bench_placement"
    return jax.jit(kernel)


def section_reference(robot, capsules, trajs, scenes, larc_s: float) -> dict:
    from larc_jax import certify

    res, t = _timed(lambda: certify(trajs, scenes, robot, capsules, method="reference", enclosure=ENCLOSURE))
    return {"set_s": t, "evaluations": int(res.evaluations.sum()), "reference_over_larc": t / larc_s}


def section_audit(larc_s: float) -> dict:
    from experiments import audit

    items = audit.dataset_items(STAGEB_DIR)
    (rows), t = _timed(lambda: audit.audit_dataset(items, hz=250.0, workers=2))
    states = sum(int(r["audit_states"]) for r in rows)
    return {"set_s": t, "states": states, "workers": 2, "audit_over_larc": t / larc_s}


def section_stream(robot, capsules, trajs, scenes, n: int) -> dict:
    from larc_jax import certify_stream

    list(certify_stream(stageB_like(robot, trajs, scenes, 256, seed=1), robot, capsules, enclosure=ENCLOSURE))  # compile
    evals, start = 0, time.perf_counter()
    for chunk in certify_stream(stageB_like(robot, trajs, scenes, n, seed=2), robot, capsules, enclosure=ENCLOSURE):
        evals += int(chunk.evaluations.sum())
    dt = time.perf_counter() - start
    return {"n": n, "s": dt, "trajectories_per_s": n / dt, "intervals_per_s": evals / dt}


def section_rss(ns: list[int], mode: str) -> list[dict]:
    out = []
    for n in ns:
        cmd = [sys.executable, "-m", "experiments.bench_rss", "--n", str(n), "--mode", mode]
        p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, env=dict(os.environ))
        if p.returncode != 0:
            out.append({"n": n, "mode": mode, "error": p.stderr.strip().splitlines()[-1:]})
            continue
        out.append(json.loads(p.stdout.strip().splitlines()[-1]))
        print(f"  rss {mode:6s} n={n:>7d}: {out[-1]['peak_rss_mb']:.0f} MB, {out[-1]['s']:.1f} s", flush=True)
    return out


def tightness_rows() -> list[tuple[Path, Path]]:
    """``(trajectory file, scene file)`` of every planned trajectory of the tightness set."""
    from experiments import generate as gen
    from experiments import tightness as tt

    plan = tt.Plan(out=ROOT / "results" / "tightness", scenes=tt.SCENES, paddings_mm=tt.PADDINGS_MM, pairs=tt.PAIRS)
    config = gen.load_config(tt.CONFIG_PATH)
    return [(Path(r["path"]).resolve(), (ROOT / config["scenes"][r["scene"]]["file"]).resolve())
            for r in plan.trajectories()]


_MANIFEST_RUN = """import json, sys, time
from experiments.bench_rss import peak_rss_mb
from larc_jax.drivers.cli import main
t0 = time.perf_counter()
rc = main(sys.argv[1:])
print(json.dumps(dict(rc=rc, s=time.perf_counter() - t0, peak_rss_mb=peak_rss_mb())))
"""


def section_manifest(n: int) -> dict:
    """``larc certify --manifest`` of ``n`` rows (module docstring), one fresh process."""
    import tempfile

    import pandas as pd

    rows = tightness_rows()
    with tempfile.TemporaryDirectory() as d:
        manifest = Path(d) / "manifest.csv"
        lines = ["trajectory,scene,id"] + [f"{t},{s},row{k}" for k, (t, s) in
                                           ((k, rows[k % len(rows)]) for k in range(n))]
        manifest.write_text("\n".join(lines) + "\n")
        cmd = [sys.executable, "-c", _MANIFEST_RUN, "-q", "certify", "--manifest", str(manifest),
               "--out", str(Path(d) / "out.parquet"), "--no-fail-on-uncertified"]
        env = dict(os.environ, LARC_COMPILE_CACHE=str(Path(d) / "cache"))  # compiling included
        t0 = time.perf_counter()
        p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, env=env)
        wall = time.perf_counter() - t0
        if p.returncode != 0:
            raise RuntimeError(f"larc certify --manifest failed:\n{p.stderr[-2000:]}")
        run = json.loads(p.stdout.strip().splitlines()[-1])
        df = pd.read_parquet(Path(d) / "out.parquet")
    read_ms = _read_ms_per_row(rows)
    return {"n": n, "distinct_trajectories": len(rows), "rows_written": len(df),
            "certified": int(df["certified"].sum()), "wall_s": wall, "peak_rss_mb": run["peak_rss_mb"],
            "trajectories_per_s": n / wall, "read_ms_per_row": read_ms, "read_share": n * read_ms / 1e3 / wall}


def _read_ms_per_row(rows: list[tuple[Path, Path]]) -> float:
    """Milliseconds to read one manifest row's trajectory file (``read_trajectory`` with the robot,
    as a manifest chunk reads it), measured alone in this process: median over the distinct files
    of the best of 3 reads. Times the rows of the manifest section, it is the part of that run's
    wall spent reading files (scenes are read once per chunk, and not counted)."""
    import larc_jax as lj
    from larc_jax.model.trajectory_files import read_trajectory

    robot = lj.load_robot()
    per_file = []
    for path, _ in rows:
        best = min(_timed(lambda: read_trajectory(path, robot))[1] for _ in range(3))
        per_file.append(best)
    return 1e3 * statistics.median(per_file)


def _print(prefix: str, obj) -> None:
    if isinstance(obj, dict):
        for k, v in obj.items():
            _print(f"{prefix}.{k}" if prefix else k, v)
    else:
        print(f"{prefix:48s} {obj:.4g}" if isinstance(obj, float) else f"{prefix:48s} {obj}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--json", help="write the figures as JSON")
    p.add_argument("--quick", action="store_true", help="small sizes (a smoke run)")
    p.add_argument("--skip-reference", action="store_true")
    p.add_argument("--skip-audit", action="store_true")
    p.add_argument("--enclosures", default=",".join(ENCLOSURES),
                   help="comma-separated enclosures of the Stage B section (a short run on a lent machine)")
    p.add_argument("--skip-paired", action="store_true", help="leave out the one-trajectory-per-call timings")
    p.add_argument("--stageB-only", action="store_true", help="only the Stage B section")
    p.add_argument("--stream-n", type=int, default=4096)
    p.add_argument("--rss-n", default="1000,10000,100000", help="comma-separated N for the RSS section ('' skips)")
    p.add_argument("--manifest-n", type=int, default=20_000, help="rows of the manifest section (0 skips)")
    p.add_argument("--peak-gflops", type=float, help="nominal float64 peak of the machine (module doc)")
    p.add_argument("--render", action="store_true",
                   help="only write the Markdown table of the --json file an earlier run wrote (one stopped part-way)")
    args = p.parse_args(argv)
    enclosures = list(dict.fromkeys(args.enclosures.split(",")))
    for enc in enclosures:
        if enc not in ENCLOSURES:
            p.error(f"--enclosures: {enc!r} is not one of {', '.join(ENCLOSURES)}")
    if ENCLOSURE not in enclosures and not args.stageB_only:
        p.error(f"--enclosures without {ENCLOSURE!r} needs --stageB-only (the later sections are "
                f"compared with the {ENCLOSURE!r} run)")
    if args.render:
        if not args.json or not Path(args.json).is_file():
            p.error("--render needs --json FILE, an existing file an earlier run wrote")
        from larc_jax.io import atomic_write_text

        atomic_write_text(Path(args.json).with_suffix(".md"), markdown(json.loads(Path(args.json).read_text())))
        return 0

    import jax

    import larc_jax as lj
    from larc_jax.io import atomic_write_json, atomic_write_text

    robot = lj.load_robot()
    capsules = lj.load_capsules(lj.default_capsule_path(), robot)
    trajs, scenes = stageB_dataset(robot)
    if args.quick:
        trajs, scenes = trajs[::8], scenes[::8]
        args.stream_n, args.rss_n, args.manifest_n = 300, "300", min(args.manifest_n, 300)
    cores = os.cpu_count() or 1
    peak = args.peak_gflops or cores * 2.6 * 16  # GHz of this machine's cores (lscpu), module doc
    out = {"machine": {"processor": platform.processor() or platform.machine(), "cores": cores,
                       "device": str(jax.devices()[0]), "jax": jax.__version__,
                       "peak_gflops_float64_nominal": peak}}
    t0 = time.perf_counter()

    def checkpoint() -> None:
        # A run stopped part-way (a time limit, a lost machine) keeps every section it finished.
        if args.json:
            atomic_write_json(args.json, out)

    def finish() -> int:
        out["bench_wall_s"] = time.perf_counter() - t0
        _print("", out)
        if args.json:
            checkpoint()
            atomic_write_text(Path(args.json).with_suffix(".md"), markdown(out))
        return 0

    out["stageB"] = {}
    for k, enc in enumerate(enclosures):
        if k:
            _release_executables()  # the one-trajectory trees of one enclosure (8 shapes) before the next's
        out["stageB"][enc] = section_stageB(robot, capsules, trajs, scenes, enc, paired=not args.skip_paired)
        checkpoint()
    if args.stageB_only:
        return finish()
    larc_s = out["stageB"][ENCLOSURE]["larc"]["warm_s"]
    _release_executables()
    out["kernel"] = section_kernel(robot, capsules, trajs, scenes, peak)
    out["kernel"]["achieved_gflops_larc"] = (  # intervals run through the broad-phase kernel
        out["kernel"]["broad_phase"]["flops_per_interval"] * out["stageB"][ENCLOSURE]["larc"]["intervals_per_s"] / 1e9)
    out["kernel"]["fraction_of_peak"] = out["kernel"]["achieved_gflops_larc"] / peak
    checkpoint()
    if not args.skip_reference:
        out["reference"] = section_reference(robot, capsules, trajs, scenes, larc_s)
        checkpoint()
    if not args.skip_audit:
        out["audit"] = section_audit(larc_s)
        checkpoint()
    _release_executables()
    out["stream"] = section_stream(robot, capsules, trajs, scenes, args.stream_n)
    checkpoint()
    ns = [int(x) for x in args.rss_n.split(",") if x.strip()]
    # One certify call holds every input trajectory and every leaf in memory at once, so it is
    # measured up to 10^4; streaming (constant memory) at every N.
    out["rss"] = section_rss([n for n in ns if n <= MAX_CALL_N], "call") + section_rss(ns, "stream")
    checkpoint()
    from experiments import bench_coldstart

    out["coldstart"] = bench_coldstart.measure(3)
    checkpoint()
    if args.manifest_n:
        out["manifest"] = section_manifest(args.manifest_n)
    return finish()


def markdown(out: dict) -> str:
    """The README's benchmark table, from one run's figures (written beside the JSON). A run that
    measured only part of the sections (``--enclosures``, ``--skip-paired``, ``--stageB-only``, or
    one stopped part-way) gets the rows of what it measured."""
    runs = out["stageB"]
    names = {"capsules": "capsules", "hull": "cascade"}
    encs = [e for e in ENCLOSURES if e in runs]
    cols = [(runs[e], m) for e in encs for m in ("larc", "fine")]
    paired = all("paired" in runs[e] for e in encs)

    def row(label: str, fmt) -> str:
        return f"| {label} | " + " | ".join(fmt(r[m]) for r, m in cols) + " |"

    def ratio_row(label: str, fmt, target: str) -> str:
        return f"| {label} | " + " | ".join(fmt(runs[e]) for e in encs) + (f" | {target} |" if target else " | |")

    lines = [
        f"Stage B: {runs[encs[0]]['n_trajectories']} trajectories, JAX device `{out['machine']['device']}`, "
        f"{out['machine']['cores']} CPU cores, one run:", "",
        "| | " + " | ".join(f"{names[e]}: {m}" for e in encs for m in ("LARC", "fine")) + " |",
        "|---|" + "---|" * len(cols),
        row("certified", lambda r: f"{r['certified']}"),
        row("interval evaluations", lambda r: f"{r['evaluations']:,}"),
        row("warm whole-set time" + (f" (median of {runs[encs[0]]['warm_rounds']} alternating rounds)"
                                     if "warm_rounds" in runs[encs[0]] else ""), lambda r: f"{r['warm_s']:.3f} s"),
        *([row("left open by the capsule test", lambda r: f"{r['capsule_open']:,} ({100 * r['capsule_open'] / r['evaluations']:.0f} %)")]
          if all("capsule_open" in r[m] for r, m in cols) else []),
        row("compile time (first call − warm call)", lambda r: f"{r['compile_s']:.2f} s"),
        row("intervals / s", lambda r: f"{r['intervals_per_s']:,.0f}"),
        row("real capsule–box pairs / s", lambda r: f"{r['pairs_per_s']:,.0f}"),
        *(["| one trajectory per call: median time | " + " | ".join(
            f"{r['paired'][m + '_median_ms']:.2f} ms" for r, m in cols) + " |"] if paired else []),
        "",
        "| fine / LARC | " + " | ".join(names[e] for e in encs) + " | target (issue 20) |",
        "|---|" + "---|" * (len(encs) + 1),
        ratio_row("interval evaluations", lambda r: f"{r['fine_over_larc_evaluations']:.2f}×", ""),
        ratio_row("warm whole-set time", lambda r: f"{r['fine_over_larc_time']:.2f}×",
                  "≥ 0.7 × evaluations (" + " / ".join(f"{0.7 * runs[e]['fine_over_larc_evaluations']:.2f}×"
                                                        for e in encs) + ")"),
        *([ratio_row("one trajectory per call, median of per-trajectory ratios",
                     lambda r: f"{r['paired']['median_fine_over_larc']:.2f}×", "≥ 1.5×")] if paired else []),
    ]
    if len(encs) == 2:
        cap, hull = runs["capsules"], runs["hull"]
        per_call = (f" and {hull['paired']['larc_median_ms'] / cap['paired']['larc_median_ms']:.2f}× one trajectory "
                    f"per call" if paired else "")
        lines += ["", f"The cascade costs LARC {hull['larc']['warm_s'] / cap['larc']['warm_s']:.2f}× the capsule test "
                      f"on the whole set{per_call} (target ≤ 2×)."]
        if "capsule_open" in hull["larc"]:
            extra = {m: hull[m]["warm_s"] - cap[m]["warm_s"] for m in ("larc", "fine")}
            # Not the later stages' own cost: the two runs differ in padding (so in evaluations) and
            # in LARC's step 1 (the screened kernel); the difference is all that is measured.
            lines[-1] += (f" The cascade's warm whole-set time exceeds the capsule test's by {extra['larc']:.3f} s for "
                          f"LARC and {extra['fine']:.3f} s for fine: "
                          f"{1e6 * extra['larc'] / hull['larc']['capsule_open']:.1f} and "
                          f"{1e6 * extra['fine'] / hull['fine']['capsule_open']:.1f} µs per interval its capsule "
                          f"stage leaves open, {hull['larc']['capsule_open']:,} of LARC's and "
                          f"{hull['fine']['capsule_open']:,} of fine's.")
    if paired and all("tree_median_ms" in runs[e]["paired"] for e in encs):
        lines += ["", "One trajectory per call with LARC on the device tree (as after `warm_up_tree`; by default "
                      "`certify` runs a batch of fewer than 16 on the host frontier), in the same rounds: median " + ", ".join(
                          f"{runs[e]['paired']['tree_median_ms']:.2f} ms ({names[e]})" for e in encs)
                  + "; fine / tree, median of per-trajectory ratios, " + ", ".join(
                      f"{runs[e]['paired']['median_fine_over_tree']:.2f}× ({names[e]})" for e in encs) + "."]
    floors = [f"{runs[e]['floor']['one_interval_median_ms']:.2f} ms ({names[e]})" for e in encs if "floor" in runs[e]]
    if floors:
        lines += ["", f"One trajectory certified on one interval (`method=\"coarse\"`, `coarse_depth=0`: that "
                      f"interval's kernel calls, and all `certify` does around them), the floor of a one-trajectory "
                      f"call, median of {runs[encs[0]]['floor']['n']}: " + ", ".join(floors) + "."]
    if "coldstart" in out:
        c = out["coldstart"]
        lines += ["", f"| `{c['command']}`, a fresh process (median of {c['repeats']}) | wall | target |",
                  "|---|---|---|",
                  f"| first ever (empty compilation cache) | {c['first_ever']['wall_s']:.2f} s | ≤ 15 s |",
                  f"| second and later (warm cache) | {c['warm_cache']['wall_s']:.2f} s | ≤ 2 s |",
                  f"| a wrong `--hold`, refused (exit 2) | {c['bad_option_s']:.2f} s | < 1 s |"]
        if "tree" in c:
            lines += ["", tree_sentence(c["tree"])]
    if "manifest" in out:
        m = out["manifest"]
        lines += ["", f"`larc certify --manifest`, {m['n']:,} rows (the {m['distinct_trajectories']} planned "
                      f"trajectories of the tightness set, cycled), default cascade, one fresh process with an empty "
                      f"compilation cache: {m['wall_s']:.0f} s ({m['trajectories_per_s']:.1f} trajectories/s, "
                      f"compiling included), peak RSS {m['peak_rss_mb']:,.0f} MB (target ≤ 10 min, ≤ 4 GB); "
                      f"{m['certified']:,} certified. Reading a row's trajectory file alone takes "
                      f"{m['read_ms_per_row']:.1f} ms (median of the distinct files): {100 * m['read_share']:.0f} % of "
                      f"that wall."]
    if "kernel" not in out:
        return "\n".join(lines) + "\n"
    k = out["kernel"]
    lines += [
        "",
        "| kernel (XLA cost analysis, per interval) | flops | bytes accessed |", "|---|---|---|",
        *(f"| {name.replace('_', ' ')} | {k[name]['flops_per_interval']:,.0f} | {k[name]['bytes_per_interval']:,.0f} |"
          for name in ("broad_phase", "all_pairs")),
        "",
        f"Achieved {k['achieved_gflops_larc']:.2f} GFLOP/s by XLA's count, {100 * k['fraction_of_peak']:.2f} % of a "
        f"nominal {k['peak_gflops_nominal']:.1f} GFLOP/s float64 peak.",
    ]
    if "bucket_s" in k["broad_phase"]:
        b = k["broad_phase"]
        lines[-1] += (f" The broad-phase kernel alone, on one bucket of {k['bucket_intervals']:,} Stage B intervals "
                      f"(best of {b['repeats']} calls, inputs prepared): {1e3 * b['bucket_s']:.2f} ms, "
                      f"{b['kernel_pairs_per_s']:,.0f} real capsule–box pairs/s, {b['kernel_gflops']:.2f} GFLOP/s "
                      f"({100 * b['kernel_gflops'] / k['peak_gflops_nominal']:.2f} % of that peak).")
    if "stages" in k:
        st, whole = k["stages"], k["broad_phase"]["bucket_s"]
        lines[-1] += (f" Its parts, each compiled alone and timed in the same turns: placing the capsules (the "
                      f"midpoint configuration, the exact speed maxima, forward kinematics, the segments) "
                      f"{1e3 * st['placement_s']:.2f} ms ({100 * st['placement_s'] / whole:.0f} % of the kernel), "
                      f"and with every pair's distance lower bound {1e3 * st['pair_bounds_s']:.2f} ms "
                      f"({100 * st['pair_bounds_s'] / whole:.0f} %); the rest, choosing the {st['exact_pairs']} pairs "
                      f"of smallest bound and their exact distances, "
                      f"{100 * (1 - st['pair_bounds_s'] / whole):.0f} %. The placement is work per interval, "
                      f"whatever its pairs: the bucket has {st['real_pairs'] / k['bucket_intervals']:.1f} real "
                      f"pairs per interval, and the placement's time alone would bound the kernel at "
                      f"{st['real_pairs'] / st['placement_s']:,.0f} real pairs/s.")
    ratios = []
    if "reference" in out:
        ratios.append(f"NumPy reference / LARC: **{out['reference']['reference_over_larc']:.1f}×**")
    if "audit" in out:
        ratios.append(f"FCL audit at 250 Hz ({out['audit']['workers']} workers) / LARC: "
                      f"**{out['audit']['audit_over_larc']:.1f}×**")
    if ratios:
        lines += ["", "; ".join(ratios) + " (same trajectories, same run)."]
    if "stream" not in out:
        return "\n".join(lines) + "\n"
    st = out["stream"]
    lines += ["", f"Streaming (`certify_stream`, {st['n']:,} Stage B-like trajectories): "
                  f"{st['trajectories_per_s']:,.0f} trajectories/s, {st['intervals_per_s']:,.0f} intervals/s."]
    if not out.get("rss"):
        return "\n".join(lines) + "\n"
    lines += ["", "| N trajectories | one `certify` call: peak RSS, time | streamed: peak RSS, time |", "|---|---|---|"]
    rows = {}
    for r in out["rss"]:
        cell = (f"{r['peak_rss_mb']:,.0f} MB, {r['s']:.0f} s" if "peak_rss_mb" in r
                else f"failed: {' '.join(r.get('error', []))}")
        rows.setdefault(r["n"], {})[r["mode"]] = cell
    for n, cells in rows.items():
        lines.append(f"| {n:,} | {cells.get('call', '–')} | {cells.get('stream', '–')} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
