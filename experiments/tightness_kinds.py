"""How tight is the certificate for each obstacle kind? Planned paths through a window built of
oriented boxes, balls, cylinders, a mesh or a point cloud; their true clearance; the certificates.

    python -m experiments.tightness_kinds [--quick] [--out DIR] [--force] [--workers 2]

The window of ``configs/scenes/easy_window.yaml`` (a 4 cm wall at x = 0.20..0.24 m, base frame,
with a 0.50 m x 0.50 m opening at y = -0.25..0.25, z = 0.02..0.52) is built once of each kind
(:data:`KINDS`, :func:`kind_entries`):

* ``box`` — its four boxes turned 20 degrees about the wall's normal (x) around the opening's
  centre: oriented boxes;
* ``sphere`` — balls of radius 5 cm, 9 cm apart, over the wall but the opening;
* ``cylinder`` — bars of radius 4 cm: six along y above the opening, six below, six upright
  beside it on each side;
* ``mesh`` — the four boxes as one triangle mesh in millimetres (``scale`` 0.001, as CAD
  exports it; triangles at most 6 cm long, about 11,600), turned 10 degrees about z: a
  non-convex surface;
* ``points`` — what a depth camera in front of the wall sees: its front face and the opening's
  four sides sampled every 1 cm, jittered by up to 1 mm, each point a ball of radius 3 mm
  (about 16,500 points: a scene the engine culls).

Stages (each skipped while its inputs' fingerprint is unchanged; ``--force`` reruns all):

1. ``scenes`` — the scene files (YAML; ``window_mm.stl``; ``window_cloud.npy``) into
   ``<out>/scenes``.
2. ``generate`` — per kind and planning padding (:data:`PADDINGS_MM`), :data:`PAIRS` accepted
   start-goal pairs by :func:`experiments.generate.run_attempt` (OMPL RRTConnect, TOPP-RA timing,
   the recorded waypoints, a Hermite recheck at 50 Hz) with easy_window's endpoint regions and
   protocol. The validity checker (python-fcl) sees every obstacle grown by the padding: boxes,
   balls and cylinders grown, a ball of radius r + padding per point, and for the mesh the four
   solid boxes it is made of, posed as the mesh and grown (FCL's distance between meshes, the
   only way to pad a mesh, took 0.2-0.4 s a state).
3. ``truth`` — :func:`experiments.mesh_truth.mesh_truth` against FCL objects built here from the
   numbers written to the files, not through larc's readers: ``fcl.Box`` with its rotation,
   ``Sphere``, ``Cylinder``, a ``BVHModel`` of the mesh's triangles as the STL holds them, a
   ``Sphere`` per cloud point. Fingers closed, 1 kHz plus refinement.
4. ``certify`` — LARC, rho = 10 mm, gripper stated, for each of :data:`CONFIGS`.
5. ``tables`` — ``table.md`` (certified per kind and true-clearance bin), ``goal.md`` (issue 22's
   tightness targets per kind), ``summary.json``.

``--quick``: two kinds (box, points), one padding, one pair, into ``results/tightness_kinds_quick``
(git-ignored; run by ``tests/test_tightness_kinds.py``).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import multiprocessing as mp
import sys
import time
from pathlib import Path

import numpy as np

from experiments.generate import SceneContext
from experiments.mesh_truth import HOLD, TRUTH_HZ
from experiments.tightness import (BINS_MM, MARGIN_M, bin_labels, driver_args, files_fingerprint, run_stage,
                                   write_frame)

ROOT = Path(__file__).resolve().parent.parent
CONFIG_PATH = ROOT / "configs" / "stageB.yaml"
BASE_SCENE = "easy_window"
"""The Stage B scene whose protocol (endpoint regions, seed) every kind's window uses."""
KINDS = ("box", "sphere", "cylinder", "mesh", "points")
PADDINGS_MM = (10, 20, 30)
PAIRS = 6
MAX_ATTEMPTS = 60
CLEAR_BY_MM = 5.0
"""Issue 22's target set: paths whose meshes clear rho by more than this."""
CONFIGS = (  # (name, enclosure, depth)
    ("capsules_d9", "capsules", 9),
    ("cascade_d9", "hull", 9),
    ("cascade_d12", "hull", 12),
)
TARGET = "cascade_d12"
OPENING_CENTRE = np.array([0.22, 0.0, 0.27])
WALL = {  # easy_window's four boxes, base frame, m
    "wall_below": ((0.20, -0.85, -0.70), (0.24, 0.85, 0.02)),
    "wall_above": ((0.20, -0.85, 0.52), (0.24, 0.85, 0.95)),
    "wall_right": ((0.20, -0.85, 0.02), (0.24, -0.25, 0.52)),
    "wall_left": ((0.20, 0.25, 0.02), (0.24, 0.85, 0.52)),
}
STL_NAME = "window_mm.stl"
CLOUD_NAME = "window_cloud.npy"
POINT_RADIUS_M = 0.003
CLOUD_GROUP_M = 0.08
MESH_GROUP_M = 0.2
"""Edges of the grid cells that group the cloud's points and the mesh's triangles (by centroid)
for the truth's pruning."""
MESH_EDGE_MM = 60.0
FIELDS = ["traj_id", "kind", "padding_mm", "duration_s", "n_waypoints", "truth_m", "truth_t", "truth_link",
          "truth_box", "fcl_queries", "truth_time_s", "key"]

