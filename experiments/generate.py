"""Stage B trajectory generation: OMPL RRTConnect paths, TOPP-RA timing, MoveIt-style records.

For each scene (``configs/stageB.yaml``), attempt ``k`` is a pure function of the scene's
generation seed and ``k`` (``numpy.random.default_rng([seed, k])``; OMPL's RNG is reseeded from it
and the planner budget is a *count* of validity checks, so the result does not depend on the
machine's speed or load: there is no wall-clock limit, and the outputs hold no wall times, so
generating twice writes the same bytes). An attempt:

1. **Endpoints.** Draws the OMPL seed and a coin (swap start/goal), then two configurations
   uniformly within the MoveIt joint limits (``moveit_joint_limits.yaml``, narrower than the
   URDF's). Each endpoint is redrawn until its *gripper-base point* (the origin of ``link7``,
   i.e. the joint7 origin on the gripper axis) lies in the endpoint's region of the scene's
   ``endpoints`` spec and the two points are at least ``min_point_distance_m`` apart. These are
   purely kinematic conditions (no collision check), which make start and goal meaningfully
   different: window scenes put one gripper point in front of the wall and the other behind it
   (the arm must pass through the opening), the shelf puts one inside the shelf's compartments
   and the other outside, the open scene only asks for distance. With probability 1/2 the two
   are swapped, so both directions occur.
2. **Validity** (FCL on the official meshes, scene boxes + self-collision minus the allowed
   pairs of ``configs/piper_allowed_collisions.yaml``): failure → ``invalid_start`` /
   ``invalid_goal``.
3. **Planning.** OMPL ``RRTConnect`` in a 6-D ``RealVectorStateSpace`` with the MoveIt bounds,
   the same FCL validity checker, state-validity resolution ``state_validity_resolution`` (a
   fraction of the space's extent, MoveIt's ``longest_valid_segment_fraction``), then
   ``PathSimplifier.simplifyMax`` and MoveIt's post-interpolation (``interpolate`` to
   ``max(minimum_waypoint_count, round(length / (extent / 100)))`` states). No exact solution
   within ``planner_max_validity_checks`` validity checks (an OMPL
   ``PlannerTerminationCondition`` on that count: the only planner limit), or a failed time
   parameterisation → ``planning_failure``.
4. **Timing.** TOPP-RA (``toppra`` 0.6): cubic ``SplineInterpolator`` through the path states
   over their cumulative joint-space arc length, joint velocity and acceleration limits from
   the yaml times the 0.1 scaling factors, ``ParametrizeConstAccel``, zero end velocities.
5. **Record** (as MoveIt's controller would receive it): waypoints at the times TOPP-RA assigns
   to the path states (the validated states, exactly on the spline) plus a uniform
   ``record_dt_s`` grid (MoveIt's TOTG resample period, 0.1 s), grid points closer than
   ``record_min_gap_s`` to a path-state time dropped, with positions AND velocities from the
   TOPP-RA trajectory, times rounded to 1 ns as in the message. Positions are clipped into the
   MoveIt limits (the cubic may overshoot by micro-radians near a bound).
6. **Recheck.** The recorded waypoints are reconstructed by piecewise-cubic Hermite
   interpolation (``scipy.interpolate.CubicHermiteSpline``) and every state of a
   ``recheck_hz`` grid (plus the end) is checked with FCL: any collision →
   ``hermite_recheck_failure``; else ``accepted``.

Each accepted pair is written as ``<scene>_p<NN>_ompl_planned.yaml`` and a
``<scene>_p<NN>_direct_smoothstep.yaml`` control: same endpoints and duration ``T``,
``q(t) = q0 + (q1 - q0) s(t/T)``, ``s(u) = 3u^2 - 2u^3``, recorded at the same number of uniformly
spaced waypoints with exact velocities (not checked: it may collide).

Outputs under ``out_dir``: ``trajectories/<scene>/*.yaml``, ``generation/<scene>_attempts.csv`` and
the done-marker ``generation/<scene>.done.json`` (both atomic, written when the scene ends: a
killed run loses no finished scene, and a rerun skips scenes whose marker matches the current
inputs: :func:`scene_fingerprint`, which covers the protocol, the scene file, the allowed pairs,
the URDF and its meshes, and the generator's code), and ``attempts.csv`` (all scenes, rewritten
atomically whenever a scene finishes).

CLI: ``python -m experiments.generate [--quick] [--scenes ...] [--out DIR] [--workers 2]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
import multiprocessing as mp
import time
from pathlib import Path
from typing import Sequence

import numpy as np
import yaml

from experiments.common import CONFIG_PATH, OUTCOMES, ROOT, csv_text, load_config, read_csv, resolve
from experiments.planning import hermite_states, plan_path, record, smoothstep_trajectory, time_parameterise

CODE = ("experiments.generate",)
"""Modules whose import closure is the generator's code (part of every scene's fingerprint)."""
CSV_FIELDS = [
    "scene", "attempt", "seed", "ompl_seed", "outcome", "detail", "pair", "duration_s",
    "n_waypoints", "planner_checks", "path_states", "path_length_rad",
    "recheck_states", "max_clip_rad", "start", "goal",
]

__all__ = [
    "SceneContext",
    "attempt_endpoints",
    "moveit_limits",
    "generate_scene",
    "generate_all",
    "scene_fingerprint",
    "scene_is_done",
    "smoothstep_trajectory",
    "hermite_states",
    "main",
]


# ----------------------------------------------------------------------------------------------
# Configuration
# ----------------------------------------------------------------------------------------------


def moveit_limits(robot, path: str | Path | None = None) -> dict:
    """MoveIt joint limits for the robot's active joints: lo, hi, vmax, amax (n,) and scalings."""
    from larc_jax.model.urdf import piper_description_dir

    path = Path(path) if path is not None else piper_description_dir() / "config" / "moveit_joint_limits.yaml"
    doc = yaml.safe_load(path.read_text())
    lim = doc["joint_limits"]
    names = robot.active_joint_names
    return {
        "path": str(path),
        "lo": np.array([float(lim[j]["min_position"]) for j in names]),
        "hi": np.array([float(lim[j]["max_position"]) for j in names]),
        "vmax": np.array([float(lim[j]["max_velocity"]) for j in names]),
        "amax": np.array([float(lim[j]["max_acceleration"]) for j in names]),
        "velocity_scaling": float(doc.get("default_velocity_scaling_factor", 0.1)),
        "acceleration_scaling": float(doc.get("default_acceleration_scaling_factor", 0.1)),
    }


