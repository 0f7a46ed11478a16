"""Stage B end to end: generation, FCL audit, certification, paired timing, tables, figures.

    python -m experiments.stageB [--quick] [--out DIR] [--force] [--from STAGE] [--check] [--workers 2]

Reproduces the paper's "Simulation Study" and "Results" on our own data, with the frozen protocol
of ``configs/stageB.yaml``. Stages (each in its own module; every output is written atomically):

1. ``generate`` — :mod:`experiments.generate`: per scene, accepted start-goal pairs, each an
   ``ompl_planned`` and a ``direct_smoothstep`` JointTrajectory YAML, plus ``attempts.csv``.
   Full run: 20 pairs per scene into ``results/stageB/dataset/`` (committed); ``--quick``: 2
   pairs per scene into ``<out>/dataset/`` (default ``results/stageB_quick``, git-ignored).
2. ``audit`` — :func:`experiments.audit.audit_stage` on the official meshes at ``audit_hz`` plus
   every waypoint, ``audit/audit.csv``.
3. ``certify`` — :func:`experiments.timing.certify_stage`: LARC, fixed-fine and fixed-coarse,
   each certifying the WHOLE dataset in one batched call (first call = compile, reported
   separately; batch time = median of warm calls).
4. ``timing`` — :func:`experiments.timing.timing_stage`: per trajectory, the three methods in a
   random order (``timing_seed``), ``timing_repeats`` repeats, median per method; paired
   speedup fine/larc.
5. ``tables`` — :func:`experiments.tables.make_tables` (``trajectories``, ``overall``,
   ``per_scene``, ..., ``README.md`` with the discussion template filled in) and the must-hold
   checks (printed, not asserted).
6. ``figures`` — :func:`experiments.figures.make_figures` into ``figures/``.

Resuming. A stage is skipped when all of its outputs exist and its fingerprint — a SHA-256 of
its data inputs, its parameters and its *code* (the import closure of its module, see
:mod:`experiments.fingerprints`) — equals the one recorded in ``_stages/<stage>.json`` when they
were written (generation: each scene's done-marker). A code change that a stage does not depend
on (the command line, ``explain``, a docstring) leaves it up to date; a change it depends on
reruns it and every stage downstream whose inputs then change. Run the command again after
changing the library, and only what is out of date is redone: that is the one step that brings
the committed results up to date. ``--check`` only reports the out-of-date stages (exit 1 if
any; ``tests/test_stageB_fingerprints.py`` runs it on the committed results). ``--force``
reruns every stage (generation included; generation is deterministic, so the dataset comes out
byte-identical); ``--from STAGE`` reruns that stage and the later ones. Wall times of the last
run go to ``_cache/last_run.json`` (git-ignored): the committed outputs hold none except the
measured timings themselves.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import sys
import time
from pathlib import Path
from typing import Callable, Sequence

from experiments.common import CONFIG_PATH, ROOT, Layout, dataset_index, load_config, resolve, scene_paths
from experiments.fingerprints import environment, fingerprint

STAGES = ("generate", "audit", "certify", "timing", "tables", "figures")

__all__ = ["STAGES", "Stage", "stage_plan", "out_of_date", "main"]


class Stage:
    """One stage after generation: its fingerprint (computed when first asked for), its outputs
    and how to run it."""

    def __init__(self, name: str, fp: Callable[[], str], outputs: Callable[[], Sequence[Path]],
                 run: Callable[[], dict | None]):
        self.name, self._fp, self.outputs, self.run = name, fp, outputs, run

    @functools.cached_property
    def fingerprint(self) -> str:
        return self._fp()

    def manifest(self, layout: Layout) -> Path:
        return layout.stages_dir / f"{self.name}.json"

    def recorded(self, layout: Layout) -> str | None:
        try:
            return json.loads(self.manifest(layout).read_text()).get("fingerprint")
        except (OSError, json.JSONDecodeError):
            return None

    def up_to_date(self, layout: Layout) -> bool:
        return self.recorded(layout) == self.fingerprint and all(Path(o).exists() for o in self.outputs())


# ----------------------------------------------------------------------------------------------
# Fingerprints: what each stage depends on
# ----------------------------------------------------------------------------------------------


def _n_pairs(config: dict, quick: bool) -> int:
    return int(config.get("quick_pairs_per_scene", 2)) if quick else int(config["pairs_per_scene"])


def _max_attempts(config: dict, scene: str) -> int:
    return int(config["scenes"][scene].get("max_attempts", config["generation"]["max_attempts_per_scene"]))


def generation_out_of_date(layout: Layout, config: dict, quick: bool) -> list[str]:
    """Scenes whose done-marker does not match their inputs (or ``attempts.csv`` missing)."""
    from experiments.generate import scene_fingerprint, scene_is_done

    n_pairs = _n_pairs(config, quick)
    stale = [s for s in scene_paths(config)
             if not scene_is_done(layout.dataset, s, scene_fingerprint(s, config, n_pairs, _max_attempts(config, s)))]
    if not stale and not layout.attempts_csv.is_file():
        stale = ["attempts.csv"]
    return stale


def stage_plan(layout: Layout, config: dict, config_path: Path, quick: bool, workers: int,
               forced: set[str]) -> list[Stage]:
    """The stages after generation, with the fingerprints of their current inputs."""
    from experiments import audit, figures, stageB_report, timing

    params = dict(config={k: config[k] for k in ("margin_m", "max_depth", "coarse_depth", "audit_hz",
                                                    "timing_seed", "timing_repeats", "batch_timing_repeats")
                          if k in config})
    capsules = resolve(config["capsules"])

    @functools.lru_cache(maxsize=None)
    def dataset() -> tuple[Path, ...]:  # the trajectory files and the scenes
        return tuple([r["path"] for r in dataset_index(layout, config)] + list(scene_paths(config).values()))

    @functools.lru_cache(maxsize=None)
    def geometry() -> tuple[Path, ...]:  # the allowed pairs, the URDF and its collision meshes
        return tuple(audit.audit_inputs(config))

    def fp_cert() -> str:  # certification reads the URDF (kinematics) and the capsules, not the meshes
        from larc_jax.model.urdf import piper_urdf_path

        return fingerprint([*dataset(), piper_urdf_path(), capsules], params, code=timing.CODE)

    def fp_tables() -> str:
        inputs = [layout.cert_results_csv, layout.cert_levels_csv, layout.cert_batch_csv, layout.audit_csv,
                  layout.timing_summary_csv, layout.timing_raw_csv, layout.attempts_csv, config_path,
                  stageB_report.DISCUSSION]
        return fingerprint(inputs, dict(params, quick=quick), code=stageB_report.CODE)

    def fp_figures() -> str:
        extra = dict(scene_order=config.get("scene_order"), workspace_seed=config.get("workspace_seed"),
                     workspace_samples=config.get("workspace_samples"),
                     point_link=config["generation"].get("endpoint_point_link"))
        return fingerprint([layout.trajectories_csv, layout.out / "frontier_levels.csv", capsules, *dataset(),
                            *geometry()], dict(params, **extra), code=figures.CODE)

    timing_stage = Stage("timing", fp_cert, lambda: [layout.timing_raw_csv, layout.timing_summary_csv],
                         lambda: timing.timing_stage(layout, config, timing_stage.fingerprint, "timing" in forced))
    return [
        Stage("audit", lambda: fingerprint([*dataset(), *geometry()], params, code=audit.CODE),
              lambda: [layout.audit_csv],
              lambda: audit.audit_stage(layout, config, workers, "audit" in forced)),
        Stage("certify", fp_cert, lambda: [layout.cert_results_csv, layout.cert_levels_csv, layout.cert_batch_csv],
              lambda: timing.certify_stage(layout, config, int(config.get("batch_timing_repeats", 3)))),
        timing_stage,
        Stage("tables", fp_tables, lambda: stageB_report.stage_outputs(layout, quick),
              lambda: stageB_report.make_tables(layout, config, quick=quick)),
        Stage("figures", fp_figures, lambda: figures.figure_outputs(layout),
              lambda: figures.make_figures(layout, config)),
    ]


def out_of_date(layout: Layout, config: dict, config_path: Path = CONFIG_PATH, quick: bool = False) -> list[str]:
    """Stages whose committed outputs do not match what the current code and inputs would write
    (``generate: scene, ...`` for generation). Later stages are judged on the current outputs
    of earlier ones, so after rerunning the first stale stage, later ones may become stale."""
    out = []
    stale_scenes = generation_out_of_date(layout, config, quick)
    if stale_scenes:
        out.append("generate: " + ", ".join(stale_scenes))
    for st in stage_plan(layout, config, config_path, quick, workers=1, forced=set()):
        if not st.up_to_date(layout):
            out.append(st.name)
    return out


# ----------------------------------------------------------------------------------------------
# Driver
# ----------------------------------------------------------------------------------------------


def _generate(layout: Layout, config: dict, quick: bool, force: bool, workers: int) -> tuple[str, float]:
    from experiments.generate import generate_all

    if not force and not generation_out_of_date(layout, config, quick):
        print("[stageB] generate: skipped (every scene's done-marker matches its inputs)", flush=True)
        return "skipped", 0.0
    n_pairs = _n_pairs(config, quick)
    print(f"[stageB] generate: running ({n_pairs} pairs per scene, {workers} workers) -> {layout.dataset}",
          flush=True)
    t0 = time.perf_counter()
    results = generate_all(config, layout.dataset, list(scene_paths(config)), n_pairs, workers=workers, force=force)
    for r in results:
        if "error" in r:
            print(f"[stageB] generate: {r['scene']}: ERROR {r['error']}\n{r.get('traceback', '')}", flush=True)
        else:
            print(f"[stageB] generate: {r['scene']}: {r['n_pairs_accepted']}/{r['n_pairs_requested']} pairs, "
                  f"{r['attempts']} attempts {r['outcomes']}{' (skipped)' if r.get('skipped') else ''}", flush=True)
    errors = [r["scene"] for r in results if "error" in r]
    if errors:
        raise RuntimeError(f"generation failed for {errors}")
    return "ran", time.perf_counter() - t0


def _run_stage(layout: Layout, st: Stage, forced: set[str]) -> tuple[str, float]:
    from larc_jax.io import atomic_write_json

    if st.name not in forced and st.up_to_date(layout):
        print(f"[stageB] {st.name}: skipped (outputs up to date with their inputs and code)", flush=True)
        return "skipped", 0.0
    print(f"[stageB] {st.name}: running", flush=True)
    t0 = time.perf_counter()
    extra = st.run() or {}
    dt = time.perf_counter() - t0
    outs = []
    for o in st.outputs():
        try:
            outs.append(str(Path(o).resolve().relative_to(layout.out.resolve())))
        except ValueError:
            outs.append(str(o))
    # No wall time here: a manifest changes only when its stage's inputs or results do.
    extra = {k: v for k, v in extra.items() if not k.endswith("_s")}
    atomic_write_json(st.manifest(layout), dict(stage=st.name, fingerprint=st.fingerprint, outputs=outs,
                                                environment=environment(), **extra))
    print(f"[stageB] {st.name}: done in {dt:.1f} s", flush=True)
    return "ran", dt


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="Stage B: generation, audit, certification, timing, tables, figures")
    ap.add_argument("--quick", action="store_true", help="2 pairs per scene into results/stageB_quick (or --out)")
    ap.add_argument("--out", default=None, help="output folder (default results/stageB, or results/stageB_quick)")
    ap.add_argument("--force", action="store_true", help="rerun every stage (generation included)")
    ap.add_argument("--from", dest="from_stage", choices=STAGES, default=None,
                    help="rerun this stage and every later one")
    ap.add_argument("--check", action="store_true",
                    help="run nothing: list the stages whose outputs are out of date (exit 1 if any)")
    ap.add_argument("--workers", type=int, default=2, help="processes for generation and audit")
    ap.add_argument("--config", default=str(CONFIG_PATH))
    args = ap.parse_args(argv)

    os.environ.setdefault("MPLBACKEND", "Agg")
    t_all = time.perf_counter()
    config_path = Path(args.config).resolve()
    config = load_config(config_path)
    out = Path(args.out) if args.out else ROOT / "results" / ("stageB_quick" if args.quick else "stageB")
    layout = Layout(out.resolve())
    if args.check:
        stale = out_of_date(layout, config, config_path, args.quick)
        for s in stale:
            print(f"[stageB] out of date: {s}", flush=True)
        print(f"[stageB] {layout.out}: " + ("up to date" if not stale else
              "run `python -m experiments.stageB` to bring it up to date"), flush=True)
        return 1 if stale else 0
    forced = set(STAGES) if args.force else (set(STAGES[STAGES.index(args.from_stage):]) if args.from_stage
                                             else set())
    print(f"[stageB] {'quick' if args.quick else 'full'} run -> {layout.out}", flush=True)

    report = [("generate", *_generate(layout, config, args.quick, "generate" in forced, args.workers))]
    # Fingerprints are taken after generation (they hash the dataset), and each stage's just
    # before it runs (they hash the outputs of the stages before it).
    for name in STAGES[1:]:
        st = next(s for s in stage_plan(layout, config, config_path, args.quick, args.workers, forced)
                  if s.name == name)
        report.append((name, *_run_stage(layout, st, forced)))
        if name == "tables":
            from experiments.tables import load_checks, print_checks

            print_checks(load_checks(layout))

    total = time.perf_counter() - t_all
    print("[stageB] summary:", flush=True)
    for stage, status, secs in report:
        print(f"[stageB]   {stage:<9} {status:<8} {secs:8.1f} s", flush=True)
    print(f"[stageB]   total              {total:8.1f} s", flush=True)
    from larc_jax.io import atomic_write_json

    atomic_write_json(layout.out / "_cache" / "last_run.json", dict(
        mode="quick" if args.quick else "full",
        stages=[dict(stage=s, status=st, seconds=round(x, 2)) for s, st, x in report], total_s=round(total, 2)))
    return 0


if __name__ == "__main__":
    from larc_jax.errors import LarcInputError

    try:
        sys.exit(main())
    except LarcInputError as exc:  # e.g. PIPER not found: one line, not a traceback
        print(f"stageB: error: {exc}", file=sys.stderr)
        sys.exit(2)
