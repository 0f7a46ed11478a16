"""Benchmark: what each obstacle kind costs per interval (issue 22 item 3, the kinds built so far).

    python -m experiments.bench_obstacles [--json results/bench/obstacles_cpu.json] [--n 16]

The first ``--n`` (16) committed Stage B trajectories, each certified by fixed-fine (512 intervals,
depth 9: the same work whatever the scene decides) in one call, against one scene at a time:

* ``one box``: one axis-aligned box (the table top of ``configs/scenes``-like cells);
* ``one posed box``: the same box turned 30 degrees about z (a posed shape: the kernels map
  every segment into its frame);
* ``one cylinder``: a cylinder of that box's height and half its width (two box kernels per pair);
* ``10 meshes``: ten L brackets (24 triangles each, 2 pieces each) around the arm;
* ``10^5-point cloud``: the box's top face as 400 x 250 points (2,048 pieces);
* ``cell (3 boxes)``: ``configs/examples/cell.yaml``;
* ``cell_shapes (1 box + 3 shapes)``: ``configs/examples/cell_shapes.yaml``.

For the capsule test and the cascade (capsules, then hulls; finger strokes enclosed): a first
call (compilation included), then the median of ``--repeats`` warm calls; intervals/s = 512 x
trajectories / warm median; compile = first call - warm median (reported apart). Ratios are
warm time over that of ``one box`` with the same enclosure, measured in this run. Then LARC (the
default method, the cascade) on the same trajectories: its warm median and its ratio to ``one
box``'s (LARC evaluates different intervals in each scene, so this ratio is per call, not per
interval). The 10^5-point cloud is culled per subtree of intervals (:mod:`larc_jax.engine.cull`).
Writes the JSON and ``results/bench/obstacles_cpu.md`` (the table the README quotes).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = ROOT / "configs" / "examples"
TABLE = ROOT / "results" / "bench" / "obstacles_cpu.md"
ENCLOSURES = (("capsules", "capsules", "fine"), ("cascade", "hull", "fine"), ("larc", "hull", "larc"))

__all__ = ["main", "scenes"]


def scenes() -> dict:
    """The benchmark's scenes by label (module docstring)."""
    from scipy.spatial.transform import Rotation

    from larc_jax.model.scene import Scene, read_scene
    from larc_jax.model.shapes import Shapes

    lo, hi = np.array([0.25, -0.3, -0.05]), np.array([0.6, 0.3, 0.0])
    centre, size = (lo + hi) / 2, hi - lo

    def shaped(kind, dims, R):
        return Scene(lo=np.zeros((0, 3)), hi=np.zeros((0, 3)), shapes=Shapes(
            kinds=(kind,), names=(kind,), dims=[dims], p_world_shape=[centre], R_world_shape=[R]))

    return {
        "one box": Scene(lo=[lo], hi=[hi], box_names=("table",)),
        "10 meshes": _meshes(),
        "10^5-point cloud": _cloud(),
        "one posed box": shaped("box", size, Rotation.from_euler("z", 30, degrees=True).as_matrix()),
        "one cylinder": shaped("cylinder", [size[0] / 4, size[2], 0.0], np.eye(3)),
        "cell (3 boxes)": read_scene(EXAMPLES / "cell.yaml"),
        "cell_shapes (1 box + 3 shapes)": read_scene(EXAMPLES / "cell_shapes.yaml"),
    }


def _meshes():
    """Ten L brackets (``experiments.example_cell``) on a circle of radius 0.45 m around the arm."""
    from larc_jax.model.point_sets import MESH_PIECE_TRIANGLES, PointSets, convex_pieces
    from larc_jax.model.scene import Scene

    from experiments.example_cell import bracket_mesh

    mesh = bracket_mesh()
    V, F = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    pieces, owner = [], []
    for k in range(10):
        a = 2 * np.pi * k / 10
        c, s = np.cos(a), np.sin(a)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        for piece in convex_pieces(V @ R.T + [0.45 * c, 0.45 * s, 0.0], F, MESH_PIECE_TRIANGLES):
            pieces.append(piece)
            owner.append(k)
    return Scene(lo=np.zeros((0, 3)), hi=np.zeros((0, 3)), point_sets=PointSets(
        kinds=("mesh",) * 10, names=tuple(f"bracket{k}" for k in range(10)), files=("",) * 10,
        file_sha256=("",) * 10, radius=(0.0,) * 10, pieces=tuple(pieces), owner=tuple(owner)))


