"""The smallest segment–box clearance of one configuration, with a sound broad phase.

The interval test needs ``g = min_{s, b} dist(segment_s, box_b) - offset_s - offset_b`` over
every capsule segment ``s`` and real box ``b`` (``offset_s = r_s + b_s(I) + rho``, ``offset_b``
a per-box term such as a rounding guard), and the pair attaining it. Computing the exact
distance (:func:`larc_jax.obstacles.geometry.segment_box_distance`, a few thousand operations) for every
pair makes the interval kernel cost ``C * B`` exact distances, although at most a few pairs are
ever close to the minimum.

Broad phase (:func:`min_clearance`). For every pair a cheap *lower bound* of the distance,
``lb = |gap(AABB(segment), box)|``, the distance between the segment's axis-aligned bounding
box and the box (every point of the segment lies in its AABB, so the true distance is at least
that), rounded down by a bound on its rounding error. The ``k`` pairs with the smallest lower
clearance ``lam = lb - offsets`` get the exact distance, ``e_1..e_k``; ``m = min e_j``. Every
other pair ``p`` has exact clearance ``>= lam_p >= lam_(k+1)`` (the (k+1)-th smallest), so

    if m <= lam_(k+1):   m is the exact minimum over ALL pairs (``exact`` is True);

otherwise ``exact`` is False and the caller recomputes the interval with every pair exact
(``k=None``). Either way the returned ``g`` is the exact minimum clearance the all-pairs
computation gives (ties: the smallest flat pair index ``s * B + b``, as in the all-pairs
``argmin``), so the broad phase changes the cost, never a result. Masked (padding) boxes get
``+inf`` everywhere: they can never attain the minimum or force a recomputation.

:func:`min_clearance_np` is the NumPy float64 reference: every pair exact, plain loops.
"""

from __future__ import annotations

import math

import numpy as np

from ..obstacles.geometry import segment_box_distance, segment_box_distance_np
from ..lazy_jax import jax, jnp

__all__ = ["segment_box_lower_bound", "min_clearance", "min_clearance_np", "BROAD_PHASE_K"]

BROAD_PHASE_K = 4
"""Pairs per interval that get the exact distance in the broad phase (the rest only a bound)."""


def segment_box_lower_bound(p0, p1, lo, hi) -> jax.Array:
    """A lower bound on ``dist(segment [p0, p1], box [lo, hi])``, valid for the numbers as
    computed: the AABB gap, lowered by a bound on its rounding error (module doc)."""
    dtype = jnp.result_type(p0, p1, lo, hi, 0.0)
    eps = jnp.finfo(dtype).eps
    f = jnp.zeros((), dtype)
    scale = jnp.zeros((), dtype)
    for i in range(3):
        a, b, l, h = p0[i].astype(dtype), p1[i].astype(dtype), lo[i].astype(dtype), hi[i].astype(dtype)
        gap = jnp.maximum(jnp.maximum(l - jnp.maximum(a, b), jnp.minimum(a, b) - h), 0)
        f = f + gap * gap
        scale = jnp.maximum(scale, jnp.maximum(jnp.maximum(jnp.abs(a), jnp.abs(b)), jnp.maximum(jnp.abs(l), jnp.abs(h))))
    # Each gap is one rounded subtraction (error <= eps * scale); the sum of squares and the
    # square root add a few relative eps. Lowering by 8 eps (1 + scale) (1 + the bound) is a
    # bound on the total, so the result never exceeds the exact AABB distance.
    bound = jnp.sqrt(f)
    return bound - 8 * eps * (1 + scale) * (1 + bound)