__all__ = ["main", "KINDS", "CONFIGS", "kind_entries", "fcl_groups", "quaternion_matrix", "pool_map"]


# ----------------------------------------------------------------------------------------------
# The windows
# ----------------------------------------------------------------------------------------------


def quaternion_matrix(q) -> np.ndarray:
    """Rotation matrix of a unit quaternion ``[qx, qy, qz, qw]`` (ROS order)."""
    x, y, z, w = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _about(axis: int, degrees: float) -> list[float]:
    q = [0.0, 0.0, 0.0, math.cos(math.radians(degrees) / 2)]
    q[axis] = math.sin(math.radians(degrees) / 2)
    return q


def _pose(position, orientation=(0.0, 0.0, 0.0, 1.0)) -> dict:
    return {"position": [float(v) for v in position], "orientation": [float(v) for v in orientation]}


def _box_mesh_mm():
    """The four wall boxes as one triangle mesh, millimetres, about the opening's centre."""
    import trimesh

    parts = []
    for lo, hi in WALL.values():
        lo, hi = (np.array(lo) - OPENING_CENTRE) * 1000.0, (np.array(hi) - OPENING_CENTRE) * 1000.0
        parts.append(trimesh.creation.box(extents=hi - lo, transform=trimesh.transformations.translation_matrix(
            (lo + hi) / 2)))
    whole = trimesh.util.concatenate(parts)
    # Triangles at most 6 cm long, as a CAD export of a large part has: FCL's distance between
    # BVHs of long thin triangles and the link meshes takes milliseconds a query.
    V, F = trimesh.remesh.subdivide_to_size(whole.vertices, whole.faces, max_edge=MESH_EDGE_MM)
    return trimesh.Trimesh(V, F, process=False)


def _cloud() -> np.ndarray:
    """The camera's points (base frame, m): the front face and the opening's sides, 1 cm apart."""
    rng = np.random.default_rng(20271203)
    s = 0.01
    y, z = np.meshgrid(np.arange(-0.70, 0.70 + 1e-9, s), np.arange(-0.40, 0.90 + 1e-9, s), indexing="ij")
    front = np.stack([np.full(y.size, 0.20), y.ravel(), z.ravel()], 1)
    front = front[~((np.abs(front[:, 1]) < 0.25) & (front[:, 2] > 0.02) & (front[:, 2] < 0.52))]
    x = np.arange(0.20, 0.24 + 1e-9, s)
    sides = []
    for yv in (-0.25, 0.25):
        xx, zz = np.meshgrid(x, np.arange(0.02, 0.52 + 1e-9, s), indexing="ij")
        sides.append(np.stack([xx.ravel(), np.full(xx.size, yv), zz.ravel()], 1))
    for zv in (0.02, 0.52):
        xx, yy = np.meshgrid(x, np.arange(-0.25, 0.25 + 1e-9, s), indexing="ij")
        sides.append(np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, zv)], 1))
    pts = np.concatenate([front, *sides])
    return pts + rng.uniform(-0.001, 0.001, pts.shape)


