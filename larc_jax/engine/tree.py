"""The adaptive tree on the device: LARC's bisection as one jitted program per batch.

The host-driven frontier (:func:`larc_jax.engine.certify._larc_batched`) makes a kernel call per
depth and moves every result to the host between calls. Here the whole tree of the capsule test
runs inside one ``jax.lax.while_loop``:

* a work stack of ``(trajectory, depth, index)`` intervals, ``capacity`` long, seeded with the
  roots; each step pops the top ``chunk`` intervals (fewer when the stack holds fewer), evaluates
  them (the same per-interval kernel as every scheduler, :func:`~larc_jax.engine.kernels.batched_intervals`,
  with the same dyadic ends, :func:`~larc_jax.leaf.interval.dyadic_ends`, rebased outwards, budget T1),
  writes the finished ones (passed, or at ``max_depth``) into preallocated leaf buffers at offsets
  given by a prefix sum, and pushes both children of every open one by a second prefix sum and
  scatter (stream compaction);
* two step sizes, both compiled into the program: a wide step while the stack holds at least half
  of it, a narrow one below (one trajectory certified alone starts from one interval; a wide step
  there would evaluate padding);
* the loop stops when the stack is empty, or when the next step could overflow the stack or the leaf
  buffers; the host then takes the leaves out and calls again with what is left (:func:`run_tree`).
  A stopped call never changes a result: each interval's test depends on that interval alone.

Why the order does not matter: an interval is evaluated exactly when its parent was evaluated and
failed (or it is a root), whatever order the stack takes them in, so the set of evaluated intervals,
the leaves and their records equal those of the level-by-level frontier; :func:`run_tree` returns
the leaves sorted as that frontier emits them (by depth, trajectory, index), and the per-depth
evaluation counts.

Scope: the capsule test against whole scenes (no hull, swept or self stage, no culling, one device);
:func:`supports` says when a batch qualifies, and the certifier runs the host frontier otherwise.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from ..compilation import tracked_call
from ..lazy_jax import jax, jnp
from ..leaf.clearance import BROAD_PHASE_K
from ..leaf.record import LeafRecord, Stage, box_record
from .batch import size_class
from .kernels import batched_intervals

__all__ = ["supports", "run_tree", "tree_program", "TreeLeaves", "dyadic_ends_jnp", "rebase_ends_jnp", "WIDE_STEP",
           "NARROW_STEP", "STACK_SLACK", "LEAF_CAPACITY"]

WIDE_STEP = 256
"""Intervals a wide step evaluates (the stack holds at least half of it)."""
NARROW_STEP = 16
"""Intervals a narrow step evaluates (the stack holds fewer than ``WIDE_STEP // 2``)."""
STACK_SLACK = 2
"""The stack holds ``size_class(seeds) + STACK_SLACK * wide * (max_depth + 1)`` intervals: a step
grows it by at most its width, and the loop stops before a step could overflow it (depth first,
the stack holds about one step's width per level)."""
LEAF_CAPACITY = 1 << 16
"""Leaves one call may write before it returns them to the host (9 columns, 4.7 MB)."""


def supports(batch) -> bool:
    """Whether the device tree runs ``batch``: the capsule test alone on whole scenes, one device."""
    return (batch.hulls is None and batch.swept is None and batch.self_pairs is None and batch.cull is None
            and len(batch.devices) <= 1)


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
    (by trajectory, then time), each with its capsule-stage record, and the per-trajectory,
    per-depth evaluation counts ``frontier`` (``(n_traj, max_depth + 1)``)."""

    traj: np.ndarray
    depth: np.ndarray
    index: np.ndarray
    t0: np.ndarray
    """Leaf start in the trajectory's own time axis, s (:func:`~larc_jax.leaf.interval.dyadic_ends`)."""
    t1: np.ndarray
    record: LeafRecord
    """The capsule stage's record (:func:`~larc_jax.leaf.record.box_record`): ``stage > 0`` iff certified."""
    frontier: np.ndarray
    calls: int
    """Device programs run (more than one when a stack or leaf buffer filled)."""


_LEAF_DTYPES = (np.int32, np.int32, np.int64, np.float64, np.float64, np.float64, np.float64, np.int32, np.int32)
"""Leaf buffer columns: trajectory, depth, index, t0, t1, g, guard, capsule, box."""


def _step(width: int, args, max_depth: int, broad: bool, state):
    """One step: pop up to ``width`` intervals off the stack, evaluate them, write the finished ones
    into the leaf buffers and push both children of the open ones."""
    robot, capsules, splines, obstacles, bounds, scene_of, t_start, t_end, margin = args
    s_traj, s_depth, s_index, top, leaves, n_leaves, frontier = state
    capacity = s_traj.shape[0]
    n = jnp.minimum(top, width)
    start = top - n
    lane = jnp.arange(width, dtype=top.dtype)
    valid = lane < n
    rows = jnp.where(valid, start + lane, 0)
    # A padding lane evaluates trajectory 0's root (a real interval); nothing it computes is kept.
    tr = jnp.where(valid, s_traj[rows], 0)
    dp = jnp.where(valid, s_depth[rows], 0)
    ix = jnp.where(valid, s_index[rows], 0)
    t0, t1 = dyadic_ends_jnp(t_start[tr], t_end[tr], dp, ix)
    a, b = rebase_ends_jnp(t0, t1, bounds.offset_s[tr])
    sel = (scene_of[tr],)
    kernel = functools.partial(batched_intervals, robot, capsules, splines, obstacles, bounds, tr, sel, a, b, margin)
    if broad:  # as Batch._stages: the broad phase, then every pair where it could not prove its pick
        g, guard, cap, box, exact = kernel(BROAD_PHASE_K)
        redo = ~exact.astype(bool) & valid

        def all_pairs(picked):
            return tuple(jnp.where(redo, x, y) for x, y in zip(kernel(None)[:4], picked))

        g, guard, cap, box = jax.lax.cond(redo.any(), all_pairs, lambda picked: picked, (g, guard, cap, box))
    else:
        g, guard, cap, box, _ = kernel(None)
    passed = g > guard  # NaN never passes (larc_jax.leaf.record)
    final = valid & (passed | (dp == max_depth))
    open_ = valid & ~final
    # Stream compaction by prefix sums; a write to an index past the end is dropped.
    at = jnp.where(final, n_leaves + jnp.cumsum(final) - 1, leaves[0].shape[0])
    leaves = tuple(buf.at[at].set(x.astype(buf.dtype), mode="drop")
                   for buf, x in zip(leaves, (tr, dp, ix, t0, t1, g, guard, cap, box)))
    first = start + 2 * (jnp.cumsum(open_) - 1)
    left, right = jnp.where(open_, first, capacity), jnp.where(open_, first + 1, capacity)
    s_traj = s_traj.at[left].set(tr, mode="drop").at[right].set(tr, mode="drop")
    s_depth = s_depth.at[left].set(dp + 1, mode="drop").at[right].set(dp + 1, mode="drop")
    s_index = s_index.at[left].set(2 * ix, mode="drop").at[right].set(2 * ix + 1, mode="drop")
    frontier = frontier.at[jnp.where(valid, tr, frontier.shape[0]), dp].add(1, mode="drop")
    return (s_traj, s_depth, s_index, (start + 2 * open_.sum()).astype(top.dtype), leaves,
            (n_leaves + final.sum()).astype(n_leaves.dtype), frontier)


@functools.partial(jax.jit, static_argnames=("max_depth", "broad", "wide", "narrow", "leaf_capacity"))
def tree_program(robot, capsules, splines, obstacles, bounds, scene_of, t_start, t_end, margin, stack, top, frontier,
                 *, max_depth: int, broad: bool, wide: int, narrow: int, leaf_capacity: int):
    """The tree from ``stack`` (trajectory, depth, index arrays, the first ``top`` in use) until the
    stack is empty or the next step could overflow it or the leaf buffers. Returns ``(stack, top,
    leaves, n_leaves, frontier)``: what is left, the leaf columns (:data:`_LEAF_DTYPES`; the first
    ``n_leaves`` in use) and ``frontier`` with this call's evaluations added."""
    args = (robot, capsules, splines, obstacles, bounds, scene_of, t_start, t_end, margin)
    capacity = stack[0].shape[0]
    leaves = tuple(jnp.zeros(leaf_capacity, d) for d in _LEAF_DTYPES)

    def room(state):
        top, n_leaves = state[3], state[5]
        return (top > 0) & (top + wide <= capacity) & (n_leaves + wide <= leaf_capacity)

    def body(state):  # a wide step while the stack holds half of one, else a narrow one
        return jax.lax.cond(state[3] >= wide // 2, functools.partial(_step, wide, args, max_depth, broad),
                            functools.partial(_step, narrow, args, max_depth, broad), state)

    s_traj, s_depth, s_index, top, leaves, n_leaves, frontier = jax.lax.while_loop(
        room, body, (*stack, top, leaves, jnp.int32(0), frontier))
    return (s_traj, s_depth, s_index), top, leaves, n_leaves, frontier


@functools.lru_cache(maxsize=None)
def _program(max_depth: int, broad: bool, wide: int, narrow: int, leaf_capacity: int):
    """One callable per static configuration (:func:`~larc_jax.compilation.tracked_call` knows a
    shape it has seen by the callable)."""
    return functools.partial(tree_program, max_depth=max_depth, broad=broad, wide=wide, narrow=narrow,
                             leaf_capacity=leaf_capacity)


def run_tree(batch, n_traj: int, max_depth: int, on_compile=None, *, wide: int = WIDE_STEP,
             narrow: int = NARROW_STEP, leaf_capacity: int = LEAF_CAPACITY) -> TreeLeaves:
    """LARC on the first ``n_traj`` trajectories of ``batch`` (one :func:`supports`), from every
    trajectory's root down to ``max_depth``: the device program, called again with what is left
    while a call stops short. ``on_compile``: as :meth:`Batch.evaluate <larc_jax.engine.batch.Batch.evaluate>`."""
    if not supports(batch):
        raise ValueError("run_tree: the device tree runs the capsule test alone on whole scenes, on one device")
    if not (1 <= narrow <= wide <= leaf_capacity) or n_traj < 1 or max_depth < 0:
        raise ValueError(f"run_tree: need 1 <= narrow ({narrow}) <= wide ({wide}) <= leaf_capacity "
                         f"({leaf_capacity}), n_traj >= 1, max_depth >= 0")
    capacity = size_class(n_traj, 1) + STACK_SLACK * wide * (max_depth + 1)
    pending = [np.arange(n_traj, dtype=np.int32), np.zeros(n_traj, np.int32), np.zeros(n_traj, np.int64)]
    rows = size_class(len(batch.t_start), 1)  # per-trajectory arrays padded as the splines are (one shape per class)
    pad = lambda x: np.concatenate([x, np.repeat(x[:1], rows - len(x))])  # noqa: E731
    frontier = np.zeros((rows, max_depth + 1), np.int64)
    program = _program(max_depth, bool(batch.use_broad_phase), wide, narrow, leaf_capacity)
    args = (batch.robot, batch.capsules, batch.splines, batch.obstacles, batch.bounds, pad(batch.scene_of),
            pad(batch.t_start), pad(batch.t_end), batch.margin)
    found, calls = [], 0
    while len(pending[0]):
        take = min(len(pending[0]), capacity - wide)  # the top of the pending stack, deepest first
        stack = tuple(np.concatenate([p[len(p) - take:], np.zeros(capacity - take, p.dtype)]) for p in pending)
        pending = [p[: len(p) - take] for p in pending]
        with jax.enable_x64(True):
            out = tracked_call(program, (*args, stack, np.int32(take), frontier), on_compile)
            (s_traj, s_depth, s_index), top, leaves, n_leaves, frontier = jax.tree.map(np.asarray, out)
        calls += 1
        found.append([x[: int(n_leaves)] for x in leaves])
        pending = [np.concatenate([p, s[: int(top)]]) for p, s in zip(pending, (s_traj, s_depth, s_index))]
    traj, depth, index, t0, t1, g, guard, cap, box = (np.concatenate(c) for c in zip(*found))
    order = np.lexsort((t0, traj))
    record = box_record(g[order], guard[order], cap[order].astype(np.int64), box[order].astype(np.int64),
                        Stage.CAPSULE)
    return TreeLeaves(traj[order].astype(np.int64), depth[order].astype(np.int64), index[order], t0[order], t1[order],
                      record, frontier[:n_traj].copy(), calls)
