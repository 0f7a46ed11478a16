"""Many trajectories' Hermite curves in one batch, their range-maximum tables stored ragged.

A batch pads every trajectory to one knot count (:func:`~larc_jax.model.hermite.pad_waypoints`),
so the kernels see one shape; but a sparse table padded the same way holds ``L(N-1) * (N-1)``
rows per trajectory, ``N`` the longest trajectory's knot count, whatever each one's own length.
On the Stage B set (59 to 305 waypoints, padded to 512) that was 4.1x the rows the trajectories
have, and building it took a third of a warm LARC call (85 of 255 ms): the table is written once
per call and is memory traffic, not arithmetic.

Here trajectory ``k`` (``K_k`` real segments) keeps its own table,
``L_k = num_table_levels(K_k)`` levels of ``K_k`` rows, one block after another in ``rows``:
entry ``(l, i)`` of trajectory ``k`` is ``rows[start[k] + l * K_k + i]``. It equals the padded
table's entry wherever a query reads it, bit for bit:

* level 0 is the same computation (:func:`~larc_jax.model.hermite.segment_speed_max` on the
  same knots, compiled once for the batch);
* level ``l`` at ``i`` is the exact maximum of level 0 over segments ``i .. i + 2**l - 1``
  (a maximum has no rounding), computed here in NumPy;
* a query (:func:`~larc_jax.model.hermite.speed_max` on an interval inside the horizon) reads
  ``(l, i)`` only with ``i + 2**l - 1 <= ib - 1 <= K_k - 1`` and ``l <= floor(log2(K_k - 2))
  < L_k``: real segments, where neither table is clipped. A read whose result is masked (no
  covered segment) may land in another block; its index is clamped into ``rows``, so it is a
  finite value and then discarded.

``rows`` is padded to a power of two (few compiled shapes); a batch of one trajectory (certified
one per call) gets the row count of its padded knot count, whatever its own length, so its
shape depends on the knot count alone, as before.

:class:`SplineRow` reads one trajectory of the batch in place (the single-item kernels are
mapped over intervals with ``jax.vmap``; copying each interval's spline would cost more than the
interval's arithmetic).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..lazy_jax import jax, jnp, pytree_dataclass
from .hermite import num_table_levels, segment_accel_max, segment_speed_max

__all__ = ["SplineBatch", "SplineRow", "spline_batch", "ragged_table"]


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class SplineBatch:
    """``B`` trajectories padded to ``N`` knots, with ragged sparse tables (module docstring)."""

    t_knots: jax.Array
    """(B, N) knot times, s (padding knots after each trajectory's end)."""
    q_knots: jax.Array
    """(B, N, n) knot positions."""
    qd_knots: jax.Array
    """(B, N, n) knot velocities."""
    start: jax.Array
    """(B,) int32: the row of each trajectory's table entry (0, 0)."""
    n_segments: jax.Array
    """(B,) int32: each trajectory's own segment count ``K_k`` (the stride between its levels)."""
    speed_rows: jax.Array
    """(R, n) every trajectory's speed table (``HermiteSpline.speed_table``'s entries), rad/s or m/s."""
    accel_rows: jax.Array | None
    """(R, n) the same for ``|qddot|``; None when built without it (only the swept stage reads it)."""


def ragged_table(level0: np.ndarray, n_segments: np.ndarray, n_rows: int) -> tuple[np.ndarray, np.ndarray]:
    """``(rows (n_rows, n), start (B,))``: the sparse tables of trajectories whose level 0 is
    ``level0[k, :n_segments[k]]`` (``level0`` (B, N-1, n), NumPy), one block of
    ``num_table_levels(K_k) * K_k`` rows each (module docstring), padded with zeros to ``n_rows``.
    A trajectory with ``n_segments[k] == 0`` (a batch's padding, never queried) has no block."""
    B, _, n = level0.shape
    K = np.maximum(np.asarray(n_segments, np.int64), 0)
    levels = np.array([num_table_levels(k) if k else 0 for k in K], np.int64)
    start = np.concatenate([[0], np.cumsum(levels * K)[:-1]]).astype(np.int64)
    rows = np.zeros((n_rows, n), level0.dtype)
    if not K.any():
        return rows, start
    # Trajectories with more levels first, so those still building level lv are a prefix of ``flat``.
    order = np.argsort(-levels, kind="stable")
    K_o = K[order]
    flat = np.concatenate([level0[k, :K[k]] for k in order if K[k]])  # level 0 of all, one after another
    seg = np.arange(len(flat))
    last = np.repeat(np.cumsum(K_o) - 1, K_o)  # each segment's trajectory's last segment, in ``flat``
    dest = np.repeat(start[order], K_o) + seg - np.repeat(np.cumsum(K_o) - K_o, K_o)  # row of (level 0, i)
    stride = np.repeat(K_o, K_o)
    level = flat
    for lv in range(int(levels.max())):
        m = int(K[levels > lv].sum())  # the prefix of segments whose trajectory has a level lv
        if lv:
            half = 1 << (lv - 1)  # level lv at i: max(level lv-1 at i, at min(i + half, K - 1))
            level = np.maximum(level[:m], level[np.minimum(seg[:m] + half, last[:m])])
        rows[dest[:m] + lv * stride[:m]] = level
    return rows, start


def _segments(t, q, qd):
    h = (t[1:] - t[:-1])[:, None]
    return q[:-1], qd[:-1], q[1:], qd[1:], h, jnp.zeros_like(h), jnp.ones_like(h)


@jax.jit
def _level0_speed(t, q, qd):
    """(B, N-1, n) whole-segment speed maxima (the tables' level 0)."""
    return (jax.vmap(lambda *x: segment_speed_max(*_segments(*x)))(t, q, qd),)


@jax.jit
def _level0_accel(t, q, qd):
    """(B, N-1, n) whole-segment speed and acceleration maxima."""
    return jax.vmap(lambda *x: (segment_speed_max(*_segments(*x)), segment_accel_max(*_segments(*x))))(t, q, qd)


def spline_batch(t, q, qd, n_knots: np.ndarray, accel: bool, call=None) -> SplineBatch:
    """A :class:`SplineBatch` on the default device from padded knots ``t`` (B, N), ``q``, ``qd``
    (B, N, n) (float64, NumPy) of trajectories with ``n_knots`` (B,) real knots each (0: a
    padding trajectory, never queried, given no table rows); ``accel``:
    also the acceleration tables. ``call(fn, args)``: how to run the jitted level-0 kernel
    (default: call it; e.g. :func:`~larc_jax.compilation.tracked_call` to report compiling)."""
    fn = _level0_accel if accel else _level0_speed
    with jax.enable_x64(True):
        level0 = [np.asarray(x) for x in (fn(t, q, qd) if call is None else call(fn, (t, q, qd)))]
    K = np.maximum(np.asarray(n_knots, np.int64) - 1, 0)
    n_rows = int(sum(num_table_levels(k) * k for k in K if k))
    if len(K) == 1:  # one trajectory (certified one per call): a shape of its knot count alone
        n_rows = num_table_levels(t.shape[1] - 1) * (t.shape[1] - 1)
    n_rows = 1 << max(4, (n_rows - 1).bit_length())  # a few shapes: the next power of two
    tables = [ragged_table(x, K, n_rows) for x in level0]
    batch = SplineBatch(t_knots=t, q_knots=q, qd_knots=qd, start=tables[0][1].astype(np.int32),
                        n_segments=K.astype(np.int32), speed_rows=tables[0][0],
                        accel_rows=tables[1][0] if accel else None)
    with jax.enable_x64(True):
        return jax.device_put(batch)  # once per batch, not per kernel call


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class SplineRow:
    """Trajectory ``k`` of a :class:`SplineBatch`, read in place.

    The single-item kernels (:func:`~larc_jax.model.hermite.evaluate`,
    :func:`~larc_jax.model.hermite.speed_max`) read a spline only through ``knots()``,
    ``knot(i)`` and ``table(level, i)``; mapped over intervals with ``jax.vmap``, ``batch[k]``
    would first copy each interval's whole spline, where a row reads just the elements the kernel
    touches (gathers), which keeps the interval kernel compute-bound.
    """

    batch: SplineBatch
    k: jax.Array
    """Index of the trajectory in the batch (scalar int)."""

    @property
    def num_segments(self) -> int:
        return self.batch.t_knots.shape[-1] - 1

    @property
    def num_joints(self) -> int:
        return self.batch.q_knots.shape[-1]

    def knots(self):
        return self.batch.t_knots[self.k]

    def knot(self, i):
        b = self.batch
        return b.t_knots[self.k, i], b.q_knots[self.k, i], b.qd_knots[self.k, i]

    def _row(self, rows, level, i):
        b = self.batch
        return rows[jnp.clip(b.start[self.k] + level * b.n_segments[self.k] + i, 0, rows.shape[0] - 1)]

    def table(self, level, i):
        return self._row(self.batch.speed_rows, level, i)

    def has_accel(self) -> bool:
        return self.batch.accel_rows is not None

    def accel_table_at(self, level, i):
        return self._row(self.batch.accel_rows, level, i)
