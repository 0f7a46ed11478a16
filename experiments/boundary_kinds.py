"""Each obstacle kind at the boundary: an obstacle slid toward a certified path until its
certificate flips, and the true clearance where it last held (issue 22's boundary target).

    python -m experiments.boundary_kinds [--out DIR] [--force]

Input: what ``python -m experiments.tightness_kinds`` wrote (``results/tightness_kinds``): the
window of each kind (its scene file, mesh and cloud), the OMPL-planned paths, their true
clearance and their certification. Per kind (:data:`experiments.tightness_kinds.KINDS`):

1. **The path.** Among the kind's paths the default configuration (``cascade_d12``: LARC with
   the capsule test then the link hulls, rho = 10 mm, gripper stated, padding 0, depth <= 12)
   certified, the one of least true clearance.
2. **The direction** (:func:`toward_arm`). At the truth's time, the hull vertices of the truth's
   link (points of its mesh) and the box of the truth's obstacle group (in the group's frame):
   the unit vector from the box's nearest point to the nearest vertex. The whole window slides
   along it, rigidly (every entry's ``pose.position`` moved, the cloud's too).
3. **The flip** (:func:`find_flip`). The window is slid by 2, 4, 8, ... mm until the path is not
   certified (at most :data:`MAX_SHIFT_M`), then bisected to :data:`RESOLUTION_M`: the last
   certified shift ``s`` and the first refused one. Each try certifies the moved window as larc
   reads it: the kind's scene file with every ``pose.position`` moved (:func:`write_moved`).
4. **The truth at the flip.** :func:`experiments.mesh_truth.mesh_truth` (python-fcl, official
   meshes, fingers closed, 1 kHz plus refinement) against FCL objects built from the moved
   entries' numbers (:func:`experiments.tightness_kinds.fcl_groups`), not through larc's readers.

The slack is the true clearance at the last certified shift less rho. It must be positive (a
certificate holds there: soundness), and the issue's target is at most the run's padding (0 for
the cascade) plus 1 mm. It holds what every part of the chain adds: the motion bound at the
deepest leaf, each link's convex hull around its mesh, the obstacle's representation (a mesh's
or cloud's convex pieces) and the rounding guard. Output in ``<out>``: ``boundary.csv`` (a row
per kind), ``table.md``, ``summary.json``.
"""

from __future__ import annotations

import functools
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from experiments.mesh_truth import HOLD, TRUTH_HZ
from experiments.tightness import MARGIN_M, driver_args, files_fingerprint, run_stage, write_frame
from experiments.tightness_kinds import (CLOUD_NAME, KINDS, PADDINGS_MM, PAIRS, STL_NAME, TARGET, Plan, fcl_groups,
                                         scene_entries, truth_obstacles)

__all__ = ["main", "shifted_entries", "write_moved", "toward_arm", "piece_obstacles", "find_flip", "MAX_SHIFT_M", "RESOLUTION_M",
           "TARGET_SLACK_M"]

ROOT = Path(__file__).resolve().parent.parent
SOURCE = ROOT / "results" / "tightness_kinds"
MAX_SHIFT_M = 0.256
"""The farthest slide tried (2 mm doubled 7 times)."""
FIRST_SHIFT_M = 0.002
RESOLUTION_M = 5e-5
"""The bisection stops when the certified and refused shifts are this close (0.05 mm)."""
TARGET_SLACK_M = 0.001
"""Issue 22: slack within the run's padding (0 for the cascade) plus 1 mm."""
FIELDS = ["kind", "traj_id", "truth_m", "truth_link", "truth_group", "direction", "shift_certified_m",
          "shift_refused_m", "truth_at_flip_m", "slack_m", "truth_at_flip_link", "truth_at_flip_group", "pieces_at_flip_m",
          "certify_calls", "seconds"]


def shifted_entries(entries: list[dict], offset) -> list[dict]:
    """Scene-file ``obstacles:`` entries with every ``pose.position`` moved by ``offset``."""
    out = []
    for e in entries:
        pose = dict(e.get("pose", {}))
        pose["position"] = [float(v) for v in np.add(pose.get("position", [0.0, 0.0, 0.0]), offset)]
        pose.setdefault("orientation", [0.0, 0.0, 0.0, 1.0])
        out.append(dict(e, pose=pose))
    return out