def _region(spec) -> tuple[np.ndarray, np.ndarray]:
    lo = np.full(3, -np.inf)
    hi = np.full(3, np.inf)
    if spec:
        for i, v in enumerate(spec.get("min") or [None] * 3):
            if v is not None:
                lo[i] = float(v)
        for i, v in enumerate(spec.get("max") or [None] * 3):
            if v is not None:
                hi[i] = float(v)
    return lo, hi


# ----------------------------------------------------------------------------------------------
# Per-process context
# ----------------------------------------------------------------------------------------------


class SceneContext:
    """Everything an attempt needs, built once per process and scene."""

    def __init__(self, scene_name: str, config: dict):
        from experiments.collision import CollisionModel, SceneBoxes
        from experiments.self_collision import load_allowed_pairs

        self.scene_name = scene_name
        self.config = config
        self.scene_cfg = config["scenes"][scene_name]
        self.model = CollisionModel()
        self.robot = self.model.robot
        self.allowed = load_allowed_pairs(resolve(config["allowed_collisions"]), self.robot)
        scene_path = resolve(self.scene_cfg["file"])
        self.scene_path = scene_path
        scene = SceneBoxes.from_file(scene_path, frame=self.robot.link_names[0])
        # MoveIt-style world padding: the planner, the endpoint checks and the recheck see every
        # box grown by this much on each side (the audit sees the true boxes).
        pad = float(config["generation"].get("planning_padding_m", 0.0))
        if not (math.isfinite(pad) and pad >= 0.0):
            raise ValueError(f"generation.planning_padding_m must be a finite number >= 0, got {pad!r}")
        self.padding = pad
        self.boxes = SceneBoxes(scene.lo - pad, scene.hi + pad, scene.names)
        self.limits = moveit_limits(self.robot, config.get("joint_limits_file"))
        gen = config["generation"]
        self.gen = gen
        vs = float(config.get("velocity_scaling", self.limits["velocity_scaling"]))
        acs = float(config.get("acceleration_scaling", self.limits["acceleration_scaling"]))
        self.vlim = self.limits["vmax"] * vs
        self.alim = self.limits["amax"] * acs
        ep = self.scene_cfg.get("endpoints") or {}
        self.region_a = _region(ep.get("a"))
        self.region_b = _region(ep.get("b"))
        self.min_dist = float(ep.get("min_point_distance_m", 0.0))
        self.swap_p = float(ep.get("swap_probability", 0.5))
        self.point_link = self.robot.link_index(gen.get("endpoint_point_link", "link7"))
        self.extent = float(np.linalg.norm(self.limits["hi"] - self.limits["lo"]))

    def valid(self, q) -> bool:
        return self.model.state_valid(q, self.boxes, self.allowed)

    def point(self, q) -> np.ndarray:
        from larc_jax.model.robot import forward_kinematics_np

        return forward_kinematics_np(self.robot, q)[self.point_link][:3, 3]


