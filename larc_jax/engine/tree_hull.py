"""The hull stage inside the device tree (:mod:`larc_jax.engine.tree`): steps 2-5 of the cascade
(:mod:`larc_jax.leaf.cascade`) on the lanes of one hull step, with fixed shapes.

The host cascade (:meth:`Batch._hull_stage <larc_jax.engine.batch.Batch>`) selects intervals,
pairs and triples with NumPy between kernel calls; here the shapes are fixed when the program
compiles, and every selection of triples is a stream compaction (a prefix sum and a scatter) into
a buffer of fixed size:

* the lanes the capsule stage fails whose screen passes (the host's ``open_`` after
  ``_hopeless``) are gathered by the tree's hull queue into the lanes of a hull step, ``H`` of
  them (:func:`hull_sizes`); step 2 runs on every lane of the step (a lane the step does not
  fill is padding: its results are not read) with every capsule-box pair exact
  (:func:`~larc_jax.leaf.cascade.interval_pairs`: what the host's bounded call gives wherever its
  result could matter, :func:`~larc_jax.leaf.cascade.exact_enough`; the bounded call with the
  exact one on the lanes it leaves, tried here in two ways, made a Stage B trajectory 5-8 % slower
  one per call, measured while developing);
* step 3 (:func:`~larc_jax.leaf.cascade.select_pairs`) marks the tried (link, item) pairs and
  their (part, item) triples, dense ``(H, P, N)`` in the host's order (lane, part, item);
* step 4 runs the three rounds of :func:`~larc_jax.leaf.rounds.hull_rounds` with the same rule:
  the first axis on every triple, the middle round (with its upper bound) on those it leaves at
  or below their guard, the full search on those the middle round leaves undecided; each round
  compacts its triples ``M0``, ``M1`` or ``M2`` at a time (:func:`chunked`);
* step 5 is :func:`combine_jnp`, :func:`~larc_jax.leaf.cascade.combine` on the dense arrays.

Every compaction is a ``lax.while_loop`` that runs until nothing is left (each round its buffer's
width at a time): a step needing more than a buffer holds runs the loop again, so nothing
overflows or is deferred. The sizes only trade padding (work in every iteration)
against iterations.

The decisions are those of the host cascade: the same kernels (one program instead of several,
so a value may differ in its last bit, as between any two programs) and the same rules. A
hull-stage record may differ from the host's in its last bits for the same reason.
"""

from __future__ import annotations

from ..lazy_jax import jax, jnp
from ..leaf.record import Stage, box_record
from .kernels import batched_interval_pairs, hull_early, hull_first_axis, hull_pairs

__all__ = ["hull_sizes", "compact", "chunked", "link_min", "combine_jnp", "hull_stage_lanes"]