def kind_entries(kind: str) -> list[dict]:
    """The scene file's ``obstacles:`` entries of ``kind``'s window (module docstring)."""
    out = []
    if kind == "box":
        R = quaternion_matrix(_about(0, 20.0))
        for name, (lo, hi) in WALL.items():
            lo, hi = np.array(lo), np.array(hi)
            centre = OPENING_CENTRE + R @ ((lo + hi) / 2 - OPENING_CENTRE)
            out.append({"name": name, "type": "box", "size": [float(v) for v in hi - lo],
                        "pose": _pose(centre, _about(0, 20.0))})
    elif kind == "sphere":
        r = 0.05
        for i in range(-8, 9):
            for k in range(-8, 8):
                y, z = 0.09 * i, 0.27 + 0.09 * k
                gap = math.hypot(max(abs(y) - 0.25, 0.0), max(abs(z - 0.27) - 0.25, 0.0))
                if gap >= r:
                    out.append({"name": f"ball_{i + 8:02d}_{k + 8:02d}", "type": "sphere", "radius": r,
                                "pose": _pose((0.22, y, z))})
    elif kind == "cylinder":
        r = 0.04
        for k in range(6):
            for side, z in (("above", 0.52 + r + 0.07 * k), ("below", 0.02 - r - 0.07 * k)):
                out.append({"name": f"bar_{side}_{k}", "type": "cylinder", "radius": r, "length": 1.44,
                            "pose": _pose((0.22, 0.0, z), _about(0, -90.0))})
            for side, y in (("right", -(0.25 + r + 0.07 * k)), ("left", 0.25 + r + 0.07 * k)):
                out.append({"name": f"post_{side}_{k}", "type": "cylinder", "radius": r, "length": 0.58,
                            "pose": _pose((0.22, y, 0.27))})
    elif kind == "mesh":
        out.append({"name": "window", "type": "mesh", "file": STL_NAME, "scale": [0.001, 0.001, 0.001],
                    "pose": _pose(OPENING_CENTRE, _about(2, 10.0))})
    elif kind == "points":
        out.append({"name": "camera", "type": "points", "file": CLOUD_NAME, "radius": POINT_RADIUS_M})
    else:
        raise ValueError(f"unknown kind {kind!r}; kinds: {', '.join(KINDS)}")
    return out


def write_scenes(folder: Path, kinds) -> dict[str, Path]:
    """Write each kind's scene file (and the mesh and cloud files) into ``folder``."""
    import yaml

    from larc_jax.io import atomic_write_bytes, atomic_write_text

    folder.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(folder / STL_NAME, _box_mesh_mm().export(file_type="stl"))
    import io

    buf = io.BytesIO()
    np.save(buf, _cloud())
    atomic_write_bytes(folder / CLOUD_NAME, buf.getvalue())
    paths = {}
    for kind in kinds:
        doc = {"frame": "base_link", "obstacles": kind_entries(kind)}
        head = f"# easy_window's wall built of {kind} obstacles (experiments/tightness_kinds.py writes this file)\n"
        paths[kind] = folder / f"{kind}.yaml"
        atomic_write_text(paths[kind], head + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None))
    return paths


# ----------------------------------------------------------------------------------------------
# FCL objects of a window (independent of larc's scene reader)
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Group:
    """FCL objects of one obstacle or part of one, in a box ``lo``..``hi`` of the frame (R, p)."""

    name: str
    lo: np.ndarray
    hi: np.ndarray
    objects: tuple
    is_box: bool = False
    """The group is exactly its box (a solid box)."""
    R: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(3))
    p: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))


