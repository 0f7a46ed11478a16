"""The smallest segment–obstacle clearance of one configuration, with a sound broad phase.

The interval test needs ``g = min_{s, b} dist(segment_s, item_b) - offset_s - offset_b`` over
every capsule segment ``s`` and real obstacle ``b`` of an obstacle set
(:mod:`larc_jax.obstacles`; ``offset_s = r_s + b_s(I) + rho``, ``offset_b`` a per-item term such
as a rounding guard), and the pair attaining it. Computing the distance (the kind's
``segment_distance``; for a box, :func:`larc_jax.obstacles.geometry.segment_box_distance`, a few thousand
operations) for every pair makes the interval kernel cost ``C * B`` distances, although at most
a few pairs are ever close to the minimum.

Broad phase (:func:`min_clearance`). For every pair a cheap *lower bound* of the distance, the
kind's ``segment_lower_bound`` (for a box, the gap between the segment's axis-aligned bounding
box and the box, rounded down by a bound on its rounding error). The ``k`` pairs with the
smallest lower clearance ``lam = lb - offsets`` get the distance, ``e_1..e_k``; ``m = min e_j``.
Every other pair ``p`` has clearance ``>= lam_p >= lam_(k+1)`` (the (k+1)-th smallest), so

    if m <= lam_(k+1):   m is the exact minimum over ALL pairs (``exact`` is True);

otherwise ``exact`` is False and the caller recomputes the interval with every pair
(``k=None``). Either way the returned ``g`` is the minimum clearance the all-pairs computation
gives (ties: the smallest flat pair index ``s * B + b``, as in the all-pairs ``argmin``), so the
broad phase changes the cost, never a result. Masked (padding) items get ``+inf`` everywhere:
they can never attain the minimum or force a recomputation.

:func:`min_clearance_np` is the NumPy float64 reference: every pair, plain loops.
"""

from __future__ import annotations

import math

from ..lazy_jax import jnp

__all__ = ["min_clearance", "pair_clearances", "min_clearance_np", "BROAD_PHASE_K", "PAIR_EXACT_K"]

BROAD_PHASE_K = 4
"""Pairs per interval that get the exact distance in the broad phase (the rest only a bound)."""
PAIR_EXACT_K = 8
"""Pairs per interval that get the exact distance in step 2 of the cascade
(:func:`pair_clearances`; larc_jax.leaf.cascade): every pair its capsules may fail, in nearly every interval."""


def min_clearance(p_a, p_b, offset_seg, obstacles, offset_box, k: int | None = BROAD_PHASE_K,
                  dist_scale=1.0, guard_seg=None):
    """``(g, seg, box, exact)`` for one configuration (module docstring).

    Args:
      p_a, p_b: (S, 3) segment ends, m.
      offset_seg: (S,) subtracted from each segment's distances (e.g. r + b + rho), m.
      obstacles: one scene's obstacle set (:class:`~larc_jax.obstacles.ObstacleSet`, B items, its
        ``mask`` the real ones); offset_box: (B,) subtracted per item, m.
      k: pairs that get the exact distance (static); ``None``: every pair exact.
      dist_scale: a positive factor applied to every distance first (e.g. the interval test's
        rounding deflation); distances and bounds are cast to ``offset_seg``'s dtype before it.
      guard_seg: (S,) per-segment guard: the pair chosen minimises ``g - guard_seg[s]`` (the
        interval test's rounding guards); default 0.

    Returns ``g = dist * dist_scale - offset_seg[s] - offset_box[b]`` of the chosen pair (+inf
    without real items), its segment and item indices, and whether it is certainly the pair the
    all-pairs computation chooses (always True for ``k=None``). Scaling and subtracting are
    monotone under rounding, so the bounds stay below the values they bound.
    """
    S, B = p_a.shape[0], obstacles.n_items
    mask = obstacles.mask
    dt = jnp.result_type(offset_seg, 0.0)
    inf = jnp.asarray(jnp.inf, dt)
    guard = jnp.zeros((S,), dt) if guard_seg is None else guard_seg

    def value(dist, s, b):
        return dist.astype(dt) * dist_scale - offset_seg[s] - offset_box[b]

    if k is None or k >= S * B:
        dist = obstacles.segment_distances(p_a, p_b)
        g_pair = jnp.where(mask[None, :], dist.astype(dt) * dist_scale - offset_seg[:, None] - offset_box[None, :], inf)
        flat = jnp.argmin((g_pair - guard[:, None]).reshape(-1))
        return g_pair.reshape(-1)[flat], flat // B, flat % B, jnp.asarray(True)
    lb = obstacles.segment_lower_bounds(p_a, p_b)
    lam = lb.astype(dt) * dist_scale - offset_seg[:, None] - offset_box[None, :] - guard[:, None]
    lam = jnp.where(mask[None, :], lam, inf).reshape(-1)
    exact_v, exact_x = [], []
    chosen, lam_chosen, lam = _smallest(lam, k)
    for i, lam_i in zip(chosen, lam_chosen):
        s, b = i // B, i % B
        v = value(obstacles.take(b).segment_distance(p_a[s], p_b[s]), s, b)
        real = mask[b] & (lam_i < inf)
        exact_v.append(jnp.where(real, v, inf))
        exact_x.append(jnp.where(real, v - guard[s], inf))
    exact_v, exact_x, chosen = jnp.stack(exact_v), jnp.stack(exact_x), jnp.stack(chosen)
    m = jnp.min(exact_x)
    # Ties between chosen pairs: the smallest flat index, as the all-pairs argmin picks.
    flat = jnp.min(jnp.where(exact_x == m, chosen, S * B))
    pick = jnp.argmax(chosen == flat)
    pick = jnp.where(flat == S * B, 0, pick)  # m is NaN: keep the first choice
    flat = chosen[pick]
    return exact_v[pick], flat // B, flat % B, m <= jnp.min(lam)