def _sample_endpoint(ctx: SceneContext, rng, region, other_point=None, max_draws: int = 200_000):
    lo, hi = ctx.limits["lo"], ctx.limits["hi"]
    for _ in range(max_draws):
        q = rng.uniform(lo, hi)
        p = ctx.point(q)
        if (p < region[0]).any() or (p > region[1]).any():
            continue
        if other_point is not None and np.linalg.norm(p - other_point) < ctx.min_dist:
            continue
        return q, p
    raise RuntimeError(f"scene {ctx.scene_name}: no configuration within {max_draws} draws puts the "
                       f"gripper point in region {region}; fix the endpoints spec")


def attempt_endpoints(ctx: SceneContext, seed: int, attempt: int):
    """(start, goal, ompl_seed) of an attempt: a pure function of (seed, attempt)."""
    rng = np.random.default_rng([int(seed), int(attempt)])
    ompl_seed = int(rng.integers(1, 2**31 - 1))
    swap = bool(rng.random() < ctx.swap_p)
    qa, pa = _sample_endpoint(ctx, rng, ctx.region_a)
    qb, _ = _sample_endpoint(ctx, rng, ctx.region_b, other_point=pa)
    return (qb, qa, ompl_seed) if swap else (qa, qb, ompl_seed)


def run_attempt(ctx: SceneContext, seed: int, attempt: int):
    """One generation attempt → (CSV row, (planned, start, goal) or None)."""
    from larc_jax.model.trajectory import Trajectory

    start, goal, ompl_seed = attempt_endpoints(ctx, seed, attempt)
    row = {k: "" for k in CSV_FIELDS}
    row.update(scene=ctx.scene_name, attempt=attempt, seed=seed, ompl_seed=ompl_seed,
               start=" ".join(repr(float(x)) for x in start),
               goal=" ".join(repr(float(x)) for x in goal))

    def done(outcome, detail="", result=None):
        row["outcome"] = outcome
        row["detail"] = detail
        return row, result

    if not ctx.valid(start):
        return done("invalid_start", _contact_detail(ctx, start))
    if not ctx.valid(goal):
        return done("invalid_goal", _contact_detail(ctx, goal))
    states, info = plan_path(ctx, start, goal, ompl_seed)
    row["planner_checks"] = info["planner_checks"]
    if states is None:
        return done("planning_failure", info.get("detail", ""))
    row["path_length_rad"] = round(info["path_length_rad"], 6)
    jnt, t_states, states = time_parameterise(ctx, states)
    row["path_states"] = len(states)
    if jnt is None:
        return done("planning_failure", "toppra_failed")
    t, q, qd, max_clip = record(ctx, jnt, t_states, states)
    row["max_clip_rad"] = f"{max_clip:.3g}"
    row["duration_s"] = round(float(t[-1]), 9)
    row["n_waypoints"] = len(t)
    _, Q = hermite_states(t, q, qd, float(ctx.config["recheck_hz"]))
    row["recheck_states"] = len(Q)
    for k, qk in enumerate(Q):
        if not ctx.valid(qk):
            return done("hermite_recheck_failure",
                        f"state {k} t={k / float(ctx.config['recheck_hz']):.2f}s "
                        + _contact_detail(ctx, qk))
    traj = Trajectory(t=t, q=q, qd=qd, joint_names=tuple(ctx.robot.active_joint_names),
                      source="ompl_planned")
    return done("accepted", "", (traj, start, goal))


