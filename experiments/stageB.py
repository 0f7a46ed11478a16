"""Stage B end to end: generation, FCL audit, certification, paired timing, tables, figures.

    python -m experiments.stageB [--quick] [--out DIR] [--force] [--from STAGE] [--workers 2]

Reproduces the paper's "Simulation Study" and "Results" on our own data, with the frozen protocol
of ``configs/stageB.yaml``. Stages (each one's outputs are written atomically):

1. ``generate`` — :mod:`experiments.generate`: per scene, accepted start-goal pairs, each an
   ``ompl_planned`` and a ``direct_smoothstep`` JointTrajectory YAML, plus ``attempts.csv``.
   Full run: 20 pairs per scene into ``results/stageB/dataset/`` (committed); ``--quick``: 2
   pairs per scene into ``<out>/dataset/`` (default ``results/stageB_quick``, git-ignored).
2. ``audit`` — :mod:`experiments.audit` on the official meshes at ``audit_hz`` plus every
   waypoint; one row per trajectory in ``audit/audit.csv``, rewritten atomically after every
   finished trajectory (a killed run loses no finished record; rows are reused when their key,
   a hash of the trajectory file, the scene file and the audit code, still matches).
3. ``certify`` — LARC, fixed-fine and fixed-coarse, each certifying the WHOLE dataset in one
   batched call (first call = compile, reported separately; batch time = median of warm calls).
4. ``timing`` — :func:`experiments.timing.paired_timing`: per trajectory, the three methods in a
   random order (``timing_seed``), ``timing_repeats`` repeats, median per method; paired
   speedup fine/larc. Raw rows are cached per trajectory in ``timing/raw.csv``.
5. ``tables`` — :mod:`experiments.tables` (``trajectories``, ``overall``, ``per_scene``, ...,
   ``README.md``) and the must-hold checks (printed, not asserted).
6. ``figures`` — :mod:`experiments.figures` into ``figures/``.

Resuming. A stage is skipped when all of its outputs exist and are up to date with its inputs.
"Up to date" is decided by content, not file times (a git checkout gives every file the same
age): each finished stage writes ``_stages/<stage>.json`` with a SHA-256 fingerprint of its input
files (data, configuration and the code that produces the outputs) and parameters; the stage
reruns when the fingerprint changes or an output is missing. ``--force`` reruns every stage
(generation included); ``--from STAGE`` reruns that stage and the later ones. The stage times of
the last run are written to ``_cache/last_run.json`` (not committed).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import hashlib
import io
import json
import os
import re
import sys
import time
from pathlib import Path
from typing import Callable, Sequence

ROOT = Path(__file__).resolve().parent.parent
CONFIG_PATH = ROOT / "configs" / "stageB.yaml"
STAGES = ("generate", "audit", "certify", "timing", "tables", "figures")
METHODS = ("larc", "fine", "coarse")
TRAJ_RE = re.compile(r"^(?P<pair>(?P<scene>.+)_p(?P<num>\d+))_(?P<variant>ompl_planned|direct_smoothstep)$")
AUDIT_FIELDS = ["traj_id", "scene", "audit_states", "audit_collision", "audit_collision_states",
                "first_collision_t", "collision_contacts", "self_collision", "self_collision_states",
                "audit_time_s", "key"]

__all__ = ["Layout", "load_config", "dataset_index", "main", "STAGES"]


# ----------------------------------------------------------------------------------------------
# Layout, configuration, fingerprints
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Layout:
    """Where every stage reads and writes, under one output folder."""

    out: Path

    @property
    def dataset(self) -> Path:
        return self.out / "dataset"

    @property
    def trajectories_dir(self) -> Path:
        return self.dataset / "trajectories"

    @property
    def attempts_csv(self) -> Path:
        return self.dataset / "attempts.csv"

    @property
    def audit_csv(self) -> Path:
        return self.out / "audit" / "audit.csv"

    @property
    def cert_dir(self) -> Path:
        return self.out / "certification"

    @property
    def cert_results_csv(self) -> Path:
        return self.cert_dir / "results.csv"

    @property
    def cert_levels_csv(self) -> Path:
        return self.cert_dir / "larc_levels.csv"

    @property
    def cert_batch_csv(self) -> Path:
        return self.cert_dir / "batch_timing.csv"

    @property
    def timing_dir(self) -> Path:
        return self.out / "timing"

    @property
    def timing_raw_csv(self) -> Path:
        return self.timing_dir / "raw.csv"

    @property
    def timing_summary_csv(self) -> Path:
        return self.timing_dir / "per_trajectory.csv"

    @property
    def figures_dir(self) -> Path:
        return self.out / "figures"

    @property
    def stages_dir(self) -> Path:
        return self.out / "_stages"


def load_config(path: str | Path = CONFIG_PATH) -> dict:
    import yaml

    doc = yaml.safe_load(Path(path).read_text())
    if not isinstance(doc, dict):
        raise ValueError(f"{path}: expected a mapping")
    return doc


def _resolve(p: str | Path) -> Path:
    p = Path(p)
    return p if p.is_absolute() else ROOT / p


def scene_paths(config: dict) -> dict[str, Path]:
    order = config.get("scene_order") or list(config["scenes"])
    return {s: _resolve(config["scenes"][s]["file"]) for s in order}


def _sha_file(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def fingerprint(files: Sequence[Path], params: dict | None = None) -> str:
    """SHA-256 over the contents of ``files`` (by path relative to the repo when possible)
    and the JSON of ``params``."""
    h = hashlib.sha256()
    for f in sorted(Path(x) for x in files):
        try:
            name = str(f.resolve().relative_to(ROOT))
        except ValueError:
            name = f.name
        h.update(name.encode() + b"\0")
        h.update(_sha_file(f).encode() if f.is_file() else b"<missing>")
    h.update(json.dumps(params or {}, sort_keys=True, default=str).encode())
    return h.hexdigest()


def _library_sources() -> list[Path]:
    return sorted((ROOT / "larc_jax").rglob("*.py"))


class StageBook:
    """Manifests of finished stages (``_stages/<stage>.json``) and the per-run report."""

    def __init__(self, layout: Layout, forced: set[str]):
        self.layout = layout
        self.forced = forced
        self.report: list[tuple[str, str, float]] = []

    def _manifest(self, stage: str) -> Path:
        return self.layout.stages_dir / f"{stage}.json"

    def up_to_date(self, stage: str, fp: str, outputs: Sequence[Path]) -> bool:
        if stage in self.forced:
            return False
        m = self._manifest(stage)
        if not m.is_file() or not all(Path(o).exists() for o in outputs):
            return False
        try:
            doc = json.loads(m.read_text())
        except (OSError, json.JSONDecodeError):
            return False
        return doc.get("fingerprint") == fp

    def done(self, stage: str, fp: str, outputs: Sequence[Path], elapsed: float, extra: dict | None = None):
        from larc_jax.io import atomic_write_json

        outs = []
        for o in outputs:
            try:
                outs.append(str(Path(o).resolve().relative_to(self.layout.out.resolve())))
            except ValueError:
                outs.append(str(o))
        atomic_write_json(self._manifest(stage), dict(stage=stage, fingerprint=fp, outputs=outs,
                                                       elapsed_s=round(elapsed, 2), **(extra or {})))

    def run(self, stage: str, fp: str, outputs: Callable[[], Sequence[Path]] | Sequence[Path],
            fn: Callable[[], dict | None]):
        outs = outputs() if callable(outputs) else outputs
        if self.up_to_date(stage, fp, outs):
            print(f"[stageB] {stage}: skipped (outputs up to date with their inputs)", flush=True)
            self.report.append((stage, "skipped", 0.0))
            return
        print(f"[stageB] {stage}: running", flush=True)
        t0 = time.perf_counter()
        extra = fn() or {}
        dt = time.perf_counter() - t0
        outs = outputs() if callable(outputs) else outputs
        self.done(stage, fp, outs, dt, extra)
        self.report.append((stage, "ran", dt))
        print(f"[stageB] {stage}: done in {dt:.1f} s", flush=True)


# ----------------------------------------------------------------------------------------------
# Dataset
# ----------------------------------------------------------------------------------------------


def dataset_index(layout: Layout, config: dict) -> list[dict]:
    """Trajectory files of the dataset: one dict per file (traj_id, scene, pair_id, variant,
    path), scenes in the configured order, then by id."""
    rows = []
    for scene in scene_paths(config):
        folder = layout.trajectories_dir / scene
        for p in sorted(folder.glob("*.yaml")):
            m = TRAJ_RE.match(p.stem)
            if not m or m["scene"] != scene:
                continue
            rows.append(dict(traj_id=p.stem, scene=scene, pair_id=m["pair"], variant=m["variant"], path=p))
    return rows


def _load_dataset(layout: Layout, config: dict, robot):
    from larc_jax.scene import read_scene
    from larc_jax.trajectory_files import read_trajectory

    index = dataset_index(layout, config)
    scenes = {s: read_scene(p) for s, p in scene_paths(config).items()}
    scenes = {s: dataclasses.replace(sc, name=s) for s, sc in scenes.items()}
    trajs = [read_trajectory(r["path"], robot) for r in index]
    return index, trajs, [scenes[r["scene"]] for r in index]


def _write_csv(path: Path, rows: Sequence[dict], fields: Sequence[str] | None = None):
    from larc_jax.io import atomic_write_text

    fields = list(fields or (rows[0].keys() if rows else []))
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n", extrasaction="ignore")
    w.writeheader()
    for r in rows:
        w.writerow({k: r.get(k, "") for k in fields})
    atomic_write_text(path, buf.getvalue())


def _read_csv(path: Path) -> list[dict]:
    if not Path(path).is_file():
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


# ----------------------------------------------------------------------------------------------
# Stage 1: generation
# ----------------------------------------------------------------------------------------------


def _n_pairs(config: dict, quick: bool) -> int:
    return int(config.get("quick_pairs_per_scene", 2)) if quick else int(config["pairs_per_scene"])


def stage_generate(layout: Layout, config: dict, quick: bool, force: bool, workers: int,
                   config_path: str | Path = CONFIG_PATH):
    """Returns (ran, seconds). Delegates resuming to the generator's per-scene done-markers."""
    from experiments import generate as gen

    gconfig = gen.load_config(config_path)
    scenes = list(scene_paths(config))
    n_pairs = _n_pairs(config, quick)
    t0 = time.perf_counter()
    if not force:
        try:
            done = all(
                gen.scene_is_done(layout.dataset, s, gen.scene_fingerprint(
                    s, gconfig, n_pairs,
                    int(gconfig["scenes"][s].get("max_attempts", gconfig["generation"]["max_attempts_per_scene"]))))
                for s in scenes
            ) and layout.attempts_csv.is_file()
        except Exception:  # noqa: BLE001 - API drift: let the generator decide
            done = False
        if done:
            print("[stageB] generate: skipped (every scene's done-marker matches its inputs)", flush=True)
            return False, 0.0
    print(f"[stageB] generate: running ({n_pairs} pairs per scene, {workers} workers) -> {layout.dataset}",
          flush=True)
    results = gen.generate_all(gconfig, layout.dataset, scenes, n_pairs, workers=workers, force=force)
    errors = [r for r in results if "error" in r]
    for r in results:
        if "error" in r:
            print(f"[stageB] generate: {r['scene']}: ERROR {r['error']}\n{r.get('traceback', '')}", flush=True)
        else:
            print(f"[stageB] generate: {r['scene']}: {r['n_pairs_accepted']}/{r['n_pairs_requested']} pairs, "
                  f"{r['attempts']} attempts {r['outcomes']}{' (skipped)' if r.get('skipped') else ''}",
                  flush=True)
    if errors:
        raise RuntimeError(f"generation failed for {[r['scene'] for r in errors]}")
    return True, time.perf_counter() - t0