def _smallest(lam, k: int):
    """The flat indices of the ``k`` smallest of ``lam`` in order (ties: the smallest index), their
    values, and ``lam`` with them set to +inf."""
    n, inf = lam.shape[0], jnp.asarray(jnp.inf, lam.dtype)
    iota, chosen, values = jnp.arange(n), [], []
    for _ in range(k):
        # argmin as two plain min-reductions (XLA's variadic argmin reduce is much slower).
        i = jnp.min(jnp.where(lam == jnp.min(lam), iota, n - 1))
        chosen.append(i)
        values.append(lam[i])
        lam = jnp.where(iota == i, inf, lam)
    return chosen, values, lam


def pair_clearances(p_a, p_b, offset_seg, obstacles, k: int, dist_scale=1.0, guard_seg=None):
    """``(g, rest)``: every pair's clearance ``g = dist * dist_scale - offset_seg[s]`` (S, B) with the
    ``k`` pairs of smallest lower excess ``lam = lb * dist_scale - offset_seg - guard_seg`` (module
    docstring) exact and every other pair at its lower bound ``lb * dist_scale - offset_seg``
    (never above its exact value: scaling and subtracting are monotone under rounding), and
    ``rest``, the smallest ``lam`` of the pairs left at their bound (+inf if none): a lower bound of
    ``g - guard_seg`` for each of them. Masked items: +inf."""
    S, B = p_a.shape[0], obstacles.n_items
    dt = jnp.result_type(offset_seg, 0.0)
    g = jnp.where(obstacles.mask[None, :], obstacles.segment_lower_bounds(p_a, p_b).astype(dt) * dist_scale
                  - offset_seg[:, None], jnp.inf).reshape(-1)
    chosen, _, rest = _smallest(g - jnp.repeat(guard_seg, B), min(k, S * B))
    iota = jnp.arange(S * B)
    for i in chosen:
        s, b = i // B, i % B
        v = obstacles.take(b).segment_distance(p_a[s], p_b[s]).astype(dt) * dist_scale - offset_seg[s]
        g = jnp.where(iota == i, jnp.where(obstacles.mask[b], v, jnp.inf), g)  # a select, not a scatter
    return g.reshape(S, B), jnp.min(rest, initial=jnp.inf)


def min_clearance_np(p_a, p_b, offset_seg, obstacles, offset_box):
    """NumPy float64 reference of :func:`min_clearance` (every pair exact): ``(g, seg, item)``."""
    g_best, best = math.inf, (0, 0)
    for s in range(len(p_a)):
        for b in range(obstacles.n_items):
            if not obstacles.mask[b]:
                continue
            g = obstacles.take(b).segment_distance_np(p_a[s], p_b[s]) - float(offset_seg[s]) - float(offset_box[b])
            if g < g_best or (math.isnan(g) and not math.isnan(g_best)):
                g_best, best = g, (s, b)
    return g_best, best[0], best[1]