def hull_sizes(lanes: int) -> tuple[int, int, int, int]:
    """``(H, M0, M1, M2)`` for a hull step of ``lanes`` lanes: the lanes step 2 runs on (all of
    them), and the triples each round searches at once (first axis, middle round, full search).
    Sized from the Stage B set (LARC, the cascade): the hull stage runs with 1.6 triples an interval; the
    middle round takes about a third of them, the full search 2 %. A step needing more runs its
    loops again (module docstring); padding costs work in every run, so each size is about what a
    step needs."""
    return lanes, 2 * lanes, max(2, lanes // 2), max(2, lanes // 8)


def compact(mask, size: int):
    """The first ``size`` true entries of ``mask`` (1-D): ``(src, valid, kept)``, ``src`` (size,)
    their indices (0 past the last), ``valid`` (size,) which of ``src`` are in use, ``kept`` (like
    ``mask``) the entries that got a place."""
    pos = jnp.cumsum(mask.astype(jnp.int32)) - 1
    kept = mask & (pos < size)
    src = jnp.zeros(size, jnp.int32).at[jnp.where(kept, pos, size)].set(
        jnp.arange(mask.shape[0], dtype=jnp.int32), mode="drop")
    return src, jnp.arange(size) < kept.sum(), kept


def chunked(mask, size: int, run, values):
    """``run(src)`` on every true entry of ``mask`` (1-D), ``size`` entries a call (compacted, the last
    call padded), its outputs (a tuple of (size,) arrays) scattered into ``values`` (a tuple of arrays
    shaped like ``mask``) at their entries: a loop that runs as often as the entries need."""

    def body(state):
        remaining, values = state
        src, used, kept = compact(remaining, size)
        at = jnp.where(used, src, mask.shape[0])
        return remaining & ~kept, tuple(v.at[at].set(o, mode="drop") for v, o in zip(values, run(src)))

    return jax.lax.while_loop(lambda state: state[0].any(), body, (mask, values))[1]


def link_min(values, owner, n_links: int):
    """(H, E, N) values per capsule or part -> (H, L, N) the least per link, ``owner`` (E,) each
    one's link (a NaN makes it NaN; a link with none: +inf), as :meth:`Links.reduce_min
    <larc_jax.leaf.cascade.Links.reduce_min>`. The NaN is carried explicitly: XLA's CPU reduction may
    drop a NaN operand (measured: ``jnp.min`` over this axis returned a number beside a NaN)."""
    on = (owner[None, :] == jnp.arange(n_links)[:, None])[None, :, :, None]  # (1, L, E, 1)
    nan = jnp.isnan(values)[:, None]  # (H, 1, E, N)
    least = jnp.min(jnp.where(on & ~nan, values[:, None], jnp.inf), axis=2)
    return jnp.where((on & nan).any(axis=2), jnp.nan, least)


def _first_least(values, on):
    """Per row, the index ``np.argmin`` gives over ``values`` where ``on`` (elsewhere +inf): the first
    NaN, else the first least (explicit, as :func:`link_min`)."""
    nan = on & jnp.isnan(values)
    least = jnp.argmin(jnp.where(on & ~nan, values, jnp.inf), axis=1)
    return jnp.where(nan.any(axis=1), jnp.argmax(nan, axis=1), least)


def combine_jnp(of_capsule, of_part, n_links: int, g_capsule, guard_capsule, tried, g_hull, guard_hull):
    """Step 5 (:func:`~larc_jax.leaf.cascade.combine`) on dense arrays: ``g_capsule`` (H, C, N),
    ``guard_capsule`` (H, C), ``tried`` (H, L, N), ``g_hull`` and ``guard_hull`` (H, P, N) (+inf and 0
    where no triple). Returns ``(g, guard, capsule, item)`` (H,), the same picks as ``combine``: the
    least (link, item) excess (NaN first), the least capsule of that link, and where the hull decided
    it the part of least excess (NaN first, then the lowest part)."""
    H, C, N = g_capsule.shape
    cap_ex = g_capsule - guard_capsule[:, :, None]
    cap = link_min(cap_ex, of_capsule, n_links)  # (H, L, N)
    hull_ex = g_hull - guard_hull
    hull = link_min(hull_ex, of_part, n_links)
    use_hull = tried & (hull > cap)
    value = jnp.where(use_hull, hull, cap)
    value = jnp.where(tried & (jnp.isnan(hull) | jnp.isnan(cap)), jnp.nan, value)
    flat = value.reshape(H, -1)
    nan = jnp.isnan(flat).any(axis=1)
    best = jnp.argmin(jnp.where(jnp.isnan(flat), -jnp.inf, flat), axis=1)
    link, item = best // N, best % N
    rows = jnp.arange(H)
    on_link = of_capsule[None, :] == link[:, None]  # (H, C)
    capsule = _first_least(cap_ex[rows, :, item], on_link)
    part = _first_least(hull_ex[rows, :, item], of_part[None, :] == link[:, None])
    won = use_hull.reshape(H, -1)[rows, best]
    g = jnp.where(won, g_hull[rows, part, item], g_capsule[rows, capsule, item])
    guard = jnp.where(won, guard_hull[rows, part, item], guard_capsule[rows, capsule])
    return jnp.where(nan, jnp.nan, g), guard, capsule, item


def hull_stage_lanes(model, tr, a, b, need):
    """Steps 2-5 on the lanes ``need`` (n,) of a hull step of n lanes (``tr`` trajectory, ``a, b``
    rebased ends; the sizes are :func:`hull_sizes` of n): step 2 runs on every lane, and a lane
    outside ``need`` is padding whose results are not read.
    ``model = (robot, capsules, hulls, splines, obstacles, bounds, scene_of, margin, of_capsule,
    of_part, n_links, slack)``, ``slack`` :func:`~larc_jax.leaf.rounds.early_stop_slack`. Returns the
    lanes' hull-stage records (n,) (:class:`~larc_jax.leaf.record.LeafRecord`, stage HULL; read
    only on ``need``)."""
    robot, capsules, hulls, splines, obstacles, bounds, scene_of, margin, of_capsule, of_part, n_links, slack = model
    H, M0, M1, M2 = hull_sizes(tr.shape[0])
    scene = scene_of[tr]
    g_cap, T_part, motion_b, g_up = batched_interval_pairs(robot, capsules, hulls, splines, obstacles, bounds, tr,
                                                           (scene,), a, b, margin)
    G_c, G_p = bounds.guard_m[tr], bounds.hull_guard_m[tr]  # (H, C), (H, P)
    P, N = g_up.shape[1], g_up.shape[2]
    # Step 3: a pair is tried when its capsules fail and every one of its parts could pass.
    cap = link_min(g_cap - G_c[:, :, None], of_capsule, n_links)
    upper = link_min(g_up - G_p[:, :, None], of_part, n_links)
    tried = ~(cap > 0) & (upper > 0) & ~jnp.isnan(cap) & need[:, None, None]
    want = tried[:, of_part, :].reshape(-1)  # (H * P * N): every part of every tried link
    guard = jnp.broadcast_to(G_p[:, :, None], (H, P, N)).reshape(-1)

    def search(kernel):  # one round's kernel on the triples src (flat (lane, part, item) indices)
        def run(src):
            i, p, k = src // (P * N), (src // N) % P, src % N
            return kernel(hulls, p, T_part[i, p], obstacles.take((scene[i], k)), motion_b[i, p], margin)
        return run

    def middle(src):
        lower, up = search(hull_early)(src).T
        return lower, (lower > guard[src]) | (up <= guard[src] - slack)

    # Step 4 in the rounds of larc_jax.leaf.rounds.hull_rounds.
    g = jnp.full(want.shape, jnp.inf, g_up.dtype)
    (g,) = chunked(want, M0, lambda src: (search(hull_first_axis)(src),), (g,))
    redo = want & ~(g > guard)
    g, stop = chunked(redo, M1, middle, (g, jnp.zeros(want.shape, bool)))
    (g,) = chunked(redo & ~stop, M2, lambda src: (search(hull_pairs)(src),), (g,))
    g_rec, guard_rec, capsule, item = combine_jnp(of_capsule, of_part, n_links, g_cap, G_c, tried,
                                                  g.reshape(H, P, N), jnp.where(want, guard, 0.0).reshape(H, P, N))
    return box_record(g_rec, guard_rec, capsule.astype(jnp.int64), item.astype(jnp.int64), Stage.HULL, xp=jnp)