def fcl_groups(entries: list[dict], folder: Path, pad_m: float = 0.0) -> list[Group]:
    """FCL objects of ``entries``, each grown by ``pad_m`` where its kind can be grown."""
    import fcl
    import trimesh

    groups = []
    for e in entries:
        pose = e.get("pose", {})
        p = np.array(pose.get("position", [0.0, 0.0, 0.0]), np.float64)
        R = quaternion_matrix(pose.get("orientation", [0.0, 0.0, 0.0, 1.0]))
        tf = fcl.Transform(R, p)
        if e["type"] in ("box", "sphere", "cylinder"):
            if e["type"] == "box":
                half = np.array(e["size"]) / 2 + pad_m
                geom = fcl.Box(*(2 * half))
            elif e["type"] == "sphere":
                half = np.full(3, e["radius"] + pad_m)
                geom = fcl.Sphere(e["radius"] + pad_m)
            else:  # FCL's cylinder, as URDF's and MoveIt's, is centred with its axis along z
                half = np.array([e["radius"] + pad_m, e["radius"] + pad_m, e["length"] / 2 + pad_m])
                geom = fcl.Cylinder(e["radius"] + pad_m, e["length"] + 2 * pad_m)
            groups.append(Group(e["name"], -half, half, (fcl.CollisionObject(geom, tf),), is_box=e["type"] == "box",
                                R=R, p=p))
        elif e["type"] == "mesh":
            if pad_m:
                raise ValueError(f"{e['name']}: a mesh cannot be grown by a padding (plan with planning_entries)")
            mesh = trimesh.load(folder / e["file"], process=False)
            V = (np.asarray(mesh.vertices, np.float64) * np.array(e["scale"])) @ R.T + p
            F = np.asarray(mesh.faces)
            for k, faces in enumerate(_cells(V[F].mean(axis=1), MESH_GROUP_M)):
                used, local = np.unique(F[faces], return_inverse=True)
                bvh = fcl.BVHModel()
                bvh.beginModel(len(used), len(faces))
                bvh.addSubModel(V[used], local.reshape(-1, 3))
                bvh.endModel()
                groups.append(Group(f"{e['name']}[{k}]", V[used].min(0), V[used].max(0), (fcl.CollisionObject(bvh),)))
        elif e["type"] == "points":
            P = np.load(folder / e["file"]) @ R.T + p
            r = e["radius"] + pad_m
            for g, members in enumerate(_cells(P, CLOUD_GROUP_M)):
                Pg = P[members]
                objs = tuple(fcl.CollisionObject(fcl.Sphere(r), fcl.Transform(np.eye(3), x)) for x in Pg)
                groups.append(Group(f"{e['name']}[{g}]", Pg.min(0) - r, Pg.max(0) + r, objs))
        else:
            raise ValueError(f"{e['name']}: unknown type {e['type']!r}")
    return groups


def _cells(points: np.ndarray, edge_m: float) -> list[np.ndarray]:
    """Indices of ``points`` per occupied cell of a grid of cubes of edge ``edge_m``."""
    _, inverse = np.unique(np.floor(points / edge_m).astype(np.int64), axis=0, return_inverse=True)
    inverse = inverse.ravel()
    return [np.flatnonzero(inverse == g) for g in range(inverse.max() + 1)]


def planning_entries(kind: str) -> list[dict]:
    """What the planner avoids for ``kind``: its entries, but for the mesh the four boxes it is
    made of, posed as the mesh (a box can be grown by the padding, a mesh cannot)."""
    if kind != "mesh":
        return kind_entries(kind)
    (mesh,) = kind_entries("mesh")
    R = quaternion_matrix(mesh["pose"]["orientation"])
    return [{"name": name, "type": "box", "size": [float(v) for v in np.subtract(hi, lo)],
             "pose": _pose(OPENING_CENTRE + R @ ((np.add(lo, hi)) / 2 - OPENING_CENTRE), mesh["pose"]["orientation"])}
            for name, (lo, hi) in WALL.items()]


def truth_obstacles(groups: list[Group]):
    from experiments.mesh_truth import TruthObstacles

    return TruthObstacles(tuple(g.name for g in groups), np.array([g.lo for g in groups]),
                          np.array([g.hi for g in groups]), tuple(g.objects for g in groups),
                          np.array([g.is_box for g in groups]), np.array([g.R for g in groups]),
                          np.array([g.p for g in groups]))


# ----------------------------------------------------------------------------------------------
# Stage 2: planning among the padded window
# ----------------------------------------------------------------------------------------------


