"""Piecewise-cubic Hermite trajectories and their exact joint-speed maxima.

A joint trajectory (as MoveIt records it) is ``K+1`` waypoints with strictly increasing times
``t_0 < ... < t_K`` (s), positions ``q_k`` (n joints; rad for revolute, m for prismatic joints)
and velocities ``v_k`` (rad/s or m/s). It is reconstructed as a piecewise-cubic Hermite curve:
on segment ``k`` (``t_k <= t <= t_{k+1}``), with ``h_k = t_{k+1} - t_k`` and
``s = (t - t_k) / h_k`` in [0, 1],

    q(s) = H00(s) q_k + H10(s) h_k v_k + H01(s) q_{k+1} + H11(s) h_k v_{k+1},

    H00 = (1 + 2s)(1 - s)^2,   H10 = s (1 - s)^2,   H01 = s^2 (3 - 2s),   H11 = s^2 (s - 1).

Differentiating, with the chord slope ``d_k = (q_{k+1} - q_k) / h_k``,

    qdot(s) = (1 - s)(1 - 3s) v_k + s (3s - 2) v_{k+1} + 6 s (1 - s) d_k          (*)
            = c0 + c1 s + c2 s^2,
    c0 = v_k,   c1 = 6 d_k - 4 v_k - 2 v_{k+1},   c2 = 3 v_k + 3 v_{k+1} - 6 d_k.

Exactness argument (paper eq. 5). On each segment every component ``qdot_j`` is a polynomial
of degree <= 2 in ``s``. The maximum of ``|p|`` over a closed sub-range ``[s0, s1]`` of a
quadratic ``p`` is attained either at an end of the sub-range or at a critical point of ``p``
inside it; ``p`` has at most one critical point, the vertex ``s* = -c1 / (2 c2)`` (none when
``c2 = 0``). Hence

    max_{s in [s0, s1]} |qdot_j(s)| = max(|p(s0)|, |p(s1)|, |p(clip(s*, s0, s1))|)

*exactly* (the clipped vertex is a point of the sub-range, so it can never over-estimate; when
the vertex lies inside it is the true candidate). For an interval ``I = [a, b]`` the maximum
over ``I`` is the maximum over the segments that ``I`` touches, each restricted to its part of
``I``: the first and last touched segments are evaluated on their clipped sub-ranges, and every
segment fully covered by ``I`` contributes its whole-segment maximum, which is precomputed in a
sparse table (range-maximum query, O(1) per query). The only error is floating-point rounding
in evaluating (*); no safety margin is added here (the certifier adds its own documented
rounding guard).

Accelerations (the swept test, :mod:`larc_jax.leaf.swept`). Differentiating (*) once more,

    qddot(s) h_k = (6s - 4) v_k + (6s - 2) v_{k+1} + (6 - 12s) d_k                  (**)

is *linear* in ``s`` (the curve is C1, its second derivative jumps at the knots), so
``max_{s in [s0, s1]} |qddot_j(s)| = max(|qddot_j(s0)|, |qddot_j(s1)|)`` exactly, and
:func:`accel_max` takes the maximum over an interval with the same range query as the speeds
(its own sparse table, :attr:`HermiteSpline.accel_table`). Rounding: the coefficients of (**)
are at most 4, 4 and 6 in magnitude on [0, 1], so its error is ``<= 16 u A_kj``, ``A_kj = (4 |v_kj|
+ 4 |v_k+1,j| + 6 |d_kj|) / h_k`` (:func:`~larc_jax.leaf.interval.trajectory_rounding` adds it).

Form (*) is used for evaluation because it is exact at the knots: at ``s = 0`` it returns
``v_k`` and at ``s = 1`` it returns ``v_{k+1}`` bit-for-bit, so both segments adjacent to a
knot give the same velocity there. The power-form coefficients are used only to locate the
vertex (an error in ``s*`` changes ``p(s*)`` only to second order since ``p'(s*) = 0``).

Batches. :func:`pad_waypoints` appends extra knots after ``t_K`` (at ``t_K + 1, t_K + 2, ...``,
position repeated, zero velocity) so that trajectories with different ``K`` share one array
shape; no interval inside the original ``[t_0, t_K]`` ever touches a padding segment. A batch
of splines is a :class:`HermiteSpline` whose arrays carry a leading batch axis, built with
``jax.vmap(HermiteSpline.from_waypoints)`` on stacked padded arrays (see
:func:`batch_from_waypoints`); the single-item kernels :func:`evaluate`, :func:`speed_max` are
then mapped with ``jax.vmap``.

All JAX functions are pure ``jnp``, jit- and vmap-able, dtype-polymorphic (float32 in gives
float32 out, float64 in gives float64 out under ``jax.enable_x64``) and never flip global JAX
configuration. :func:`evaluate_np`, :func:`speed_max_np` and :func:`accel_max_np` are independent
float64 NumPy references (:mod:`larc_jax.model.hermite_reference`: power form, plain loops).
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np

from ..errors import LarcInputError
from ..lazy_jax import jax, jnp, pytree_dataclass
from .hermite_reference import accel_max_np, evaluate_np, speed_max_np

__all__ = [
    "HermiteSpline",
    "num_table_levels",
    "pad_waypoints",
    "pad_waypoints_batch",
    "batch_from_waypoints",
    "evaluate",
    "segment_speed_max",
    "speed_max",
    "segment_accel_max",
    "accel_max",
    "accel_max_np",
    "evaluate_np",
    "speed_max_np",
]


def num_table_levels(num_segments: int) -> int:
    """Number of sparse-table levels for ``K`` segments: ``max(1, ceil(log2 K) + 1)``."""
    K = int(num_segments)
    if K < 1:
        raise ValueError(f"need at least one segment, got K={K}")
    return max(1, (K - 1).bit_length() + 1)  # (K-1).bit_length() == ceil(log2 K) for K >= 1


# ------------------------------------------------------------------------------------------
# Single-segment kernel (paper eq. 5)
# ------------------------------------------------------------------------------------------


def _segment_velocity(v0, v1, d, s):
    """Velocity (*) at normalised time ``s``; exact at ``s = 0`` (-> v0) and ``s = 1`` (-> v1)."""
    one = jnp.ones_like(s)
    return (one - s) * (one - 3 * s) * v0 + s * (3 * s - 2 * one) * v1 + 6 * s * (one - s) * d


def segment_speed_max(q0, v0, q1, v1, h, s0, s1):
    """Exact ``max_{s in [s0, s1]} |qdot_j(s)|`` on one Hermite segment (paper eq. 5).

    Args (all broadcast against each other; typically ``q0, v0, q1, v1`` are ``(n,)`` and
    ``h, s0, s1`` are scalars):
      q0, q1: positions at the segment's start/end knot (rad or m).
      v0, v1: velocities at the start/end knot (rad/s or m/s).
      h: segment duration ``t_{k+1} - t_k`` (s), > 0.
      s0, s1: normalised sub-range, ``0 <= s0 <= s1 <= 1``; ``s0 == s1`` gives ``|qdot(s0)|``.

    Returns:
      Componentwise maximum speed over the sub-range (rad/s or m/s), dtype of the inputs.

    Candidates are ``s0``, ``s1`` and the vertex of the quadratic ``qdot_j`` clipped into
    ``[s0, s1]`` (clipping keeps it a point of the sub-range; when ``c2 == 0`` the speed is
    linear and the ends suffice, so the vertex candidate is set to ``s0``). No NaN for finite
    input with ``h > 0``; zero speed returns 0.
    """
    d = (q1 - q0) / h
    c1 = 6 * d - 4 * v0 - 2 * v1
    c2 = 3 * v0 + 3 * v1 - 6 * d
    flat = c2 == 0
    c2_safe = jnp.where(flat, jnp.ones_like(c2), c2)
    s_vertex = -c1 / (2 * c2_safe)  # may be +-inf if c2 is tiny; clip handles that
    s0 = jnp.asarray(s0, dtype=d.dtype)
    s1 = jnp.asarray(s1, dtype=d.dtype)
    s_vertex = jnp.where(flat, s0, jnp.clip(s_vertex, s0, s1))
    w0 = jnp.abs(_segment_velocity(v0, v1, d, s0))
    w1 = jnp.abs(_segment_velocity(v0, v1, d, s1))
    wv = jnp.abs(_segment_velocity(v0, v1, d, s_vertex))
    return jnp.maximum(jnp.maximum(w0, w1), wv)


def _segment_accel(v0, v1, d, h, s):
    """Acceleration (**) at normalised time ``s`` of a segment of duration ``h``."""
    return ((6 * s - 4) * v0 + (6 * s - 2) * v1 + (6 - 12 * s) * d) / h


def segment_accel_max(q0, v0, q1, v1, h, s0, s1):
    """Exact ``max_{s in [s0, s1]} |qddot_j(s)|`` on one Hermite segment (arguments as
    :func:`segment_speed_max`): (**) is linear in ``s``, so the larger end value."""
    d = (q1 - q0) / h
    s0 = jnp.asarray(s0, dtype=d.dtype)
    s1 = jnp.asarray(s1, dtype=d.dtype)
    return jnp.maximum(jnp.abs(_segment_accel(v0, v1, d, h, s0)), jnp.abs(_segment_accel(v0, v1, d, h, s1)))


# ------------------------------------------------------------------------------------------
# Spline pytree
# ------------------------------------------------------------------------------------------


def _build_table(t_knots, q_knots, qd_knots, segment_max):
    """Sparse table ``(L, K, n)`` of the whole-segment maxima of ``segment_max``
    (:func:`segment_speed_max` or :func:`segment_accel_max`; jnp, works under jit/vmap)."""
    K = t_knots.shape[0] - 1
    L = num_table_levels(K)
    h = t_knots[1:] - t_knots[:-1]  # (K,)
    zero = jnp.zeros_like(h)
    one = jnp.ones_like(h)
    level = segment_max(
        q_knots[:-1], qd_knots[:-1], q_knots[1:], qd_knots[1:], h[:, None], zero[:, None], one[:, None]
    )  # (K, n): exact maximum over the whole segment k
    levels = [level]
    for lv in range(1, L):
        half = min(1 << (lv - 1), K - 1)
        # level[min(k + half, K - 1)]: a shifted slice, the last row repeated (a slice, not a
        # gather: under vmap a gather of the whole table cost ~10x the arithmetic on a CPU).
        shifted = jnp.concatenate([level[half:], jnp.broadcast_to(level[K - 1:], (half,) + level.shape[1:])])
        level = jnp.maximum(level, shifted)
        levels.append(level)
    return jnp.stack(levels, axis=0)


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class HermiteSpline:
    """A piecewise-cubic Hermite joint trajectory with a segment-speed range-maximum table.

    All fields are arrays (pytree children). A *batch* of splines is the same class with a
    leading batch axis ``B`` on every field (build it with :func:`batch_from_waypoints` or
    ``jax.vmap(HermiteSpline.from_waypoints)`` on padded, stacked waypoints); the kernels in
    this module take single items and are mapped with ``jax.vmap``.
    """

    t_knots: jax.Array
    """(K+1,) knot times ``t_0 < ... < t_K``, s."""
    q_knots: jax.Array
    """(K+1, n) knot positions, rad (revolute) or m (prismatic)."""
    qd_knots: jax.Array
    """(K+1, n) knot velocities, rad/s or m/s."""
    speed_table: jax.Array
    """(L, K, n) sparse table, rad/s or m/s: ``speed_table[l, k, j]`` is the exact max of
    ``|qdot_j|`` over segments ``k .. min(k + 2**l - 1, K - 1)`` (level 0: segment ``k``
    alone); ``L = max(1, ceil(log2 K) + 1)``."""
    accel_table: jax.Array | None
    """(L, K, n) the same table of the maxima of ``|qddot_j|`` (eq. (**)), rad/s^2 or m/s^2; None
    when built without it (``from_waypoints(..., accel=False)``: only the swept stage reads it)."""

    @property
    def num_segments(self) -> int:
        """``K`` (static, from the array shape; padding segments included)."""
        return self.t_knots.shape[-1] - 1

    # Element access used by the single-item kernels. :class:`~larc_jax.model.spline_batch.SplineRow`
    # offers the same methods for one spline of a batch, read in place.
    def knots(self):
        return self.t_knots

    def knot(self, i):
        """``(t_i, q_i, qd_i)``."""
        return self.t_knots[i], self.q_knots[i], self.qd_knots[i]

    def table(self, level, i):
        return self.speed_table[level, i]

    def accel_table_at(self, level, i):
        return self.accel_table[level, i]

    def has_accel(self) -> bool:
        return self.accel_table is not None

    @property
    def num_joints(self) -> int:
        """``n`` (static)."""
        return self.q_knots.shape[-1]

    @classmethod
    def from_waypoints(cls, t, q, qd, accel: bool = True) -> "HermiteSpline":
        """Build a spline from waypoint times ``(K+1,)``, positions and velocities ``(K+1, n)``.

        Accepts NumPy or JAX arrays; the common floating dtype of the inputs is used (float32
        unless x64 is enabled and an input is float64). Shapes are checked; values are not
        (times must be strictly increasing — checked by the trajectory loader). Works under
        ``jax.jit`` and ``jax.vmap`` (the table is built with ``jnp``). ``accel`` (static): build
        :attr:`accel_table` too (:func:`accel_max` needs it; the speed queries do not).
        """
        t = jnp.asarray(t)
        q = jnp.asarray(q)
        qd = jnp.asarray(qd)
        if t.ndim != 1 or t.shape[0] < 2:
            raise LarcInputError(f"hermite: t must have shape (K+1,) with K >= 1, got {t.shape}")
        if q.ndim != 2 or q.shape[0] != t.shape[0]:
            raise LarcInputError(f"hermite: q must have shape ({t.shape[0]}, n), got {q.shape}")
        if qd.shape != q.shape:
            raise LarcInputError(f"hermite: qd must have shape {q.shape}, got {qd.shape}")
        dtype = jnp.result_type(t.dtype, q.dtype, qd.dtype, jnp.float32)
        t = t.astype(dtype)
        q = q.astype(dtype)
        qd = qd.astype(dtype)
        return cls(t_knots=t, q_knots=q, qd_knots=qd, speed_table=_build_table(t, q, qd, segment_speed_max),
                   accel_table=_build_table(t, q, qd, segment_accel_max) if accel else None)


# ------------------------------------------------------------------------------------------
# Padding and batching
# ------------------------------------------------------------------------------------------


def pad_waypoints(t, q, qd, n_knots: int):
    """Pad a trajectory to exactly ``n_knots`` knots (NumPy).

    Extra knots are *appended* after ``t_K`` at ``t_K + 1, t_K + 2, ...`` s, with ``q_K``
    repeated and zero velocity, so times stay strictly increasing and any interval inside the
    original ``[t_0, t_K]`` only touches original segments (:func:`speed_max` assigns an
    interval ending at ``t_K`` to the last original segment). Returns new arrays
    ``(t (n_knots,), q (n_knots, n), qd (n_knots, n))``; the dtype of each input is kept.
    """
    t = np.asarray(t)
    q = np.asarray(q)
    qd = np.asarray(qd)
    if t.ndim != 1 or q.ndim != 2 or q.shape[0] != t.shape[0] or qd.shape != q.shape:
        raise LarcInputError(
            f"hermite: pad_waypoints needs t (K+1,), q and qd (K+1, n); got {t.shape}, {q.shape}, {qd.shape}"
        )
    m = int(n_knots) - t.shape[0]
    if m < 0:
        raise LarcInputError(f"hermite: cannot pad {t.shape[0]} knots down to n_knots={n_knots}")
    if m == 0:
        return t.copy(), q.copy(), qd.copy()
    t_pad = (t[-1] + np.arange(1, m + 1, dtype=np.float64)).astype(t.dtype)
    if not np.all(np.diff(np.concatenate([t[-1:], t_pad])) > 0):
        raise LarcInputError(f"hermite: padding times after t_K={t[-1]!r} are not increasing in {t.dtype}")
    t_out = np.concatenate([t, t_pad])
    q_out = np.concatenate([q, np.repeat(q[-1:], m, axis=0)], axis=0)
    qd_out = np.concatenate([qd, np.zeros((m, qd.shape[1]), dtype=qd.dtype)], axis=0)
    return t_out, q_out, qd_out


def pad_waypoints_batch(trajectories, n_knots: int, n_batch: int):
    """``(t (B, N), q (B, N, n), qd (B, N, n))`` float64, ``B = n_batch``, ``N = n_knots``: row
    ``k < len(trajectories)`` is :func:`pad_waypoints` of ``trajectories[k] = (t, q, qd)`` (the
    same elementwise arithmetic, so bit for bit), the rows after it repeat row 0 (a batch's
    padding). One pass over the trajectories, without :func:`pad_waypoints`' per-call copies."""
    n = np.shape(trajectories[0][1])[1]
    t_out = np.empty((n_batch, n_knots), np.float64)
    q_out = np.empty((n_batch, n_knots, n), np.float64)
    qd_out = np.zeros((n_batch, n_knots, n), np.float64)
    steps = np.arange(1, n_knots + 1, dtype=np.float64)
    for k, (t, q, qd) in enumerate(trajectories):
        m = n_knots - len(t)
        if m < 0 or np.shape(q) != (len(t), n) or np.shape(qd) != (len(t), n):
            raise LarcInputError(f"hermite: cannot pad trajectory {k} ({len(t)} knots, q {np.shape(q)}, qd "
                                 f"{np.shape(qd)}) to n_knots={n_knots} with {n} joints")
        t_out[k, :len(t)] = t
        t_out[k, len(t):] = t[-1] + steps[:m]
        q_out[k, :len(t)] = q
        q_out[k, len(t):] = q[-1]
        qd_out[k, :len(t)] = qd
    t_out[len(trajectories):] = t_out[0]
    q_out[len(trajectories):] = q_out[0]
    qd_out[len(trajectories):] = qd_out[0]
    rising = np.diff(t_out, axis=1) > 0
    if not np.all(rising):  # times strictly increasing, padding knots too
        k = int(np.flatnonzero(~np.all(rising, axis=1))[0])
        j = int(np.flatnonzero(~rising[k])[0])  # the first step that does not rise
        m = len(trajectories[k][0]) if k < len(trajectories) else n_knots
        what = (f"knot times t[{j}], t[{j + 1}] of trajectory {k} are not increasing" if j + 1 < m
                else f"padding times after t_K of trajectory {k} are not increasing in float64")
        raise LarcInputError(f"hermite: {what}")
    return t_out, q_out, qd_out


