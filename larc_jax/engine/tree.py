"""The adaptive tree on the device: LARC's bisection as one jitted program per batch.

The host-driven frontier (``larc`` in :mod:`larc_jax.engine.certify`) makes a kernel call per
depth and moves every result to the host between calls. Here the whole tree (the capsule test or
the cascade, and the self test where the run checks self-collision) runs inside one
``jax.lax.while_loop``:

* a work stack of ``(trajectory, depth, index)`` intervals, ``capacity`` long, seeded with the
  roots; each step pops the top intervals (at most a step's width), evaluates them (the same
  per-interval kernels as every scheduler, :func:`~larc_jax.engine.kernels.batched_intervals` (or
  its screened twin and the hull stage, :mod:`larc_jax.engine.tree_hull`) and
  :func:`~larc_jax.engine.kernels.self_intervals`, composed by :func:`~larc_jax.leaf.record.compose`,
  with the same dyadic ends, :func:`~larc_jax.leaf.interval.dyadic_ends`, rebased outwards, budget T1),
  writes the finished ones (passed, or at ``max_depth``) into preallocated leaf buffers at offsets
  given by a prefix sum, and pushes both children of every open one by a second prefix sum and
  scatter (stream compaction);
* two step sizes, both compiled into the program: a wide step while the stack holds at least half
  of it, a narrow one below (one trajectory certified alone starts from one interval; a wide step
  there would evaluate padding); only the evaluation is under the branch, never the buffers;
* the depth is traced and the buffers are sized by the batch's trajectory count (its power-of-two
  class), never by its depth: one compiled program per batch class, whatever ``max_depth``;
* the loop stops when the stack is empty, or when the next step could overflow the stack or the leaf
  buffers; the host then takes the leaves out and calls again with what is left (:func:`run_tree`).
  A stopped call never changes a result: each interval's test depends on that interval alone.

Why the order does not matter: an interval is evaluated exactly when its parent was evaluated and
failed (or it is a root), whatever order the stack takes them in, so the set of evaluated intervals,
the leaves and their decisions equal those of the level-by-level frontier; :func:`run_tree`
returns the leaves sorted as the certifiers' leaf tables are (by trajectory, then time), and the
per-depth evaluation counts. A record's clearance may differ from the host frontier's in its last
bits: XLA compiles the kernel inside the loop with its own fusions (fused multiply-adds where the
host's kernel has none, or the reverse); the interval ends, which decide which interval a leaf is,
are rounded as NumPy rounds them (:func:`dyadic_ends_jnp`).

Scope: the capsule test or the cascade (the capsule test, the screen, then the hull stage on the
lanes it leaves open, :mod:`larc_jax.engine.tree_hull`), with the self test or without, against
whole scenes (no swept stage, no culling, no point-cloud pieces), on one device; :func:`supports`
says when a batch qualifies. ``certify`` does not use it yet (README, "The depth loop on the
device", has its timings against the host frontier).
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from ..compilation import tracked_call
from ..defaults import DEFAULT_MAX_DEPTH, MAX_DEPTH_LIMIT
from ..lazy_jax import jax, jnp
from ..leaf.clearance import BROAD_PHASE_K
from ..leaf.rounds import early_stop_slack
from ..leaf.record import LeafRecord, Stage, box_record, compose, needs_hull, self_record
from .buckets import size_class
from .kernels import (batched_intervals, evaluate_intervals_screened, evaluate_intervals_screened_broad,
                      self_intervals)
from .tree_hull import hull_stage_lanes

__all__ = ["supports", "run_tree", "tree_program", "TreeLeaves", "dyadic_ends_jnp", "rebase_ends_jnp", "WIDE_STEP",
           "NARROW_STEP", "STACK_SLACK", "LEAF_CAPACITY", "MAX_TRIPLES"]

WIDE_STEP = 256
"""Intervals a wide step evaluates (the stack holds at least half of it)."""
NARROW_STEP = 16
"""Intervals a narrow step evaluates (the stack holds fewer than ``WIDE_STEP // 2``). A third,
middle width (or four widths, 8 to 256, each step taking the smallest that holds the stack) was
slower one trajectory per call on Stage B and about doubled the compile time (measured while
developing, README "The depth loop on the device"): a wide step mostly evaluates padding on a
short stack, and every width is another compiled copy of the kernel."""
STACK_SLACK = 2
"""The stack holds ``size_class(seeds) + STACK_SLACK * wide * (DEFAULT_MAX_DEPTH + 1)`` intervals: a
step grows it by at most its width, and the loop stops before a step could overflow it (depth
first, the stack holds about one step's width per level). Sized by the default depth, not the
run's, so the depth is not a compiled shape; a deeper tree that fills it continues in a further
call."""
LEAF_CAPACITY = 1 << 16
"""Leaves one call may write before it returns them to the host (11 columns, 5.5 MB). A call
returns its whole buffers, so a small batch gets smaller ones: ``size_class(trajectories) <<
DEFAULT_MAX_DEPTH`` leaves (all a trajectory can have at the default depth), plus a step's width
for the loop's room test. A deeper tree that fills them continues in a further call."""


def supports(batch) -> bool:
    """Whether the device tree runs ``batch``: the capsule test, or the cascade (the hull stage after
    it) without point-cloud pieces and with at most :data:`MAX_TRIPLES` (part, item) pairs per
    interval, with the self test or without, on whole scenes (unculled), one device, without the
    swept stage."""
    if batch.swept is not None or batch.cull is not None or len(batch.devices) > 1:
        return False
    return batch.hulls is None or (not batch.obstacles.separate_points().any()
                                   and batch.hulls.n_parts * batch.obstacles.n_items <= MAX_TRIPLES)


MAX_TRIPLES = 512
"""The most (hull part, item) pairs per interval the device tree takes: the hull stage keeps its
triples dense, ``H x P x N`` per slot loop (:func:`~larc_jax.engine.tree_hull.hull_stage_lanes`),
so this bounds those arrays; a larger scene is left to the host frontier."""


def dyadic_ends_jnp(t_start, t_end, depth, index):
    """:func:`~larc_jax.leaf.interval.dyadic_ends` in JAX (float64; the same operations)."""
    n = jnp.ldexp(jnp.ones_like(t_start), depth)
    f0, f1 = index.astype(jnp.float64) / n, (index + 1).astype(jnp.float64) / n
    span = t_end - t_start
    # Each product rounded on its own, as NumPy rounds it: a select between the multiply and the
    # add keeps LLVM from contracting them into one fused multiply-add (XLA allows contraction).
    rounded = lambda p: jnp.where(p != p, jnp.nan, p)  # noqa: E731 - the identity, opaque to contraction
    a = jnp.where(f0 == 0.0, t_start, t_start + rounded(span * f0))
    b = jnp.where(f1 == 1.0, t_end, t_start + rounded(span * f1))
    return a, b


def rebase_ends_jnp(a, b, offset):
    """:func:`~larc_jax.leaf.interval.rebase_ends` in JAX: ``(a - o, b - o)`` rounded outwards."""

    def two_diff(x, y):  # Knuth's TwoSum on x + (-y): s = fl(x - y), x - y = s + e exactly
        y = -y
        s = x + y
        bp = s - x
        ap = s - bp
        return s, (x - ap) + (y - bp)

    sa, ea = two_diff(a, offset)
    sb, eb = two_diff(b, offset)
    return (jnp.where(ea < 0, jnp.nextafter(sa, -jnp.inf), sa), jnp.where(eb > 0, jnp.nextafter(sb, jnp.inf), sb))


@dataclasses.dataclass(frozen=True)
class TreeLeaves:
    """What :func:`run_tree` found (NumPy): the leaves, sorted as the certifiers' leaf tables are
    (by trajectory, then time), each with its record, and the per-trajectory,
    per-depth evaluation counts ``frontier`` (``(n_traj, max_depth + 1)``)."""

    traj: np.ndarray
    depth: np.ndarray
    index: np.ndarray
    t0: np.ndarray
    """Leaf start in the trajectory's own time axis, s (:func:`~larc_jax.leaf.interval.dyadic_ends`)."""
    t1: np.ndarray
    record: LeafRecord
    """The leaf test's record (the capsule stage's, composed with the self test's:
    :func:`~larc_jax.leaf.record.compose`): ``stage > 0`` iff certified."""
    frontier: np.ndarray
    calls: int
    """Device programs run (more than one when a stack or leaf buffer filled)."""
    steps: int = 0
    """Steps the programs' loops ran (each evaluates up to a step's width of intervals): what a
    call's time grows with when the steps are narrow (``experiments.bench_tree``)."""


_LEAF_DTYPES = (np.int32, np.int32, np.int64, np.float64, np.float64, np.float64, np.float64, np.int32, np.int32,
                np.int32, np.int8)
"""Leaf buffer columns: trajectory, depth, index, t0, t1, then the record's (:class:`LeafRecord`)."""


def _evaluate(args, broad: bool, tr, dp, ix, valid):
    """The leaf test of the intervals ``(tr, dp, ix)`` (lanes; ``valid`` those in use): their ends and
    record, as :meth:`Batch._stages <larc_jax.engine.batch.Batch>` takes them (the hull stage:
    :mod:`larc_jax.engine.tree_hull`)."""
    robot, capsules, splines, obstacles, bounds, scene_of, t_start, t_end, margin, self_check, cascade = args
    t0, t1 = dyadic_ends_jnp(t_start[tr], t_end[tr], dp, ix)
    a, b = rebase_ends_jnp(t0, t1, bounds.offset_s[tr])
    hulls, of_capsule, part_table, of_part, slack = (None,) * 5 if cascade is None else cascade
    sel = (scene_of[tr],)

    def step1(k):
        """The capsule stage (broad phase ``k``): ``(g, guard, capsule, box, screen), exact``; with the
        cascade, step 1 and the screen from one placement (larc_jax.leaf.cascade), else no screen."""
        if cascade is None:
            g, guard, cap, box, exact = batched_intervals(robot, capsules, splines, obstacles, bounds, tr, sel, a, b,
                                                          margin, k)
            return (g, guard, cap, box, g), exact
        kernel = evaluate_intervals_screened if k is None else evaluate_intervals_screened_broad
        g, guard, cap, box, exact, screen = kernel(robot, capsules, hulls, (of_capsule, part_table), splines, obstacles,
                                                   bounds, tr, sel, a, b, margin)
        return (g, guard, cap, box, screen), exact

    if broad:  # the broad phase, then every pair where it could not prove its pick
        picked, exact = step1(BROAD_PHASE_K)
        redo = ~exact.astype(bool) & valid

        def all_pairs(picked):
            return tuple(jnp.where(redo, x, y) for x, y in zip(step1(None)[0], picked))

        out = jax.lax.cond(redo.any(), all_pairs, lambda picked: picked, picked)
    else:
        out = step1(None)[0]
    g, guard, cap, box = out[:4]
    record = box_record(g, guard, cap.astype(jnp.int64), box.astype(jnp.int64), Stage.CAPSULE, xp=jnp)
    self_test = None
    if self_check is not None:
        gs, gds, c1, c2 = self_intervals(robot, capsules, splines, bounds, tr, a, b, self_check)
        self_test = self_record(gs, gds, c1.astype(jnp.int64), c2.astype(jnp.int64), xp=jnp)
    if cascade is not None:  # the hull stage where the capsules fail and the screen leaves it a chance
        need = valid & needs_hull(record, self_test, xp=jnp) & (out[4] > 0)
        model = (robot, capsules, hulls, splines, obstacles, bounds, scene_of, margin, of_capsule, of_part,
                 part_table.shape[0], slack)
        hull = hull_stage_lanes(model, tr, a, b, need)
        record = LeafRecord(*(jnp.where(need, h, r) for h, r in zip(hull, record)))
    return t0, t1, compose(record, self_test, xp=jnp)


def _step(args, max_depth, broad: bool, wide: int, narrow: int, state):
    """One step: pop up to ``wide`` intervals off the stack (``narrow`` while it holds fewer than
    ``wide // 2``), evaluate them, write the finished ones into the leaf buffers and push both
    children of the open ones. Only the evaluation is under the branch: its operands are a step's
    lanes, not the buffers (a branch over the whole state would copy them each step)."""
    s_traj, s_depth, s_index, top, leaves, n_leaves, frontier, steps = state
    capacity = s_traj.shape[0]
    use_wide = top >= wide // 2
    n = jnp.minimum(top, jnp.where(use_wide, wide, narrow))
    start = top - n
    lane = jnp.arange(wide, dtype=top.dtype)
    valid = lane < n
    rows = jnp.where(valid, start + lane, 0)
    # A padding lane evaluates trajectory 0's root (a real interval); nothing it computes is kept.
    tr = jnp.where(valid, s_traj[rows], 0)
    dp = jnp.where(valid, s_depth[rows], 0)
    ix = jnp.where(valid, s_index[rows], 0)

    def narrow_step(lanes):  # the first `narrow` lanes, the rest padded (never valid in a narrow step)
        out = _evaluate(args, broad, *(x[:narrow] for x in lanes))
        return jax.tree.map(lambda x: jnp.concatenate([x, jnp.zeros((wide - narrow,), x.dtype)]), out)

    t0, t1, record = jax.lax.cond(use_wide, lambda lanes: _evaluate(args, broad, *lanes), narrow_step,
                                  (tr, dp, ix, valid))
    passed = record.stage > 0  # g > guard for every stage that ran; NaN never passes (larc_jax.leaf.record)
    final = valid & (passed | (dp == max_depth))
    open_ = valid & ~final
    # Stream compaction by prefix sums; a write to an index past the end is dropped.
    at = jnp.where(final, n_leaves + jnp.cumsum(final) - 1, leaves[0].shape[0])
    leaves = tuple(buf.at[at].set(x.astype(buf.dtype), mode="drop")
                   for buf, x in zip(leaves, (tr, dp, ix, t0, t1, *record)))
    first = start + 2 * (jnp.cumsum(open_) - 1)
    left, right = jnp.where(open_, first, capacity), jnp.where(open_, first + 1, capacity)
    s_traj = s_traj.at[left].set(tr, mode="drop").at[right].set(tr, mode="drop")
    s_depth = s_depth.at[left].set(dp + 1, mode="drop").at[right].set(dp + 1, mode="drop")
    s_index = s_index.at[left].set(2 * ix, mode="drop").at[right].set(2 * ix + 1, mode="drop")
    frontier = frontier.at[jnp.where(valid, tr, frontier.shape[0]), dp].add(1, mode="drop")
    return (s_traj, s_depth, s_index, (start + 2 * open_.sum()).astype(top.dtype), leaves,
            (n_leaves + final.sum()).astype(n_leaves.dtype), frontier, steps + 1)


@functools.partial(jax.jit, static_argnames=("broad", "wide", "narrow", "leaf_capacity"))
def tree_program(robot, capsules, splines, obstacles, bounds, scene_of, t_start, t_end, margin, self_check, cascade, stack,
                 top, frontier, max_depth, *, broad: bool, wide: int, narrow: int, leaf_capacity: int):
    """The tree from ``stack`` (trajectory, depth, index arrays, the first ``top`` in use) until the
    stack is empty or the next step could overflow it or the leaf buffers. Returns ``(stack, top,
    leaves, n_leaves, frontier, steps)``: what is left, the leaf columns (:data:`_LEAF_DTYPES`; the
    first ``n_leaves`` in use), ``frontier`` with this call's evaluations added, and the steps run. ``self_check``: as
    :func:`~larc_jax.engine.kernels.self_intervals` takes it, or None (no self test). ``cascade``:
    ``(hulls, Links.of_capsule, Links.part_table, Links.of_part, early_stop_slack)`` for the
    cascade (the hull stage after the capsule stage), or None (the capsule test). ``max_depth``
    is traced (an int32 scalar): every depth runs the same compiled program."""
    args = (robot, capsules, splines, obstacles, bounds, scene_of, t_start, t_end, margin, self_check, cascade)
    capacity = stack[0].shape[0]
    leaves = tuple(jnp.zeros(leaf_capacity, d) for d in _LEAF_DTYPES)

    def room(state):
        top, n_leaves = state[3], state[5]
        return (top > 0) & (top + wide <= capacity) & (n_leaves + wide <= leaf_capacity)

    s_traj, s_depth, s_index, top, leaves, n_leaves, frontier, steps = jax.lax.while_loop(
        room, functools.partial(_step, args, max_depth, broad, wide, narrow),
        (*stack, top, leaves, jnp.int32(0), frontier, jnp.int32(0)))
    return (s_traj, s_depth, s_index), top, leaves, n_leaves, frontier, steps


@functools.lru_cache(maxsize=None)
def _program(broad: bool, wide: int, narrow: int, leaf_capacity: int):
    """One callable per static configuration (:func:`~larc_jax.compilation.tracked_call` knows a
    shape it has seen by the callable)."""
    return functools.partial(tree_program, broad=broad, wide=wide, narrow=narrow, leaf_capacity=leaf_capacity)


def run_tree(batch, n_traj: int, max_depth: int, on_compile=None, *, wide: int = WIDE_STEP,
             narrow: int = NARROW_STEP, leaf_capacity: int = LEAF_CAPACITY) -> TreeLeaves:
    """LARC on the first ``n_traj`` trajectories of ``batch`` (one :func:`supports`), from every
    trajectory's root down to ``max_depth``: the device program, called again with what is left
    while a call stops short. ``on_compile``: as :meth:`Batch.evaluate <larc_jax.engine.batch.Batch.evaluate>`."""
    if not supports(batch):
        raise ValueError("run_tree: the device tree runs the capsule test or the cascade (and the self test) on whole "
                         f"scenes, on one device, without the swept stage or point-cloud pieces, at most {MAX_TRIPLES} "
                         "(part, item) pairs per interval")
    if not (1 <= narrow <= wide <= leaf_capacity) or n_traj < 1 or not 0 <= max_depth <= MAX_DEPTH_LIMIT:
        raise ValueError(f"run_tree: need 1 <= narrow ({narrow}) <= wide ({wide}) <= leaf_capacity "
                         f"({leaf_capacity}), n_traj >= 1, 0 <= max_depth ({max_depth}) <= {MAX_DEPTH_LIMIT}")
    capacity = size_class(n_traj, 1) + STACK_SLACK * wide * (DEFAULT_MAX_DEPTH + 1)
    leaf_capacity = min(leaf_capacity, (size_class(n_traj, 1) << DEFAULT_MAX_DEPTH) + wide)  # LEAF_CAPACITY
    pending = [np.arange(n_traj, dtype=np.int32), np.zeros(n_traj, np.int32), np.zeros(n_traj, np.int64)]
    rows = size_class(len(batch.t_start), 1)  # per-trajectory arrays padded as the splines are (one shape per class)
    pad = lambda x: np.concatenate([x, np.repeat(x[:1], rows - len(x))])  # noqa: E731
    frontier = np.zeros((rows, MAX_DEPTH_LIMIT + 1), np.int64)
    program = _program(bool(batch.use_broad_phase), wide, narrow, leaf_capacity)
    sp = batch.self_pairs
    self_check = None if sp is None else (sp.first, sp.second, sp.motion_a, np.asarray(sp.margin_m, np.float64),
                                          batch.self_skip)
    links = batch.links
    cascade = None if batch.hulls is None else (batch.hulls, links.of_capsule, links.part_table, links.of_part,
                                                np.float64(early_stop_slack(batch.dtype)))
    args = (batch.robot, batch.capsules, batch.splines, batch.obstacles, batch.bounds, pad(batch.scene_of),
            pad(batch.t_start), pad(batch.t_end), batch.margin, self_check, cascade)
    found, calls, steps = [], 0, 0
    while len(pending[0]):
        take = min(len(pending[0]), capacity - wide)  # the top of the pending stack, deepest first
        stack = tuple(np.concatenate([p[len(p) - take:], np.zeros(capacity - take, p.dtype)]) for p in pending)
        pending = [p[: len(p) - take] for p in pending]
        with jax.enable_x64(True):
            out = tracked_call(program, (*args, stack, np.int32(take), frontier, np.int32(max_depth)), on_compile)
            (s_traj, s_depth, s_index), top, leaves, n_leaves = jax.tree.map(np.asarray, out[:4])
            frontier = out[4]
        calls, steps = calls + 1, steps + int(out[5])
        found.append([x[: int(n_leaves)] for x in leaves])
        pending = [np.concatenate([p, s[: int(top)]]) for p, s in zip(pending, (s_traj, s_depth, s_index))]
    traj, depth, index, t0, t1, *columns = (np.concatenate(c) for c in zip(*found))
    order = np.lexsort((t0, traj))
    g, guard, cap, box, other, stage = (x[order] for x in columns)
    record = LeafRecord(g, guard, cap.astype(np.int64), box.astype(np.int64), other.astype(np.int64), stage)
    return TreeLeaves(traj[order].astype(np.int64), depth[order].astype(np.int64), index[order], t0[order], t1[order],
                      record, np.array(frontier)[:n_traj, : max_depth + 1], calls, steps)