class KindContext(SceneContext):
    """easy_window's planning protocol (endpoint regions, limits, timing) with its wall replaced
    by a window of one kind, grown by the planning padding (module docstring, stage 2)."""

    def __init__(self, kind: str, config: dict, scene_file: Path):
        import fcl

        from experiments.collision import SceneBoxes

        super().__init__(BASE_SCENE, config)
        self.scene_name = kind
        self.boxes = SceneBoxes(np.zeros((0, 3)), np.zeros((0, 3)))  # the wall is replaced
        groups = fcl_groups(planning_entries(kind), scene_file.parent, self.padding)
        self.manager = fcl.DynamicAABBTreeCollisionManager()
        self.manager.registerObjects([o for g in groups for o in g.objects])
        self.manager.setup()
        self.fcl = fcl

    def scene_hit(self) -> bool:
        fcl = self.fcl
        for obj in self.model.objects:
            data = fcl.CollisionData()
            self.manager.collide(obj, data, fcl.defaultCollisionCallback)
            if data.result.is_collision:
                return True
        return False

    def valid(self, q) -> bool:
        self.model.set_configuration(q)
        return not self.scene_hit() and not self.model.self_hits(self.allowed)


def scene_entries(path: Path) -> list[dict]:
    import yaml

    return yaml.safe_load(Path(path).read_text())["obstacles"]


@dataclasses.dataclass(frozen=True)
class Plan:
    out: Path
    kinds: tuple[str, ...]
    paddings_mm: tuple[int, ...]
    pairs: int

    def scene(self, kind: str) -> Path:
        return self.out / "scenes" / f"{kind}.yaml"

    def folder(self, kind: str, padding_mm: int) -> Path:
        return self.out / "dataset" / f"pad{padding_mm:02d}mm" / kind

    def trajectories(self) -> list[dict]:
        rows = []
        for p in self.paddings_mm:
            for kind in self.kinds:
                for f in sorted(self.folder(kind, p).glob(f"{kind}_p*.yaml")):
                    rows.append(dict(traj_id=f"pad{p:02d}_{f.stem}", kind=kind, padding_mm=p, path=f))
        return rows


def _generate_job(job: dict) -> dict:
    from experiments import generate as gen
    from larc_jax.io import atomic_write_json
    from larc_jax.model.trajectory_files import write_trajectory

    config = gen.load_config(CONFIG_PATH)
    config["generation"] = dict(config["generation"], planning_padding_m=job["padding_mm"] / 1000.0)
    ctx = KindContext(job["kind"], config, Path(job["scene"]))
    folder = Path(job["folder"])
    folder.mkdir(parents=True, exist_ok=True)
    for old in folder.glob("*.yaml"):
        old.unlink()
    seed = int(config["scenes"][BASE_SCENE]["seed"]) + 1000 * (KINDS.index(job["kind"]) + 1) + job["padding_mm"]
    accepted, attempt, outcomes = 0, 0, {}
    t0 = time.perf_counter()
    while accepted < job["pairs"] and attempt < MAX_ATTEMPTS:
        row, result = gen.run_attempt(ctx, seed, attempt)
        outcomes[row["outcome"]] = outcomes.get(row["outcome"], 0) + 1
        if result is not None:
            traj = dataclasses.replace(result[0], id=f"{job['kind']}_p{accepted:02d}")
            write_trajectory(folder / f"{traj.id}.yaml", traj)
            accepted += 1
        attempt += 1
    summary = dict(kind=job["kind"], padding_mm=job["padding_mm"], accepted=accepted, attempts=attempt,
                   outcomes=outcomes, fingerprint=job["fingerprint"])
    atomic_write_json(folder / "done.json", summary)
    return dict(summary, elapsed_s=round(time.perf_counter() - t0, 1))