def batch_from_waypoints(
    ts: Sequence[np.ndarray],
    qs: Sequence[np.ndarray],
    qds: Sequence[np.ndarray],
    n_knots: int | None = None,
) -> HermiteSpline:
    """Pad each trajectory with :func:`pad_waypoints` and build a batched :class:`HermiteSpline`.

    ``n_knots`` defaults to the largest knot count. Every field of the result has a leading
    batch axis ``B = len(ts)``: ``t_knots (B, N)``, ``q_knots (B, N, n)``, ``qd_knots (B, N, n)``,
    ``speed_table (B, L, N-1, n)``.
    """
    if not (len(ts) == len(qs) == len(qds)) or len(ts) == 0:
        raise LarcInputError("hermite: batch_from_waypoints needs equally many (>= 1) t, q, qd arrays")
    if n_knots is None:
        n_knots = max(np.asarray(t).shape[0] for t in ts)
    padded = [pad_waypoints(t, q, qd, n_knots) for t, q, qd in zip(ts, qs, qds)]
    T = np.stack([p[0] for p in padded])
    Q = np.stack([p[1] for p in padded])
    QD = np.stack([p[2] for p in padded])
    return jax.vmap(HermiteSpline.from_waypoints)(T, Q, QD)


# ------------------------------------------------------------------------------------------
# Single-item kernels
# ------------------------------------------------------------------------------------------