def write_moved(scene_path: Path, offset, folder: Path) -> Path:
    """The scene file ``scene_path`` with every obstacle moved by ``offset`` (m, base frame),
    written into ``folder`` beside copies of its mesh and cloud files."""
    import shutil

    import yaml

    from larc_jax.io import atomic_write_text

    for name in (STL_NAME, CLOUD_NAME):
        if not (folder / name).is_file():
            shutil.copy(scene_path.parent / name, folder / name)
    path = folder / f"moved_{scene_path.name}"
    atomic_write_text(path, yaml.safe_dump({"frame": "base_link", "obstacles": shifted_entries(
        scene_entries(scene_path), offset)}, sort_keys=False, default_flow_style=None))
    return path


def toward_arm(W: np.ndarray, lo, hi, R=np.eye(3), p=np.zeros(3)) -> np.ndarray:
    """Unit vector (world) along which a box ``lo..hi`` of the frame ``(R, p)`` moves toward the
    nearest of the points ``W`` (N, 3, world): from the box's nearest point to that point; if a
    point is inside the box, from the box's centre to the points' mean."""
    x = (np.asarray(W, np.float64) - p) @ np.asarray(R)  # in the box's frame
    gap = x - np.clip(x, lo, hi)
    d = np.linalg.norm(gap, axis=1)
    v = gap[np.argmin(d)] if d.min() > 0 else x.mean(axis=0) - (np.asarray(lo) + hi) / 2
    return np.asarray(R) @ v / np.linalg.norm(v)


def piece_obstacles(scene):
    """Truth groups of ``scene``'s mesh and cloud pieces as larc reads them: each piece's convex
    hull (an FCL triangle surface; a flat piece's polygon), its box the group's box. Their FCL
    distance less the piece's point radius is the distance to what larc certifies against."""
    import fcl
    from scipy.spatial import ConvexHull, QhullError

    from experiments.mesh_truth import TruthObstacles

    names, lo, hi, objects = [], [], [], []
    for k, (P, o) in enumerate(zip(scene.point_sets.pieces, scene.point_sets.owner)):
        P = np.asarray(P, np.float64)
        try:
            F = ConvexHull(P).simplices
        except QhullError:  # flat (or a segment, a point): the polygon of its plane, fanned
            c = P.mean(axis=0)
            _, _, Vt = np.linalg.svd(P - c)
            try:
                ring = ConvexHull((P - c) @ Vt[:2].T).vertices
            except QhullError:
                ring = np.array([np.argmin(P @ Vt[0]), np.argmax(P @ Vt[0])] * 2)
            F = np.array([[ring[0], ring[i], ring[i + 1]] for i in range(1, len(ring) - 1)])
        bvh = fcl.BVHModel()
        bvh.beginModel(len(P), len(F))
        bvh.addSubModel(P, np.asarray(F, np.int64))
        bvh.endModel()
        names.append(f"{scene.point_sets.names[o]}[piece {k}]")
        lo.append(P.min(axis=0))
        hi.append(P.max(axis=0))
        objects.append((fcl.CollisionObject(bvh),))
    return TruthObstacles(tuple(names), np.array(lo), np.array(hi), tuple(objects), np.zeros(len(names), bool))


def find_flip(ok, first: float = FIRST_SHIFT_M, limit: float = MAX_SHIFT_M, resolution: float = RESOLUTION_M):
    """``(certified, refused, calls)``: shifts with ``ok(certified)`` and not ``ok(refused)``,
    at most ``resolution`` apart (``ok(0)`` is taken as true); ``refused`` None if ``ok`` held up
    to ``limit``. Doubling from ``first``, then bisection."""
    lo, s, calls = 0.0, first, 0
    while True:
        calls += 1
        if not ok(s):
            break
        lo = s
        if s >= limit:
            return lo, None, calls
        s = min(2 * s, limit)
    hi = s
    while hi - lo > resolution:
        mid = (lo + hi) / 2
        calls += 1
        if ok(mid):
            lo = mid
        else:
            hi = mid
    return lo, hi, calls


