"""Stage B timing: whole-batch certification times and the paper's paired per-trajectory protocol.

Two measurements (paper, "Sampled MoveIt/FCL Audit and Computational Timing"):

* **Whole batch** (:func:`batch_certify`): each method certifies the whole dataset in ONE
  :func:`larc_jax.engine.certify.certify` call. The first call compiles (JAX traces and compiles the
  interval kernel for the dataset's shapes); it is reported separately as ``first_call_s`` and
  ``compile_s`` (first call minus the median warm call; also the XLA backend-compile seconds
  counted by a :mod:`jax.monitoring` listener). The batch time is the median of
  ``repeats`` warm calls.
* **Paired per trajectory** (:func:`paired_timing`): for every trajectory, one untimed warm-up
  call per method (compiles the shapes of that trajectory if they are new), then ``repeats``
  rounds; in each round the three methods run in an order drawn from
  ``numpy.random.default_rng(seed)`` (one permutation per trajectory and round, trajectories in
  dataset order). Each call certifies that one trajectory alone. The per-method time of a
  trajectory is the median of its repeats; the paired speedup is ``fine / larc`` of those
  medians, per trajectory, and the reported speedup is the median of the per-trajectory ratios
  (not the ratio of the marginal medians). Repeats are technical measurements, not samples.

Every timed call is watched for XLA compilations (``compiles`` column). A timed call that
compiles measured compile time, not certification: :func:`summarise_timing` counts them so the
report can say so.
"""

from __future__ import annotations

import contextlib
import gc
import statistics
import time
from typing import Callable, Sequence

import numpy as np

from experiments.common import METHODS, Layout, read_csv, write_csv

__all__ = [
    "CODE",
    "batch_certify",
    "paired_timing",
    "summarise_timing",
    "certify_stage",
    "timing_stage",
]

CODE = ("experiments.timing",)
ENCLOSURE = "capsules"
"""Stage B reproduces the paper: its capsule model alone (the cascade of larc_jax.leaf.cascade is
measured by experiments.tightness)."""
"""Modules whose import closure is the certification and timing stages' code."""
CLEAR_CACHES_AFTER_COMPILES = 200
"""Paired timing calls ``jax.clear_caches()`` between trajectories once this many XLA executables
were compiled since the last clear. Every compiled CPU executable keeps ~100 memory mappings
alive (measured: ~750 per new waypoint count, i.e. per set of larc/fine/coarse kernels), and
the kernel shapes depend on the trajectory's waypoint count, so timing trajectories of many
different lengths in one process otherwise exhausts ``vm.max_map_count`` (65530): LLVM then
fails with "Cannot allocate memory" and the process crashes (seen after ~78 distinct lengths).
Clearing only happens between trajectories, before the next one's untimed warm-up calls."""


@contextlib.contextmanager
def _no_gc():
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def _timed_call(fn: Callable[[], object]):
    """(result, seconds, XLA compilations, XLA compile seconds) of one call, garbage collection
    paused."""
    from larc_jax.compilation import CompileClock

    with CompileClock() as clock, _no_gc():
        t0 = time.perf_counter()
        out = fn()
        dt = time.perf_counter() - t0
    return out, dt, clock.compiles, clock.compile_s


def _decisions(result) -> tuple:
    return tuple((r.id, r.certified, r.evaluations) for r in result.trajectories)


def batch_certify(trajectories, scenes, robot, capsules, *, methods: Sequence[str] = METHODS,
                  margin: float, max_depth: int, coarse_depth: int, repeats: int = 3,
                  progress: bool = True):
    """Certify the whole dataset with each method in one batched call per repetition.

    Returns ``(results, rows)``: ``results[method]`` is the :class:`DatasetResult` of the last
    warm call; ``rows`` one dict per method with the first-call (compile) and warm batch times.
    Raises ``RuntimeError`` if repeated calls disagree (the certifier must be deterministic).
    """
    from larc_jax.engine.certify import certify

    results, rows = {}, []
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(methods) * (repeats + 1), desc="certify (batch)", unit="call",
                   dynamic_ncols=True)
    for m in methods:
        def call(m=m):
            return certify(trajectories, scenes, robot, capsules, method=m, margin=margin,
                           max_depth=max_depth, coarse_depth=coarse_depth, enclosure=ENCLOSURE)

        first, t_first, n_comp, comp_s = _timed_call(call)
        if bar is not None:
            bar.update(1)
        warm, warm_compiles = [], 0
        res = first
        for _ in range(repeats):
            res, dt, nc, _ = _timed_call(call)
            warm.append(dt)
            warm_compiles += nc
            if _decisions(res) != _decisions(first):
                raise RuntimeError(f"certify(method={m}) gave different results on a repeated call")
            if bar is not None:
                bar.update(1)
        results[m] = res
        med = statistics.median(warm)
        evals = sum(r.evaluations for r in res.trajectories)
        rows.append(dict(
            method=m,
            trajectories=len(res.trajectories),
            evaluations=evals,
            first_call_s=t_first,
            compile_s=max(0.0, t_first - med),
            xla_compiles_first_call=n_comp,
            xla_compile_s_first_call=comp_s,
            batch_s_median=med,
            batch_s_min=min(warm),
            batch_s_max=max(warm),
            warm_repeats=len(warm),
            xla_compiles_warm_calls=warm_compiles,
            ms_per_trajectory=1e3 * med / max(1, len(res.trajectories)),
            evaluations_per_s=evals / med if med > 0 else float("nan"),
            certified=sum(r.certified for r in res.trajectories),
        ))
    if bar is not None:
        bar.close()
    return results, rows


