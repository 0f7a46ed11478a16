"""Benchmark: the device tree (:mod:`larc_jax.engine.tree`) against the host frontier (issue 20).

    python -m experiments.bench_tree [--json results/bench/tree_cpu.json] [--every 10] [--repeats 5] [--cpus N]

The committed Stage B set, float64, with the capsule test and with the cascade (the default: the
hull stage after the capsule test, :mod:`larc_jax.engine.tree_hull` on the device), one prepared
batch per run, so that only the scheduler differs (``certify``'s own work around it, the same for
all, is left out):

* **whole set** (160 trajectories in one call): the host frontier (``larc``'s scheduler today,
  one kernel call per depth), the device tree (one program), and fixed-fine (512 intervals a
  trajectory); first call (compiling: each scheduler's own shapes; the host frontier's and fine's
  kernel shapes overlap, so fine's first call is measured after LARC's) and the best of
  ``--repeats`` warm calls;
* **one trajectory per call** (every ``--every``-th trajectory): the median over the trajectories
  of each one's median warm call, per scheduler; for the device tree also the steps its loop runs
  (:attr:`~larc_jax.engine.tree.TreeLeaves.steps`, and of them the cascade's hull steps), a call
  on the root alone (its first-stage step, and a hull step where the cascade sends the root to the
  hull stage: what a call costs whatever its work) and the time of each further step (the call
  less that, over the steps less the root call's), which is what one trajectory's time grows with;
* **agreement**: the device tree's evaluations per depth and trajectory, its leaves (trajectory,
  depth, index, ends) and decisions against the host frontier's, and the largest difference of a
  leaf's clearance (XLA compiles the kernel inside the loop with its own fusions).

``--cpus N`` runs the process on its first N CPUs (set before JAX starts, so XLA's thread pool
has N threads): the committed runs are on both cores of this machine (``tree_cpu``) and on one
(``tree_cpu1``), which tells how much of a scheduler's speed is XLA's parallelism across cores.

Writes the JSON and the Markdown table beside it (the tables the README quotes).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
MAX_DEPTH = 9


def _timed(fn):
    t = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t


def _schedulers(batch, scenes, n: int):
    """Each scheduler on ``batch`` (prepared from ``n`` trajectories in ``scenes``): a call
    returning its result."""
    from larc_jax.engine.certify import _Names, _fixed, _larc_batched  # noqa: PLC2701 - the benchmark measures internals
    from larc_jax.engine.tree import run_tree

    names = _Names(scenes)
    return {
        "host frontier": lambda: _larc_batched(batch, n, names, MAX_DEPTH, None),
        "device tree": lambda: run_tree(batch, n, MAX_DEPTH),
        "fixed-fine": lambda: _fixed(batch, n, names, MAX_DEPTH, MAX_DEPTH, None),
    }


ENCLOSURES = {"capsules": "capsule test", "hull": "cascade"}
"""The enclosures measured (``RunSpec.enclosure``) and their names in the table."""


def _batch(robot, capsules, trajs, scenes, enclosure: str):
    """The trajectories prepared as ``certify`` prepares them for ``enclosure``."""
    from larc_jax.engine.batch import prepare
    from larc_jax.engine.certify import run_spec
    from larc_jax.leaf.interval import trajectory_roundings
    from larc_jax.leaf.reference import leaf_enclosures

    spec = run_spec(enclosure=enclosure)
    enc = leaf_enclosures(robot, capsules.with_padding(spec.padding_m), enclosure, None, None, False)
    bounds = trajectory_roundings(trajs, robot, enc.capsules, np.float64, enc.hulls)
    return prepare(trajs, scenes, robot, enc.capsules, spec.margin_m, np.float64, bounds, None, hulls=enc.hulls)


def agreement(host, tree) -> dict:
    """How the device tree's result compares with the host frontier's."""
    frontier, leaves = host
    same_nodes = all(np.array_equal(getattr(tree, f), getattr(leaves, f)) for f in ("traj", "depth", "index", "t0", "t1"))
    g_host, g_tree = leaves.clearance_m, tree.record.clearance_m
    finite = np.isfinite(g_host) & np.isfinite(g_tree)
    same = (g_host == g_tree) | (np.isnan(g_host) & np.isnan(g_tree))  # +-inf equal as values; NaN with NaN
    return {
        "evaluations": int(frontier.sum()), "evaluations_equal": bool(np.array_equal(frontier, tree.frontier)),
        "leaves": len(leaves), "leaves_equal": bool(same_nodes and len(leaves) == len(tree.traj)),
        "decisions_equal": bool(same_nodes and np.array_equal(leaves.certified, tree.record.stage > 0)),
        "guards_equal": bool(same_nodes and np.array_equal(leaves.guard_m, tree.record.guard_m)),
        "clearance_bit_identical": int(np.sum(same)),
        "clearance_max_abs_diff_m": float(np.max(np.abs(g_host[finite] - g_tree[finite]), initial=0.0)),
    }


def table(out: dict) -> str:
    rows = [f"Stage B: {out['trajectories']} trajectories, float64, JAX device `{out['device']}`, "
            f"{out['cpu_count']} CPU {'core' if out['cpu_count'] == 1 else 'cores'}, one run:"]
    for enclosure, label in ENCLOSURES.items():
        run = out[enclosure]
        w, p, a = run["whole_set"], run["paired"], run["agreement"]
        names = list(w)
        rows += [
            "",
            f"| {label} | " + " | ".join(names) + " |",
            "|---|" + "---|" * len(names),
            "| whole set: warm call | " + " | ".join(f"{w[m]['warm_s']:.3f} s" for m in names) + " |",
            "| whole set: first call (compiling) | " + " | ".join(f"{w[m]['first_s']:.1f} s" for m in names) + " |",
            f"| one trajectory per call ({p['n']}): median | " + " | ".join(f"{p[m]:.2f} ms" for m in names) + " |",
            "",
            f"{label.capitalize()}, device tree, one trajectory per call (medians): {p['tree_steps']:.0f} steps of its "
            f"loop, {p['tree_hull_steps']:.0f} of them hull steps; a call on the root alone (the call's fixed cost: "
            f"{p['tree_root_steps']:.0f} {'step' if p['tree_root_steps'] == 1 else 'steps'} on one interval) "
            f"{p['tree_root_ms']:.2f} ms; each further step {p['tree_us_per_step']:.0f} µs.",
            "",
            f"{label.capitalize()}, device tree against the host frontier: evaluations {a['evaluations']:,} "
            f"({'equal' if a['evaluations_equal'] else 'DIFFERENT'} per trajectory and depth); leaves {a['leaves']:,} "
            f"({'the same intervals' if a['leaves_equal'] else 'DIFFERENT intervals'}, decisions "
            f"{'equal' if a['decisions_equal'] else 'DIFFERENT'}, guards {'equal' if a['guards_equal'] else 'DIFFERENT'}); "
            f"clearance bit-identical on {a['clearance_bit_identical']:,} leaves, elsewhere within "
            f"{a['clearance_max_abs_diff_m']:.1e} m.",
        ]
    return "\n".join(rows) + "\n"


def _machine() -> dict:
    import jax

    return dict(device=str(jax.devices()[0]), machine=platform.processor() or platform.machine(),
                cpu_count=len(os.sched_getaffinity(0)), load_average_start=os.getloadavg())


def _measure(robot, capsules, trajs, scenes, enclosure: str, args) -> dict:
    """The three schedulers on the whole set and one trajectory per call (the device tree's steps,
    its call on the root alone and its time per further step beside), and the agreement."""
    from larc_jax.engine.tree import run_tree

    out = {"whole_set": {}}
    batch = _batch(robot, capsules, trajs, scenes, enclosure)
    results = {}
    for name, call in _schedulers(batch, scenes, len(trajs)).items():
        results[name], first = _timed(call)
        warm = min(_timed(call)[1] for _ in range(args.repeats))
        out["whole_set"][name] = {"first_s": first, "warm_s": warm}
        print(f"{enclosure:8s} {name:14s} whole set: warm {warm:.3f} s, first call {first:.1f} s", flush=True)
    out["agreement"] = agreement(results["host frontier"], results["device tree"])
    per = {name: [] for name in out["whole_set"]}
    steps, hull_steps, floor, root_steps = [], [], [], []
    picked = list(range(0, len(trajs), args.every))
    for k in picked:
        one = _batch(robot, capsules, trajs[k:k + 1], scenes[k:k + 1], enclosure)
        for name, call in _schedulers(one, scenes[k:k + 1], 1).items():
            first = call()
            if name == "device tree":
                steps.append(first.steps)
                hull_steps.append(first.hull_steps)
            per[name].append(1e3 * statistics.median(_timed(call)[1] for _ in range(args.repeats)))
        root = lambda: run_tree(one, 1, 0)  # noqa: E731 - the root alone: the call's fixed cost
        root_steps.append(root().steps)  # its first-stage step, and a hull step where it goes to the hull stage
        floor.append(1e3 * statistics.median(_timed(root)[1] for _ in range(args.repeats)))
    out["paired"] = {"n": len(picked), **{name: statistics.median(v) for name, v in per.items()},
                     "tree_steps": statistics.median(steps), "tree_hull_steps": statistics.median(hull_steps),
                     "tree_root_ms": statistics.median(floor), "tree_root_steps": statistics.median(root_steps),
                     "tree_us_per_step": statistics.median(
                         1e3 * (ms - f) / max(1, s - r) for ms, f, s, r in zip(per["device tree"], floor, steps,
                                                                                root_steps))}
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", help="write the figures as JSON (and the table beside it)")
    parser.add_argument("--repeats", type=int, default=5, help="warm calls per measurement")
    parser.add_argument("--every", type=int, default=10, help="one trajectory per call: every EVERY-th trajectory")
    parser.add_argument("--cpus", type=int, help="run on the first CPUS CPUs of this process's affinity")
    args = parser.parse_args(argv)
    if args.cpus is not None:
        allowed = sorted(os.sched_getaffinity(0))
        if not 1 <= args.cpus <= len(allowed):
            parser.error(f"--cpus {args.cpus}: this process may use 1 to {len(allowed)} CPUs")
        if "jax" in sys.modules and args.cpus < len(allowed):
            parser.error("--cpus: JAX is already loaded in this process (its thread pool is sized)")
        os.sched_setaffinity(0, allowed[: args.cpus])
    from experiments.bench import stageB_dataset
    from larc_jax.enclosure.robot_file import load_robot_file
    from larc_jax.io import atomic_write_json, atomic_write_text

    robot, capsules = load_robot_file(None)
    trajs, scenes = stageB_dataset(robot)
    out = {**_machine(), "trajectories": len(trajs), "repeats": args.repeats}
    for enclosure in ENCLOSURES:
        out[enclosure] = _measure(robot, capsules, trajs, scenes, enclosure, args)
    out["load_average_end"] = os.getloadavg()
    text = table(out)
    print(text)
    if args.json:  # the figures, then the table rendered from them
        for path, write, data in ((Path(args.json), atomic_write_json, out),
                                  (Path(args.json).with_suffix(".md"), atomic_write_text, text)):
            write(path, data)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
