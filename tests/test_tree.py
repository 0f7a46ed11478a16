"""The device tree (larc_jax.engine.tree) against the host frontier: the same intervals, leaves and
decisions; its time ends against the NumPy dyadic ends, bit for bit."""

from __future__ import annotations

import collections
import dataclasses

import numpy as np
import pytest

from larc_jax.engine.batch import prepare
from larc_jax.engine.certify import _Names, _larc_batched, run_spec  # noqa: PLC2701 - the host frontier is the reference
from larc_jax.engine.tree import (NARROW_STEP, SPECULATION_LEVELS, WIDE_STEP, dyadic_ends_jnp, rebase_ends_jnp,
                                  run_tree, supports)
from larc_jax.leaf.interval import dyadic_ends, rebase_ends, trajectory_roundings
from larc_jax.leaf.self_collision import curve_ranges, load_separation, self_pairs
from larc_jax.model.scene import Scene

from .test_certify import random_scene, random_trajectory

MAX_DEPTH = 9
SMALL = dict(wide=32, narrow=4, leaf_capacity=64)
"""Buffers small enough that a run needs many calls (the continuation path)."""


def _batch(robot, capsules, trajs, scenes, dtype=np.float64, self_collision=False):
    """The trajectories prepared as ``certify`` prepares them (with the self test's pairs, and the
    pairs proven apart for each trajectory, when ``self_collision``)."""
    spec = run_spec(enclosure="capsules", self_collision=self_collision)
    caps = capsules.with_padding(spec.padding_m)
    bounds = trajectory_roundings(trajs, robot, caps, dtype, None)
    pairs = skips = None
    if self_collision:
        pairs = self_pairs(robot, caps, spec.self_margin_m, spec.self_skip, proven=load_separation(robot))
        skips = [pairs.skip_mask(*curve_ranges(t, None)) for t in trajs]
    batch = prepare(trajs, scenes, robot, caps, spec.margin_m, dtype, bounds, None, self_pairs=pairs, self_skip=skips)
    return batch, _Names(scenes)


def _compare(batch, names, n, tree, ulps: float, max_depth: int = MAX_DEPTH, hull_m: float = 0.0):
    """The tree's leaves are the host frontier's, interval for interval, with the same decisions;
    the clearance agrees to ``ulps`` units in the last place of the pair's shell (XLA compiles
    the kernel inside the loop with its own fusions: the same bound, rounded within its guard),
    a leaf the capsule stage did not pass to ``hull_m`` (the hull stage may have recorded it: its
    GJK search takes a few dozen operations more)."""
    frontier, leaves = _larc_batched(batch, n, names, max_depth, None)
    assert np.array_equal(tree.frontier, frontier)
    for field in ("traj", "depth", "index", "t0", "t1"):
        assert np.array_equal(getattr(tree, field), getattr(leaves, field)), field
    rec = tree.record
    assert np.array_equal(rec.stage > 0, leaves.certified) and np.array_equal(rec.stage, leaves.stage)
    assert np.array_equal(rec.guard_m, leaves.guard_m)
    assert np.array_equal(rec.other, leaves.other_capsule)
    assert np.array_equal(np.where(leaves.capsule >= 0, rec.capsule, -1), leaves.capsule)  # -1: nothing to hit
    assert np.array_equal(np.isnan(rec.clearance_m), np.isnan(leaves.clearance_m))
    both = np.isfinite(leaves.clearance_m)
    assert np.array_equal(np.isinf(rec.clearance_m), np.isinf(leaves.clearance_m))
    scale = np.maximum(1.0, np.abs(leaves.clearance_m[both]))
    tol = np.where(leaves.stage[both] != 1, np.maximum(hull_m, ulps * np.finfo(np.float64).eps * scale),
                   ulps * np.finfo(np.float64).eps * scale)
    assert np.all(np.abs(rec.clearance_m[both] - leaves.clearance_m[both]) <= tol)
    return frontier


@pytest.fixture(scope="module")
def random_set(robot):
    rng = np.random.default_rng(11)
    trajs = [random_trajectory(rng, robot, k) for k in range(12)]
    scenes = [random_scene(rng, k, max_boxes=6) for k in range(12)]
    return trajs, scenes


def test_tree_matches_host_frontier_on_random_set(robot, capsules, random_set):
    trajs, scenes = random_set
    batch, names = _batch(robot, capsules, trajs, scenes)
    assert supports(batch)
    tree = run_tree(batch, len(trajs), MAX_DEPTH)
    frontier = _compare(batch, names, len(trajs), tree, ulps=8)
    assert tree.calls == 1 and frontier[:, MAX_DEPTH].sum() > 0  # some trajectory reached the deepest level
    assert 0 < (tree.record.stage > 0).mean() < 1
    assert tree.steps == _steps(len(trajs), tree) and tree.hull_steps == 0  # no hull queue without the cascade


