"""Benchmark: what the enclosure cascade costs against today's capsule test, per trajectory.

    python -m experiments.bench_cascade [--json results/bench/bench_cascade.json] [--single 30]

Two datasets: the planned trajectories of ``results/tightness`` (next to obstacles, where the
capsule test fails most; run ``python -m experiments.tightness`` first) and the Stage B
trajectories with their scenes (:func:`experiments.bench.stageB_dataset`). For each, three certificate configurations at depth 9, margin
10 mm: ``capsules`` (today's: the capsule test, finger strokes enclosed), ``cascade`` (capsules
then hulls, finger strokes enclosed: the new default without ``--hold``) and
``cascade_stated`` (the cascade with the gripper opening stated, ``--hold joint7=0 --hold
joint8=0``). Timed, in one run on this machine:

* the whole dataset in one call: a first call (compilation included), then the median of
  ``--repeats`` warm calls; compile time = first call - warm median (reported separately);
* one trajectory per call, for the first ``--single`` trajectories: a warm-up pass, then the
  median over ``--repeats`` passes of the summed time (what a user certifying plans one by one
  pays).

Ratios are cascade / capsules of the warm times. The load average of the machine is recorded
(other jobs share its two cores).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = (("capsules", "capsules", False), ("cascade", "hull", False), ("cascade_stated", "hull", True))
HOLD = {"joint7": 0.0, "joint8": 0.0}

__all__ = ["main"]


def _datasets(n_synthetic: int):
    import dataclasses

    from experiments.bench import stageB_dataset
    from larc_jax.model.scene import read_scene
    from larc_jax.model.trajectory_files import read_trajectory
    from larc_jax.model.urdf import load_robot

    robot = load_robot()
    out = {}
    plan = ROOT / "results" / "tightness" / "dataset"
    files = sorted(plan.glob("pad*/trajectories/*/*_ompl_planned.yaml"))
    if files:
        from experiments import generate as gen

        config = gen.load_config(ROOT / "configs" / "stageB.yaml")
        scenes = {s: read_scene(ROOT / c["file"]) for s, c in config["scenes"].items()}
        trajs = [dataclasses.replace(read_trajectory(f, robot), id=f"{f.parent.parent.parent.name}_{f.stem}")
                 for f in files]
        out["tightness"] = (trajs, [scenes[f.parent.name] for f in files])
    trajs, scenes = stageB_dataset(robot)
    out["stageB"] = (trajs[:n_synthetic], scenes[:n_synthetic])
    return out


def _timed(fn):
    start = time.perf_counter()
    result = fn()
    return result, time.perf_counter() - start


def main(argv=None) -> int:
    import jax

    import larc_jax as lj
    from larc_jax.enclosure.robot_file import load_robot_file
    from larc_jax.io import atomic_write_json

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--json", help="write the figures as JSON")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--single", type=int, default=30, help="trajectories timed one per call")
    p.add_argument("--n-synthetic", type=int, default=160, help="Stage B trajectories used")
    args = p.parse_args(argv)
    out = {"device": str(jax.devices()[0]), "machine": platform.processor() or platform.machine(),
           "cpu_count": os.cpu_count(), "load_average_start": os.getloadavg(), "datasets": {}}
    for name, (trajs, scenes) in _datasets(args.n_synthetic).items():
        rows = {}
        for cname, enclosure, stated in CONFIGS:
            robot, capsules = load_robot_file(None, hold=HOLD if stated else None)
            trajs_r = [lj.Trajectory(t=t.t, q=t.q, qd=t.qd, joint_names=t.joint_names, id=t.id) for t in trajs]

            def call(ts=trajs_r, sc=scenes):
                return lj.certify(ts, sc, robot, capsules, max_depth=9, enclosure=enclosure)

            first, t_first = _timed(call)
            warm = [_timed(call)[1] for _ in range(args.repeats)]
            med = statistics.median(warm)
            single = trajs_r[: args.single]
            for t, s in zip(single, scenes):  # warm-up: every shape compiled
                lj.certify([t], [s], robot, capsules, max_depth=9, enclosure=enclosure)
            passes = []
            for _ in range(args.repeats):
                _, dt = _timed(lambda: [lj.certify([t], [s], robot, capsules, max_depth=9, enclosure=enclosure)
                                        for t, s in zip(single, scenes)])
                passes.append(dt)
            rows[cname] = dict(
                trajectories=len(trajs), certified=int(first.certified.sum()), evaluations=int(first.evaluations.sum()),
                hull_leaves=int((first.leaves.stage == 2).sum()), first_call_s=t_first,
                compile_s=max(0.0, t_first - med), batch_s_median=med, batch_ms_per_trajectory=1e3 * med / len(trajs),
                single_trajectories=len(single), single_ms_per_trajectory=1e3 * statistics.median(passes) / len(single))
            print(f"{name:17s} {cname:15s} certified {rows[cname]['certified']:3d}/{len(trajs)}  "
                  f"evals {rows[cname]['evaluations']:7d}  batch {1e3 * med / len(trajs):7.2f} ms/traj  "
                  f"one-by-one {rows[cname]['single_ms_per_trajectory']:7.2f} ms/traj  compile {rows[cname]['compile_s']:.1f} s",
                  flush=True)
        for cname in ("cascade", "cascade_stated"):
            rows[f"{cname}_over_capsules_batch"] = rows[cname]["batch_s_median"] / rows["capsules"]["batch_s_median"]
            rows[f"{cname}_over_capsules_single"] = (rows[cname]["single_ms_per_trajectory"]
                                                     / rows["capsules"]["single_ms_per_trajectory"])
            print(f"{name:17s} {cname} / capsules: batch {rows[f'{cname}_over_capsules_batch']:.2f}x, "
                  f"one-by-one {rows[f'{cname}_over_capsules_single']:.2f}x", flush=True)
        out["datasets"][name] = rows
    out["load_average_end"] = os.getloadavg()
    if args.json:
        atomic_write_json(args.json, out)
    print(json.dumps({k: v for k, v in out.items() if k != "datasets"}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