def evaluate(spline: HermiteSpline, t):
    """Position and velocity at scalar time ``t`` (s): returns ``(q (n,), qd (n,))``.

    ``t`` in ``[t_k, t_{k+1})`` uses segment ``k``; ``t = t_K`` uses the last segment at
    ``s = 1``. Outside ``[t_0, t_K]`` the end segment's cubic is *extrapolated* (segment 0
    before ``t_0``, segment ``K-1`` after ``t_K``), like SciPy's ``extrapolate=True``. For a
    padded spline, times after the original ``t_K`` fall in the padding segments.
    """
    tk = spline.knots()
    K = tk.shape[0] - 1
    t = jnp.asarray(t, dtype=tk.dtype)
    k = jnp.clip(jnp.searchsorted(tk, t, side="right").astype(jnp.int32) - 1, 0, K - 1)
    t0, q0, v0 = spline.knot(k)
    t1, q1, v1 = spline.knot(k + 1)
    h = t1 - t0
    s = (t - t0) / h
    one = jnp.ones_like(s)
    om = one - s
    h00 = (one + 2 * s) * om * om
    h10 = s * om * om
    h01 = s * s * (3 * one - 2 * s)
    h11 = s * s * (s - one)
    q = h00 * q0 + (h10 * h) * v0 + h01 * q1 + (h11 * h) * v1
    qd = _segment_velocity(v0, v1, (q1 - q0) / h, s)
    return q, qd


