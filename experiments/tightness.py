"""How tight is the certificate? Planned paths next to obstacles, mesh truth, four certificates.

    python -m experiments.tightness [--quick] [--out DIR] [--force] [--workers 2]

A MoveIt user plans with a world padding around the obstacles; the closer the padding, the
closer the paths come. This driver plans such a dataset, measures how far the *official meshes*
really stay from the boxes, and asks which certificates prove it (issue 12):

1. ``generate`` — :mod:`experiments.generate` (OMPL RRTConnect, MoveIt-style simplification and
   interpolation, TOPP-RA timing, records as MoveIt's controller receives them) on the window
   and shelf scenes of ``configs/stageB.yaml``, once per planning padding in :data:`PADDINGS_MM`
   (0 included: the planner then only avoids contact at its checked states). Only the planned
   trajectories are used. Resumable through the generator's per-scene done-markers.
2. ``truth`` — for each trajectory, the smallest python-fcl distance between any link mesh and
   any box over the Hermite reconstruction (:mod:`experiments.mesh_truth`: ``scipy``
   ``CubicHermiteSpline``, as a controller replays it, fingers closed (joint7 = joint8 = 0, the
   stated opening); a 1 kHz grid, then a bounded scalar minimisation around every grid minimum
   within 1 mm of the best; FCL only where a proven capsule lower bound is below the best
   distance found so far, so pruning never changes the minimum). Rows are cached per trajectory (keyed by the trajectory, scene and
   code hashes) in ``truth.csv``, rewritten atomically after every trajectory.
3. ``certify`` — LARC on the whole dataset, margin rho = 10 mm, for each configuration of
   :data:`CONFIGS`: the paper's capsules with the gripper unknown (stroke enclosed), capsules
   with the gripper stated (``hold joint7 = joint8 = 0``), and the cascade (capsules, then
   convex hulls) with the gripper stated, with no padding (its default) and with 1 mm; and the
   capsules and the cascade with the swept stage (:mod:`larc_jax.leaf.swept`); at depths 6, 9 and
   12. ``certification.csv``; and :data:`STAGEB_CONFIGS` on the Stage B dataset
   (``results/stageB``), whose evaluations are compared with fixed-fine's ``512`` per trajectory
   (``stageB.csv``).
4. ``tables`` — ``table.md`` / ``table.csv`` (certified count per true-clearance bin, the
   issue's table, and in ``table.md`` the interval evaluations per bin), ``goal.md`` (the issue's goal lines), ``blocking.md`` (what still blocks
   the cascade at depth 12 on clear trajectories), ``summary.json``; and
   ``certified_vs_clearance.png`` (certified fraction against true clearance).

Every output is written atomically; a stage is skipped when its outputs exist and its input
fingerprint (data, code, parameters) is unchanged (``_stages/<stage>.json``); ``--force``
reruns everything. ``--quick``: one scene, one padding, 2 pairs, into ``results/tightness_quick``
(git-ignored; run by tests/test_tightness.py).
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import multiprocessing as mp
import sys
import time
from pathlib import Path

import numpy as np

from experiments.mesh_truth import COARSE_HZ, HOLD, TRUTH_HZ

ROOT = Path(__file__).resolve().parent.parent
CONFIG_PATH = ROOT / "configs" / "stageB.yaml"
SCENES = ("easy_window", "medium_window", "easy_shelf")
PADDINGS_MM = (0, 5, 10, 20, 30)
PAIRS = 10
MARGIN_M = 0.01
CONFIGS = (  # (name, enclosure, gripper stated, depth, padding_m: None = the enclosure's default, swept stage)
    ("capsules_d9", "capsules", False, 9, None, False),
    ("capsules_d12", "capsules", False, 12, None, False),
    ("capsules_stated_d6", "capsules", True, 6, None, False),
    ("capsules_stated_d9", "capsules", True, 9, None, False),
    ("capsules_stated_d12", "capsules", True, 12, None, False),
    ("capsules_swept_d6", "capsules", True, 6, None, True),
    ("capsules_swept_d9", "capsules", True, 9, None, True),
    ("capsules_swept_d12", "capsules", True, 12, None, True),
    ("cascade_pad1_d9", "hull", True, 9, 0.001, False),
    ("cascade_pad1_d12", "hull", True, 12, 0.001, False),
    ("cascade_d6", "hull", True, 6, None, False),
    ("cascade_d9", "hull", True, 9, None, False),
    ("cascade_d12", "hull", True, 12, None, False),
    ("cascade_swept_d6", "hull", True, 6, None, True),
    ("cascade_swept_d9", "hull", True, 9, None, True),
    ("cascade_swept_d12", "hull", True, 12, None, True),
)
STAGEB_CONFIGS = ("capsules_stated_d9", "capsules_swept_d9", "cascade_d9", "cascade_swept_d9")
"""Configurations also run on the Stage B dataset (``stageB.csv``: evaluations against fixed-fine)."""
LABELS = {"capsules_d9": "capsules, d9", "capsules_d12": "capsules, d12", "capsules_stated_d9": "capsules + gripper, d9",
          "capsules_stated_d12": "capsules + gripper, d12", "cascade_pad1_d9": "cascade + gripper, 1 mm padding, d9",
          "cascade_pad1_d12": "cascade + gripper, 1 mm padding, d12", "cascade_d6": "cascade + gripper, d6",
          "cascade_d9": "cascade + gripper, d9", "cascade_d12": "cascade + gripper, d12",
          "capsules_stated_d6": "capsules + gripper, d6", "capsules_swept_d6": "capsules + gripper + swept, d6",
          "capsules_swept_d9": "capsules + gripper + swept, d9", "capsules_swept_d12": "capsules + gripper + swept, d12",
          "cascade_swept_d6": "cascade + gripper + swept, d6", "cascade_swept_d9": "cascade + gripper + swept, d9",
          "cascade_swept_d12": "cascade + gripper + swept, d12"}
"""The table's column of each configuration."""
BINS_MM = (-math.inf, 10, 15, 20, 30, 50, math.inf)
TRUTH_FIELDS = ["traj_id", "padding_mm", "scene", "duration_s", "n_waypoints", "truth_m", "truth_t", "truth_link",
                "truth_box", "fcl_queries", "truth_time_s", "key"]