def test_tree_pool_deals_trajectories_to_threads(robot, capsules, random_set, monkeypatch):
    """Dealt round-robin to three threads, the tree gives what one thread gives, bit for bit (the
    same program on the same batch); its progress counts every evaluation; and ``certify``'s
    LARC runs it from :data:`TREE_FROM_TRAJECTORIES` trajectories (its leaves are the pool's)."""
    import larc_jax
    import larc_jax.engine.tree_pool as pool_module
    from larc_jax.engine.tree_pool import run_tree_pool, tree_workers, uses_tree

    trajs, scenes = random_set
    batch, names = _batch(robot, capsules, trajs, scenes)
    one = run_tree(batch, len(trajs), MAX_DEPTH)
    told, compiled = [], []
    pool = run_tree_pool(batch, len(trajs), MAX_DEPTH, compiled.append, told.append, workers=3)
    for field in ("traj", "depth", "index", "t0", "t1", "frontier"):
        assert np.array_equal(getattr(pool, field), getattr(one, field)), field
    for a, b in zip(pool.record, one.record):
        assert np.array_equal(a, b, equal_nan=np.asarray(a).dtype.kind == "f")
    assert pool.calls >= 3 and sum(told) == one.frontier.sum() and compiled in ([], [True, False])
    assert 1 <= tree_workers(batch, 1) == 1 <= tree_workers(batch, len(trajs)) <= len(trajs)
    assert not uses_tree(batch, len(trajs)) and uses_tree(batch, pool_module.TREE_FROM_TRAJECTORIES)
    monkeypatch.setattr(pool_module, "TREE_FROM_TRAJECTORIES", len(trajs))
    result = larc_jax.certify(trajs, scenes, robot, capsules, enclosure="capsules")
    assert np.array_equal(result.leaves.clearance_m, one.record.clearance_m, equal_nan=True)
    assert np.array_equal(result.frontier, one.frontier) and np.array_equal(result.leaves.t0, one.t0)


def _steps(n_traj: int, tree, wide: int = WIDE_STEP, narrow: int = NARROW_STEP,
           levels: int = SPECULATION_LEVELS) -> int:
    """The steps one call of the tree takes, replayed on the host from its leaves (an evaluated
    interval that is not a leaf was bisected): each step pops the top ``wide`` intervals of the
    stack (``narrow`` while it holds fewer than ``wide // 2``); a step that pops them all and has
    room for them and their descendants ``L`` levels down (``L <= levels``, the most
    that fit) settles those levels too; the open intervals of the last level it settled push
    both children, in order."""
    leaves = set(zip(tree.traj.tolist(), tree.depth.tolist(), tree.index.tolist()))
    stack, steps = [(k, 0, 0) for k in range(n_traj)], 0
    while stack:
        width = wide if len(stack) >= wide // 2 else narrow
        n = min(len(stack), width)
        ahead = max(lv for lv in range(levels + 1) if lv == 0 or n * (2 ** (lv + 1) - 1) <= width)
        popped, stack = stack[len(stack) - n:], stack[: len(stack) - n]
        for _ in range(ahead + 1):  # one level settled per round
            popped = [(k, d + 1, 2 * i + c) for k, d, i in popped if (k, d, i) not in leaves for c in (0, 1)]
        stack += popped
        steps += 1
    return steps


def test_tree_evaluates_ahead_and_again(robot, capsules, random_set, monkeypatch):
    """Two trajectories start from two intervals: narrow steps evaluate them with their descendants
    (:func:`~larc_jax.engine.tree.speculation_levels`) and keep only what the level-by-level
    frontier evaluates, in fewer steps than without. With a broad phase of one exact pair, lanes
    evaluated ahead whose pick it did not prove go back on the stack (``again``) and are evaluated
    again as a step's own: the host frontier's leaves either way."""
    import larc_jax.engine.tree as tree_module

    trajs, scenes = random_set
    batch, names = _batch(robot, capsules, trajs[:2], scenes[:2])
    tree = run_tree(batch, 2, MAX_DEPTH)
    _compare(batch, names, 2, tree, ulps=8)
    assert tree.steps == _steps(2, tree) < _steps(2, tree, levels=0) and tree.again == 0
    monkeypatch.setattr(tree_module, "BROAD_PHASE_K", 1)
    proven = run_tree(batch, 2, MAX_DEPTH, leaf_capacity=1000)  # a shape of its own: traced with k = 1
    assert proven.again > 0
    _compare(batch, names, 2, proven, ulps=8)


