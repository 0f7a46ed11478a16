"""One benchmark measurement in a fresh process: peak RSS while certifying N Stage B-like
trajectories (see :func:`experiments.bench.stageB_like`).

    python -m experiments.bench_rss --n 100000 --mode call|stream

``call``: the N trajectories are built in memory and certified in ONE ``certify`` call;
``stream``: they are generated lazily and certified with ``certify_stream`` (chunks of 256).
Prints one JSON line: ``{n, mode, s, peak_rss_mb, certified, evaluations}`` (peak RSS of the
whole process: Python, JAX, inputs, results; :func:`peak_rss_mb`).
"""

from __future__ import annotations

import argparse
import json
import resource
import time


def peak_rss_mb() -> float:
    """This process's peak resident memory, MB: ``VmHWM`` of ``/proc/self/status`` on Linux.
    Not ``getrusage``'s ``ru_maxrss``: Linux carries it across ``exec``, so a process started by
    a large one (the benchmark, holding GBs) reports its parent's peak (measured: 3,834 MB for
    every N)."""
    try:
        for line in open("/proc/self/status", encoding="ascii"):
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024  # kB
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # kB on Linux, elsewhere a bound


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, required=True)
    p.add_argument("--mode", choices=("call", "stream"), default="call")
    args = p.parse_args(argv)

    import larc_jax as lj
    from experiments.bench import ENCLOSURE, stageB_dataset, stageB_like

    robot = lj.load_robot()
    capsules = lj.load_capsules(lj.default_capsule_path(), robot)
    base, scenes = stageB_dataset(robot)
    start = time.perf_counter()
    pairs = stageB_like(robot, base, scenes, args.n, seed=3)
    certified = evaluations = 0
    if args.mode == "call":
        trajs, sc = zip(*pairs)
        res = lj.certify(list(trajs), list(sc), robot, capsules, enclosure=ENCLOSURE)
        certified, evaluations = int(res.certified.sum()), int(res.evaluations.sum())
    else:
        for chunk in lj.certify_stream(pairs, robot, capsules, enclosure=ENCLOSURE):
            certified += int(chunk.certified.sum())
            evaluations += int(chunk.evaluations.sum())
    dt = time.perf_counter() - start
    peak_mb = peak_rss_mb()
    print(json.dumps(dict(n=args.n, mode=args.mode, s=dt, peak_rss_mb=peak_mb, certified=certified,
                          evaluations=evaluations)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