__all__ = ["main", "CONFIGS", "PADDINGS_MM", "MARGIN_M", "BINS_MM", "files_fingerprint", "write_frame", "run_stage",
           "bin_labels", "driver_args"]


# ----------------------------------------------------------------------------------------------
# Small helpers: fingerprints, atomic CSV, stage book-keeping
# ----------------------------------------------------------------------------------------------


def _sha(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def files_fingerprint(files, params=None) -> str:
    h = hashlib.sha256()
    for f in sorted(Path(x) for x in files):
        h.update(str(f.name).encode() + b"\0" + (_sha(f).encode() if f.is_file() else b"<missing>"))
    h.update(json.dumps(params or {}, sort_keys=True, default=str).encode())
    return h.hexdigest()


def write_frame(path: Path, frame) -> None:
    from larc_jax.io import atomic_write_text

    atomic_write_text(path, frame.to_csv(index=False))


def run_stage(out: Path, name: str, fp: str, outputs, fn, force: bool, tag: str = "tightness") -> None:
    """Run ``fn`` unless ``out/_stages/<name>.json`` records ``fp`` and every output exists."""
    from larc_jax.io import atomic_write_json

    marker = out / "_stages" / f"{name}.json"
    if not force and marker.is_file() and all(Path(o).exists() for o in outputs):
        try:
            if json.loads(marker.read_text()).get("fingerprint") == fp:
                print(f"[{tag}] {name}: skipped (outputs up to date with their inputs)", flush=True)
                return
        except (OSError, json.JSONDecodeError):
            pass
    print(f"[{tag}] {name}: running", flush=True)
    t0 = time.perf_counter()
    fn()
    dt = time.perf_counter() - t0
    atomic_write_json(marker, dict(stage=name, fingerprint=fp, elapsed_s=round(dt, 2)))
    print(f"[{tag}] {name}: done in {dt:.1f} s", flush=True)


@dataclasses.dataclass(frozen=True)
class Plan:
    out: Path
    scenes: tuple[str, ...]
    paddings_mm: tuple[int, ...]
    pairs: int

    def dataset(self, padding_mm: int) -> Path:
        return self.out / "dataset" / f"pad{padding_mm:02d}mm"

    def trajectories(self) -> list[dict]:
        """The planned trajectories: one dict (traj_id, padding_mm, scene, path) per file."""
        rows = []
        for p in self.paddings_mm:
            for s in self.scenes:
                for f in sorted((self.dataset(p) / "trajectories" / s).glob(f"{s}_p*_ompl_planned.yaml")):
                    rows.append(dict(traj_id=f"pad{p:02d}_{f.stem.removesuffix('_ompl_planned')}", padding_mm=p,
                                     scene=s, path=f))
        return rows


def _config(padding_mm: int) -> dict:
    from experiments import generate as gen

    config = gen.load_config(CONFIG_PATH)
    config["generation"] = dict(config["generation"], planning_padding_m=padding_mm / 1000.0)
    return config


# ----------------------------------------------------------------------------------------------
# Stage 1: generation
# ----------------------------------------------------------------------------------------------


def stage_generate(plan: Plan, workers: int, force: bool) -> None:
    from experiments import generate as gen

    for p in plan.paddings_mm:
        results = gen.generate_all(_config(p), plan.dataset(p), list(plan.scenes), plan.pairs, workers=workers,
                                   force=force)
        for r in results:
            if "error" in r:
                raise RuntimeError(f"padding {p} mm, scene {r['scene']}: {r['error']}\n{r.get('traceback', '')}")
            print(f"[tightness] generate: padding {p:2d} mm, {r['scene']}: {r['n_pairs_accepted']}/"
                  f"{r['n_pairs_requested']} pairs in {r['attempts']} attempts"
                  f"{' (done before)' if r.get('skipped') else ''}", flush=True)


# ----------------------------------------------------------------------------------------------
# Stage 2: mesh truth
# ----------------------------------------------------------------------------------------------


def _truth_key(path: Path, scene_file: Path) -> str:
    code = [ROOT / "experiments" / name for name in ("tightness.py", "mesh_truth.py", "collision.py")]
    return files_fingerprint([path, scene_file, *code], dict(hz=TRUTH_HZ, coarse=COARSE_HZ, hold=HOLD))[:20]


_WORKER: dict = {}


def _truth_job(job: dict) -> dict:
    from experiments.collision import SceneBoxes
    from experiments.mesh_truth import MeshTruth, TruthObstacles, mesh_truth
    from larc_jax.model.trajectory_files import read_trajectory

    if "truth" not in _WORKER:
        _WORKER["truth"] = MeshTruth()
    truth = _WORKER["truth"]
    t0 = time.perf_counter()
    boxes = TruthObstacles.from_boxes(SceneBoxes.from_file(job["scene_file"]))
    traj = read_trajectory(job["path"], truth.robot)
    row = mesh_truth(truth, traj, boxes)
    row.update(traj_id=job["traj_id"], padding_mm=job["padding_mm"], scene=job["scene"],
               duration_s=traj.duration, n_waypoints=traj.n_waypoints, key=job["key"],
               truth_time_s=round(time.perf_counter() - t0, 2))
    return row


def stage_truth(plan: Plan, workers: int) -> None:
    import pandas as pd

    from experiments import generate as gen

    config = gen.load_config(CONFIG_PATH)
    path = plan.out / "truth.csv"
    cached = {}
    if path.is_file():
        for r in pd.read_csv(path, keep_default_na=False).to_dict("records"):
            cached[r["traj_id"]] = r
    jobs, rows = [], {}
    for r in plan.trajectories():
        scene_file = ROOT / config["scenes"][r["scene"]]["file"]
        key = _truth_key(r["path"], scene_file)
        if r["traj_id"] in cached and cached[r["traj_id"]]["key"] == key:
            rows[r["traj_id"]] = cached[r["traj_id"]]
        else:
            jobs.append(dict(r, path=str(r["path"]), scene_file=str(scene_file), key=key))
    order = [r["traj_id"] for r in plan.trajectories()]

    def flush():
        write_frame(path, pd.DataFrame([rows[i] for i in order if i in rows], columns=TRUTH_FIELDS))

    print(f"[tightness] truth: {len(rows)} cached, {len(jobs)} to compute ({workers} workers)", flush=True)
    flush()
    if workers <= 1 or len(jobs) <= 1:
        results = map(_truth_job, jobs)
        pool = None
    else:
        pool = mp.get_context("spawn").Pool(workers)
        results = pool.imap_unordered(_truth_job, jobs)
    try:
        for k, row in enumerate(results, 1):
            rows[row["traj_id"]] = row
            flush()
            print(f"[tightness] truth {k}/{len(jobs)}: {row['traj_id']} {row['truth_m'] * 1000:+.2f} mm "
                  f"({row['truth_link']} / {row['truth_box']}, {row['truth_time_s']} s)", flush=True)
    finally:
        if pool is not None:
            pool.close()
            pool.join()


# ----------------------------------------------------------------------------------------------
# Stage 3: certification
# ----------------------------------------------------------------------------------------------


def _load_dataset(plan: Plan, robot):
    from experiments import generate as gen
    from larc_jax.model.scene import read_scene
    from larc_jax.model.trajectory_files import read_trajectory

    config = gen.load_config(CONFIG_PATH)
    scenes = {s: dataclasses.replace(read_scene(ROOT / config["scenes"][s]["file"]), name=s) for s in plan.scenes}
    rows = plan.trajectories()
    trajs = [dataclasses.replace(read_trajectory(r["path"], robot), id=r["traj_id"]) for r in rows]
    return rows, trajs, [scenes[r["scene"]] for r in rows]


def stage_certify(plan: Plan) -> None:
    import pandas as pd

    import larc_jax as lj
    from larc_jax.enclosure.robot_file import load_robot_file
    from larc_jax.engine.results import STAGES

    frames = []
    stageb = []
    for name, enclosure, stated, depth, padding, swept in CONFIGS:
        robot, capsules = load_robot_file(None, hold=HOLD if stated else None)
        rows, trajs, scenes = _load_dataset(plan, robot)
        spec = lj.RunSpec(method="larc", margin_m=MARGIN_M, max_depth=depth, enclosure=enclosure, padding_m=padding,
                          swept=swept)
        res = lj.certify(trajs, scenes, robot, capsules, spec=spec)
        df = res.to_dataframe()
        first = res.first_inconclusive_rows()
        lv = res.leaves
        worst = np.full(len(trajs), -1)
        order = np.argsort(np.where(np.isnan(lv.clearance_m), -np.inf, lv.clearance_m), kind="stable")
        for r in order[::-1]:
            worst[lv.traj[r]] = r  # ends on the smallest clearance of each trajectory
        caps = np.array(("",) + tuple(res.capsule_names), dtype=object)
        links = {n: l for n, l in zip(capsules.names, capsules.link_names)}
        frames.append(pd.DataFrame({
            "traj_id": df["id"], "config": name, "enclosure": enclosure, "gripper": "stated" if stated else "stroke",
            "max_depth": depth, "padding_m": res.padding_m, "certified": df["certified"], "evaluations": df["evaluations"],
            "min_clearance_m": df["min_clearance_m"],
            "worst_capsule": caps[np.where(worst >= 0, lv.capsule[worst] + 1, 0)],
            "worst_link": [links.get(c, "") for c in caps[np.where(worst >= 0, lv.capsule[worst] + 1, 0)]],
            "worst_stage": np.array(STAGES, dtype=object)[np.where(worst >= 0, lv.stage[worst], 0)],
            "swept": swept, "hull_leaves": np.bincount(lv.traj[lv.stage == 2], minlength=len(trajs)),
            "swept_leaves": np.bincount(lv.traj[lv.stage == 4], minlength=len(trajs)),
            "blocked_capsule": df["blocked_capsule"], "blocked_box": df["blocked_box"],
            "first_blocked_row": first,
        }))
        print(f"[tightness] certify {name}: {int(df['certified'].sum())}/{len(df)} certified, "
              f"{int(df['evaluations'].sum())} evaluations, {res.wall_time_s:.1f} s", flush=True)
        if name in STAGEB_CONFIGS:
            from experiments.bench import stageB_dataset

            b_trajs, b_scenes = stageB_dataset(robot)
            b = lj.certify(b_trajs, b_scenes, robot, capsules, spec=spec)
            fine = len(b_trajs) * 2**depth
            stageb.append(dict(config=name, trajectories=len(b_trajs), certified=int(b.certified.sum()),
                               evaluations=int(b.evaluations.sum()), fine_evaluations=fine,
                               larc_over_fine=round(int(b.evaluations.sum()) / fine, 4)))
            print(f"[tightness] Stage B {name}: {stageb[-1]}", flush=True)
    write_frame(plan.out / "certification.csv", pd.concat(frames, ignore_index=True).drop(columns="first_blocked_row"))
    write_frame(plan.out / "stageB.csv", pd.DataFrame(stageb))


# ----------------------------------------------------------------------------------------------
# Stage 4: tables and figure
# ----------------------------------------------------------------------------------------------


DEPTH9 = ("cascade_pad1_d9", "cascade_d9", "cascade_swept_d9")
"""The columns of goal.md's depth-9 table."""


def bin_labels() -> list[str]:
    out = []
    for lo, hi in zip(BINS_MM[:-1], BINS_MM[1:]):
        if lo == -math.inf:
            out.append(f"< {hi:g} mm (within rho: must be rejected)")
        elif hi == math.inf:
            out.append(f"> {lo:g} mm")
        else:
            out.append(f"{lo:g}-{hi:g} mm")
    return out


def stage_tables(plan: Plan) -> None:
    import pandas as pd

    from larc_jax.io import atomic_write_json, atomic_write_text

    truth = pd.read_csv(plan.out / "truth.csv")
    cert = pd.read_csv(plan.out / "certification.csv", keep_default_na=False)
    wide = cert.pivot(index="traj_id", columns="config", values="certified").astype(bool)
    df = truth.set_index("traj_id").join(wide, how="inner")
    df["truth_mm"] = df["truth_m"] * 1000
    labels = bin_labels()
    df["bin"] = pd.cut(df["truth_mm"], BINS_MM, labels=labels, right=False)
    names = [c[0] for c in CONFIGS]
    rows = []
    for label in labels:
        sub = df[df["bin"] == label]
        rows.append({"true mesh clearance": label, "n": len(sub), **{n: int(sub[n].sum()) for n in names}})
    table = pd.DataFrame(rows)
    write_frame(plan.out / "table.csv", table)
    head = "| true mesh clearance | n | " + " | ".join(LABELS[n] for n in names) + " |"
    lines = [head, "|" + "---|" * (2 + len(names))]
    for r in rows:
        lines.append(f"| {r['true mesh clearance']} | {r['n']} | " + " | ".join(str(r[n]) for n in names) + " |")
    evals = cert.pivot(index="traj_id", columns="config", values="evaluations").astype(int)
    ev = df[["bin"]].join(evals, how="inner")
    ev_lines = [head, lines[1]]
    for label in labels:
        sub = ev[ev["bin"] == label]
        ev_lines.append(f"| {label} | {len(sub)} | " + " | ".join(str(int(sub[n].sum())) for n in names) + " |")
    n_traj = len(df)
    md = [f"# Certified trajectories by true mesh clearance ({n_traj} planned trajectories)", "",
          f"rho = {MARGIN_M * 1000:g} mm. Truth: python-fcl, official meshes, fingers closed (joint7 = joint8 = 0), "
          f"{TRUTH_HZ:g} Hz + refinement. 'gripper' = the opening stated (hold joint7 = joint8 = 0); without it "
          "the finger enclosures cover the whole 38 mm stroke. 'cascade' = capsule test, then convex hulls. "
          "Padding on every enclosure beyond its proven containment of the meshes (RunSpec.padding_m): the "
          "enclosure's default (capsules 1 mm, cascade 0) unless the column says otherwise. "
          f"Planning paddings (mm): {', '.join(str(p) for p in plan.paddings_mm)}; scenes: {', '.join(plan.scenes)}.",
          "", *lines, "", "Interval evaluations by true mesh clearance (the sum over the bin's trajectories):", "",
          *ev_lines, ""]
    atomic_write_text(plan.out / "table.md", "\n".join(md))

    # The goal, measured.
    clear2 = df[df["truth_mm"] > MARGIN_M * 1000 + 2]
    near = df[(df["truth_mm"] > MARGIN_M * 1000 + 0.5) & (df["truth_mm"] <= MARGIN_M * 1000 + 2)]
    clear10 = df[df["truth_mm"] > MARGIN_M * 1000 + 10]
    within = df[df["truth_mm"] <= MARGIN_M * 1000]
    best = "cascade_d12"
    goal = {
        "trajectories": n_traj,
        "clear_by_2mm": len(clear2), "clear_by_2mm_certified": int(clear2[best].sum()),
        "clear_by_10mm": len(clear10), "clear_by_10mm_certified": int(clear10[best].sum()),
        "within_rho": len(within), "within_rho_certified_any_config": int(within[names].any(axis=1).sum()),
        "clear_by_0p5_to_2mm": len(near),
        "depth9": {n: dict(clear_by_2mm_certified=int(clear2[n].sum()), clear_by_0p5_to_2mm_certified=int(near[n].sum()))
                   for n in DEPTH9},
        "per_config": {n: dict(certified=int(df[n].sum()),
                               clear_by_2mm=int(clear2[n].sum()), clear_by_10mm=int(clear10[n].sum()),
                               within_rho=int(within[n].sum()),
                               evaluations=int(cert[cert["config"] == n]["evaluations"].sum()))
                       for n in names},
    }

    def pct(a, b):
        return f"{100.0 * a / b:.1f} %" if b else "n/a"

    stageb = pd.read_csv(plan.out / "stageB.csv")
    goal["stageB_larc_over_fine"] = {r["config"]: r["larc_over_fine"] for _, r in stageb.iterrows()}

    gl = ["# Goal (issue 12), cascade with the gripper stated, depth <= 12", "",
          "| requirement | target | measured |", "|---|---|---|",
          f"| certified, meshes clear rho by > 2 mm | >= 95 % | {goal['clear_by_2mm_certified']}/{goal['clear_by_2mm']} "
          f"= {pct(goal['clear_by_2mm_certified'], goal['clear_by_2mm'])} |",
          f"| certified, meshes clear rho by > 10 mm | >= 99 % | {goal['clear_by_10mm_certified']}/{goal['clear_by_10mm']} "
          f"= {pct(goal['clear_by_10mm_certified'], goal['clear_by_10mm'])} |",
          f"| certified, meshes within rho (any configuration) | 0 | {goal['within_rho_certified_any_config']} of "
          f"{goal['within_rho']} |", "",
          "**Depth 9 (issue 21), cascade with the gripper stated**", "",
          "| requirement | target | 1 mm padding | no padding (the cascade's default) | no padding + swept stage |",
          "|---|---|---|---|---|",
          "| certified, meshes clear rho by > 2 mm | >= 95 % | " + " | ".join(
              f"{goal['depth9'][n]['clear_by_2mm_certified']}/{goal['clear_by_2mm']} = "
              f"{pct(goal['depth9'][n]['clear_by_2mm_certified'], goal['clear_by_2mm'])}"
              for n in DEPTH9) + " |",
          "| certified, meshes clear rho by 0.5-2 mm | >= 80 % | " + " | ".join(
              f"{goal['depth9'][n]['clear_by_0p5_to_2mm_certified']}/{goal['clear_by_0p5_to_2mm']} = "
              f"{pct(goal['depth9'][n]['clear_by_0p5_to_2mm_certified'], goal['clear_by_0p5_to_2mm'])}"
              for n in DEPTH9) + " |", "",
          "Interval evaluations per configuration (whole dataset): "
          + ", ".join(f"{n} {goal['per_config'][n]['evaluations']}" for n in names) + ".", "",
          "Stage B (160 trajectories, depth 9), interval evaluations LARC / fixed-fine: "
          + ", ".join(f"{n} {goal['stageB_larc_over_fine'][n]:.3f}" for n in STAGEB_CONFIGS) + ".", ""]
    atomic_write_text(plan.out / "goal.md", "\n".join(gl))

    # What blocks the cascade at depth 12 on trajectories that really clear rho.
    c12 = cert[cert["config"] == best].set_index("traj_id")
    blocked = df[(df["truth_mm"] > MARGIN_M * 1000) & ~df[best]].join(c12[["worst_link", "min_clearance_m"]])
    bl = ["# Not certified by the cascade at depth 12 although the meshes clear rho", "",
          "| trajectory | true clearance - rho (mm) | worst leaf clearance g (mm) | link at the worst leaf |",
          "|---|---|---|---|"]
    for tid, r in blocked.sort_values("truth_mm").iterrows():
        bl.append(f"| {tid} | {r['truth_mm'] - MARGIN_M * 1000:+.2f} | {r['min_clearance_m'] * 1000:+.2f} | "
                  f"{r['worst_link']} |")
    atomic_write_text(plan.out / "blocking.md", "\n".join(bl + [""]))
    atomic_write_json(plan.out / "summary.json", goal)
    _figure(df, names, plan.out / "certified_vs_clearance.png")


def _figure(df, names, path: Path) -> None:
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from larc_jax.io import atomic_write_bytes

    edges = np.array([-1e9, 10, 12, 14, 16, 18, 20, 25, 30, 40, 50, 1e9])
    centres = np.array([8, 11, 13, 15, 17, 19, 22.5, 27.5, 35, 45, 55])
    fig, ax = plt.subplots(figsize=(7.5, 4.2), dpi=130)
    styles = {"capsules_d9": ("C0", "--"), "capsules_d12": ("C0", "-"), "capsules_stated_d9": ("C1", "--"),
              "capsules_stated_d12": ("C1", "-"), "cascade_pad1_d9": ("C3", "--"), "cascade_pad1_d12": ("C3", "-"),
              "cascade_d6": ("C2", ":"), "cascade_d9": ("C2", "--"), "cascade_d12": ("C2", "-")}
    idx = np.digitize(df["truth_mm"].to_numpy(), edges) - 1
    counts = np.bincount(idx, minlength=len(centres))[: len(centres)]
    for n in names:
        frac = np.array([df[n].to_numpy()[idx == k].mean() if counts[k] else np.nan for k in range(len(centres))])
        c, ls = styles.get(n, ("k", "-"))
        ax.plot(centres, frac, color=c, ls=ls, marker="o", ms=3, label=n.replace("_", " "))
    ax.axvline(MARGIN_M * 1000, color="r", lw=0.8)
    ax.text(MARGIN_M * 1000 + 0.3, 0.02, "rho", color="r")
    for k, n in enumerate(counts):
        ax.text(centres[k], 1.03, str(n), ha="center", fontsize=7, color="0.4")
    ax.set_xlabel("true mesh clearance over the trajectory (mm; last bin > 50)")
    ax.set_ylabel("fraction certified")
    ax.set_ylim(-0.02, 1.08)
    ax.set_title("Certified fraction vs true clearance (numbers: trajectories per bin)", fontsize=9)
    ax.legend(fontsize=7, loc="center right")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


# ----------------------------------------------------------------------------------------------
# Driver
# ----------------------------------------------------------------------------------------------


def driver_args(argv, description: str, name: str, quick_help: str):
    """``(args, out)`` of a tightness driver's command line: ``--out`` (default
    ``results/<name>``, or ``results/<name>_quick`` with ``--quick``), ``--force``, ``--workers``."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--out", default=None, help=f"output folder (default results/{name}, or "
                    f"results/{name}_quick with --quick)")
    ap.add_argument("--quick", action="store_true", help=quick_help)
    ap.add_argument("--force", action="store_true", help="rerun every stage")
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args(argv)
    return args, Path(args.out) if args.out else ROOT / "results" / (f"{name}_quick" if args.quick else name)


def main(argv=None) -> int:
    args, out = driver_args(argv, __doc__.splitlines()[0], "tightness", "one scene, one padding, 2 pairs")
    plan = Plan(out=out, scenes=SCENES[:1] if args.quick else SCENES,
                paddings_mm=(0,) if args.quick else PADDINGS_MM, pairs=2 if args.quick else PAIRS)
    lib = sorted((ROOT / "larc_jax").rglob("*.py")) + [ROOT / "larc_jax" / "data" / "piper_capsules.yaml"]
    me = [ROOT / "experiments" / "tightness.py"]
    params = dict(scenes=plan.scenes, paddings=plan.paddings_mm, pairs=plan.pairs)
    t0 = time.perf_counter()
    gen_files = [ROOT / "experiments" / "generate.py", CONFIG_PATH]
    run_stage(out, "generate", files_fingerprint(gen_files, params), [plan.dataset(p) for p in plan.paddings_mm],
           lambda: stage_generate(plan, args.workers, args.force), args.force)
    data = [r["path"] for r in plan.trajectories()]
    truth_code = [ROOT / "experiments" / "collision.py", ROOT / "experiments" / "mesh_truth.py"]
    run_stage(out, "truth", files_fingerprint(data + me + truth_code, params),
           [out / "truth.csv"], lambda: stage_truth(plan, args.workers), args.force)
    stageb_data = sorted((ROOT / "results" / "stageB" / "dataset" / "trajectories").rglob("*.yaml"))
    run_stage(out, "certify", files_fingerprint(data + stageb_data + lib + me, dict(params, configs=CONFIGS)),
           [out / "certification.csv", out / "stageB.csv"], lambda: stage_certify(plan), args.force)
    run_stage(out, "tables", files_fingerprint([out / "truth.csv", out / "certification.csv", out / "stageB.csv"] + me,
                                       params),
           [out / "table.md", out / "certified_vs_clearance.png"], lambda: stage_tables(plan), args.force)
    print(f"[tightness] all stages in {time.perf_counter() - t0:.1f} s; results in {out}", flush=True)
    print((out / "table.md").read_text(), flush=True)
    print((out / "goal.md").read_text(), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