def test_tree_continues_when_buffers_fill(robot, capsules, random_set):
    trajs, scenes = random_set
    batch, names = _batch(robot, capsules, trajs, scenes)
    tree = run_tree(batch, len(trajs), MAX_DEPTH, **SMALL)
    assert tree.calls > 5
    _compare(batch, names, len(trajs), tree, ulps=8)


def test_tree_without_broad_phase_and_empty_scenes(robot, capsules, random_set, monkeypatch):
    from larc_jax.engine.batch import Batch

    monkeypatch.setattr(Batch, "use_broad_phase", property(lambda self: False))  # both schedulers: every pair
    trajs, _ = random_set
    lone = Scene(lo=np.array([[0.2, -0.1, 0.1]]), hi=np.array([[0.3, 0.1, 0.3]]), box_names=("lone",), name="lone")
    empty = Scene(lo=np.zeros((0, 3)), hi=np.zeros((0, 3)), box_names=(), name="empty")
    scenes = [lone if k % 2 else empty for k in range(len(trajs))]
    batch, names = _batch(robot, capsules, trajs, scenes)
    assert not batch.use_broad_phase
    tree = run_tree(batch, len(trajs), MAX_DEPTH, **SMALL)
    _compare(batch, names, len(trajs), tree, ulps=8)
    in_empty = np.isin(tree.traj, np.arange(0, len(trajs), 2))
    assert np.all(tree.depth[in_empty] == 0) and np.all(np.isposinf(tree.record.clearance_m[in_empty]))


def test_tree_with_self_collision(robot, capsules, random_set):
    """The self test composed on the device as on the host: some leaves are decided by a capsule
    pair (``other >= 0``), and every decision is the host frontier's."""
    trajs, scenes = random_set
    batch, names = _batch(robot, capsules, trajs, scenes, self_collision=True)
    assert batch.self_pairs is not None and supports(batch)
    tree = run_tree(batch, len(trajs), MAX_DEPTH, **SMALL)
    _compare(batch, names, len(trajs), tree, ulps=8)
    assert (tree.record.other >= 0).any()


def test_tree_one_program_for_every_depth(robot, capsules, random_set):
    """The depth is traced: depths 3, 9 and 12 run one compiled program (a compile is reported
    once), each giving the host frontier's leaves at that depth."""
    trajs, scenes = random_set
    batch, names = _batch(robot, capsules, trajs[:6], scenes[:6])
    compiles = []
    for depth in (3, 9, 12):
        tree = run_tree(batch, 6, depth, compiles.append, **SMALL)
        assert tree.frontier.shape == (6, depth + 1)
        _compare(batch, names, 6, tree, ulps=8, max_depth=depth)
    assert compiles.count(True) <= 1  # none when an earlier test compiled this shape already


def test_tree_program_kept_compiled_is_the_same(robot, capsules, random_set, tmp_path, monkeypatch):
    """With the cache on, the program is kept as an executable: compiled and written by a first
    process, loaded by a later one (simulated: released) without tracing it, and both give what
    the plainly jitted program gives, bit for bit."""
    from larc_jax import compilation

    trajs, scenes = random_set
    batch, _ = _batch(robot, capsules, trajs[:6], scenes[:6])
    monkeypatch.setattr(compilation, "_EXPORT_DIR", None)
    plain = run_tree(batch, 6, MAX_DEPTH, **SMALL)
    monkeypatch.setattr(compilation, "_EXPORT_DIR", tmp_path)
    monkeypatch.setattr(compilation, "_LOADED", collections.OrderedDict())
    first = run_tree(batch, 6, MAX_DEPTH, **SMALL)
    assert len(list(tmp_path.glob("tree_program-*.xlaexe"))) == 1
    compilation.release_kernels()
    with compilation.CompileClock() as clock:
        loaded = run_tree(batch, 6, MAX_DEPTH, **SMALL)
    assert clock.cache_hits == clock.compiles == 1 and clock.trace_s == 0
    for tree in (first, loaded):
        for field in ("traj", "depth", "index", "t0", "t1", "frontier"):
            assert np.array_equal(getattr(tree, field), getattr(plain, field)), field
        for a, b in zip(tree.record, plain.record):
            assert np.array_equal(a, b, equal_nan=np.asarray(a).dtype.kind == "f")


def test_tree_float32_geometry(robot, capsules, random_set):
    trajs, scenes = random_set
    batch, names = _batch(robot, capsules, trajs[:5], scenes[:5], dtype=np.float32)
    tree = run_tree(batch, 5, MAX_DEPTH, **SMALL)
    _compare(batch, names, 5, tree, ulps=2**30)  # float32 geometry: agreement to its own precision