def stage_generate(plan: Plan, workers: int, code_fp: str) -> None:
    jobs = []
    for p in plan.paddings_mm:
        for kind in plan.kinds:
            fp = files_fingerprint([plan.scene(kind), CONFIG_PATH], dict(code=code_fp, pairs=plan.pairs, pad=p))
            marker = plan.folder(kind, p) / "done.json"
            if marker.is_file() and json.loads(marker.read_text()).get("fingerprint") == fp:
                continue
            jobs.append(dict(kind=kind, padding_mm=p, pairs=plan.pairs, scene=str(plan.scene(kind)),
                             folder=str(plan.folder(kind, p)), fingerprint=fp))
    print(f"[tightness_kinds] generate: {len(jobs)} (kind, padding) jobs to run", flush=True)
    results = pool_map(_generate_job, jobs, workers)
    for r in results:
        print(f"[tightness_kinds] generate: {r['kind']}, padding {r['padding_mm']} mm: {r['accepted']} pairs in "
              f"{r['attempts']} attempts, {r['elapsed_s']} s {r['outcomes']}", flush=True)


def pool_map(fn, jobs, workers: int):
    """``fn`` over ``jobs`` in ``workers`` spawned processes (in this one for one worker or one job), results
    as they finish: the planning and truth stages' only way to run their jobs."""
    if workers <= 1 or len(jobs) <= 1:
        yield from map(fn, jobs)
        return
    with mp.get_context("spawn").Pool(min(workers, len(jobs)), maxtasksperchild=4) as pool:
        yield from pool.imap_unordered(fn, jobs)


# ----------------------------------------------------------------------------------------------
# Stage 3: truth
# ----------------------------------------------------------------------------------------------


_WORKER: dict = {}


def _truth_job(job: dict) -> dict:
    from experiments.mesh_truth import MeshTruth, mesh_truth
    from larc_jax.model.trajectory_files import read_trajectory

    if "truth" not in _WORKER:
        _WORKER["truth"] = MeshTruth()
    truth = _WORKER["truth"]
    if job["scene"] not in _WORKER:
        scene = Path(job["scene"])
        _WORKER[job["scene"]] = truth_obstacles(fcl_groups(scene_entries(scene), scene.parent))
    t0 = time.perf_counter()
    traj = read_trajectory(job["path"], truth.robot)
    row = mesh_truth(truth, traj, _WORKER[job["scene"]])
    row.update(traj_id=job["traj_id"], kind=job["kind"], padding_mm=job["padding_mm"], duration_s=traj.duration,
               n_waypoints=traj.n_waypoints, key=job["key"], truth_time_s=round(time.perf_counter() - t0, 2))
    return row


def stage_truth(plan: Plan, workers: int, code_fp: str) -> None:
    import pandas as pd

    path = plan.out / "truth.csv"
    cached = {}
    if path.is_file():
        cached = {r["traj_id"]: r for r in pd.read_csv(path, keep_default_na=False).to_dict("records")}
    jobs, rows = [], {}
    for r in plan.trajectories():
        scene = plan.scene(r["kind"])
        data = [r["path"], scene, scene.parent / STL_NAME, scene.parent / CLOUD_NAME]
        key = files_fingerprint(data, dict(code=code_fp, hz=TRUTH_HZ, hold=HOLD))[:20]
        if r["traj_id"] in cached and cached[r["traj_id"]]["key"] == key:
            rows[r["traj_id"]] = cached[r["traj_id"]]
        else:
            jobs.append(dict(r, path=str(r["path"]), scene=str(scene), key=key))
    order = [r["traj_id"] for r in plan.trajectories()]
    print(f"[tightness_kinds] truth: {len(rows)} cached, {len(jobs)} to compute", flush=True)
    for k, row in enumerate(pool_map(_truth_job, jobs, workers), 1):
        rows[row["traj_id"]] = row
        write_frame(path, pd.DataFrame([rows[i] for i in order if i in rows], columns=FIELDS))
        print(f"[tightness_kinds] truth {k}/{len(jobs)}: {row['traj_id']} {row['truth_m'] * 1000:+.2f} mm "
              f"({row['truth_link']} / {row['truth_box']}, {row['truth_time_s']} s)", flush=True)
    write_frame(path, pd.DataFrame([rows[i] for i in order if i in rows], columns=FIELDS))


# ----------------------------------------------------------------------------------------------
# Stage 4: certification; stage 5: tables
# ----------------------------------------------------------------------------------------------


