"""Benchmark: batched LARC vs fixed-fine vs the NumPy reference on synthetic window trajectories.

    python -m experiments.bench [--n 160] [--json results/bench/bench.json]

Prints, from one run: interval evaluations per second, compile time (first call minus a warm
call, reported separately), whole-set times and the reference/LARC speed ratio.
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import jax
import numpy as np

from larc_jax.enclosure import default_capsule_path, load_capsules
from larc_jax.certify import certify
from larc_jax.io import atomic_write_json
from larc_jax.urdf import load_robot
from larc_jax.scene import Scene
from larc_jax.trajectory import Trajectory

# A wall at x = 0.30..0.34 m in front of the arm with a 0.30 m wide, 0.25 m high opening.
WINDOW = Scene(
    lo=np.array([[0.30, -0.60, -0.05], [0.30, 0.15, -0.05], [0.30, -0.15, -0.05], [0.30, -0.15, 0.40]]),
    hi=np.array([[0.34, -0.15, 0.70], [0.34, 0.60, 0.70], [0.34, 0.15, 0.15], [0.34, 0.15, 0.70]]),
    box_names=("left", "right", "sill", "lintel"), name="bench_window",
)


def synthetic_trajectories(robot, n: int, seed: int = 0) -> list[Trajectory]:
    """Smooth multi-waypoint trajectories (quadratic Bezier between random configurations,
    finite-difference velocities), 2-6 s long, 5-40 waypoints; one in four faces the window."""
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(robot.q_lower), np.asarray(robot.q_upper)
    mid, half = (lo + hi) / 2, (hi - lo) / 2
    out = []
    for k in range(n):
        K = int(rng.integers(5, 41))
        T = rng.uniform(2.0, 6.0)
        t = np.linspace(0.0, T, K)
        ends = mid + half * rng.uniform(-0.7, 0.7, (3, robot.n_joints))
        if k % 4:  # three in four work beside/behind the base, away from the wall (x > 0.3)
            ends[:, 0] = rng.choice([-1.0, 1.0]) * rng.uniform(1.5, 2.5, 3)
        u = np.linspace(0, 1, K)[:, None]
        q = (1 - u) ** 2 * ends[0] + 2 * u * (1 - u) * ends[1] + u**2 * ends[2]
        qd = np.gradient(q, t, axis=0)
        out.append(Trajectory(t=t, q=q, qd=qd, joint_names=robot.active_joint_names, id=f"bench{k:03d}"))
    return out


def timed(fn):
    start = time.perf_counter()
    result = fn()
    return result, time.perf_counter() - start


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=160, help="number of trajectories (default 160)")
    p.add_argument("--json", help="write the figures as JSON")
    p.add_argument("--skip-reference", action="store_true", help="do not run the slow reference")
    args = p.parse_args(argv)

    robot = load_robot()
    capsules = load_capsules(default_capsule_path(), robot)
    trajs = synthetic_trajectories(robot, args.n)

    def run(method):
        return certify(trajs, WINDOW, robot, capsules, method=method)

    larc_first, t_larc_first = timed(lambda: run("larc"))
    larc, t_larc = timed(lambda: run("larc"))
    fine_first, t_fine_first = timed(lambda: run("fine"))
    fine, t_fine = timed(lambda: run("fine"))
    evals_larc = sum(r.evaluations for r in larc)
    evals_fine = sum(r.evaluations for r in fine)
    out = {
        "n_trajectories": len(trajs),
        "device": str(jax.devices()[0]),
        "machine": platform.processor() or platform.machine(),
        "larc_certified": sum(r.certified for r in larc),
        "fine_certified": sum(r.certified for r in fine),
        "larc_evaluations": evals_larc,
        "fine_evaluations": evals_fine,
        "larc_compile_s": max(0.0, t_larc_first - t_larc),
        "larc_set_s": t_larc,
        "larc_interval_evals_per_s": evals_larc / t_larc,
        "fine_compile_s": max(0.0, t_fine_first - t_fine),
        "fine_set_s": t_fine,
        "fine_interval_evals_per_s": evals_fine / t_fine,
        "larc_frontier_sizes": list(larc.frontier_sizes),
    }
    if not args.skip_reference:
        ref, t_ref = timed(lambda: run("reference"))
        assert [r.evaluations for r in ref] == [r.evaluations for r in larc]
        assert [r.certified for r in ref] == [r.certified for r in larc]
        out.update(reference_set_s=t_ref, reference_interval_evals_per_s=evals_larc / t_ref,
                   speedup_reference_over_larc=t_ref / t_larc)
    out["speedup_fine_over_larc"] = t_fine / t_larc
    for k, v in out.items():
        print(f"{k:32s} {v:.4g}" if isinstance(v, float) else f"{k:32s} {v}")
    if args.json:
        atomic_write_json(args.json, out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