def _contact_detail(ctx: SceneContext, q) -> str:
    hits = ctx.model.scene_contacts(q, ctx.boxes) if len(ctx.boxes) else []
    selfh = ctx.model.self_contacts(q, ctx.allowed)
    parts = [f"{a}~{b}" for a, b in hits[:3]] + [f"{a}~{b}" for a, b in selfh[:3]]
    return "contact " + ",".join(parts) if parts else ""


# ----------------------------------------------------------------------------------------------
# Scenes
# ----------------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=1)
def _robot_geometry() -> tuple[Path, ...]:
    from experiments.collision import geometry_files
    from larc_jax.model.urdf import load_robot

    return tuple(geometry_files(load_robot()))


def scene_fingerprint(scene_name: str, config: dict, n_pairs: int, max_attempts: int) -> str:
    """Hash of every input that determines a scene's output (resume check): the protocol values
    the generator reads, the scene file, the allowed pairs, the URDF and its collision meshes,
    and the generator's code (:mod:`experiments.fingerprints`)."""
    from experiments.fingerprints import fingerprint

    sc = config["scenes"][scene_name]
    params = {
        "scene_cfg": sc,
        "generation": config["generation"],
        "recheck_hz": config["recheck_hz"],
        "scaling": [config.get("velocity_scaling"), config.get("acceleration_scaling")],
        "joint_limits_file": config.get("joint_limits_file"),
        "n_pairs": n_pairs,
        "max_attempts": max_attempts,
    }
    files = [resolve(sc["file"]), resolve(config["allowed_collisions"]), *_robot_geometry()]
    return fingerprint(files, params, code=CODE)


def _done_marker(out_dir: Path, scene: str) -> Path:
    return out_dir / "generation" / f"{scene}.done.json"


def _scene_csv(out_dir: Path, scene: str) -> Path:
    return out_dir / "generation" / f"{scene}_attempts.csv"


def scene_is_done(out_dir: Path, scene: str, fingerprint: str) -> bool:
    marker = _done_marker(out_dir, scene)
    if not marker.is_file() or not _scene_csv(out_dir, scene).is_file():
        return False
    try:
        doc = json.loads(marker.read_text())
    except (OSError, json.JSONDecodeError):
        return False
    return doc.get("fingerprint") == fingerprint