def test_tree_refuses_what_it_does_not_run(robot, capsules, random_set):
    trajs, scenes = random_set
    batch, _ = _batch(robot, capsules, trajs[:2], scenes[:2])
    swept = dataclasses.replace(batch, swept=object())  # the swept stage is not on the device
    assert not supports(swept)
    with pytest.raises(ValueError, match="without the swept stage"):
        run_tree(swept, 2, MAX_DEPTH)
    batch, _ = _batch(robot, capsules, trajs[:2], scenes[:2])
    with pytest.raises(ValueError, match="narrow"):
        run_tree(batch, 2, MAX_DEPTH, wide=4, narrow=8)


def test_dyadic_and_rebased_ends_bit_identical():
    import jax

    rng = np.random.default_rng(3)
    n = 4000
    t_start = np.concatenate([rng.uniform(-1e6, 1e6, n // 2), rng.choice([0.0, 1e-300, 1e9, 3.0], n // 2)])
    t_end = t_start + np.concatenate([rng.uniform(1e-9, 100.0, n // 2), rng.choice([1e-6, 0.1, 7.0, 1e5], n // 2)])
    depth = rng.integers(0, 40, n)
    index = (rng.random(n) * np.ldexp(1.0, depth)).astype(np.int64)
    index[:8] = 0
    index[8:16] = (1 << depth[8:16]) - 1  # the last interval: its end is t_end verbatim
    offset = np.where(rng.random(n) < 0.5, t_start, rng.uniform(-1e6, 1e6, n))
    with jax.enable_x64(True):
        a, b = (np.asarray(x) for x in jax.jit(dyadic_ends_jnp)(t_start, t_end, depth.astype(np.int32), index))
        ra, rb = (np.asarray(x) for x in jax.jit(rebase_ends_jnp)(a, b, offset))
    a_np, b_np = dyadic_ends(t_start, t_end, depth, index)
    assert np.array_equal(a, a_np) and np.array_equal(b, b_np)
    assert np.array_equal(b[8:16], t_end[8:16]) and np.array_equal(a[:8], t_start[:8])
    ra_np, rb_np = rebase_ends(a_np, b_np, offset)
    assert np.array_equal(ra, ra_np) and np.array_equal(rb, rb_np)


def test_warm_up_runs_small_batches_on_the_tree(robot, capsules, random_set):
    """``warm_up_tree`` certifies with the tree and leaves the process running small batches on it:
    the host frontier's leaves, evaluations and decisions (clearances to the last bits), and a
    later one-trajectory ``certify`` gives the tree's own leaves bit for bit; a run that is not
    LARC is refused and changes nothing; turned off again, small batches go back to the host."""
    import larc_jax
    from larc_jax.engine.tree_pool import small_batches_on_tree, uses_tree

    trajs, scenes = random_set
    batch, _ = _batch(robot, capsules, trajs[1:2], scenes[1:2])
    host = larc_jax.certify(trajs[:1], scenes[:1], robot, capsules, enclosure="capsules")
    assert not small_batches_on_tree() and not uses_tree(batch, 1)
    with pytest.raises(larc_jax.LarcInputError, match="method 'fine'"):
        larc_jax.warm_up_tree(trajs[:1], scenes[:1], robot, capsules, method="fine")
    assert not small_batches_on_tree()
    try:
        warm = larc_jax.warm_up_tree(trajs[:1], scenes[:1], robot, capsules, enclosure="capsules")
        assert small_batches_on_tree() and uses_tree(batch, 1)
        assert np.array_equal(warm.certified, host.certified) and np.array_equal(warm.evaluations, host.evaluations)
        assert np.array_equal(warm.frontier, host.frontier)
        for field in ("traj", "t0", "t1", "stage", "certified"):
            assert np.array_equal(getattr(warm.leaves, field), getattr(host.leaves, field)), field
        np.testing.assert_allclose(warm.leaves.clearance_m, host.leaves.clearance_m, rtol=0, atol=1e-12)
        one = larc_jax.certify(trajs[1:2], scenes[1:2], robot, capsules, enclosure="capsules")
        tree = run_tree(batch, 1, MAX_DEPTH)
        assert np.array_equal(one.leaves.clearance_m, tree.record.clearance_m, equal_nan=True)
        assert np.array_equal(one.leaves.t0, tree.t0) and np.array_equal(one.frontier, tree.frontier)
    finally:
        assert small_batches_on_tree(False)
    assert not uses_tree(batch, 1)