def min_clearance(p_a, p_b, offset_seg, lo, hi, offset_box, mask, k: int | None = BROAD_PHASE_K,
                  dist_scale=1.0, guard_seg=None):
    """``(g, seg, box, exact)`` for one configuration (module docstring).

    Args:
      p_a, p_b: (S, 3) segment ends, m.
      offset_seg: (S,) subtracted from each segment's distances (e.g. r + b + rho), m.
      lo, hi: (B, 3) boxes, m; offset_box: (B,) subtracted per box, m; mask: (B,) real boxes.
      k: pairs that get the exact distance (static); ``None``: every pair exact.
      dist_scale: a positive factor applied to every distance first (e.g. the interval test's
        rounding deflation); distances and bounds are cast to ``offset_seg``'s dtype before it.
      guard_seg: (S,) per-segment guard: the pair chosen minimises ``g - guard_seg[s]`` (the
        interval test's rounding guards); default 0.

    Returns ``g = dist * dist_scale - offset_seg[s] - offset_box[b]`` of the chosen pair (+inf
    without real boxes), its segment and box indices, and whether it is certainly the pair the
    all-pairs computation chooses (always True for ``k=None``). Scaling and subtracting are
    monotone under rounding, so the bounds stay below the values they bound.
    """
    S, B = p_a.shape[0], lo.shape[0]
    dt = jnp.result_type(offset_seg, 0.0)
    inf = jnp.asarray(jnp.inf, dt)
    guard = jnp.zeros((S,), dt) if guard_seg is None else guard_seg

    def value(dist, s, b):
        return dist.astype(dt) * dist_scale - offset_seg[s] - offset_box[b]

    if k is None or k >= S * B:
        per_box = jax.vmap(segment_box_distance, in_axes=(None, None, 0, 0))
        dist = jax.vmap(per_box, in_axes=(0, 0, None, None))(p_a, p_b, lo, hi)
        g_pair = jnp.where(mask[None, :], dist.astype(dt) * dist_scale - offset_seg[:, None] - offset_box[None, :], inf)
        flat = jnp.argmin((g_pair - guard[:, None]).reshape(-1))
        return g_pair.reshape(-1)[flat], flat // B, flat % B, jnp.asarray(True)
    per_box = jax.vmap(segment_box_lower_bound, in_axes=(None, None, 0, 0))
    lb = jax.vmap(per_box, in_axes=(0, 0, None, None))(p_a, p_b, lo, hi)
    lam = lb.astype(dt) * dist_scale - offset_seg[:, None] - offset_box[None, :] - guard[:, None]
    lam = jnp.where(mask[None, :], lam, inf).reshape(-1)
    chosen, exact_v, exact_x = [], [], []
    iota = jnp.arange(S * B)
    for _ in range(k):
        # argmin as two plain min-reductions (XLA's variadic argmin reduce is much slower).
        i = jnp.min(jnp.where(lam == jnp.min(lam), iota, S * B - 1))
        s, b = i // B, i % B
        v = value(segment_box_distance(p_a[s], p_b[s], lo[b], hi[b]), s, b)
        real = mask[b] & (lam[i] < inf)
        exact_v.append(jnp.where(real, v, inf))
        exact_x.append(jnp.where(real, v - guard[s], inf))
        chosen.append(i)
        lam = jnp.where(iota == i, inf, lam)
    exact_v, exact_x, chosen = jnp.stack(exact_v), jnp.stack(exact_x), jnp.stack(chosen)
    m = jnp.min(exact_x)
    # Ties between chosen pairs: the smallest flat index, as the all-pairs argmin picks.
    flat = jnp.min(jnp.where(exact_x == m, chosen, S * B))
    pick = jnp.argmax(chosen == flat)
    pick = jnp.where(flat == S * B, 0, pick)  # m is NaN: keep the first choice
    flat = chosen[pick]
    return exact_v[pick], flat // B, flat % B, m <= jnp.min(lam)


def min_clearance_np(p_a, p_b, offset_seg, lo, hi, offset_box, mask):
    """NumPy float64 reference of :func:`min_clearance` (every pair exact): ``(g, seg, box)``."""
    g_best, best = math.inf, (0, 0)
    for s in range(len(p_a)):
        for b in range(len(lo)):
            if not mask[b]:
                continue
            g = segment_box_distance_np(p_a[s], p_b[s], lo[b], hi[b]) - float(offset_seg[s]) - float(offset_box[b])
            if g < g_best or (math.isnan(g) and not math.isnan(g_best)):
                g_best, best = g, (s, b)
    return g_best, best[0], best[1]