def stage_certify(plan: Plan) -> None:
    import pandas as pd

    import larc_jax as lj
    from larc_jax.enclosure.robot_file import load_robot_file
    from larc_jax.model.trajectory_files import read_trajectory

    robot, capsules = load_robot_file(None, hold=HOLD)
    rows = plan.trajectories()
    scenes = {k: lj.read_scene(plan.scene(k)) for k in plan.kinds}
    trajs = [dataclasses.replace(read_trajectory(r["path"], robot), id=r["traj_id"]) for r in rows]
    frames = []
    for name, enclosure, depth in CONFIGS:
        spec = lj.RunSpec(method="larc", margin_m=MARGIN_M, max_depth=depth, enclosure=enclosure)
        res = lj.certify(trajs, [scenes[r["kind"]] for r in rows], robot, capsules, spec=spec)
        df = res.to_dataframe()
        frames.append(pd.DataFrame({"traj_id": df["id"], "kind": [r["kind"] for r in rows], "config": name,
                                    "certified": df["certified"], "evaluations": df["evaluations"],
                                    "min_clearance_m": df["min_clearance_m"]}))
        print(f"[tightness_kinds] certify {name}: {int(df['certified'].sum())}/{len(df)} certified, "
              f"{res.wall_time_s:.1f} s", flush=True)
    write_frame(plan.out / "certification.csv", pd.concat(frames, ignore_index=True))


def stage_tables(plan: Plan) -> None:
    import pandas as pd

    from larc_jax.io import atomic_write_json, atomic_write_text

    truth = pd.read_csv(plan.out / "truth.csv")
    cert = pd.read_csv(plan.out / "certification.csv")
    wide = cert.pivot(index="traj_id", columns="config", values="certified").astype(bool)
    df = truth.set_index("traj_id").join(wide, how="inner")
    df["truth_mm"] = df["truth_m"] * 1000
    labels = bin_labels()
    df["bin"] = pd.cut(df["truth_mm"], BINS_MM, labels=labels, right=False)
    names = [c[0] for c in CONFIGS]
    rho_mm = MARGIN_M * 1000
    head = "| kind | true mesh clearance | n | " + " | ".join(names) + " |"
    lines = [head, "|" + "---|" * (3 + len(names))]
    for kind in plan.kinds:
        for label in labels:
            sub = df[(df["kind"] == kind) & (df["bin"] == label)]
            if len(sub):
                lines.append(f"| {kind} | {label} | {len(sub)} | " + " | ".join(str(int(sub[n].sum())) for n in names)
                             + " |")
    md = [f"# Certified trajectories by obstacle kind and true mesh clearance ({len(df)} planned trajectories)", "",
          f"rho = {rho_mm:g} mm, gripper stated (hold joint7 = joint8 = 0). Truth: python-fcl, official meshes, "
          f"fingers closed, {TRUTH_HZ:g} Hz + refinement, against FCL objects built from the scene files' numbers. "
          f"Planning paddings (mm): {', '.join(str(p) for p in plan.paddings_mm)}. 'cascade' = capsule test, then "
          "convex hulls; the number is the deepest level.", "", *lines, ""]
    atomic_write_text(plan.out / "table.md", "\n".join(md))

    def pct(a, b):
        return f"{100.0 * a / b:.1f} %" if b else "n/a"

    summary = {"trajectories": len(df), "target_config": TARGET, "clear_by_mm": CLEAR_BY_MM, "kinds": {}}
    gl = [f"# Goal (issue 22), cascade with the gripper stated, depth <= 12 ({TARGET})", "",
          f"| kind | paths | meshes clear rho by > {CLEAR_BY_MM:g} mm | certified of those | target | "
          "meshes within rho | certified of those (any configuration) |", "|---|---|---|---|---|---|---|"]
    clear = df[df["truth_mm"] > rho_mm + CLEAR_BY_MM]
    within = df[df["truth_mm"] <= rho_mm]
    for kind in plan.kinds:
        c, w = clear[clear["kind"] == kind], within[within["kind"] == kind]
        k = dict(paths=int((df["kind"] == kind).sum()), clear=len(c), clear_certified=int(c[TARGET].sum()),
                 within_rho=len(w), within_rho_certified_any=int(w[names].any(axis=1).sum()))
        summary["kinds"][kind] = k
        gl.append(f"| {kind} | {k['paths']} | {k['clear']} | {k['clear_certified']} = "
                  f"{pct(k['clear_certified'], k['clear'])} | >= 80 % | {k['within_rho']} | "
                  f"{k['within_rho_certified_any']} |")
    summary.update(clear=len(clear), clear_certified=int(clear[TARGET].sum()), within_rho=len(within),
                   within_rho_certified_any=int(within[names].any(axis=1).sum()))
    gl.append(f"| all | {len(df)} | {len(clear)} | {summary['clear_certified']} = "
              f"{pct(summary['clear_certified'], len(clear))} | >= 90 % | {len(within)} | "
              f"{summary['within_rho_certified_any']} |")
    atomic_write_text(plan.out / "goal.md", "\n".join(gl + [""]))
    atomic_write_json(plan.out / "summary.json", summary)


