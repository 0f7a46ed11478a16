"""The device tree on every CPU core: one batch's trajectories dealt to worker threads.

The device tree (:mod:`larc_jax.engine.tree`) is one XLA program of ``while`` loops, and XLA's
CPU backend runs a loop's small steps (256 intervals at most) on the thread that runs the
program: the program does not spread over the cores as the host frontier's large calls do
(``results/bench/tree_cpu*.md``: the Stage B set's capsule test took the tree 0.127 s on two
cores and 0.132 s on one, the host frontier 0.101 s and 0.134 s). Measured while developing
(Stage B, 160 trajectories, 2 CPU cores, best of 5 warm calls): the tree took 0.121 s for the
capsule test against the host frontier's 0.084 s, and its two halves, prepared as two batches and
run at once on two threads, 0.078 s; the cascade 0.220 s alone, 0.178 s on two threads, the host
frontier 0.182 s.

:func:`run_tree_pool` deals the trajectories round-robin to ``workers`` threads; each runs
:func:`~larc_jax.engine.tree.run_tree` on the same prepared batch (one device copy) seeded with its
trajectories, and the same compiled program (its buffers are sized by the batch, not by the
seeds), compiled once before the threads start. Each interval's test depends on that interval
alone, and each trajectory's tree on its own intervals, so the leaves, decisions and evaluation
counts do not depend on the dealing; the leaves are merged in the order the tree returns them
(by trajectory, then time).
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..lazy_jax import jax
from ..leaf.record import LeafRecord
from .tree import TreeLeaves, run_tree, supports

__all__ = ["run_tree_pool", "tree_workers", "uses_tree", "small_batches_on_tree", "TREE_FROM_TRAJECTORIES"]

TREE_FROM_TRAJECTORIES = 16
"""``certify``'s LARC runs the device tree on a batch of at least this many trajectories
(:func:`uses_tree`), the host frontier (:mod:`larc_jax.engine.certify`) on a smaller one. The
tree is one large program per batch class, compiled (or, with the persistent cache on, loaded)
once per process, where the host frontier's kernels are small: with the tree, the README example
(two trajectories, the cascade) took a fresh process 25.7 s with an empty cache and 7.1 s with a
warm one (2 CPU cores, the test suite running beside it), against 6.5 s and 1.9 s with the host
frontier (README, "Cold start"). From 16 trajectories the tree's first call costs less than the
host frontier's and its warm calls about the same (Stage B trajectories, capsules, 2 CPU cores,
the test suite running beside it; first calls tree / host 14.5 / 18.6 s for 16, 15.6 / 24.0 s for
32, 15.8 / 25.5 s for 64; warm, median of alternating rounds, host / tree 0.98, 0.91, 0.99).
A process that certifies one trajectory per call for a while runs small batches on the tree too
after :func:`~larc_jax.engine.warm_up.warm_up_tree` (:func:`small_batches_on_tree`)."""


_SMALL_ON_TREE = threading.Event()
"""Set: this process runs small batches on the tree too (:func:`small_batches_on_tree`)."""


def small_batches_on_tree(on: bool | None = None) -> bool:
    """Whether ``certify``'s LARC runs a batch smaller than :data:`TREE_FROM_TRAJECTORIES` on the
    device tree in this process (default: no, the host frontier; :func:`~larc_jax.engine.warm_up.warm_up_tree`
    turns it on); with ``on``, set it. Returns the setting it found. Decisions, leaves and
    evaluations do not depend on it (a clearance may differ in its last bits, far inside its
    guard: :mod:`larc_jax.engine.tree`); only the time does: one trajectory per call, the tree
    takes a fraction of the host frontier's warm time, after a first call that compiles it
    (README, "One trajectory per call")."""
    was = _SMALL_ON_TREE.is_set()
    if on is not None:
        (_SMALL_ON_TREE.set if on else _SMALL_ON_TREE.clear)()
    return was


def uses_tree(batch, n_traj: int) -> bool:
    """Whether ``certify``'s LARC runs ``batch`` (its first ``n_traj`` trajectories) on the device
    tree: one it :func:`~larc_jax.engine.tree.supports`, of at least :data:`TREE_FROM_TRAJECTORIES`
    (or of any size after :func:`small_batches_on_tree`)."""
    return (n_traj >= TREE_FROM_TRAJECTORIES or _SMALL_ON_TREE.is_set()) and supports(batch)


def tree_workers(batch, n_traj: int) -> int:
    """Threads for ``batch``: the CPUs this process may run on (XLA's CPU thread pool is sized by
    them), at most one per trajectory; one on an accelerator, whose own cores run a step's lanes
    (not measured there)."""
    if (batch.devices or jax.devices())[0].platform != "cpu":
        return 1
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, min(cpus, n_traj))


def run_tree_pool(batch, n_traj: int, max_depth: int, on_compile=None, progress=None,
                  workers: int | None = None) -> TreeLeaves:
    """:func:`~larc_jax.engine.tree.run_tree` on the first ``n_traj`` trajectories of ``batch``,
    dealt to ``workers`` threads (None: :func:`tree_workers`); the same result as one thread."""
    workers = tree_workers(batch, n_traj) if workers is None else max(1, min(int(workers), n_traj))
    if workers == 1:
        return run_tree(batch, n_traj, max_depth, on_compile, progress=progress)
    run_tree(batch, n_traj, max_depth, on_compile, seeds=np.empty(0, np.int32))  # compile once, here
    lock = threading.Lock()

    def told(n: int) -> None:  # progress from the threads, one at a time
        with lock:
            progress(n)

    def work(k: int) -> TreeLeaves:
        return run_tree(batch, n_traj, max_depth, seeds=np.arange(k, n_traj, workers, dtype=np.int32),
                        progress=None if progress is None else told)

    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="larc-tree") as pool:
        parts = list(pool.map(work, range(workers)))
    return merge_tree_leaves(parts)


def merge_tree_leaves(parts: list[TreeLeaves]) -> TreeLeaves:
    """Leaves of disjoint trajectory sets as one :class:`TreeLeaves`, sorted by trajectory, then time."""
    cat = lambda f: np.concatenate([f(p) for p in parts])  # noqa: E731
    order = np.lexsort((cat(lambda p: p.t0), cat(lambda p: p.traj)))
    record = LeafRecord(*(np.concatenate(column)[order] for column in zip(*(p.record for p in parts))))
    return TreeLeaves(*(cat(lambda p, f=f: getattr(p, f))[order] for f in ("traj", "depth", "index", "t0", "t1")),
                      record, sum(p.frontier for p in parts), sum(p.calls for p in parts),
                      sum(p.steps for p in parts), sum(p.hull_steps for p in parts), sum(p.again for p in parts))