def speed_max(spline: HermiteSpline, a, b):
    """Exact ``max_{t in [a, b]} |qdot_j(t)|`` for every joint ``j`` (paper eq. 5): ``(n,)``.

    Preconditions: ``t_0 <= a <= b <= t_K`` (scalars, s). Values outside ``[t_0, t_K]`` are
    clamped into it (for a padded spline "``t_K``" is the padded end); ``a > b`` gives an
    unspecified, finite value.

    Method. The first touched segment is ``ia`` (the ``k`` with ``t_k <= a < t_{k+1}``) and the
    last is ``ib`` (the ``k`` with ``t_k < b <= t_{k+1}``), both located with
    ``jnp.searchsorted``; ``ib`` uses ``side='left'`` so that ``b = t_k`` ends on segment
    ``k-1`` (an interval ending at the original ``t_K`` of a padded spline never touches
    padding). A zero-width interval at a knot has ``ia = ib + 1``; then ``ia := ib`` and the
    value is read at ``s = 1`` of segment ``ib``, which equals the knot velocity exactly.
    The first and last segments contribute exact partial maxima over their clipped
    sub-ranges (:func:`segment_speed_max`); the ``c = ib - ia - 1`` fully covered segments
    contribute ``max(T[l, ia+1], T[l, ib - 2**l])`` with ``l = floor(log2 c)`` from the sparse
    table (masked out when ``c = 0``). Cost is O(n) plus the two binary searches.
    """
    return _range_max(spline, a, b, segment_speed_max, spline.table)


