"""Sampled MoveIt/FCL-style audit of recorded trajectories on the official collision meshes.

A trajectory's recorded waypoints are reconstructed by piecewise-cubic Hermite interpolation
(``scipy.interpolate.CubicHermiteSpline`` of positions and velocities, as a controller replays
them) and checked with FCL (:mod:`experiments.collision`) at every ``1/hz`` s from the first
waypoint (250 Hz in the protocol), at the last time, and at every original waypoint (exact
recorded positions). Scene collision (any link mesh intersecting any box) and self-collision
(any link pair not in the allowed pairs) are reported separately. A trajectory is
*sampled-clear* when no scene collision is detected at those states; this cannot exclude
collisions between audit states.

``python -m experiments.audit --trajectories DIR [--out audit.csv]`` audits every
``<scene>/*.yaml`` under DIR (the scene is the folder name, its file from the protocol config)
with 2 worker processes.
"""

from __future__ import annotations

import argparse
import csv
import io
import multiprocessing as mp
import time
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

ROOT = Path(__file__).resolve().parent.parent

__all__ = ["audit_times", "audit_trajectory", "audit_dataset", "dataset_items", "main"]

AUDIT_FIELDS = [
    "trajectory_id", "scene", "variant", "path", "duration_s", "n_waypoints", "audit_states",
    "audit_collision", "scene_collision_states", "first_collision_time", "first_contact",
    "self_collision", "self_collision_states", "first_self_collision_time", "first_self_contact",
    "audit_time_s",
]


def audit_times(t: np.ndarray, hz: float) -> np.ndarray:
    """Audit times: the ``hz`` grid from t[0], the last time, and every waypoint time."""
    t = np.asarray(t, dtype=np.float64)
    n = int(np.floor((t[-1] - t[0]) * hz + 1e-9))
    grid = t[0] + np.arange(n + 1) / float(hz)
    grid = grid[grid <= t[-1]]
    return np.union1d(grid, t)


def audit_trajectory(traj, boxes, collision_model, hz: float = 250.0, allowed_pairs=()) -> dict:
    """Audit one trajectory (a :class:`larc_jax.trajectory.Trajectory` in the robot's joint
    order) against ``boxes`` (anything :func:`experiments.collision.scene_boxes` accepts).

    Returns {audit_states, audit_collision (scene, bool), self_collision (bool),
    first_collision_time (s from t[0] or None), first_self_collision_time, counts of colliding
    states, the first contacts}.
    """
    from scipy.interpolate import CubicHermiteSpline

    from experiments.collision import scene_boxes

    t0 = time.perf_counter()
    boxes = scene_boxes(boxes)
    allowed = allowed_pairs if isinstance(allowed_pairs, frozenset) else frozenset(
        __import__("experiments.collision", fromlist=["normalise_pairs"]).normalise_pairs(allowed_pairs or ()))
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
            hits = m._scene_hits(boxes)
            if hits:
                scene_hit[k] = True
                if not first_contact:
                    first_contact = f"{hits[0][0]}~{hits[0][1]}"
        sh = m._self_hits(allowed)
        if sh:
            self_hit[k] = True
            if not first_self:
                first_self = f"{sh[0][0]}~{sh[0][1]}"
    first = float(ts[np.argmax(scene_hit)] - t[0]) if scene_hit.any() else None
    first_s = float(ts[np.argmax(self_hit)] - t[0]) if self_hit.any() else None
    return {
        "audit_states": int(len(ts)),
        "audit_collision": bool(scene_hit.any()),
        "scene_collision_states": int(scene_hit.sum()),
        "first_collision_time": first,
        "first_contact": first_contact,
        "self_collision": bool(self_hit.any()),
        "self_collision_states": int(self_hit.sum()),
        "first_self_collision_time": first_s,
        "first_self_contact": first_self,
        "duration_s": float(t[-1] - t[0]),
        "n_waypoints": int(len(t)),
        "audit_time_s": time.perf_counter() - t0,
    }


# ----------------------------------------------------------------------------------------------
# Datasets
# ----------------------------------------------------------------------------------------------


def dataset_items(traj_root: str | Path, config: dict | None = None, scenes: Sequence[str] | None = None,
                  root: Path = ROOT) -> list[dict]:
    """Items {path, scene, scene_file, variant, trajectory_id} for every ``<scene>/*.yaml`` under
    ``traj_root``; scene files from the protocol config."""
    from experiments.generate import DEFAULT_CONFIG, _resolve, load_config

    config = config if config is not None else load_config(DEFAULT_CONFIG)
    traj_root = Path(traj_root)
    items = []
    for scene in (scenes or list(config["scenes"])):
        folder = traj_root / scene
        if not folder.is_dir():
            continue
        scene_file = str(_resolve(config["scenes"][scene]["file"], root))
        for p in sorted(folder.glob("*.yaml")):
            variant = next((v for v in ("ompl_planned", "direct_smoothstep") if p.stem.endswith(v)), "")
            items.append({"path": str(p), "scene": scene, "scene_file": scene_file,
                          "variant": variant, "trajectory_id": p.stem})
    return items


