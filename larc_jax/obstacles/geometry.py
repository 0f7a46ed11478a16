"""Exact Euclidean distance between line segments and axis-aligned boxes.

The certifier needs, for a segment ``[p0, p1]`` swept by a point of the robot and an obstacle
box ``[lo, hi]``, the true minimum distance ``min_{t in [0,1]} dist(x(t), box)`` with
``x(t) = p0 + t (p1 - p0)`` (all lengths in metres). A lower bound would be safe but loose, and
sampling ``t`` is unsafe (it over-estimates), so the kernel computes the minimum exactly (up to
floating-point rounding) with a fixed amount of sort-free work per pair, which vectorises well.

Why it is exact. The squared distance

    f(t) = sum_i max(lo_i - x_i(t), 0, x_i(t) - hi_i)^2

is convex (a sum of squares of convex non-negative functions of an affine argument) and
piecewise quadratic. On each axis i the state of ``x_i(t)`` ("below lo_i", "inside",
"above hi_i") changes only at the breakpoints ``t`` where ``x_i(t) = lo_i`` or ``hi_i``, so
between consecutive breakpoints f equals one quadratic ``q(t) = sum_{active i} (d_i t - e_i)^2``
(``d = p1 - p0``; ``e_i = lo_i - p0_i`` if below, ``hi_i - p0_i`` if above).

Let S = {0, 1} ∪ {breakpoints clipped to [0, 1]} (8 values). For every c in S we build the
quadratic of the piece just *right* of c and take its stationary point, clipped to [c, 1]
(or c itself when the piece is flat). Every value we evaluate is the true f at a real point of
the segment, so the minimum over them is >= min f. Conversely let t_m be a minimiser and c the
largest element of S with c <= t_m:

* if t_m = c, c itself is evaluated: the right piece's quadratic is non-decreasing at c
  (f is convex with its minimum at c), so its stationary point clipped to [c, 1] is c;
* otherwise t_m lies inside the open piece (c, c'), where f = q; q is either flat (then
  f(c) = f(t_m) by continuity and we evaluate c) or strictly convex with its stationary point
  at t_m, which we evaluate.

Hence the minimum over the evaluated points is exactly min f. The argument needs the active set
of (c, c + eps) even when c coincides with a breakpoint (exact ties: a segment starting on a
face and leaving it, passing through an edge or vertex, or a flat box). We therefore never
classify by the sign of ``x_i(c) - lo_i`` (ambiguous at 0), but by comparing c with the
breakpoints themselves, with the direction of travel breaking the tie: for ``d_i > 0`` the
axis is below on (c, c+) iff ``c < t_lo_i`` and above iff ``c >= t_hi_i``; for ``d_i < 0``
below iff ``c >= t_lo_i`` and above iff ``c < t_hi_i``. Comparisons use the same computed
floats that define S, so the classification is consistent with the pieces S delimits. Axes
with ``d_i = 0`` have constant state and contribute nothing to the slope of q, so they are
left out of the stationary-point formula (and their breakpoints are replaced by the harmless
candidate 0).
"""

from __future__ import annotations

import math

import numpy as np

from ..lazy_jax import jax, jnp, lazy_jit

__all__ = [
    "segment_box_distance",
    "segment_box_distance_np",
    "segment_box_distances",
    "segment_box_lower_bound",
    "segment_box_lower_bound_np",
    "point_box_distance",
    "point_box_distance_np",
]


