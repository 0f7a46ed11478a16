"""The adaptive tree on the device: LARC's bisection as one jitted program per batch.

The host-driven frontier (``larc`` in :mod:`larc_jax.engine.certify`) makes a kernel call per
depth and moves every result to the host between calls. Here the whole tree (the capsule test or
the cascade, and the self test where the run checks self-collision) runs inside one jitted
program of ``jax.lax.while_loop``s:

* a work stack of ``(trajectory, depth, index)`` intervals, ``capacity`` long, seeded with the
  roots; a *first-stage* step pops the top intervals (at most a step's width) and evaluates their
  capsule stage (with the cascade, the screened one) and self test with the same per-interval
  kernels as every scheduler (:func:`~larc_jax.engine.kernels.batched_intervals` or its screened
  twin, :func:`~larc_jax.engine.kernels.self_intervals`, composed by
  :func:`~larc_jax.leaf.record.compose`), with the same dyadic ends,
  :func:`~larc_jax.leaf.interval.dyadic_ends`, rebased outwards, budget T1;
* with the cascade, the lanes the hull stage decides (the capsules fail a box, the screen leaves
  the hulls a chance, the self test passes) go onto a *hull queue* with their self test's record;
  a *hull* step, taken whenever the queue holds :data:`HULL_STEP` of them (or the stack is empty
  and it holds any), runs the hull stage (:mod:`larc_jax.engine.tree_hull`) on them, a full step
  at once: its fixed work would otherwise be paid by the one or two lanes of each narrow step;
* either step writes its finished lanes (passed, or at ``max_depth``) into preallocated leaf
  buffers at offsets given by a prefix sum, and pushes both children of every open one by a
  second prefix sum and scatter (stream compaction);
* two phases, each a loop of its own over the same state, both compiled into the program: wide
  steps while the stack holds at least half of one (and the queue less than a hull step), narrow
  steps (first-stage or hull) otherwise (one trajectory certified alone starts from one interval;
  a wide step there would evaluate padding). A step's prefix sums and scatters run on its phase's
  lanes (a narrow step's on 16 or 32, not 256); only the evaluation is under a branch, never the
  buffers;
* a narrow step whose stack is short fills its lanes with its intervals' descendants, up to
  :data:`SPECULATION_LEVELS` levels down (:func:`speculation_levels`), and keeps a descendant's
  result only where every interval above it opened: one trajectory's first four levels take one
  step instead of four;
* the depth is traced and the buffers are sized by the batch's trajectory count (its power-of-two
  class), never by its depth: one compiled program per batch class, whatever ``max_depth``;
* the loop stops when the stack and the queue are empty, or when the next step could overflow the
  stack or the leaf buffers; the host then takes the leaves out and calls again with what is left,
  the queue's intervals included (evaluated again: an interval's evaluation is counted where it
  finishes or opens, so it counts once) (:func:`run_tree`). A stopped call never changes a result:
  each interval's test depends on that interval alone.

Why the order does not matter: an interval counts as evaluated exactly when its parent was
evaluated and failed (or it is a root), whatever order the stack and the queue take them in (a
descendant evaluated ahead is kept only then, and one whose broad phase did not prove its pick is
evaluated again later, :func:`_first_stage`), so the set of evaluated intervals,
the leaves and their decisions equal those of the level-by-level frontier; :func:`run_tree`
returns the leaves sorted as the certifiers' leaf tables are (by trajectory, then time), and the
per-depth evaluation counts. A record's clearance may differ from the host frontier's in its last
bits: XLA compiles the kernel inside the loop with its own fusions (fused multiply-adds where the
host's kernel has none, or the reverse); the interval ends, which decide which interval a leaf is,
are rounded as NumPy rounds them (:func:`dyadic_ends_jnp`).

Scope: the capsule test or the cascade (the capsule test, the screen, then the hull stage on the
lanes it leaves open, :mod:`larc_jax.engine.tree_hull`), with the self test or without, against
whole scenes (no swept stage, no culling, no point-cloud pieces), on one device; :func:`supports`
says when a batch qualifies. ``certify`` runs it, dealt to one thread per CPU core, on batches of
:data:`~larc_jax.engine.tree_pool.TREE_FROM_TRAJECTORIES` or more (:mod:`larc_jax.engine.tree_pool`).
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from ..compilation import cached_kernel, tracked_call
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
           "NARROW_STEP", "SPECULATION_LEVELS", "speculation_levels", "HULL_STEP", "HULL_WIDE_FROM", "STACK_SLACK",
           "LEAF_CAPACITY", "MAX_TRIPLES"]

WIDE_STEP = 256
"""Intervals a wide step evaluates (the stack holds at least half of it)."""
NARROW_STEP = 16
"""Intervals a narrow step evaluates (the stack holds fewer than ``WIDE_STEP // 2``, or the hull
queue a full hull step, :func:`tree_program`). A third,
middle width (or four widths, 8 to 256, each step taking the smallest that holds the stack) was
slower one trajectory per call on Stage B and about doubled the compile time (measured while
developing, README "The depth loop on the device"): a wide step mostly evaluates padding on a
short stack, and every width is another compiled copy of the kernel."""
HULL_STEP = 16
"""Intervals a hull step takes from the hull queue (:func:`_step`) in a batch of fewer than
:data:`HULL_WIDE_FROM` trajectories, twice as many from there. The lanes whose capsule stage fails
and whose screen leaves the hulls a chance wait on the queue until this many have gathered (or
the stack is empty), so that the hull stage's fixed work per run (its kinematics, its three
rounds' loops) is shared by a full step rather than paid by the one or two lanes of each narrow
step. Measured on Stage B against the hull stage run inside every step, in one process (README,
"The depth loop on the device"): one trajectory per call, 16 took 0.86-0.89 of the old time, as
fast as 8 and faster than 32; the whole set 0.95 of it with 16, 0.89 with 32."""
HULL_WIDE_FROM = 16
"""The batch class (:func:`~larc_jax.engine.buckets.size_class`) from which a hull step takes
``2 * HULL_STEP`` intervals (its wide steps fill the queue fast); one compiled program per batch
class either way."""
STACK_SLACK = 2
"""The stack holds ``size_class(seeds) + STACK_SLACK * grow * (DEFAULT_MAX_DEPTH + 1)`` intervals,
``grow = max(wide, 2 * hull)``: a first-stage step grows it by at most its width, a hull step by
twice its width, and the loop stops before a step could overflow it (depth
first, the stack holds about one step's width per level). Sized by the default depth, not the
run's, so the depth is not a compiled shape; a deeper tree that fills it continues in a further
call."""
LEAF_CAPACITY = 1 << 16
"""Leaves one call may write before it returns them to the host (11 columns, 5.5 MB). A call
returns its whole buffers, so a small batch gets smaller ones: ``size_class(trajectories) <<
DEFAULT_MAX_DEPTH`` leaves (all a trajectory can have at the default depth), plus a step's width
for the loop's room test. A deeper tree that fills them continues in a further call."""

SPECULATION_LEVELS = 3
"""The most levels below its intervals a first-stage step evaluates ahead (:func:`speculation_levels`)."""


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
triples dense, ``H x P x N`` per hull step (:func:`~larc_jax.engine.tree_hull.hull_stage_lanes`),
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
    hull_steps: int = 0
    """Of :attr:`steps`, the hull steps (the cascade's hull stage on the hull queue, :func:`_step`)."""
    again: int = 0
    """Intervals evaluated ahead (:func:`speculation_levels`) and needed, whose broad phase did not
    prove its pick: pushed back and evaluated again as a step's own (:func:`_first_stage`)."""


_LEAF_DTYPES = (np.int32, np.int32, np.int64, np.float64, np.float64, np.float64, np.float64, np.int32, np.int32,
                np.int32, np.int8)
"""Leaf buffer columns: trajectory, depth, index, t0, t1, then the record's (:class:`LeafRecord`)."""
_RECORD_DTYPES = (np.float64, np.float64, np.int64, np.int64, np.int64, np.int8)
"""A :class:`LeafRecord`'s columns as the kernels return them (the self test's, on the hull queue)."""


def _ends(args, tr, dp, ix):
    """The lanes' dyadic ends, and those ends rebased to the knot interval's start (outwards)."""
    bounds, t_start, t_end = args[4], args[6], args[7]
    t0, t1 = dyadic_ends_jnp(t_start[tr], t_end[tr], dp, ix)
    return (t0, t1, *rebase_ends_jnp(t0, t1, bounds.offset_s[tr]))


def _first_stage(args, broad: bool, tr, dp, ix, roots, queued):
    """The capsule stage (with the cascade, the screened one) and the self test on the lanes ``(tr,
    dp, ix)``, as :meth:`Batch._stages <larc_jax.engine.batch.Batch>` takes them: ``(t0, t1,
    record, to_hull, self columns, exact)``, ``to_hull`` the lanes the hull stage decides (the
    capsules fail a box and the screen leaves the hulls a chance), the self test's record columns,
    which go with them to the hull queue (``queued`` is not read here), and ``exact``, whether a
    lane's capsule stage is the all-pairs one: the broad phase proved its pick, or every pair was
    computed again, as on the ``roots`` lanes (the step's own intervals) wherever it did not; a
    lane evaluated ahead (:func:`speculation_levels`) whose pick was not proven is evaluated
    again later (:func:`_step`), so that a speculative lane never costs a step the all-pairs kernel."""
    robot, capsules, splines, obstacles, bounds, scene_of, t_start, t_end, margin, self_check, cascade = args
    t0, t1, a, b = _ends(args, tr, dp, ix)
    hulls, of_capsule, part_table = (None,) * 3 if cascade is None else cascade[:3]
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
        redo = ~exact.astype(bool) & roots

        def all_pairs(picked):
            return tuple(jnp.where(redo, x, y) for x, y in zip(step1(None)[0], picked))

        out = jax.lax.cond(redo.any(), all_pairs, lambda picked: picked, picked)
        exact = exact.astype(bool) | redo
    else:
        out, exact = step1(None)[0], jnp.ones(tr.shape, bool)
    g, guard, cap, box = out[:4]
    record = box_record(g, guard, cap.astype(jnp.int64), box.astype(jnp.int64), Stage.CAPSULE, xp=jnp)
    self_test = None
    if self_check is not None:
        gs, gds, c1, c2 = self_intervals(robot, capsules, splines, bounds, tr, a, b, self_check)
        self_test = self_record(gs, gds, c1.astype(jnp.int64), c2.astype(jnp.int64), xp=jnp)
    to_hull = jnp.zeros(tr.shape, bool)
    if cascade is not None:  # the hull stage where the capsules fail and the screen leaves it a chance
        to_hull = needs_hull(record, self_test, xp=jnp) & (out[4] > 0)
    return t0, t1, compose(record, self_test, xp=jnp), to_hull, () if self_test is None else tuple(self_test), exact


def _hull_stage(args, broad: bool, tr, dp, ix, valid, queued):
    """The hull stage (:mod:`larc_jax.engine.tree_hull`) on the lanes ``(tr, dp, ix)`` taken from the
    hull queue (``valid`` those in use, every one a root; ``queued``: their self test's record columns, saved by
    :func:`_first_stage`), composed with the self test as :func:`_first_stage` composes the capsule
    stage's. Returns what :func:`_first_stage` returns (no lane goes to the queue again)."""
    robot, capsules, splines, obstacles, bounds, scene_of, t_start, t_end, margin, self_check, cascade = args
    hulls, of_capsule, part_table, of_part, slack = cascade
    t0, t1, a, b = _ends(args, tr, dp, ix)
    model = (robot, capsules, hulls, splines, obstacles, bounds, scene_of, margin, of_capsule, of_part,
             part_table.shape[0], slack)
    record = hull_stage_lanes(model, tr, a, b, valid)
    self_test = LeafRecord(*queued) if queued else None
    return t0, t1, compose(record, self_test, xp=jnp), jnp.zeros(tr.shape, bool), queued, jnp.ones(tr.shape, bool)


def _padded(stage, lanes: int, wide: int):
    """``stage`` on the first ``lanes`` of a step's ``wide`` lanes (the rest are never valid there),
    its outputs padded back to ``wide``."""
    if lanes == wide:
        return stage

    def run(args, broad, *lane_arrays):
        cut = jax.tree.map(lambda x: x[:lanes], lane_arrays)
        out = stage(args, broad, *cut)
        return jax.tree.map(lambda x: jnp.concatenate([x, jnp.zeros((wide - lanes,), x.dtype)]), out)

    return run


def speculation_levels(n, width):
    """How many levels below each of its ``n`` intervals a first-stage step of ``width`` lanes
    evaluates too: the most ``L <= SPECULATION_LEVELS`` with ``n * (2**(L + 1) - 1) <= width`` (0
    when ``n`` is 0, a hull step). A short stack (one trajectory's first levels, the last intervals
    of a batch) would leave most of a step's lanes padding; its intervals' descendants fill them,
    and a descendant's result is kept only where every interval above it opened (:func:`_step`), so
    the tree evaluates, decides and counts what it did without them, in fewer steps."""
    return sum(((n > 0) & (n * ((2 << level) - 1) <= width)).astype(jnp.asarray(n).dtype)
               for level in range(1, SPECULATION_LEVELS + 1))


def _step(args, max_depth, broad: bool, widths, narrow_phase: bool, state):
    """One step, on ``max(narrow, hull)`` lanes in the narrow phase and ``wide`` in the wide one
    (:func:`tree_program`). A *first-stage* step pops up to its phase's width of intervals off the
    stack and evaluates their capsule stage and self test (in the narrow phase, with their
    descendants down :func:`speculation_levels`); a *hull* step (narrow phase only), taken whenever
    the hull queue holds ``hull`` intervals (or the stack is empty and it holds any), pops up to
    ``hull`` of them and runs their hull stage. Either writes its finished lanes into the leaf
    buffers and pushes both children of its open ones onto the stack; a first-stage step puts the
    lanes the hull stage decides onto the hull queue instead. Only the evaluation is under the
    branch: its operands are a step's lanes, not the buffers (a branch over the whole state would
    copy them each step)."""
    wide, narrow, hull = widths
    stack, top, queue, n_queued, leaves, n_leaves, frontier, steps = state
    capacity = stack[0].shape[0]
    width, lanes = (narrow, max(narrow, hull)) if narrow_phase else (wide, wide)
    # Only the cascade has a hull queue (static: the capsule test carries none and never takes a hull step).
    hull_now = ((n_queued >= hull) | ((top == 0) & (n_queued > 0))) if queue and narrow_phase else jnp.bool_(False)
    n = jnp.where(hull_now, 0, jnp.minimum(top, width))
    m = jnp.where(hull_now, jnp.minimum(n_queued, hull), 0)
    start, q_start = top - n, n_queued - m
    lane = jnp.arange(lanes, dtype=top.dtype)
    if narrow_phase:
        # Each of the step's `n_roots` intervals (popped, or taken from the queue) on `per` lanes: the
        # interval, then its descendants `ahead` levels down, heap order (lane = root + n_roots * node).
        ahead = speculation_levels(n, width)
        n_roots, per = n + m, (1 << (ahead + 1)) - 1
        valid = lane < n_roots * per
        root, node = lane % jnp.maximum(n_roots, 1), jnp.where(valid, lane // jnp.maximum(n_roots, 1), 0)
        level = (31 - jax.lax.clz(node + 1)).astype(top.dtype)  # floor(log2(node + 1))
    else:  # at least wide // 2 intervals: none evaluated ahead
        ahead, valid, root = 0, lane < n, lane
        node = level = jnp.zeros_like(lane)
    rows = jnp.where(valid, start + root, 0)
    # A padding lane evaluates trajectory 0's root (a real interval); nothing it computes is kept.
    tr, dp, ix = (jnp.where(valid, s[rows], 0) for s in stack)
    queued = ()
    if queue and narrow_phase:
        q_rows = jnp.where(valid & hull_now, q_start + root, 0)
        tr, dp, ix = (jnp.where(hull_now & valid, q[q_rows], x) for q, x in zip(queue, (tr, dp, ix)))
        queued = tuple(q[q_rows] for q in queue[3:])
    if narrow_phase:
        dp, ix = dp + level, (ix << level.astype(ix.dtype)) + (node + 1 - (1 << level)).astype(ix.dtype)
    operands = (tr, dp, ix, valid & (node == 0), queued)
    if not narrow_phase:
        out = _first_stage(args, broad, *operands)
    elif queue:
        branches = [functools.partial(_padded(stage, w, lanes), args, broad)
                    for stage, w in ((_first_stage, narrow), (_hull_stage, hull))]
        out = jax.lax.switch(hull_now.astype(jnp.int32), branches, *operands)
    else:
        out = _padded(_first_stage, narrow, lanes)(args, broad, *operands)
    t0, t1, record, to_hull, self_cols, exact = out
    passed = record.stage > 0  # g > guard for every stage that ran; NaN never passes (larc_jax.leaf.record)
    # A lane counts only where its parent (the lane `(node - 1) // 2` levels up) was evaluated and
    # opened: what the level-by-level frontier evaluates. One more level is settled per round. A
    # lane evaluated ahead whose broad phase did not prove its pick goes back on the stack instead
    # (`again`, evaluated as a step's own interval later; its descendants here are not kept).
    active = valid & (node == 0)
    if narrow_phase:
        parent = jnp.where(node > 0, root + n_roots * ((node - 1) // 2), 0)
        for _ in range(SPECULATION_LEVELS):
            open_ = active & exact & ~to_hull & ~passed & (dp < max_depth)
            active = valid & ((node == 0) | ((node > 0) & open_[parent]))
    again = active & ~exact
    to_hull = to_hull & active & exact
    done = active & exact & ~to_hull
    final = done & (passed | (dp == max_depth))
    open_ = done & ~final
    push = open_ & (level == ahead)  # the step evaluated the children of the others
    # Stream compaction by prefix sums; a write to an index past the end is dropped.
    at = jnp.where(final, n_leaves + jnp.cumsum(final) - 1, leaves[0].shape[0])
    leaves = tuple(buf.at[at].set(x.astype(buf.dtype), mode="drop")
                   for buf, x in zip(leaves, (tr, dp, ix, t0, t1, *record)))
    count = 2 * push + again  # stack entries a lane pushes: both children, or itself
    first = start + jnp.cumsum(count) - count
    left, right = jnp.where(count > 0, first, capacity), jnp.where(push, first + 1, capacity)
    stack = tuple(s.at[left].set(jnp.where(push, x, z), mode="drop").at[right].set(y, mode="drop")
                  for s, x, y, z in zip(stack, (tr, dp + 1, 2 * ix), (tr, dp + 1, 2 * ix + 1), (tr, dp, ix)))
    if queue:
        to = jnp.where(to_hull, q_start + jnp.cumsum(to_hull) - 1, queue[0].shape[0])
        queue = tuple(q.at[to].set(x.astype(q.dtype), mode="drop") for q, x in zip(queue, (tr, dp, ix, *self_cols)))
    # An interval counts once, where it finishes or opens: one the queue holds when a call stops
    # is evaluated again in the next call (run_tree).
    frontier = frontier.at[jnp.where(done, tr, frontier.shape[0]), dp].add(1, mode="drop")
    return (stack, (start + count.sum()).astype(top.dtype), queue,
            (q_start + to_hull.sum()).astype(n_queued.dtype), leaves, (n_leaves + final.sum()).astype(n_leaves.dtype),
            frontier, steps.at[hull_now.astype(jnp.int32)].add(1).at[2].add(again.sum().astype(steps.dtype)))


@functools.partial(jax.jit, static_argnames=("broad", "wide", "narrow", "hull", "leaf_capacity"))
def tree_program(robot, capsules, splines, obstacles, bounds, scene_of, t_start, t_end, margin, self_check, cascade, stack,
                 top, frontier, max_depth, *, broad: bool, wide: int, narrow: int, hull: int, leaf_capacity: int):
    """The tree from ``stack`` (trajectory, depth, index arrays, the first ``top`` in use) until the
    stack and the hull queue are empty or the next step could overflow the stack or the leaf
    buffers. Returns ``(stack, top, queue, n_queued, leaves, n_leaves, frontier, steps)``: what is
    left (``queue``: the hull queue's trajectory, depth and index columns, then the saved self-test
    columns, the first ``n_queued`` in use; none with the capsule test), the leaf columns
    (:data:`_LEAF_DTYPES`; the first ``n_leaves`` in use), ``frontier`` with this call's evaluations
    added, and the steps run (first-stage steps, hull steps; then :attr:`TreeLeaves.again`).
    ``self_check``: as :func:`~larc_jax.engine.kernels.self_intervals` takes it, or None (no self
    test). ``cascade``: ``(hulls, Links.of_capsule, Links.part_table, Links.of_part,
    early_stop_slack)`` for the cascade (the hull stage after the capsule stage), or None (the
    capsule test). ``max_depth`` is traced (an int32 scalar): every depth runs the same compiled
    program.

    Two phases, each its own loop over the same state: wide steps while the stack holds at least
    ``wide // 2`` intervals and the hull queue fewer than ``hull``, then narrow steps (first-stage
    or hull) until that holds again, and so on. A step's bookkeeping (its prefix sums and scatters)
    runs on its phase's lanes: a narrow step's on 16 or 32, not on the wide step's 256."""
    args = (robot, capsules, splines, obstacles, bounds, scene_of, t_start, t_end, margin, self_check, cascade)
    capacity = stack[0].shape[0]
    leaves = tuple(jnp.zeros(leaf_capacity, d) for d in _LEAF_DTYPES)
    # A first-stage step adds at most `wide` lanes to a queue holding fewer than `hull`.
    q_dtypes = (*(s.dtype for s in stack), *(() if self_check is None else _RECORD_DTYPES))
    queue = () if cascade is None else tuple(jnp.zeros(wide + hull, d) for d in q_dtypes)
    grow = max(wide, 2 * hull)
    step = functools.partial(_step, args, max_depth, broad, (wide, narrow, hull))

    def room(state):
        top, n_queued, n_leaves = state[1], state[3], state[5]
        return (((top > 0) | (n_queued > 0)) & (top + grow <= capacity) & (n_leaves + wide <= leaf_capacity))

    def wide_now(state):
        return (state[1] >= wide // 2) & (state[3] < hull)

    def phases(state):
        state = jax.lax.while_loop(lambda s: room(s) & wide_now(s), functools.partial(step, False), state)
        return jax.lax.while_loop(lambda s: room(s) & ~wide_now(s), functools.partial(step, True), state)

    return jax.lax.while_loop(room, phases, (stack, top, queue, jnp.int32(0), leaves, jnp.int32(0), frontier,
                                             jnp.zeros(3, jnp.int32)))


@functools.lru_cache(maxsize=None)
def _program(broad: bool, wide: int, narrow: int, hull: int, leaf_capacity: int):
    """One callable per static configuration (:func:`~larc_jax.compilation.tracked_call` knows a
    shape it has seen by the callable), kept compiled with the cache on."""
    return cached_kernel(functools.partial(tree_program, broad=broad, wide=wide, narrow=narrow, hull=hull,
                                           leaf_capacity=leaf_capacity))


def run_tree(batch, n_traj: int, max_depth: int, on_compile=None, *, wide: int = WIDE_STEP,
             narrow: int = NARROW_STEP, hull: int | None = None, leaf_capacity: int = LEAF_CAPACITY,
             seeds=None, progress=None) -> TreeLeaves:
    """LARC on the first ``n_traj`` trajectories of ``batch`` (one :func:`supports`), from every
    trajectory's root down to ``max_depth``: the device program, called again with what is left
    while a call stops short. ``on_compile``: as :meth:`Batch.evaluate <larc_jax.engine.batch.Batch.evaluate>`.
    ``hull``: a hull step's width (None: :data:`HULL_STEP` by the batch class). ``seeds``: the
    trajectories (of the first ``n_traj``) whose roots seed the stack (None: all; empty: one call
    that evaluates nothing, which compiles the program); the buffers are sized by ``n_traj``
    whatever the seeds, so every subset runs the same program (:mod:`larc_jax.engine.tree_pool`).
    ``progress``: called with the evaluations of each program call."""
    if not supports(batch):
        raise ValueError("run_tree: the device tree runs the capsule test or the cascade (and the self test) on whole "
                         f"scenes, on one device, without the swept stage or point-cloud pieces, at most {MAX_TRIPLES} "
                         "(part, item) pairs per interval")
    if hull is None:
        hull = HULL_STEP if size_class(n_traj, 1) < HULL_WIDE_FROM else 2 * HULL_STEP
    if (not (1 <= narrow <= wide <= leaf_capacity and 1 <= hull <= wide) or n_traj < 1
            or not 0 <= max_depth <= MAX_DEPTH_LIMIT):
        raise ValueError(f"run_tree: need 1 <= narrow ({narrow}) <= wide ({wide}) <= leaf_capacity "
                         f"({leaf_capacity}), 1 <= hull ({hull}) <= wide, n_traj >= 1, 0 <= max_depth ({max_depth}) "
                         f"<= {MAX_DEPTH_LIMIT}")
    grow = max(wide, 2 * hull)
    capacity = size_class(n_traj, 1) + STACK_SLACK * grow * (DEFAULT_MAX_DEPTH + 1)
    leaf_capacity = min(leaf_capacity, (size_class(n_traj, 1) << DEFAULT_MAX_DEPTH) + wide)  # LEAF_CAPACITY
    roots = np.arange(n_traj, dtype=np.int32) if seeds is None else np.asarray(seeds, np.int32)
    pending = [roots, np.zeros(len(roots), np.int32), np.zeros(len(roots), np.int64)]
    rows = size_class(len(batch.t_start), 1)  # per-trajectory arrays padded as the splines are (one shape per class)
    pad = lambda x: np.concatenate([x, np.repeat(x[:1], rows - len(x))])  # noqa: E731
    frontier = np.zeros((rows, MAX_DEPTH_LIMIT + 1), np.int64)
    program = _program(bool(batch.use_broad_phase), wide, narrow, hull, leaf_capacity)
    sp = batch.self_pairs
    self_check = None if sp is None else (sp.first, sp.second, sp.motion_a, np.asarray(sp.margin_m, np.float64),
                                          batch.self_skip)
    links = batch.links
    cascade = None if batch.hulls is None else (batch.hulls, links.of_capsule, links.part_table, links.of_part,
                                                np.float64(early_stop_slack(batch.dtype)))
    args = (batch.robot, batch.capsules, batch.splines, batch.obstacles, batch.bounds, pad(batch.scene_of),
            pad(batch.t_start), pad(batch.t_end), batch.margin, self_check, cascade)
    found, calls, steps = [], 0, np.zeros(3, np.int64)
    while calls == 0 or len(pending[0]):
        take = min(len(pending[0]), capacity - grow)  # the top of the pending stack, deepest first
        stack = tuple(np.concatenate([p[len(p) - take:], np.zeros(capacity - take, p.dtype)]) for p in pending)
        pending = [p[: len(p) - take] for p in pending]
        with jax.enable_x64(True):
            out = tracked_call(program, (*args, stack, np.int32(take), frontier, np.int32(max_depth)), on_compile)
            stack, top, queue, n_queued, leaves, n_leaves = jax.tree.map(np.asarray, out[:6])
            before, frontier = frontier, out[6]
        calls, steps = calls + 1, steps + np.asarray(out[7])
        if progress is not None:
            progress(int(np.asarray(frontier).sum() - np.asarray(before).sum()))
        found.append([x[: int(n_leaves)] for x in leaves])
        # What a stopped call left: its stack, and the hull queue's intervals (evaluated again).
        left = [s[: int(top)] for s in stack] if not queue else [
            np.concatenate([s[: int(top)], q[: int(n_queued)]]) for s, q in zip(stack, queue)]
        pending = [np.concatenate([p, x]) for p, x in zip(pending, left)]
    traj, depth, index, t0, t1, *columns = (np.concatenate(c) for c in zip(*found))
    order = np.lexsort((t0, traj))
    g, guard, cap, box, other, stage = (x[order] for x in columns)
    record = LeafRecord(g, guard, cap.astype(np.int64), box.astype(np.int64), other.astype(np.int64), stage)
    return TreeLeaves(traj[order].astype(np.int64), depth[order].astype(np.int64), index[order], t0[order], t1[order],
                      record, np.array(frontier)[:n_traj, : max_depth + 1], calls, int(steps[:2].sum()), int(steps[1]),
                      int(steps[2]))