def accel_max(spline: HermiteSpline, a, b):
    """Exact ``max_{t in [a, b]} |qddot_j(t)|`` for every joint ``j``: ``(n,)``, with the
    preconditions and the range query of :func:`speed_max` (eq. (**) of the module docstring is
    linear on each segment, so each touched segment's maximum is at its clipped ends). The
    spline must hold its :attr:`~HermiteSpline.accel_table`."""
    if not spline.has_accel():
        raise ValueError("hermite.accel_max: the spline was built without its acceleration table "
                         "(HermiteSpline.from_waypoints(..., accel=True))")
    return _range_max(spline, a, b, segment_accel_max, spline.accel_table_at)


def _range_max(spline, a, b, segment_max, table):
    """The range query of :func:`speed_max` for one segment kernel and its sparse table."""
    tk = spline.knots()
    K = tk.shape[0] - 1
    L = num_table_levels(K)
    dtype = tk.dtype
    a = jnp.asarray(a, dtype=dtype)
    b = jnp.asarray(b, dtype=dtype)

    ib = jnp.clip(jnp.searchsorted(tk, b, side="left").astype(jnp.int32) - 1, 0, K - 1)
    ia = jnp.clip(jnp.searchsorted(tk, a, side="right").astype(jnp.int32) - 1, 0, K - 1)
    ia = jnp.minimum(ia, ib)
    same = ia == ib

    def seg(k):
        t0, q0, v0 = spline.knot(k)
        t1, q1, v1 = spline.knot(k + 1)
        return t0, t1 - t0, q0, v0, q1, v1

    ta, ha, qa0, va0, qa1, va1 = seg(ia)
    tb, hb, qb0, vb0, qb1, vb1 = seg(ib)
    zero = jnp.zeros((), dtype)
    one = jnp.ones((), dtype)
    sa = jnp.clip((a - ta) / ha, zero, one)  # a's position in segment ia
    sb = jnp.clip((b - tb) / hb, zero, one)  # b's position in segment ib
    # First touched segment over [sa, 1] (or [sa, sb] when a and b share a segment).
    w_first = segment_max(qa0, va0, qa1, va1, ha, sa, jnp.where(same, sb, one))
    # Last touched segment over [0, sb] (or [sa, sb] when shared).
    w_last = segment_max(qb0, vb0, qb1, vb1, hb, jnp.where(same, sa, zero), sb)

    # Fully covered segments ia+1 .. ib-1: O(1) sparse-table range maximum.
    count = jnp.maximum(ib - ia - 1, 0)
    nbits = jnp.iinfo(count.dtype).bits
    lvl = jnp.clip(nbits - 1 - jax.lax.clz(count), 0, L - 1)  # floor(log2 count) for count >= 1
    pow2 = jnp.left_shift(jnp.ones_like(count), lvl)
    i_lo = jnp.clip(ia + 1, 0, K - 1)
    i_hi = jnp.clip(ib - pow2, 0, K - 1)  # (ib - 1) - 2**l + 1
    w_mid = jnp.maximum(table(lvl, i_lo), table(lvl, i_hi))
    w_mid = jnp.where(count > 0, w_mid, jnp.zeros_like(w_mid))

    return jnp.maximum(jnp.maximum(w_first, w_last), w_mid)