def generate_scene(
    scene_name: str,
    config: dict | str | Path = CONFIG_PATH,
    out_dir: str | Path = ROOT / "results" / "stageB" / "dataset",
    n_pairs: int | None = None,
    *,
    max_attempts: int | None = None,
    force: bool = False,
    progress: bool = True,
    position: int = 0,
) -> dict:
    """Generate one scene's pairs (see module docstring). Returns the scene summary (also
    written as the done-marker). Skips the work if a matching done-marker exists."""
    from larc_jax.io import atomic_write_json, atomic_write_text
    from larc_jax.model.trajectory_files import write_trajectory

    if not isinstance(config, dict):
        config = load_config(config)
    out_dir = Path(out_dir)
    sc = config["scenes"][scene_name]
    n_pairs = int(n_pairs if n_pairs is not None else config["pairs_per_scene"])
    max_attempts = int(max_attempts if max_attempts is not None else sc.get(
        "max_attempts", config["generation"]["max_attempts_per_scene"]))
    fp = scene_fingerprint(scene_name, config, n_pairs, max_attempts)
    if not force and scene_is_done(out_dir, scene_name, fp):
        doc = json.loads(_done_marker(out_dir, scene_name).read_text())
        doc["skipped"] = True
        return doc

    t_start = time.perf_counter()
    ctx = SceneContext(scene_name, config)
    seed = int(sc["seed"])
    traj_dir = out_dir / "trajectories" / scene_name
    traj_dir.mkdir(parents=True, exist_ok=True)
    marker = _done_marker(out_dir, scene_name)
    if marker.exists():
        marker.unlink()
    for old in traj_dir.glob(f"{scene_name}_p*_*.yaml"):  # stale files of an earlier run
        old.unlink()

    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=n_pairs, desc=f"{scene_name:>13}", unit="pair", position=position,
                   leave=True, dynamic_ncols=True)
    rows, accepted = [], 0
    attempt = 0
    while accepted < n_pairs and attempt < max_attempts:
        row, result = run_attempt(ctx, seed, attempt)
        if result is not None:
            traj, start, goal = result
            pid = f"{scene_name}_p{accepted:02d}"
            planned_id = f"{pid}_ompl_planned"
            traj = dataclasses.replace(traj, id=planned_id)
            write_trajectory(traj_dir / f"{planned_id}.yaml", traj)
            direct = smoothstep_trajectory(start, goal, float(traj.t[-1]), traj.n_waypoints,
                                           traj.joint_names, f"{pid}_direct_smoothstep")
            write_trajectory(traj_dir / f"{pid}_direct_smoothstep.yaml", direct)
            row["pair"] = pid
            accepted += 1
            if bar is not None:
                bar.update(1)
        rows.append(row)
        attempt += 1
        if bar is not None:
            bar.set_postfix_str(f"attempts {attempt}", refresh=True)
    if bar is not None:
        bar.close()

    counts = {o: sum(r["outcome"] == o for r in rows) for o in OUTCOMES}
    summary = {
        "scene": scene_name,
        "seed": seed,
        "n_pairs_requested": n_pairs,
        "n_pairs_accepted": accepted,
        "attempts": len(rows),
        "max_attempts": max_attempts,
        "attempt_cap_reached": accepted < n_pairs,
        "outcomes": counts,
        "fingerprint": fp,
        "trajectories": sorted(p.name for p in traj_dir.glob(f"{scene_name}_p*_*.yaml")),
    }
    atomic_write_text(_scene_csv(out_dir, scene_name), csv_text(rows, CSV_FIELDS))
    atomic_write_json(marker, summary)  # no wall time in it: the marker is reproducible too
    return dict(summary, elapsed_s=round(time.perf_counter() - t_start, 2))


def write_combined_attempts(out_dir: str | Path, scenes: Sequence[str]) -> Path:
    """Concatenate the attempt CSVs of the finished scenes (those with a done-marker) into
    ``out_dir/attempts.csv`` (atomic), in the order of ``scenes``."""
    from larc_jax.io import atomic_write_text

    out_dir = Path(out_dir)
    rows = []
    for s in scenes:
        p = _scene_csv(out_dir, s)
        if _done_marker(out_dir, s).is_file():  # finished scenes only
            rows.extend(read_csv(p))
    path = out_dir / "attempts.csv"
    atomic_write_text(path, csv_text(rows, CSV_FIELDS))
    return path