def segment_box_distance(p0, p1, lo, hi) -> jax.Array:
    """Exact minimum distance between one closed segment and one closed axis-aligned box.

    Pure, jit- and vmap-able, sort-free; see the module docstring for why the result is the
    true minimum over the segment. Returns 0 when the segment touches, crosses or lies in the
    box. Never NaN for finite inputs (zero-length segments, faces parallel to the segment,
    exact edge/vertex contacts and flat boxes included).

    Args:
      p0: (3,) segment start, m.
      p1: (3,) segment end, m (may equal ``p0``).
      lo: (3,) box minimum corner, m.
      hi: (3,) box maximum corner, m; ``lo <= hi`` componentwise (``lo_i == hi_i`` allowed).

    Returns:
      Scalar distance in metres, in the floating dtype the inputs promote to.
    """
    p0, p1, lo, hi = (jnp.asarray(v) for v in (p0, p1, lo, hi))
    # A weak Python float keeps float32 inputs float32 and turns integer inputs into floats.
    dtype = jnp.result_type(p0, p1, lo, hi, 0.0)
    # Written axis by axis and candidate by candidate on scalars (no (8, 3) intermediates and
    # no reductions over tiny axes): batched with vmap, every operation is elementwise over the
    # batch, so XLA fuses the whole kernel into one pass over the pairs (arithmetic, not
    # memory traffic). The computation is the one the module docstring proves exact.
    P0, P1, LO, HI = ([v[i].astype(dtype) for i in range(3)] for v in (p0, p1, lo, hi))
    zero, one = jnp.zeros((), dtype), jnp.ones((), dtype)
    d = [P1[i] - P0[i] for i in range(3)]
    moving = [d[i] != 0 for i in range(3)]
    forward = [d[i] > 0 for i in range(3)]
    e_lo = [LO[i] - P0[i] for i in range(3)]  # targets of the "below" / "above" states
    e_hi = [HI[i] - P0[i] for i in range(3)]
    safe_d = [jnp.where(moving[i], d[i], one) for i in range(3)]  # avoid 0/0; discarded for d_i = 0
    t_lo = [jnp.where(moving[i], e_lo[i] / safe_d[i], zero) for i in range(3)]  # x_i(t) = lo_i
    t_hi = [jnp.where(moving[i], e_hi[i] / safe_d[i], zero) for i in range(3)]  # x_i(t) = hi_i

    f_min = None
    for c in [zero, one] + [jnp.clip(t, zero, one) for t in t_lo + t_hi]:  # the candidate set S
        num = den = zero
        for i in range(3):
            # State on (c, c + eps), decided against the breakpoints (not against x(c)) so
            # that ties are broken by the direction of travel; see the module docstring.
            below = moving[i] & jnp.where(forward[i], c < t_lo[i], c >= t_lo[i])
            above = moving[i] & jnp.where(forward[i], c >= t_hi[i], c < t_hi[i])
            active = below | above
            target = jnp.where(below, e_lo[i], jnp.where(above, e_hi[i], zero))
            # Stationary point of q(t) = sum_active (d_i t - e_i)^2.
            num = num + jnp.where(active, d[i] * target, zero)
            den = den + jnp.where(active, d[i] * d[i], zero)
        curved = den > 0
        t_star = num / jnp.where(curved, den, one)
        # Clip to [c, 1]; written with comparisons (False for NaN) so that an overflowing
        # num/den (only possible for astronomically large inputs) falls back to c instead of NaN.
        t_star = jnp.where(curved & (t_star > c), jnp.where(t_star < 1, t_star, one), c)
        f = zero
        for i in range(3):
            x = (1 - t_star) * P0[i] + t_star * P1[i]  # lerp: exactly p0 / p1 at t = 0 / 1
            gap = jnp.maximum(jnp.maximum(LO[i] - x, x - HI[i]), zero)
            f = f + gap * gap
        f_min = f if f_min is None else jnp.minimum(f_min, f)
    return jnp.sqrt(f_min)  # f_min >= 0: a sum of squares


def segment_box_distance_np(p0, p1, lo, hi) -> float:
    """Float64 NumPy reference for :func:`segment_box_distance` (one segment, one box).

    Written independently of the JAX kernel: it sorts the breakpoints that fall in (0, 1),
    classifies each piece by the state at its midpoint, and minimises that piece's quadratic
    with its stationary point clipped to the piece. Slow (Python loop); for tests.

    Args:
      p0, p1: (3,) segment end points, m.
      lo, hi: (3,) box corners, m, ``lo <= hi``.

    Returns:
      The distance in metres.
    """
    p0, p1, lo, hi = (np.asarray(v, dtype=np.float64).reshape(3) for v in (p0, p1, lo, hi))
    d = p1 - p0

    def f(t: float) -> float:
        x = p0 + t * d
        gap = np.maximum(np.maximum(lo - x, x - hi), 0.0)
        return float(gap @ gap)

    knots = {0.0, 1.0}
    for i in range(3):
        if d[i] != 0.0:
            for bound in (lo[i], hi[i]):
                t = (bound - p0[i]) / d[i]
                if 0.0 < t < 1.0:
                    knots.add(float(t))
    knots = sorted(knots)

    best = min(f(t) for t in knots)
    for u, v in zip(knots[:-1], knots[1:]):
        x_mid = p0 + 0.5 * (u + v) * d
        e = np.where(x_mid < lo, lo - p0, np.where(x_mid > hi, hi - p0, np.nan))
        act = ~np.isnan(e)
        a = float(d[act] @ d[act])
        if a > 0.0:
            t = float(d[act] @ e[act]) / a
            best = min(best, f(min(max(t, u), v)))
    return math.sqrt(best)