def stage_boundary(src: Plan, out: Path, kinds) -> None:
    import pandas as pd
    from scipy.interpolate import CubicHermiteSpline

    import larc_jax as lj
    from experiments.mesh_truth import MeshTruth, mesh_truth
    from larc_jax.enclosure.robot_file import load_robot_file
    from larc_jax.model.robot import forward_kinematics_np
    from larc_jax.model.trajectory_files import read_trajectory

    truth = pd.read_csv(src.out / "truth.csv")
    cert = pd.read_csv(src.out / "certification.csv")
    cert = cert[(cert["config"] == TARGET) & cert["certified"]]
    paths = {r["traj_id"]: r["path"] for r in src.trajectories()}
    robot, capsules = load_robot_file(None, hold=HOLD)
    spec = lj.RunSpec(method="larc", margin_m=MARGIN_M, max_depth=12, enclosure="hull")
    mesh = MeshTruth()
    rows = []
    for kind in kinds:
        t0 = time.perf_counter()
        row = truth[truth["traj_id"].isin(cert["traj_id"]) & (truth["kind"] == kind)].nsmallest(1, "truth_m")
        if not len(row):
            raise SystemExit(f"[boundary_kinds] {kind}: no path certified by {TARGET} in {src.out}")
        row = row.iloc[0]
        traj = read_trajectory(paths[row["traj_id"]], robot)
        folder, entries = src.scene(kind).parent, scene_entries(src.scene(kind))
        groups = fcl_groups(entries, folder)
        g = next(x for x in groups if x.name == row["truth_box"])
        q = CubicHermiteSpline(traj.t, traj.q, traj.qd, axis=0)(float(row["truth_t"]))
        T = forward_kinematics_np(mesh.robot, q)
        li = mesh.links.index(row["truth_link"])
        Tl = T[mesh.robot.link_index(row["truth_link"])]
        u = toward_arm(mesh.vertices[li] @ Tl[:3, :3].T + Tl[:3, 3], g.lo, g.hi, g.R, g.p)

        certified = {}  # shift -> the moved window as larc read it, where the path is certified

        def ok(s):
            with tempfile.TemporaryDirectory() as tmp:
                scene = lj.read_scene(write_moved(src.scene(kind), s * u, Path(tmp)))
            passed = bool(lj.certify(traj, scene, robot, capsules, spec=spec).certified[0])
            if passed:
                certified[s] = scene
            return passed

        if not ok(0.0):
            raise SystemExit(f"[boundary_kinds] {kind}: {row['traj_id']} is not certified unmoved")
        s_ok, s_no, calls = find_flip(ok)
        moved = truth_obstacles(fcl_groups(shifted_entries(entries, s_ok * u), folder))
        at = mesh_truth(mesh, traj, moved)
        to_pieces = np.nan  # meshes and clouds: the distance to larc's pieces, their representation
        scene = certified[s_ok]
        if scene.point_sets.count:
            r = max(scene.point_sets.radius)
            assert set(scene.point_sets.radius) == {r}, "one point radius per window"
            to_pieces = mesh_truth(mesh, traj, piece_obstacles(scene))["truth_m"] - r
        rows.append(dict(kind=kind, traj_id=row["traj_id"], truth_m=row["truth_m"], truth_link=row["truth_link"],
                         truth_group=row["truth_box"], direction=" ".join(f"{v:+.4f}" for v in u),
                         shift_certified_m=s_ok, shift_refused_m=np.nan if s_no is None else s_no,
                         truth_at_flip_m=at["truth_m"], slack_m=at["truth_m"] - MARGIN_M,
                         truth_at_flip_link=at["truth_link"], truth_at_flip_group=at["truth_box"],
                         pieces_at_flip_m=to_pieces,
                         certify_calls=calls + 1, seconds=round(time.perf_counter() - t0, 1)))
        print(f"[boundary_kinds] {kind}: {row['traj_id']} slid {s_ok * 1000:.2f} mm (refused at "
              f"{'-' if s_no is None else f'{s_no * 1000:.2f}'} mm), true clearance {at['truth_m'] * 1000:.2f} mm, "
              f"slack {(at['truth_m'] - MARGIN_M) * 1000:+.2f} mm ({rows[-1]['seconds']} s)", flush=True)
        write_frame(out / "boundary.csv", pd.DataFrame(rows, columns=FIELDS))


