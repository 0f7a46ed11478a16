"""Tests for larc_jax.model.spline_batch: ragged range-maximum tables read in place.

References: the definition of the sparse table (a maximum of level 0 over a window, written
here as a loop), the padded :class:`~larc_jax.model.hermite.HermiteSpline` table and its
queries (bit for bit), and the NumPy float64 reference ``speed_max_np`` / ``accel_max_np``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from larc_jax.model.hermite import (HermiteSpline, accel_max, accel_max_np, num_table_levels, pad_waypoints,
                                    speed_max, speed_max_np)
from larc_jax.model.spline_batch import SplineRow, ragged_table, spline_batch
from tests.test_hermite import KINDS, random_interval, random_traj

N_KNOTS = 48  # every batch below is padded to this many knots: one compiled shape


def _batch(rng, Ks, n=3, accel=True):
    trajs = [random_traj(rng, K, n) for K in Ks]
    padded = [pad_waypoints(*tr, N_KNOTS) for tr in trajs]
    t, q, qd = (np.stack([p[i] for p in padded]) for i in range(3))
    return trajs, padded, spline_batch(t, q, qd, np.array(Ks) + 1, accel=accel)


def test_ragged_table_is_the_sparse_table_definition():
    """Entry (l, i) of trajectory k is the max of level 0 over segments i .. min(i + 2**l, K_k) - 1,
    for every level of its own table; blocks do not overlap; the padding rows are zero."""
    rng = np.random.default_rng(11)
    Ks = np.array([1, 2, 3, 5, 8, 9, 16, 17, 40])
    level0 = rng.normal(size=(len(Ks), 45, 2))
    level0[3, 2, 1] = np.nan  # a NaN stays where the windows hold it
    total = sum(num_table_levels(k) * k for k in Ks)
    rows, start = ragged_table(level0, Ks, total + 7)
    seen = np.zeros(len(rows), int)
    for k, K in enumerate(Ks):
        for lv in range(num_table_levels(K)):
            for i in range(K):
                want = np.max(level0[k, i:min(i + 2**lv, K)], axis=0)  # np.max propagates NaN
                got = rows[start[k] + lv * K + i]
                np.testing.assert_array_equal(got, want, err_msg=f"K={K} l={lv} i={i}")
                seen[start[k] + lv * K + i] += 1
    assert (seen[:total] == 1).all() and not seen[total:].any() and not rows[total:].any()


def test_padding_trajectories_get_no_rows():
    """A trajectory with no segments (a batch's padding) has no block; the others' blocks are
    those of the table without it, in the same order, whichever trajectory has the most levels."""
    rng = np.random.default_rng(13)
    Ks = np.array([9, 0, 40, 1, 0, 17, 0])
    level0 = rng.normal(size=(len(Ks), 45, 3))
    real = Ks > 0
    total = sum(num_table_levels(k) * k for k in Ks[real])
    rows, start = ragged_table(level0, Ks, total + 3)
    want_rows, want_start = ragged_table(level0[real], Ks[real], total + 3)
    np.testing.assert_array_equal(rows, want_rows)
    np.testing.assert_array_equal(start[real], want_start)
    empty, _ = ragged_table(level0, np.zeros(len(Ks), int), 16)
    assert not empty.any()


def test_rows_are_the_padded_tables_where_queries_read_them():
    """Every entry a query can read (level l, index i with i + 2**l - 1 <= K_k - 1) is the padded
    HermiteSpline table's, bit for bit, for speeds and accelerations, in far fewer rows."""
    rng = np.random.default_rng(12)
    Ks = [1, 2, 3, 4, 7, 12, 30, 47]
    _, padded, batch = _batch(rng, Ks)
    assert batch.speed_rows.shape[0] < len(Ks) * num_table_levels(N_KNOTS - 1) * (N_KNOTS - 1) / 2
    speed, accel, start = (np.asarray(x) for x in (batch.speed_rows, batch.accel_rows, batch.start))
    with jax.enable_x64(True):
        for k, K in enumerate(Ks):
            sp = jax.jit(HermiteSpline.from_waypoints)(*padded[k])
            for name, rows, table in (("speed", speed, sp.speed_table), ("accel", accel, sp.accel_table)):
                table = np.asarray(table)
                for lv in range(num_table_levels(K)):
                    i = np.arange(K - 2**lv + 1)
                    np.testing.assert_array_equal(rows[start[k] + lv * K + i], table[lv, i], err_msg=f"{name} K={K} l={lv}")


def test_rows_answer_queries_as_the_padded_splines():
    """speed_max and accel_max through a SplineRow against each trajectory's own padded
    HermiteSpline (a few ulps: two compiled programs) and the NumPy references, on every kind of
    interval (inside one segment, across knots, the whole horizon, knot to knot, zero width at a
    knot, up to the end)."""
    rng = np.random.default_rng(12)
    Ks = [1, 2, 3, 4, 7, 12, 30, 47]
    trajs, padded, batch = _batch(rng, Ks)
    kinds = KINDS + ("zero_at_knot", "end")
    A = np.zeros((len(Ks), len(kinds)))
    B = np.zeros_like(A)
    for k, (t, _, _) in enumerate(trajs):
        for c, kind in enumerate(kinds):
            if kind == "zero_at_knot":
                A[k, c] = B[k, c] = t[rng.integers(len(t))]
            elif kind == "end":
                A[k, c], B[k, c] = t[max(0, len(t) - 3)], t[-1]
            else:
                A[k, c], B[k, c] = random_interval(rng, t, kind)

    def rows(batch, a, b):
        one = lambda k, x, y: (speed_max(SplineRow(batch, k), x, y), accel_max(SplineRow(batch, k), x, y))  # noqa: E731
        return jax.vmap(jax.vmap(one, in_axes=(None, 0, 0)))(jnp.arange(len(Ks)), a, b)

    def own(spline, a, b):
        return jax.vmap(lambda x, y: (speed_max(spline, x, y), accel_max(spline, x, y)))(a, b)

    with jax.enable_x64(True):
        got_v, got_a = (np.asarray(x) for x in jax.jit(rows)(batch, A, B))
        for k, (t, q, v) in enumerate(trajs):
            sp = HermiteSpline.from_waypoints(*padded[k])
            want_v, want_a = (np.asarray(x) for x in jax.jit(own)(sp, A[k], B[k]))
            np.testing.assert_allclose(got_v[k], want_v, rtol=4e-16, atol=0, err_msg=f"K={Ks[k]}")
            np.testing.assert_allclose(got_a[k], want_a, rtol=4e-16, atol=0, err_msg=f"K={Ks[k]}")
            for c in range(len(kinds)):
                np.testing.assert_allclose(got_v[k, c], speed_max_np(t, q, v, A[k, c], B[k, c]), rtol=1e-12, atol=1e-12)
                np.testing.assert_allclose(got_a[k, c], accel_max_np(t, q, v, A[k, c], B[k, c]), rtol=1e-12, atol=1e-9)


def test_without_accelerations_and_errors():
    rng = np.random.default_rng(13)
    _, _, batch = _batch(rng, [3, 5], accel=False)
    assert batch.accel_rows is None and not SplineRow(batch, 0).has_accel()
    with jax.enable_x64(True), pytest.raises(ValueError, match="without its acceleration table"):
        accel_max(SplineRow(batch, 0), 0.0, 1.0)