# ----------------------------------------------------------------------------------------------
# Stage 2: audit
# ----------------------------------------------------------------------------------------------


def _audit_code_files() -> list[Path]:
    return [ROOT / "experiments" / "audit.py", ROOT / "experiments" / "collision.py"]


def _audit_key(traj_path: Path, scene_path: Path, config: dict) -> str:
    allowed = _resolve(config.get("allowed_collisions", "configs/piper_allowed_collisions.yaml"))
    return fingerprint([traj_path, scene_path, allowed, *_audit_code_files()],
                       dict(audit_hz=config["audit_hz"]))[:20]


def _audit_one(job: dict) -> dict:
    """Audit one trajectory in a worker (set up by ``experiments.audit._init_worker``) → a row
    of :data:`AUDIT_FIELDS`."""
    from experiments.audit import audit_file_in_worker

    t0 = time.perf_counter()
    res = audit_file_in_worker(job["path"], job["scene_path"])
    row = dict(traj_id=job["traj_id"], scene=job["scene"], key=job["key"],
               audit_time_s=round(time.perf_counter() - t0, 3))
    row.update(_normalise_audit(res))
    return row


def _normalise_audit(res: dict) -> dict:
    """Map :func:`experiments.audit.audit_trajectory`'s result onto :data:`AUDIT_FIELDS`."""
    def opt(x):
        return "" if x is None else x

    return dict(
        audit_states=int(res["audit_states"]),
        audit_collision=bool(res["audit_collision"]),
        audit_collision_states=int(res.get("scene_collision_states", 0)),
        first_collision_t=opt(res.get("first_collision_time")),
        collision_contacts=opt(res.get("first_contact")),
        self_collision=bool(res.get("self_collision", False)),
        self_collision_states=int(res.get("self_collision_states", 0)),
    )