def stage_tables(out: Path) -> None:
    import pandas as pd

    from larc_jax.io import atomic_write_json, atomic_write_text

    df = pd.read_csv(out / "boundary.csv")
    df["met"] = (df["slack_m"] > 0) & (df["slack_m"] <= TARGET_SLACK_M)
    lines = [f"**At the boundary (issue 22), {TARGET}: LARC, capsules then hulls, gripper stated, padding 0, "
             f"depth <= 12, rho = {MARGIN_M * 1000:g} mm**", "",
             "| kind | path | true clearance | slid until the flip | true clearance there | slack (minus rho) "
             "| target | met | larc's pieces there |", "|---|---|---|---|---|---|---|---|---|"]
    for r in df.to_dict("records"):
        pieces = f"{r['pieces_at_flip_m'] * 1000:.2f} mm" if np.isfinite(r["pieces_at_flip_m"]) else "-"
        lines.append(f"| {r['kind']} | {r['traj_id']} | {r['truth_m'] * 1000:.2f} mm "
                     f"| {r['shift_certified_m'] * 1000:.2f} mm | {r['truth_at_flip_m'] * 1000:.2f} mm "
                     f"| {r['slack_m'] * 1000:+.2f} mm | 0 < slack <= {TARGET_SLACK_M * 1000:g} mm "
                     f"| {'yes' if r['met'] else 'no'} | {pieces} |")
    lines += ["", f"Per kind: the certified path of least true clearance; its window slid toward the link the "
              f"truth names until the certificate flips ({RESOLUTION_M * 1000:g} mm); the truth (python-fcl, "
              f"official meshes, fingers closed, {TRUTH_HZ:g} Hz + refinement) at the last certified place "
              f"(`python -m experiments.boundary_kinds`). For a mesh or a cloud, 'larc's pieces there' is the "
              f"same truth against the convex hulls of larc's pieces (grown by the point radius): for a mesh, "
              f"what larc certifies against, so the true clearance less this is what the pieces add; a "
              f"cloud's pieces are also searched point by point where their hulls fail (the hull stage's "
              f"third round), so there it may be below rho."]
    atomic_write_text(out / "table.md", "\n".join(lines) + "\n")
    atomic_write_json(out / "summary.json", dict(
        config=TARGET, margin_m=MARGIN_M, target_slack_m=TARGET_SLACK_M, resolution_m=RESOLUTION_M,
        sound=bool((df["slack_m"] > 0).all()), met=int(df["met"].sum()),
        kinds=len(df), slack_m={r["kind"]: r["slack_m"] for r in df.to_dict("records")}))


def main(argv=None) -> int:
    from experiments.fingerprints import code_fingerprint, source_fingerprint

    sources = functools.partial(source_fingerprint, globals())  # a stage's own code and this module's constants
    args, out = driver_args(argv, __doc__.splitlines()[0], "boundary_kinds", "the box and points kinds only")
    kinds = ("box", "points") if args.quick else KINDS
    src = Plan(out=SOURCE, kinds=KINDS, paddings_mm=PADDINGS_MM, pairs=PAIRS)
    data = [r["path"] for r in src.trajectories()] + [src.scene(k) for k in KINDS] + [
        SOURCE / "scenes" / STL_NAME, SOURCE / "scenes" / CLOUD_NAME, SOURCE / "truth.csv",
        SOURCE / "certification.csv"]
    code = code_fingerprint(["larc_jax"]) + files_fingerprint([ROOT / "experiments" / "mesh_truth.py"]) + sources(
        shifted_entries, write_moved, toward_arm, piece_obstacles, find_flip, stage_boundary, fcl_groups, truth_obstacles)
    t0 = time.perf_counter()
    run_stage(out, "boundary", files_fingerprint(data, dict(kinds=kinds, code=code)), [out / "boundary.csv"],
              lambda: stage_boundary(src, out, kinds), args.force, tag="boundary_kinds")
    run_stage(out, "tables", files_fingerprint([out / "boundary.csv"], dict(code=sources(stage_tables))),
              [out / "table.md", out / "summary.json"], lambda: stage_tables(out), args.force, tag="boundary_kinds")
    print(f"[boundary_kinds] done in {time.perf_counter() - t0:.1f} s", flush=True)
    print((out / "table.md").read_text(), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