def segment_box_lower_bound(p0, p1, lo, hi) -> jax.Array:
    """A cheap lower bound on ``dist(segment [p0, p1], box [lo, hi])`` (the broad phase of
    :mod:`larc_jax.clearance`), valid for the numbers as computed: the gap between the segment's
    axis-aligned bounding box and the box (every point of the segment lies in its AABB), lowered
    by a bound on its rounding error."""
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


def segment_box_lower_bound_np(p0, p1, lo, hi) -> float:
    """Float64 NumPy twin of :func:`segment_box_lower_bound` (the same bound, vectorised over
    the three axes)."""
    p0, p1, lo, hi = (np.asarray(v, dtype=np.float64).reshape(3) for v in (p0, p1, lo, hi))
    eps = float(np.finfo(np.float64).eps)
    gap = np.maximum(np.maximum(lo - np.maximum(p0, p1), np.minimum(p0, p1) - hi), 0.0)
    scale = float(np.max(np.abs(np.stack([p0, p1, lo, hi]))))
    bound = math.sqrt(float(gap @ gap))
    return bound - 8 * eps * (1 + scale) * (1 + bound)


def point_box_distance(p, lo, hi) -> jax.Array:
    """Distance from points ``p`` (..., 3) to the box ``[lo, hi]``, m (no rounding care: the
    cascade uses it only for an upper bound that skips work, :mod:`larc_jax.cascade`)."""
    gap = jnp.maximum(jnp.maximum(lo - p, p - hi), 0)
    return jnp.sqrt(jnp.sum(gap * gap, axis=-1))


def point_box_distance_np(p, lo, hi) -> np.ndarray:
    """Float64 NumPy twin of :func:`point_box_distance` (points (..., 3))."""
    p, lo, hi = (np.asarray(v, np.float64) for v in (p, lo, hi))
    gap = np.maximum(np.maximum(lo - p, p - hi), 0)
    return np.sqrt((gap * gap).sum(axis=-1))


@lazy_jit
def segment_box_distances(p0, p1, lo, hi) -> jax.Array:
    """Distances from every segment to every box.

    Args:
      p0: (..., S, 3) segment starts, m.
      p1: (..., S, 3) segment ends, m.
      lo: (..., B, 3) box minimum corners, m.
      hi: (..., B, 3) box maximum corners, m.
      The leading ``...`` dimensions of segments and boxes broadcast against each other.

    Returns:
      (..., S, B) distances in metres, ``out[..., s, b]`` = distance(segment s, box b).
    """
    p0, p1 = jnp.broadcast_arrays(jnp.asarray(p0), jnp.asarray(p1))
    lo, hi = jnp.broadcast_arrays(jnp.asarray(lo), jnp.asarray(hi))
    batch = jnp.broadcast_shapes(p0.shape[:-2], lo.shape[:-2])
    p0, p1 = (jnp.broadcast_to(v, batch + v.shape[-2:]) for v in (p0, p1))
    lo, hi = (jnp.broadcast_to(v, batch + v.shape[-2:]) for v in (lo, hi))

    per_box = jax.vmap(segment_box_distance, in_axes=(None, None, 0, 0))  # (B,)
    per_pair = jax.vmap(per_box, in_axes=(0, 0, None, None))  # (S, B)
    fn = per_pair
    for _ in batch:  # one vmap per leading dimension
        fn = jax.vmap(fn)
    return fn(p0, p1, lo, hi)