def stage_audit(layout: Layout, config: dict, workers: int, force: bool):
    import multiprocessing as mp

    from tqdm import tqdm

    from experiments.audit import _init_worker as _init_audit_worker

    index = dataset_index(layout, config)
    spaths = scene_paths(config)
    jobs = []
    for r in index:
        jobs.append(dict(traj_id=r["traj_id"], scene=r["scene"], path=str(r["path"]),
                         scene_path=str(spaths[r["scene"]]),
                         key=_audit_key(r["path"], spaths[r["scene"]], config)))
    cached = {} if force else {r["traj_id"]: r for r in _read_csv(layout.audit_csv)}
    rows = {j["traj_id"]: cached[j["traj_id"]] for j in jobs
            if j["traj_id"] in cached and cached[j["traj_id"]].get("key") == j["key"]}
    todo = [j for j in jobs if j["traj_id"] not in rows]
    print(f"[stageB] audit: {len(rows)} cached, {len(todo)} to audit at {config['audit_hz']} Hz "
          f"+ waypoints ({workers} workers)", flush=True)

    def flush():
        ordered = [rows[j["traj_id"]] for j in jobs if j["traj_id"] in rows]
        _write_csv(layout.audit_csv, ordered, AUDIT_FIELDS)

    flush()
    if todo:
        # Longest first so the two workers finish together.
        todo.sort(key=lambda j: -Path(j["path"]).stat().st_size)
        bar = tqdm(total=len(todo), desc="audit", unit="traj", dynamic_ncols=True)
        init = (str(_resolve(config.get("allowed_collisions", "configs/piper_allowed_collisions.yaml"))),
                float(config["audit_hz"]))
        if workers > 1:
            ctx = mp.get_context("spawn")
            with ctx.Pool(workers, initializer=_init_audit_worker, initargs=init) as pool:
                for row in pool.imap_unordered(_audit_one, todo):
                    rows[row["traj_id"]] = row
                    flush()
                    bar.update(1)
        else:
            _init_audit_worker(*init)
            for j in todo:
                row = _audit_one(j)
                rows[row["traj_id"]] = row
                flush()
                bar.update(1)
        bar.close()
    flush()
    return dict(trajectories=len(rows), audited_now=len(todo))