def _scene_job(args):
    scene, config, out_dir, n_pairs, max_attempts, force, position = args
    try:
        return generate_scene(scene, config, out_dir, n_pairs, max_attempts=max_attempts,
                              force=force, position=position)
    except Exception as exc:  # noqa: BLE001 - report, let the other scenes finish
        import traceback

        return {"scene": scene, "error": f"{type(exc).__name__}: {exc}",
                "traceback": traceback.format_exc()}


def generate_all(config: dict, out_dir: str | Path, scenes: Sequence[str], n_pairs: int | None,
                 *, workers: int = 2, max_attempts: int | None = None, force: bool = False) -> list[dict]:
    """Run scenes in ``workers`` processes (each builds its own FCL model)."""
    out_dir = Path(out_dir)
    all_scenes = list(config["scenes"])  # attempts.csv lists every finished scene in out_dir
    order = sorted(scenes, key=lambda s: -float(config["scenes"][s].get("cost_hint", 1.0)))
    jobs = [(s, config, str(out_dir), n_pairs, max_attempts, force, k) for k, s in enumerate(order)]
    results = []
    if workers <= 1 or len(jobs) == 1:
        for j in jobs:
            results.append(_scene_job(j))
            write_combined_attempts(out_dir, all_scenes)
    else:
        ctx = mp.get_context("spawn")
        with ctx.Pool(min(workers, len(jobs)), maxtasksperchild=1) as pool:
            for res in pool.imap_unordered(_scene_job, jobs):
                results.append(res)
                write_combined_attempts(out_dir, all_scenes)
    write_combined_attempts(out_dir, all_scenes)
    return sorted(results, key=lambda r: list(scenes).index(r["scene"]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="Stage B trajectory generation (OMPL + TOPP-RA + FCL)")
    ap.add_argument("--config", default=str(CONFIG_PATH))
    ap.add_argument("--out", default=None, help="output folder (default results/stageB/dataset, "
                    "or results/stageB_quick/dataset with --quick: where python -m experiments.stageB reads it)")
    ap.add_argument("--scenes", nargs="+", default=None)
    ap.add_argument("--quick", action="store_true", help="2 pairs per scene")
    ap.add_argument("--pairs", type=int, default=None, help="pairs per scene (overrides config)")
    ap.add_argument("--max-attempts", type=int, default=None)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--force", action="store_true", help="regenerate finished scenes too")
    args = ap.parse_args(argv)
    config = load_config(args.config)
    scenes = args.scenes or list(config["scenes"])
    for s in scenes:
        if s not in config["scenes"]:
            ap.error(f"unknown scene '{s}' (config has {list(config['scenes'])})")
    n_pairs = args.pairs if args.pairs is not None else (
        int(config.get("quick_pairs_per_scene", 2)) if args.quick else None)
    out = Path(args.out) if args.out else ROOT / "results" / ("stageB_quick" if args.quick else "stageB") / "dataset"
    t0 = time.perf_counter()
    results = generate_all(config, out, scenes, n_pairs, workers=args.workers,
                           max_attempts=args.max_attempts, force=args.force)
    failed = False
    for r in results:
        if "error" in r:
            failed = True
            print(f"{r['scene']}: ERROR {r['error']}\n{r['traceback']}")
            continue
        print(f"{r['scene']}: {r['n_pairs_accepted']}/{r['n_pairs_requested']} pairs in "
              f"{r['attempts']} attempts {r['outcomes']} ({r.get('elapsed_s', 0)} s"
              f"{', skipped: already done' if r.get('skipped') else ''})")
    print(f"attempts: {out / 'attempts.csv'}; total {time.perf_counter() - t0:.1f} s")
    return 1 if failed or any(r.get("attempt_cap_reached") for r in results) else 0


if __name__ == "__main__":
    raise SystemExit(main())