def paired_timing(trajectories, scenes, robot, capsules, *, seed: int, repeats: int,
                  margin: float, max_depth: int, coarse_depth: int,
                  methods: Sequence[str] = METHODS, progress: bool = True,
                  skip: set[str] | frozenset = frozenset(),
                  on_trajectory: Callable[[list[dict]], None] | None = None) -> list[dict]:
    """The paper's per-trajectory timing protocol (module docstring).

    Returns raw rows: ``traj_id, scene, kind (warmup|timed), repeat, position, method,
    time_ms, compiles, certified, evaluations``. ``on_trajectory`` is called with each
    trajectory's rows as soon as it is finished (the driver caches them). Trajectories whose id
    is in ``skip`` (already timed) are not run, but their orders are still drawn, so a resumed
    run gives every trajectory the same method orders as an uninterrupted one.
    """
    from larc_jax.engine.certify import certify

    import jax

    rng = np.random.default_rng(int(seed))
    rows: list[dict] = []
    compiles_since_clear = 0
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=sum(t.id not in skip for t in trajectories), desc="paired timing", unit="traj",
                   dynamic_ncols=True)
    for k in range(len(trajectories)):
        traj, scene = trajectories[k], scenes[k]
        # Draw every round's order first, so the stream of draws does not depend on anything else.
        orders = [[methods[i] for i in rng.permutation(len(methods))] for _ in range(repeats)]
        if traj.id in skip:
            continue
        mine: list[dict] = []

        def run(m, kind, rep, pos):
            res, dt, nc, _ = _timed_call(lambda: certify(
                [traj], [scene], robot, capsules, method=m, margin=margin,
                max_depth=max_depth, coarse_depth=coarse_depth, enclosure=ENCLOSURE))
            r = res.trajectories[0]
            mine.append(dict(traj_id=traj.id, scene=scene.name, kind=kind, repeat=rep, position=pos,
                             method=m, time_ms=1e3 * dt, compiles=nc, certified=r.certified,
                             evaluations=r.evaluations))

        gc.collect()
        for pos, m in enumerate(methods):
            run(m, "warmup", -1, pos)
        for rep, order in enumerate(orders):
            for pos, m in enumerate(order):
                run(m, "timed", rep, pos)
        rows.extend(mine)
        if on_trajectory is not None:
            on_trajectory(mine)
        if bar is not None:
            bar.update(1)
        compiles_since_clear += sum(r["compiles"] for r in mine)
        if compiles_since_clear >= CLEAR_CACHES_AFTER_COMPILES:
            jax.clear_caches()
            gc.collect()
            compiles_since_clear = 0
    if bar is not None:
        bar.close()
    return rows


def summarise_timing(raw, methods: Sequence[str] = METHODS):
    """Per-trajectory medians and paired speedup from raw rows (list of dicts or DataFrame).

    Returns a DataFrame: ``traj_id, scene, time_<m>_ms`` (median of the timed repeats),
    ``n_repeats``, ``timed_compiles`` (XLA compilations inside timed calls; should be 0),
    ``warmup_<m>_ms``, ``speedup_fine_over_larc``.
    """
    import pandas as pd

    df = pd.DataFrame(raw)
    for col in ("repeat", "position", "time_ms", "compiles", "evaluations"):
        df[col] = pd.to_numeric(df[col])
    timed = df[df["kind"] == "timed"]
    med = timed.pivot_table(index="traj_id", columns="method", values="time_ms", aggfunc="median")
    out = pd.DataFrame(index=med.index)
    out["scene"] = timed.groupby("traj_id")["scene"].first()
    for m in methods:
        out[f"time_{m}_ms"] = med[m] if m in med else np.nan
    out["n_repeats"] = timed.groupby("traj_id")["repeat"].nunique()
    out["timed_compiles"] = timed.groupby("traj_id")["compiles"].sum()
    warm = df[df["kind"] == "warmup"].pivot_table(index="traj_id", columns="method",
                                                    values="time_ms", aggfunc="first")
    for m in methods:
        out[f"warmup_{m}_ms"] = warm[m] if m in warm else np.nan
    if "fine" in methods and "larc" in methods:
        out["speedup_fine_over_larc"] = out["time_fine_ms"] / out["time_larc_ms"]
    return out.reset_index()


# ----------------------------------------------------------------------------------------------
# Stage B's certification and timing stages
# ----------------------------------------------------------------------------------------------


def _cert_params(config: dict) -> dict:
    return dict(margin=float(config["margin_m"]), max_depth=int(config["max_depth"]),
                coarse_depth=int(config["coarse_depth"]))