# ----------------------------------------------------------------------------------------------
# Stage 3: certification (batched)
# ----------------------------------------------------------------------------------------------


def _robot_and_capsules(config: dict):
    from larc_jax.enclosure import default_capsule_path, load_capsules
    from larc_jax.urdf import load_robot

    robot = load_robot()
    cap_path = _resolve(config.get("capsules", default_capsule_path()))
    return robot, load_capsules(cap_path, robot)


def _cert_params(config: dict) -> dict:
    return dict(margin=float(config["margin_m"]), max_depth=int(config["max_depth"]),
                coarse_depth=int(config["coarse_depth"]))


def stage_certify(layout: Layout, config: dict, repeats: int = 3):
    from experiments.timing import batch_certify

    robot, caps = _robot_and_capsules(config)
    index, trajs, scenes = _load_dataset(layout, config, robot)
    if not trajs:
        raise RuntimeError(f"no trajectories under {layout.trajectories_dir}")
    results, batch_rows = batch_certify(trajs, scenes, robot, caps, methods=METHODS,
                                        repeats=repeats, **_cert_params(config))
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
                    if leaf.certified:
                        passed[leaf.depth] += 1
                for k in range(max_depth + 1):
                    f = r.frontier_sizes[k]
                    levels.append(dict(traj_id=r.id, scene=meta["scene"], variant=meta["variant"], depth=k,
                                       frontier=f, passed=passed[k], inconclusive=f - passed[k]))
    _write_csv(layout.cert_results_csv, rows)
    _write_csv(layout.cert_levels_csv, levels)
    _write_csv(layout.cert_batch_csv, batch_rows)
    for b in batch_rows:
        print(f"[stageB] certify: {b['method']:>6}: {b['certified']}/{b['trajectories']} certified, "
              f"{b['evaluations']} evaluations, batch {b['batch_s_median']:.3f} s (median of "
              f"{b['warm_repeats']}), first call {b['first_call_s']:.2f} s (compile ~{b['compile_s']:.2f} s)",
              flush=True)
    return dict(trajectories=len(trajs))