# ----------------------------------------------------------------------------------------------
# Driver
# ----------------------------------------------------------------------------------------------


def main(argv=None) -> int:
    from experiments.fingerprints import code_fingerprint, source_fingerprint

    args, out = driver_args(argv, __doc__.splitlines()[0], "tightness_kinds", "two kinds, one padding, one pair")
    plan = Plan(out=out, kinds=("box", "points") if args.quick else KINDS,
                paddings_mm=(20,) if args.quick else PADDINGS_MM, pairs=1 if args.quick else PAIRS)
    params = dict(kinds=plan.kinds, paddings=plan.paddings_mm, pairs=plan.pairs)
    # Each stage depends on the code it runs: the generator's closure and this module's planning
    # code; the truth module, the FCL models and this module's FCL objects; larc_jax whole. A stage's
    # own code is its functions' normalised source and this module's public constants, paths relative
    # to the repository (the same fingerprint in every clone).
    sources = functools.partial(source_fingerprint, globals())
    scenes_code = sources(quaternion_matrix, _about, _pose, _box_mesh_mm, _cloud, kind_entries, write_scenes)
    gen_code = code_fingerprint(["experiments.generate"]) + sources(fcl_groups, _cells, planning_entries, KindContext,
                                                                       _generate_job, stage_generate)
    truth_code = files_fingerprint([ROOT / "experiments" / "mesh_truth.py", ROOT / "experiments" / "collision.py"]) \
        + sources(fcl_groups, _cells, truth_obstacles, scene_entries, _truth_job, stage_truth)
    lib = code_fingerprint(["larc_jax"])
    t0 = time.perf_counter()
    scene_files = [plan.scene(k) for k in plan.kinds] + [out / "scenes" / STL_NAME, out / "scenes" / CLOUD_NAME]
    run_stage(out, "scenes", files_fingerprint([], dict(params, code=scenes_code)), scene_files,
              lambda: write_scenes(out / "scenes", plan.kinds), args.force, tag="tightness_kinds")
    if args.force:
        for kind in plan.kinds:
            for p in plan.paddings_mm:
                (plan.folder(kind, p) / "done.json").unlink(missing_ok=True)
    stage_generate(plan, args.workers, gen_code)
    data = [r["path"] for r in plan.trajectories()]
    run_stage(out, "truth", files_fingerprint(data + scene_files, dict(params, code=truth_code)), [out / "truth.csv"],
              lambda: stage_truth(plan, args.workers, truth_code), args.force, tag="tightness_kinds")
    _WORKER.clear()  # an in-process truth's (--workers 1) FCL models, no longer needed
    cert_code = lib + sources(stage_certify)
    run_stage(out, "certify", files_fingerprint(data + scene_files, dict(params, code=cert_code, configs=CONFIGS)),
              [out / "certification.csv"], lambda: stage_certify(plan), args.force, tag="tightness_kinds")
    run_stage(out, "tables", files_fingerprint([out / "truth.csv", out / "certification.csv"],
                                               dict(params, code=sources(stage_tables, bin_labels))),
              [out / "table.md", out / "goal.md", out / "summary.json"], lambda: stage_tables(plan), args.force,
              tag="tightness_kinds")
    print(f"[tightness_kinds] all stages in {time.perf_counter() - t0:.1f} s; results in {out}", flush=True)
    print((out / "table.md").read_text(), flush=True)
    print((out / "goal.md").read_text(), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
