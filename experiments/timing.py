"""Stage B timing: whole-batch certification times and the paper's paired per-trajectory protocol.

Two measurements (paper, "Sampled MoveIt/FCL Audit and Computational Timing"):

* **Whole batch** (:func:`batch_certify`): each method certifies the whole dataset in ONE
  :func:`larc_jax.certify.certify` call. The first call compiles (JAX traces and compiles the
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

__all__ = [
    "METHODS",
    "CompileCounter",
    "batch_certify",
    "paired_timing",
    "summarise_timing",
]

METHODS = ("larc", "fine", "coarse")
BACKEND_COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"
CLEAR_CACHES_AFTER_COMPILES = 200
"""Paired timing calls ``jax.clear_caches()`` between trajectories once this many XLA executables
were compiled since the last clear. Every compiled CPU executable keeps ~100 memory mappings
alive (measured: ~750 per new waypoint count, i.e. per set of larc/fine/coarse kernels), and
the kernel shapes depend on the trajectory's waypoint count, so timing trajectories of many
different lengths in one process otherwise exhausts ``vm.max_map_count`` (65530): LLVM then
fails with "Cannot allocate memory" and the process crashes (seen after ~78 distinct lengths).
Clearing only happens between trajectories, before the next one's untimed warm-up calls."""


class CompileCounter:
    """Counts XLA backend compilations (and their seconds) while active.

    Uses :func:`jax.monitoring.register_event_duration_secs_listener`; JAX offers no way to
    remove a single listener in every version, so one module-level listener feeds all counters.
    """

    _active: list["CompileCounter"] = []
    _installed = False

    def __init__(self):
        self.count = 0
        self.seconds = 0.0

    @classmethod
    def _install(cls):
        if cls._installed:
            return
        import jax.monitoring

        def listener(event: str, duration: float, **kwargs):
            if event == BACKEND_COMPILE_EVENT:
                for c in cls._active:
                    c.count += 1
                    c.seconds += float(duration)

        jax.monitoring.register_event_duration_secs_listener(listener)
        cls._installed = True

    def __enter__(self):
        self._install()
        self._active.append(self)
        return self

    def __exit__(self, *exc):
        self._active.remove(self)
        return False


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
    """(result, seconds, compiles) of one call, garbage collection paused."""
    with CompileCounter() as cc, _no_gc():
        t0 = time.perf_counter()
        out = fn()
        dt = time.perf_counter() - t0
    return out, dt, cc.count, cc.seconds


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
    from larc_jax.certify import certify

    results, rows = {}, []
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(methods) * (repeats + 1), desc="certify (batch)", unit="call",
                   dynamic_ncols=True)
    for m in methods:
        def call(m=m):
            return certify(trajectories, scenes, robot, capsules, method=m, margin=margin,
                           max_depth=max_depth, coarse_depth=coarse_depth)

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
    from larc_jax.certify import certify

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
                max_depth=max_depth, coarse_depth=coarse_depth))
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
