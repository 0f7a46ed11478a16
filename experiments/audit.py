"""Sampled MoveIt/FCL-style audit of recorded trajectories on the official collision meshes.

A trajectory's recorded waypoints are reconstructed by piecewise-cubic Hermite interpolation
(``scipy.interpolate.CubicHermiteSpline`` of positions and velocities, as a controller replays
them) and checked with FCL (:mod:`experiments.collision`) at every ``1/hz`` s from the first
waypoint (250 Hz in the protocol), at the last time, and at every original waypoint (exact
recorded positions). Scene collision (any link mesh intersecting any box) and self-collision
(any link pair not in the allowed pairs) are reported separately. A trajectory is
*sampled-clear* when no scene collision is detected at those states; this cannot exclude
collisions between audit states.

Stage B's audit stage is :func:`audit_stage` (one row per trajectory in ``audit/audit.csv``,
columns :data:`experiments.common.AUDIT_FIELDS`, rewritten atomically after every finished
trajectory; a row is reused while its key — a hash of the trajectory file, the scene file, the
allowed pairs, the audit rate and the audit code — still matches). The table holds no wall
times, so auditing the same inputs twice writes the same bytes.

``python -m experiments.audit --trajectories DIR [--out audit.csv]`` audits every
``<scene>/*.yaml`` under DIR (the scene is the folder name, its file from the protocol) with 2
worker processes, into a table of the same schema.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import time
from pathlib import Path
from typing import Callable, Iterable, Sequence

import numpy as np

from experiments.common import AUDIT_FIELDS, CONFIG_PATH, TRAJ_RE, load_config, read_csv, resolve, scene_paths, \
    write_csv

__all__ = ["audit_times", "audit_trajectory", "audit_stage", "audit_dataset", "dataset_items", "init_worker",
           "audit_file_in_worker", "audit_key", "audit_inputs", "CODE", "main"]

CODE = ("experiments.audit",)
"""Modules whose import closure is the audit's code (part of every row's key)."""


def audit_times(t: np.ndarray, hz: float) -> np.ndarray:
    """Audit times: the ``hz`` grid from t[0], the last time, and every waypoint time."""
    t = np.asarray(t, dtype=np.float64)
    n = int(np.floor((t[-1] - t[0]) * hz + 1e-9))
    grid = t[0] + np.arange(n + 1) / float(hz)
    grid = grid[grid <= t[-1]]
    return np.union1d(grid, t)


def audit_trajectory(traj, boxes, collision_model, hz: float = 250.0, allowed_pairs=()) -> dict:
    """Audit one trajectory (a :class:`larc_jax.model.trajectory.Trajectory` in the robot's joint
    order) against ``boxes`` (anything :func:`experiments.collision.scene_boxes` accepts).

    Returns the audit columns of :data:`~experiments.common.AUDIT_FIELDS` (without ``traj_id``,
    ``scene``, ``key``): ``audit_states``, ``audit_collision`` (scene, bool),
    ``audit_collision_states``, ``first_collision_t`` (s from t[0], or None), ``collision_contacts``
    (first ``link~box``), and the same for self-collision.
    """
    from scipy.interpolate import CubicHermiteSpline

    from experiments.collision import normalise_pairs, scene_boxes

    boxes = scene_boxes(boxes)
    allowed = allowed_pairs if isinstance(allowed_pairs, frozenset) else normalise_pairs(allowed_pairs or ())
    t = np.asarray(traj.t, dtype=np.float64)
    ts = audit_times(t, hz)
    Q = CubicHermiteSpline(t, traj.q, traj.qd, axis=0)(ts)
    Q[np.searchsorted(ts, t)] = traj.q  # exact recorded positions at the waypoints
    scene_hit = np.zeros(len(ts), dtype=bool)
    self_hit = np.zeros(len(ts), dtype=bool)
    first_contact = first_self = ""
    m = collision_model
    for k, q in enumerate(Q):
        m.set_configuration(q)
        if len(boxes):
            hits = m.scene_hits(boxes)
            if hits:
                scene_hit[k] = True
                first_contact = first_contact or f"{hits[0][0]}~{hits[0][1]}"
        sh = m.self_hits(allowed)
        if sh:
            self_hit[k] = True
            first_self = first_self or f"{sh[0][0]}~{sh[0][1]}"
    return {
        "audit_states": int(len(ts)),
        "audit_collision": bool(scene_hit.any()),
        "audit_collision_states": int(scene_hit.sum()),
        "first_collision_t": float(ts[np.argmax(scene_hit)] - t[0]) if scene_hit.any() else None,
        "collision_contacts": first_contact,
        "self_collision": bool(self_hit.any()),
        "self_collision_states": int(self_hit.sum()),
        "first_self_collision_t": float(ts[np.argmax(self_hit)] - t[0]) if self_hit.any() else None,
        "self_contacts": first_self,
    }


# ----------------------------------------------------------------------------------------------
# Worker processes (the FCL model is built once per process; FCL objects cannot be pickled)
# ----------------------------------------------------------------------------------------------


_W: dict = {}


def init_worker(allowed_path: str, hz: float):
    """Set up an audit process: the FCL model, the allowed pairs, the rate."""
    from experiments.collision import CollisionModel
    from experiments.self_collision import load_allowed_pairs

    _W["model"] = CollisionModel()
    _W["allowed"] = load_allowed_pairs(allowed_path, _W["model"].robot)
    _W["hz"] = hz
    _W["boxes"] = {}


def audit_file_in_worker(path: str, scene_file: str) -> dict:
    """Audit one trajectory file in a process set up by :func:`init_worker` (scene boxes are
    cached per scene file)."""
    from experiments.collision import SceneBoxes
    from larc_jax.model.trajectory_files import read_trajectory

    model = _W["model"]
    boxes = _W["boxes"].get(scene_file)
    if boxes is None:
        boxes = _W["boxes"][scene_file] = SceneBoxes.from_file(scene_file, frame=model.robot.link_names[0])
    traj = read_trajectory(path, model.robot)
    return audit_trajectory(traj, boxes, model, _W["hz"], _W["allowed"])


def _audit_job(job: dict) -> dict:
    """One row of :data:`AUDIT_FIELDS` for a job {traj_id, scene, path, scene_path, key}."""
    row = dict(traj_id=job["traj_id"], scene=job["scene"], key=job.get("key", ""))
    row.update(audit_file_in_worker(job["path"], job["scene_path"]))
    return row


def _run_jobs(jobs: Sequence[dict], allowed_path: str, hz: float, workers: int,
              on_row: Callable[[dict], None], progress: bool = True) -> None:
    """Audit ``jobs`` in ``workers`` processes, calling ``on_row`` with each finished row."""
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(jobs), desc="audit", unit="traj", dynamic_ncols=True)
    if workers > 1 and len(jobs) > 1:
        with mp.get_context("spawn").Pool(workers, initializer=init_worker, initargs=(allowed_path, hz)) as pool:
            for row in pool.imap_unordered(_audit_job, jobs):
                on_row(row)
                if bar is not None:
                    bar.update(1)
    else:
        init_worker(allowed_path, hz)
        for j in jobs:
            on_row(_audit_job(j))
            if bar is not None:
                bar.update(1)
    if bar is not None:
        bar.close()


# ----------------------------------------------------------------------------------------------
# Stage B's audit stage
# ----------------------------------------------------------------------------------------------


def audit_inputs(config: dict) -> list[Path]:
    """The files every audit row depends on besides its trajectory and scene: the allowed pairs,
    the URDF and its collision meshes."""
    from experiments.collision import geometry_files
    from larc_jax.model.urdf import load_robot

    return [resolve(config["allowed_collisions"]), *geometry_files(load_robot())]


def audit_key(traj_path: Path, scene_path: Path, config: dict, inputs: Sequence[Path]) -> str:
    """Hash of what one trajectory's audit row depends on (its reuse key); ``inputs`` from
    :func:`audit_inputs`."""
    from experiments.fingerprints import fingerprint

    return fingerprint([traj_path, scene_path, *inputs], dict(audit_hz=config["audit_hz"]), code=CODE)[:20]


def audit_stage(layout, config: dict, workers: int, force: bool) -> dict:
    """Audit every trajectory of the dataset into ``layout.audit_csv`` (module docstring)."""
    from experiments.common import dataset_index

    spaths = scene_paths(config)
    inputs = audit_inputs(config)
    jobs = [dict(traj_id=r["traj_id"], scene=r["scene"], path=str(r["path"]), scene_path=str(spaths[r["scene"]]),
                 key=audit_key(r["path"], spaths[r["scene"]], config, inputs))
            for r in dataset_index(layout, config)]
    cached = {} if force else {r["traj_id"]: r for r in read_csv(layout.audit_csv)}
    rows = {j["traj_id"]: cached[j["traj_id"]] for j in jobs
            if j["traj_id"] in cached and cached[j["traj_id"]].get("key") == j["key"]}
    todo = [j for j in jobs if j["traj_id"] not in rows]
    print(f"[stageB] audit: {len(rows)} cached, {len(todo)} to audit at {config['audit_hz']} Hz "
          f"+ waypoints ({workers} workers)", flush=True)

    def flush():
        write_csv(layout.audit_csv, [rows[j["traj_id"]] for j in jobs if j["traj_id"] in rows], AUDIT_FIELDS)

    def on_row(row):
        rows[row["traj_id"]] = row
        flush()

    flush()
    # Longest first so the workers finish together.
    todo.sort(key=lambda j: -Path(j["path"]).stat().st_size)
    t0 = time.perf_counter()
    if todo:
        _run_jobs(todo, str(resolve(config["allowed_collisions"])), float(config["audit_hz"]), workers, on_row)
    flush()
    return dict(trajectories=len(rows), audited_now=len(todo), audit_s=round(time.perf_counter() - t0, 1))


# ----------------------------------------------------------------------------------------------
# Stand-alone use
# ----------------------------------------------------------------------------------------------


def dataset_items(traj_root: str | Path, config: dict | None = None, scenes: Sequence[str] | None = None) -> list[dict]:
    """Jobs {traj_id, scene, path, scene_path} for every ``<scene>/*.yaml`` under ``traj_root``;
    scene files from the protocol (default ``configs/stageB.yaml``)."""
    config = load_config(CONFIG_PATH) if config is None else config
    traj_root = Path(traj_root)
    spaths = scene_paths(config)
    items = []
    for scene in (scenes or list(spaths)):
        for p in sorted((traj_root / scene).glob("*.yaml")):
            items.append({"traj_id": p.stem, "scene": scene, "path": str(p), "scene_path": str(spaths[scene])})
    return items


def audit_dataset(items: Iterable[dict], *, hz: float, allowed_path: str | Path | None = None, workers: int = 2,
                  progress: bool = True) -> list[dict]:
    """Audit many trajectories (jobs from :func:`dataset_items`) in ``workers`` processes; rows
    of :data:`AUDIT_FIELDS` in the order of ``items``. ``allowed_path``: the allowed
    self-collision pairs (default: the protocol's)."""
    items = list(items)
    if allowed_path is None:
        allowed_path = resolve(load_config(CONFIG_PATH)["allowed_collisions"])
    out: dict[str, dict] = {}
    _run_jobs(items, str(allowed_path), hz, workers, lambda row: out.__setitem__(row["traj_id"], row), progress)
    return [out[it["traj_id"]] for it in items]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="FCL audit of recorded trajectories (250 Hz + waypoints)")
    ap.add_argument("--trajectories", required=True, help="folder with <scene>/*.yaml")
    ap.add_argument("--config", default=str(CONFIG_PATH))
    ap.add_argument("--scenes", nargs="+", default=None)
    ap.add_argument("--out", default=None, help="CSV (default <trajectories>/../audit.csv)")
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args(argv)
    config = load_config(args.config)
    items = dataset_items(args.trajectories, config, args.scenes)
    t0 = time.perf_counter()
    res = audit_dataset(items, hz=float(config["audit_hz"]), allowed_path=resolve(config["allowed_collisions"]),
                        workers=args.workers)
    out = Path(args.out) if args.out else Path(args.trajectories).parent / "audit.csv"
    write_csv(out, res, AUDIT_FIELDS)
    n_states = sum(r["audit_states"] for r in res)
    print(f"audited {len(res)} trajectories, {n_states} states in {time.perf_counter() - t0:.1f} s -> {out}")
    for variant in ("ompl_planned", "direct_smoothstep"):
        sub = [r for r in res if (m := TRAJ_RE.match(r["traj_id"])) and m["variant"] == variant]
        print(f"  {variant}: {sum(r['audit_collision'] for r in sub)}/{len(sub)} scene collisions, "
              f"{sum(r['self_collision'] for r in sub)} self-collisions")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