def certify_stage(layout: Layout, config: dict, repeats: int = 3) -> dict:
    """Each method certifies the whole dataset in one call (:func:`batch_certify`): per-method
    results (``certification/results.csv``), LARC's frontier per depth and trajectory
    (``larc_levels.csv``) and the batch times (``batch_timing.csv``)."""
    from experiments.models import load_dataset, robot_and_capsules

    robot, caps = robot_and_capsules(config)
    index, trajs, scenes = load_dataset(layout, config, robot)
    if not trajs:
        raise RuntimeError(f"no trajectories under {layout.trajectories_dir}")
    results, batch_rows = batch_certify(trajs, scenes, robot, caps, methods=METHODS, repeats=repeats,
                                        **_cert_params(config))
    max_depth = int(config["max_depth"])
    rows, levels = [], []
    for m in METHODS:
        res = results[m]
        df = res.to_dataframe().set_index("id")
        for r, meta, tr in zip(res.trajectories, index, trajs):
            assert r.id == meta["traj_id"], (r.id, meta["traj_id"])
            d = df.loc[r.id]
            row = dict(traj_id=r.id, scene=meta["scene"], pair_id=meta["pair_id"], variant=meta["variant"],
                       duration_s=tr.duration, n_waypoints=tr.n_waypoints, method=m,
                       certified=r.certified, evaluations=r.evaluations, min_clearance_m=r.min_clearance_m,
                       blocked_t0=d["blocked_t0"], blocked_t1=d["blocked_t1"],
                       blocked_capsule=d["blocked_capsule"], blocked_box=d["blocked_box"])
            for k in range(max_depth + 1):
                row[f"f{k}"] = r.frontier_sizes[k] if k < len(r.frontier_sizes) else 0
            rows.append(row)
            if m == "larc":
                passed = [0] * (max_depth + 1)
                for leaf in r.leaves:
                    passed[leaf.depth] += int(leaf.certified)
                for k in range(max_depth + 1):
                    f = r.frontier_sizes[k]
                    levels.append(dict(traj_id=r.id, scene=meta["scene"], variant=meta["variant"], depth=k,
                                       frontier=f, passed=passed[k], inconclusive=f - passed[k]))
    write_csv(layout.cert_results_csv, rows)
    write_csv(layout.cert_levels_csv, levels)
    write_csv(layout.cert_batch_csv, batch_rows)
    for b in batch_rows:
        print(f"[stageB] certify: {b['method']:>6}: {b['certified']}/{b['trajectories']} certified, "
              f"{b['evaluations']} evaluations, batch {b['batch_s_median']:.3f} s (median of "
              f"{b['warm_repeats']}), first call {b['first_call_s']:.2f} s (compile ~{b['compile_s']:.2f} s)",
              flush=True)
    return dict(trajectories=len(trajs))


RAW_TIMING_FIELDS = ["traj_id", "scene", "kind", "repeat", "position", "method", "time_ms", "compiles",
                     "certified", "evaluations"]


def timing_stage(layout: Layout, config: dict, key: str, force: bool) -> dict:
    """The paired per-trajectory timing (:func:`paired_timing`) into ``timing/raw.csv`` (rows
    cached per trajectory while ``key`` matches ``timing/raw.key``) and its summary
    ``timing/per_trajectory.csv``."""
    from experiments.models import load_dataset, robot_and_capsules
    from larc_jax.io import atomic_write_text

    robot, caps = robot_and_capsules(config)
    index, trajs, scenes = load_dataset(layout, config, robot)
    key_file = layout.timing_dir / "raw.key"
    cached: dict[str, list[dict]] = {}
    if not force and key_file.is_file() and key_file.read_text().strip() == key:
        for r in read_csv(layout.timing_raw_csv):
            cached.setdefault(r["traj_id"], []).append(r)
    ids = [t.id for t in trajs]
    rows_by_id = {i: cached[i] for i in ids if i in cached}
    atomic_write_text(key_file, key + "\n")

    def flush():
        write_csv(layout.timing_raw_csv, [r for i in ids if i in rows_by_id for r in rows_by_id[i]],
                  RAW_TIMING_FIELDS)

    def on_traj(rows):
        rows_by_id[rows[0]["traj_id"]] = rows
        flush()

    flush()
    if len(rows_by_id) < len(ids):
        print(f"[stageB] timing: {len(rows_by_id)} trajectories cached, {len(ids) - len(rows_by_id)} to time "
              f"(seed {config['timing_seed']}, {config['timing_repeats']} repeats)", flush=True)
        paired_timing(trajs, scenes, robot, caps, seed=int(config["timing_seed"]),
                      repeats=int(config["timing_repeats"]), skip=set(rows_by_id),
                      on_trajectory=on_traj, **_cert_params(config))
    summary = summarise_timing([r for i in ids for r in rows_by_id[i]])
    atomic_write_text(layout.timing_summary_csv, summary.to_csv(index=False))
    n_comp = int(summary["timed_compiles"].sum())
    if n_comp:
        print(f"[stageB] timing: WARNING {n_comp} XLA compilations happened inside timed calls", flush=True)
    return dict(trajectories=len(ids), timed_compiles=n_comp)