# ----------------------------------------------------------------------------------------------
# Stage 4: paired timing
# ----------------------------------------------------------------------------------------------


RAW_TIMING_FIELDS = ["traj_id", "scene", "kind", "repeat", "position", "method", "time_ms", "compiles",
                     "certified", "evaluations"]


def stage_timing(layout: Layout, config: dict, key: str, force: bool):
    from experiments.timing import paired_timing, summarise_timing
    from larc_jax.io import atomic_write_text

    robot, caps = _robot_and_capsules(config)
    index, trajs, scenes = _load_dataset(layout, config, robot)
    key_file = layout.timing_dir / "raw.key"
    cached: dict[str, list[dict]] = {}
    if not force and key_file.is_file() and key_file.read_text().strip() == key:
        for r in _read_csv(layout.timing_raw_csv):
            cached.setdefault(r["traj_id"], []).append(r)
    ids = [t.id for t in trajs]
    rows_by_id = {i: cached[i] for i in ids if i in cached}
    atomic_write_text(key_file, key + "\n")

    def flush():
        out = [r for i in ids if i in rows_by_id for r in rows_by_id[i]]
        _write_csv(layout.timing_raw_csv, out, RAW_TIMING_FIELDS)

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
    raw = [r for i in ids for r in rows_by_id[i]]
    summary = summarise_timing(raw)
    atomic_write_text(layout.timing_summary_csv, summary.to_csv(index=False))
    n_comp = int(summary["timed_compiles"].sum())
    if n_comp:
        print(f"[stageB] timing: WARNING {n_comp} XLA compilations happened inside timed calls", flush=True)
    return dict(trajectories=len(ids), timed_compiles=n_comp)


# ----------------------------------------------------------------------------------------------
# Driver
# ----------------------------------------------------------------------------------------------