def _cloud():
    """10^5 points: the table top of ``one box`` sampled on a grid, seen from above."""
    from larc_jax.model.point_sets import CLOUD_PIECE_POINTS, PointSets, convex_pieces
    from larc_jax.model.scene import Scene

    x, y = np.meshgrid(np.linspace(0.25, 0.6, 250), np.linspace(-0.3, 0.3, 400))
    P = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    pieces = convex_pieces(P, None, CLOUD_PIECE_POINTS)
    return Scene(lo=np.zeros((0, 3)), hi=np.zeros((0, 3)), point_sets=PointSets(
        kinds=("points",), names=("cloud",), files=("",), file_sha256=("",), radius=(0.0,),
        pieces=tuple(pieces), owner=(0,) * len(pieces)))


def _timed(fn):
    start = time.perf_counter()
    result = fn()
    return result, time.perf_counter() - start


def table(out: dict) -> str:
    lines = [f"Fixed-fine (512 intervals per trajectory) on {out['trajectories']} Stage B trajectories, one call, "
             f"then LARC (the default, with the cascade) on the same; warm median of {out['repeats']}; "
             f"{out['cpu_count']} CPU cores, load average "
             f"{out['load_average_start'][0]:.2f} at the start (`python -m experiments.bench_obstacles`).",
             "",
             "| scene | items | capsule test: intervals/s | time / one box | compile | cascade: intervals/s | time / one box | compile "
             "| LARC cascade: warm | time / one box | compile |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for label, row in out["scenes"].items():
        cells = [label, str(row["items"])]
        for name, _, method in ENCLOSURES:
            r = row[name]
            first = f"{r['warm_s']:.3f} s" if method == "larc" else f"{r['intervals_per_s']:,.0f}"
            cells += [first, f"{r['time_over_one_box']:.2f}x", f"{r['compile_s']:.1f} s"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    import jax

    import larc_jax as lj
    from experiments.bench import stageB_dataset
    from larc_jax.enclosure.robot_file import load_robot_file
    from larc_jax.io import atomic_write_json, atomic_write_text

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--json", help="write the figures as JSON (and the table next to the committed one)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--n", type=int, default=16, help="Stage B trajectories")
    args = p.parse_args(argv)
    robot, capsules = load_robot_file(None)
    trajs = stageB_dataset(robot)[0][: args.n]
    out = {"device": str(jax.devices()[0]), "machine": platform.processor() or platform.machine(),
           "cpu_count": os.cpu_count(), "load_average_start": os.getloadavg(), "trajectories": len(trajs),
           "repeats": args.repeats, "scenes": {}}
    for label, scene in scenes().items():
        row = {"items": scene.n_obstacles}
        for name, enclosure, method in ENCLOSURES:
            def call():
                return lj.certify(trajs, [scene] * len(trajs), robot, capsules, method=method, enclosure=enclosure)

            first, t_first = _timed(call)
            med = statistics.median(_timed(call)[1] for _ in range(args.repeats))
            evaluations = int(first.evaluations.sum())
            row[name] = dict(evaluations=evaluations, certified=int(first.certified.sum()), warm_s=med,
                             intervals_per_s=evaluations / med, compile_s=max(0.0, t_first - med))
            print(f"{label:32s} {name:9s} {evaluations / med:10,.0f} intervals/s  certified {row[name]['certified']:3d}  "
                  f"compile {row[name]['compile_s']:.1f} s", flush=True)
        out["scenes"][label] = row
    for label, row in out["scenes"].items():
        for name, _, _ in ENCLOSURES:
            row[name]["time_over_one_box"] = row[name]["warm_s"] / out["scenes"]["one box"][name]["warm_s"]
    out["load_average_end"] = os.getloadavg()
    print(table(out))
    if args.json:
        atomic_write_json(args.json, out)
        atomic_write_text(Path(args.json).with_suffix(".md"), table(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