_W: dict = {}


def _init_worker(allowed_path: str, hz: float):
    from experiments.collision import CollisionModel
    from experiments.self_collision import load_allowed_pairs

    _W["model"] = CollisionModel()
    _W["allowed"] = load_allowed_pairs(allowed_path, _W["model"].robot)
    _W["hz"] = hz
    _W["boxes"] = {}


def audit_file_in_worker(path: str, scene_file: str) -> dict:
    """Audit one trajectory file in a process set up by :func:`_init_worker` (the FCL model
    is built once per process, scene boxes are cached per scene file)."""
    from experiments.collision import SceneBoxes
    from larc_jax.trajectory_files import read_trajectory

    model = _W["model"]
    boxes = _W["boxes"].get(scene_file)
    if boxes is None:
        boxes = _W["boxes"][scene_file] = SceneBoxes.from_file(scene_file)
    traj = read_trajectory(path, model.robot)
    return audit_trajectory(traj, boxes, model, _W["hz"], _W["allowed"])


def _audit_item(item: dict) -> dict:
    res = audit_file_in_worker(item["path"], item["scene_file"])
    return {**{k: item[k] for k in ("trajectory_id", "scene", "variant", "path")}, **res}


def audit_dataset(items: Iterable[dict], *, hz: float = 250.0, allowed_path: str | Path | None = None,
                  workers: int = 2, progress: bool = True) -> list[dict]:
    """Audit many trajectories (items from :func:`dataset_items`: path, scene_file, ...) in
    ``workers`` processes; results in the order of ``items``."""
    from experiments.self_collision import DEFAULT_PATH

    items = list(items)
    allowed_path = str(allowed_path or DEFAULT_PATH)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(items), desc="audit", unit="traj", dynamic_ncols=True)
    out: list[dict | None] = [None] * len(items)
    if workers <= 1:
        _init_worker(allowed_path, hz)
        for k, it in enumerate(items):
            out[k] = _audit_item(it)
            if bar is not None:
                bar.update(1)
    else:
        ctx = mp.get_context("spawn")
        with ctx.Pool(workers, initializer=_init_worker, initargs=(allowed_path, hz)) as pool:
            for k, res in enumerate(pool.imap(_audit_item, items, chunksize=1)):
                out[k] = res
                if bar is not None:
                    bar.update(1)
    if bar is not None:
        bar.close()
    return out  # type: ignore[return-value]


def results_csv(results: Sequence[dict]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=AUDIT_FIELDS, lineterminator="\n", extrasaction="ignore")
    w.writeheader()
    for r in results:
        w.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in AUDIT_FIELDS})
    return buf.getvalue()


def main(argv=None) -> int:
    from experiments.generate import DEFAULT_CONFIG, _resolve, load_config
    from larc_jax.io import atomic_write_text

    ap = argparse.ArgumentParser(description="FCL audit of recorded trajectories (250 Hz + waypoints)")
    ap.add_argument("--trajectories", required=True, help="folder with <scene>/*.yaml")
    ap.add_argument("--config", default=str(DEFAULT_CONFIG))
    ap.add_argument("--scenes", nargs="+", default=None)
    ap.add_argument("--out", default=None, help="CSV (default <trajectories>/../audit.csv)")
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args(argv)
    config = load_config(args.config)
    items = dataset_items(args.trajectories, config, args.scenes)
    t0 = time.perf_counter()
    res = audit_dataset(items, hz=float(config["audit_hz"]),
                        allowed_path=_resolve(config["allowed_collisions"]), workers=args.workers)
    out = Path(args.out) if args.out else Path(args.trajectories).parent / "audit.csv"
    atomic_write_text(out, results_csv(res))
    n_states = sum(r["audit_states"] for r in res)
    print(f"audited {len(res)} trajectories, {n_states} states in {time.perf_counter() - t0:.1f} s -> {out}")
    for variant in ("ompl_planned", "direct_smoothstep"):
        sub = [r for r in res if r["variant"] == variant]
        print(f"  {variant}: {sum(r['audit_collision'] for r in sub)}/{len(sub)} scene collisions, "
              f"{sum(r['self_collision'] for r in sub)} self-collisions")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