def _dataset_files(layout: Layout, config: dict) -> list[Path]:
    return [r["path"] for r in dataset_index(layout, config)] + list(scene_paths(config).values())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="Stage B: generation, audit, certification, timing, tables, figures")
    ap.add_argument("--quick", action="store_true", help="2 pairs per scene into results/stageB_quick (or --out)")
    ap.add_argument("--out", default=None, help="output folder (default results/stageB, or results/stageB_quick)")
    ap.add_argument("--force", action="store_true", help="rerun every stage (generation included)")
    ap.add_argument("--from", dest="from_stage", choices=STAGES, default=None,
                    help="rerun this stage and every later one")
    ap.add_argument("--workers", type=int, default=2, help="processes for generation and audit")
    ap.add_argument("--config", default=str(CONFIG_PATH))
    args = ap.parse_args(argv)

    os.environ.setdefault("MPLBACKEND", "Agg")
    t_all = time.perf_counter()
    config = load_config(args.config)
    out = Path(args.out) if args.out else ROOT / "results" / ("stageB_quick" if args.quick else "stageB")
    out = out.resolve()
    layout = Layout(out)
    forced = set(STAGES) if args.force else (set(STAGES[STAGES.index(args.from_stage):]) if args.from_stage else set())
    book = StageBook(layout, forced)
    print(f"[stageB] {'quick' if args.quick else 'full'} run -> {out}", flush=True)

    # 1. generation (resumes through the generator's own per-scene done-markers)
    ran, dt = stage_generate(layout, config, args.quick, "generate" in forced, args.workers,
                             args.config)
    book.report.append(("generate", "ran" if ran else "skipped", dt))

    params = dict(config={k: config[k] for k in ("margin_m", "max_depth", "coarse_depth", "audit_hz",
                                                    "timing_seed", "timing_repeats") if k in config})
    here = ROOT / "experiments"
    capsule_file = _resolve(config.get("capsules", "configs/piper_capsules.yaml"))

    # 2. audit
    fp_audit = fingerprint(_dataset_files(layout, config) + _audit_code_files()
                           + [here / "stageB.py"], params)
    book.run("audit", fp_audit, [layout.audit_csv],
             lambda: stage_audit(layout, config, args.workers, "audit" in forced))

    # 3. certification (batched)
    cert_inputs = _dataset_files(layout, config) + _library_sources() + [capsule_file, here / "timing.py",
                                                                          here / "stageB.py"]
    fp_cert = fingerprint(cert_inputs, params)
    book.run("certify", fp_cert, [layout.cert_results_csv, layout.cert_levels_csv, layout.cert_batch_csv],
             lambda: stage_certify(layout, config, int(config.get("batch_timing_repeats", 3))))

    # 4. paired timing
    fp_timing = fingerprint(cert_inputs, params)
    book.run("timing", fp_timing, [layout.timing_raw_csv, layout.timing_summary_csv],
             lambda: stage_timing(layout, config, fp_timing, "timing" in forced))

    # 5. tables (+ must-hold checks)
    from experiments import tables as tables_mod

    table_inputs = [layout.cert_results_csv, layout.cert_levels_csv, layout.cert_batch_csv, layout.audit_csv,
                    layout.timing_summary_csv, layout.attempts_csv, here / "tables.py", args.config,
                    tables_mod.DISCUSSION]
    fp_tables = fingerprint(table_inputs, dict(params, quick=args.quick))
    book.run("tables", fp_tables, lambda: tables_mod.table_outputs(layout),
             lambda: tables_mod.make_tables(layout, config, quick=args.quick))
    checks = tables_mod.load_checks(layout)
    tables_mod.print_checks(checks)

    # 6. figures
    from experiments import figures as figures_mod

    fig_inputs = table_inputs + [layout.out / "trajectories.csv", here / "figures.py", capsule_file] \
        + _dataset_files(layout, config)
    fp_fig = fingerprint(fig_inputs, dict(params, workspace_seed=config.get("workspace_seed"),
                                          workspace_samples=config.get("workspace_samples")))
    book.run("figures", fp_fig, lambda: figures_mod.figure_outputs(layout, config),
             lambda: figures_mod.make_figures(layout, config))

    total = time.perf_counter() - t_all
    print("[stageB] summary:", flush=True)
    for stage, status, secs in book.report:
        print(f"[stageB]   {stage:<9} {status:<8} {secs:8.1f} s", flush=True)
    print(f"[stageB]   total              {total:8.1f} s", flush=True)
    from larc_jax.io import atomic_write_json

    atomic_write_json(layout.out / "_cache" / "last_run.json", dict(
        mode="quick" if args.quick else "full",
        stages=[dict(stage=s, status=st, seconds=round(x, 2)) for s, st, x in book.report],
        total_s=round(total, 2)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
