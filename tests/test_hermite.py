"""Tests for larc_jax.model.hermite: Hermite reconstruction and exact joint-speed maxima (paper eq. 5).

Independent references: SciPy's ``CubicHermiteSpline`` (positions, derivatives, dense
sampling, exact second-derivative bound) and the NumPy loop reference ``speed_max_np`` (power
form, written separately from the JAX basis-form kernels). float64 JAX calls run inside the
scoped ``jax.enable_x64(True)`` context; global config is never flipped.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.interpolate import CubicHermiteSpline

from larc_jax.errors import LarcInputError
from larc_jax.model.hermite import (
    HermiteSpline,
    accel_max,
    batch_from_waypoints,
    evaluate,
    evaluate_np,
    num_table_levels,
    pad_waypoints,
    pad_waypoints_batch,
    segment_speed_max,
    speed_max,
    speed_max_np,
)

RTOL = 1e-12

_speed_max_jit = jax.jit(speed_max)
_evaluate_jit = jax.jit(evaluate)
# one spline, many intervals
_speed_max_many = jax.jit(jax.vmap(speed_max, in_axes=(None, 0, 0)))
# batch of splines, each with many intervals
_speed_max_batch = jax.jit(jax.vmap(jax.vmap(speed_max, in_axes=(None, 0, 0)), in_axes=(0, 0, 0)))
_from_waypoints_batch = jax.jit(jax.vmap(HermiteSpline.from_waypoints))


def random_traj(rng, K, n):
    """Random trajectory: non-uniform times (h spans two decades), random q and v."""
    h = np.exp(rng.uniform(np.log(0.02), np.log(2.0), K))
    t = rng.uniform(-1.0, 1.0) + np.concatenate([[0.0], np.cumsum(h)])
    q = rng.normal(size=(K + 1, n)).cumsum(axis=0)
    v = rng.normal(size=(K + 1, n)) * rng.uniform(0.1, 3.0)
    return t, q, v


def speed_scale(t, q, v):
    """Magnitude of the velocity terms (for relative tolerances)."""
    d = np.diff(q, axis=0) / np.diff(t)[:, None]
    return max(np.abs(v).max(), np.abs(d).max(), 1e-300)


# Knot-count buckets: a trajectory is padded (pad_waypoints) to the smallest bucket that holds it,
# so that random K in 1..40 needs only a few compilations; K = 1..4, 8, 16, 32, 40 stay unpadded.
BUCKETS = (2, 3, 4, 5, 9, 17, 33, 41)


def bucket(K):
    return min(nb for nb in BUCKETS if nb >= K + 1)


def random_interval(rng, t, kind):
    K = len(t) - 1
    if kind == "two" and K < 2:
        kind = "one"
    if kind == "one":
        k = rng.integers(K)
        a, b = np.sort(rng.uniform(t[k], t[k + 1], 2))
    elif kind == "two":
        k = rng.integers(K - 1)
        a = rng.uniform(t[k], t[k + 1])
        b = rng.uniform(t[k + 1], t[k + 2])
    elif kind == "many":
        a, b = np.sort(rng.uniform(t[0], t[-1], 2))
    elif kind == "all":
        a, b = t[0], t[-1]
    elif kind == "knots":
        i, j = np.sort(rng.integers(0, K + 1, 2))
        a, b = t[i], t[j]
    elif kind == "knot_to_point":
        i = rng.integers(0, K)
        a, b = t[i], rng.uniform(t[i], t[-1])
    else:
        raise AssertionError(kind)
    return float(a), float(b)


KINDS = ("one", "two", "many", "all", "knots", "knot_to_point")


# ------------------------------------------------------------------------------------------
# Hermite curve
# ------------------------------------------------------------------------------------------


def test_evaluate_interpolates_knots():
    rng = np.random.default_rng(1)
    with jax.enable_x64(True):
        for K in (1, 2, 7):
            t, q, v = random_traj(rng, K, 4)
            sp = HermiteSpline.from_waypoints(t, q, v)
            for k in range(K + 1):
                qk, vk = _evaluate_jit(sp, t[k])
                np.testing.assert_allclose(np.asarray(qk), q[k], rtol=0, atol=1e-13 * np.abs(q).max())
                np.testing.assert_allclose(np.asarray(vk), v[k], rtol=0, atol=1e-13 * speed_scale(t, q, v))
            # The basis form is exact at both ends of a segment.
            np.testing.assert_array_equal(np.asarray(_evaluate_jit(sp, t[0])[1]), v[0])
            np.testing.assert_array_equal(np.asarray(_evaluate_jit(sp, t[-1])[1]), v[-1])
            np.testing.assert_array_equal(np.asarray(_evaluate_jit(sp, t[-1])[0]), q[-1])


@pytest.mark.slow
def test_evaluate_matches_scipy():
    rng = np.random.default_rng(2)
    ev = jax.jit(jax.vmap(evaluate, in_axes=(None, 0)))
    total = 0
    with jax.enable_x64(True):
        for K, n_t in ((1, 1000), (6, 3000), (40, 6000)):
            t, q, v = random_traj(rng, K, 5)
            ref = CubicHermiteSpline(t, q, v, axis=0)
            ts = rng.uniform(t[0], t[-1], n_t)
            ts[:K + 1] = t  # include every knot
            sp = HermiteSpline.from_waypoints(t, q, v)
            qj, vj = ev(sp, jnp.asarray(ts))
            qscale = max(np.abs(q).max(), speed_scale(t, q, v) * (t[-1] - t[0]))
            np.testing.assert_allclose(np.asarray(qj), ref(ts), rtol=0, atol=RTOL * qscale)
            np.testing.assert_allclose(np.asarray(vj), ref(ts, 1), rtol=0, atol=RTOL * speed_scale(t, q, v))
            # The NumPy reference agrees with SciPy as well.
            for tt in ts[:50]:
                qn, vn = evaluate_np(t, q, v, tt)
                np.testing.assert_allclose(qn, ref(tt), rtol=0, atol=RTOL * qscale)
                np.testing.assert_allclose(vn, ref(tt, 1), rtol=0, atol=RTOL * speed_scale(t, q, v))
            total += n_t
    assert total >= 10_000


def test_evaluate_extrapolates_end_segments():
    rng = np.random.default_rng(3)
    with jax.enable_x64(True):
        t, q, v = random_traj(rng, 4, 2)
        ref = CubicHermiteSpline(t, q, v, axis=0, extrapolate=True)
        sp = HermiteSpline.from_waypoints(t, q, v)
        for tt in (t[0] - 0.3, t[-1] + 0.2):
            qj, vj = _evaluate_jit(sp, tt)
            np.testing.assert_allclose(np.asarray(qj), ref(tt), rtol=1e-11, atol=1e-11)
            np.testing.assert_allclose(np.asarray(vj), ref(tt, 1), rtol=1e-11, atol=1e-11)


# ------------------------------------------------------------------------------------------
# Sparse table
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("K,L", [(1, 1), (2, 2), (3, 3), (4, 3), (5, 4), (8, 4), (9, 5), (40, 7)])
def test_num_table_levels(K, L):
    assert num_table_levels(K) == L


def test_speed_table_definition():
    rng = np.random.default_rng(4)
    with jax.enable_x64(True):
        for K in (1, 2, 3, 5, 13):
            t, q, v = random_traj(rng, K, 3)
            sp = jax.jit(HermiteSpline.from_waypoints)(t, q, v)
            table = np.asarray(sp.speed_table)
            assert table.shape == (num_table_levels(K), K, 3)
            seg = np.stack([speed_max_np(t, q, v, t[k], t[k + 1]) for k in range(K)])
            scale = speed_scale(t, q, v)
            for lv in range(table.shape[0]):
                for k in range(K):
                    want = seg[k:min(k + 2**lv, K)].max(axis=0)
                    np.testing.assert_allclose(table[lv, k], want, rtol=0, atol=RTOL * scale)


def test_tables_are_range_maxima_of_their_first_level():
    """Every level of both sparse tables is the maximum of level 0 over ``[k, min(k + 2**l, K))``
    exactly (a max of stored numbers: no rounding), for K a power of two and not, 1..40 segments
    (the levels are built from shifted slices, the last segment repeated)."""
    rng = np.random.default_rng(11)
    with jax.enable_x64(True):
        for K in (1, 2, 3, 4, 7, 8, 9, 16, 31, 40):
            t, q, v = random_traj(rng, K, 2)
            sp = jax.jit(HermiteSpline.from_waypoints)(t, q, v)
            for table in (np.asarray(sp.speed_table), np.asarray(sp.accel_table)):
                for lv in range(table.shape[0]):
                    for k in range(K):
                        np.testing.assert_array_equal(table[lv, k], table[0, k:min(k + 2**lv, K)].max(axis=0))


def test_spline_without_acceleration_table():
    """``from_waypoints(..., accel=False)`` builds the same speed table and no acceleration table;
    ``accel_max`` on it is refused with a message, not an index error from inside JAX."""
    rng = np.random.default_rng(12)
    t, q, v = random_traj(rng, 6, 3)
    with jax.enable_x64(True):
        full = jax.jit(HermiteSpline.from_waypoints)(t, q, v)  # both compiled: the same arithmetic
        lean = jax.jit(lambda *x: HermiteSpline.from_waypoints(*x, accel=False))(t, q, v)
        assert lean.accel_table is None
        np.testing.assert_array_equal(np.asarray(lean.speed_table), np.asarray(full.speed_table))
        np.testing.assert_array_equal(np.asarray(speed_max(lean, t[1], t[4])), np.asarray(speed_max(full, t[1], t[4])))
        assert np.all(np.asarray(accel_max(full, t[1], t[4])) >= 0)
        with pytest.raises(ValueError, match="acceleration table"):
            accel_max(lean, t[1], t[4])


# ------------------------------------------------------------------------------------------
# speed_max against the NumPy reference and dense sampling
# ------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_speed_max_matches_reference_1000_cases():
    rng = np.random.default_rng(5)
    n_cases = 0
    kinds_seen = set()
    with jax.enable_x64(True):
        for K in range(1, 41):
            n = 1 + BUCKETS.index(bucket(K)) % 7  # joint count varies (per bucket)
            trajs = [random_traj(rng, K, n) for _ in range(5)]
            padded = [pad_waypoints(*tr, bucket(K)) for tr in trajs]
            T = np.stack([p[0] for p in padded])
            Q = np.stack([p[1] for p in padded])
            V = np.stack([p[2] for p in padded])
            A = np.zeros((5, len(KINDS)))
            B = np.zeros((5, len(KINDS)))
            for i, (t, _, _) in enumerate(trajs):
                for c, kind in enumerate(KINDS):
                    A[i, c], B[i, c] = random_interval(rng, t, kind)
                    kinds_seen.add(kind)
            splines = _from_waypoints_batch(T, Q, V)
            got = np.asarray(_speed_max_batch(splines, jnp.asarray(A), jnp.asarray(B)))
            assert got.dtype == np.float64 and got.shape == (5, len(KINDS), n)
            for i, (t, q, v) in enumerate(trajs):
                scale = speed_scale(t, q, v)
                for c in range(len(KINDS)):
                    want = speed_max_np(t, q, v, A[i, c], B[i, c])
                    np.testing.assert_allclose(
                        got[i, c], want, rtol=RTOL, atol=RTOL * scale,
                        err_msg=f"K={K} traj={i} kind={KINDS[c]} a={A[i, c]!r} b={B[i, c]!r}",
                    )
                    n_cases += 1
    assert n_cases >= 1000
    assert kinds_seen == set(KINDS)


@pytest.mark.slow
def test_speed_max_never_below_dense_sampling_and_tight():
    rng = np.random.default_rng(6)
    with jax.enable_x64(True):
        for case in range(30):
            K = int(rng.integers(1, 41))
            t, q, v = random_traj(rng, K, 6)
            a, b = random_interval(rng, t, ("one", "two", "many", "all", "knot_to_point")[case % 5])
            ref = CubicHermiteSpline(t, q, v, axis=0)
            grid = np.linspace(a, b, 10_000)
            dense = np.abs(ref(grid, 1)).max(axis=0)
            sp = HermiteSpline.from_waypoints(*pad_waypoints(t, q, v, bucket(K)))
            omega = np.asarray(_speed_max_jit(sp, a, b))
            scale = speed_scale(t, q, v)
            assert np.all(omega >= dense - RTOL * scale), (case, omega - dense)
            # Tightness: |qdot| is Lipschitz with constant M = max |qddot| (exact from SciPy's
            # piecewise-linear second derivative), so the true max exceeds the grid max by at
            # most M * spacing / 2.
            c2 = ref.derivative(2).c  # (2, K, n): qddot = c2[0] (t - t_k) + c2[1]
            M = np.maximum(np.abs(c2[1]), np.abs(c2[0] * np.diff(t)[:, None] + c2[1])).max(axis=0)
            spacing = (b - a) / (len(grid) - 1)
            assert np.all(omega <= dense + M * spacing / 2 + RTOL * scale), (case, omega - dense)


# ------------------------------------------------------------------------------------------
# Known maxima
# ------------------------------------------------------------------------------------------


def _one_segment(q0, v0, q1, v1, h, t0=0.0):
    t = np.array([t0, t0 + h])
    q = np.array([q0, q1], dtype=np.float64).reshape(2, -1)
    v = np.array([v0, v1], dtype=np.float64).reshape(2, -1)
    return t, q, v


def _check_known(t, q, v, a, b, want):
    with jax.enable_x64(True):
        sp = HermiteSpline.from_waypoints(t, q, v)
        got = np.asarray(_speed_max_jit(sp, a, b))
    np.testing.assert_allclose(got, want, rtol=RTOL, atol=0)
    np.testing.assert_allclose(speed_max_np(t, q, v, a, b), want, rtol=RTOL, atol=0)


@pytest.mark.parametrize("h", [0.7, 1.0, 3.25])
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_known_rest_to_rest_peak(h, sign):
    # v0 = v1 = 0, q: 0 -> +-1: qdot = 6 s (1 - s) / h, peak 1.5 / h at s = 1/2.
    t, q, v = _one_segment(0.0, 0.0, sign, 0.0, h, t0=0.4)
    _check_known(t, q, v, t[0], t[1], [1.5 / h])
    # Sub-range [0, 0.25]: increasing there, max at s = 0.25 -> 6 * 0.25 * 0.75 / h.
    _check_known(t, q, v, t[0], t[0] + 0.25 * h, [1.125 / h])
    # Vertex outside the interval [0.6, 0.9]: max at s = 0.6 -> 1.44 / h.
    _check_known(t, q, v, t[0] + 0.6 * h, t[0] + 0.9 * h, [6 * 0.6 * 0.4 / h])
    # Sub-range straddling the vertex.
    _check_known(t, q, v, t[0] + 0.3 * h, t[0] + 0.55 * h, [1.5 / h])


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_known_linear_segment_constant_speed(sign):
    h = 0.8
    dq = sign * np.array([0.4, -1.2, 0.0])
    t, q, v = _one_segment(np.zeros(3), dq / h, dq, dq / h, h)
    for s0, s1 in ((0.0, 1.0), (0.1, 0.2), (0.5, 0.5), (0.9, 1.0)):
        _check_known(t, q, v, s0 * h, s1 * h, np.abs(dq) / h)


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_known_vertex_outside_segment(sign):
    # qdot(s) = sign * (1 + s + s^2): v0 = 1, v1 = 3, chord slope 11/6 (h = 1); vertex at s = -1/2.
    t, q, v = _one_segment(0.0, sign * 1.0, sign * 11.0 / 6.0, sign * 3.0, 1.0)
    _check_known(t, q, v, 0.0, 1.0, [3.0])
    _check_known(t, q, v, 0.0, 0.5, [1.75])
    _check_known(t, q, v, 0.2, 0.2, [1.0 + 0.2 + 0.04])


def test_known_two_segments():
    # 0 -> 1 -> 0 at rest at every knot, h = 1: each segment peaks at 1.5 in its middle.
    t = np.array([0.0, 1.0, 2.0])
    q = np.array([[0.0], [1.0], [0.0]])
    v = np.zeros((3, 1))
    _check_known(t, q, v, 0.0, 2.0, [1.5])
    _check_known(t, q, v, 0.5, 1.5, [1.5])
    _check_known(t, q, v, 0.75, 1.25, [6 * 0.75 * 0.25])
    _check_known(t, q, v, 1.0, 1.0, [0.0])


def test_segment_speed_max_kernel():
    with jax.enable_x64(True):
        # Rest-to-rest, h = 2: qdot = 3 s (1 - s).
        f = jax.jit(segment_speed_max)
        args = (jnp.zeros(1), jnp.zeros(1), jnp.ones(1), jnp.zeros(1), 2.0)
        np.testing.assert_allclose(np.asarray(f(*args, 0.0, 1.0)), [0.75], rtol=RTOL)
        np.testing.assert_allclose(np.asarray(f(*args, 0.2, 0.2)), [3 * 0.2 * 0.8], rtol=RTOL)
        np.testing.assert_array_equal(np.asarray(f(*args, 0.0, 0.0)), [0.0])
        # Zero speed: no NaN.
        z = jnp.zeros(3)
        out = np.asarray(f(z, z, z, z, 1.0, 0.0, 1.0))
        np.testing.assert_array_equal(out, np.zeros(3))


# ------------------------------------------------------------------------------------------
# Edge cases
# ------------------------------------------------------------------------------------------


def test_zero_speed_everywhere():
    t = np.array([0.0, 0.5, 1.7, 2.0, 4.0, 4.1])
    q = np.tile(np.array([0.3, -1.0, 2.0]), (6, 1))
    v = np.zeros_like(q)
    with jax.enable_x64(True):
        sp = HermiteSpline.from_waypoints(t, q, v)
        assert np.all(np.asarray(sp.speed_table) == 0.0)
        for a, b in ((0.0, 4.1), (0.2, 0.2), (0.5, 4.0), (1.0, 3.0), (4.1, 4.1)):
            out = np.asarray(_speed_max_jit(sp, a, b))
            np.testing.assert_array_equal(out, np.zeros(3))
    with jax.enable_x64(False):
        out = np.asarray(_speed_max_jit(HermiteSpline.from_waypoints(t, q, v), 0.0, 4.1))
        np.testing.assert_array_equal(out, np.zeros(3))


def test_zero_width_intervals():
    rng = np.random.default_rng(7)
    with jax.enable_x64(True):
        for K in (1, 2, 9):
            t, q, v = random_traj(rng, K, 4)
            sp = HermiteSpline.from_waypoints(t, q, v)
            ref = CubicHermiteSpline(t, q, v, axis=0)
            scale = speed_scale(t, q, v)
            # Interior points.
            for tt in rng.uniform(t[0], t[-1], 10):
                out = np.asarray(_speed_max_jit(sp, tt, tt))
                np.testing.assert_allclose(out, np.abs(ref(tt, 1)), rtol=0, atol=RTOL * scale)
                np.testing.assert_allclose(out, speed_max_np(t, q, v, tt, tt), rtol=0, atol=RTOL * scale)
            # Exactly at every knot, t_0 and t_K included: exactly |v_k|.
            for k in range(K + 1):
                out = np.asarray(_speed_max_jit(sp, t[k], t[k]))
                np.testing.assert_array_equal(out, np.abs(v[k]))


def test_interval_equal_to_one_segment():
    # The middle segment is slow; its neighbours are fast. [t_1, t_2] must not see them.
    t = np.array([0.0, 1.0, 1.5, 3.0])
    q = np.array([[0.0], [5.0], [5.1], [-5.0]])
    v = np.array([[0.0], [0.2], [0.2], [0.0]])
    with jax.enable_x64(True):
        sp = HermiteSpline.from_waypoints(t, q, v)
        out = np.asarray(_speed_max_jit(sp, 1.0, 1.5))
        table = np.asarray(sp.speed_table)
    want = speed_max_np(t, q, v, 1.0, 1.5)
    # Segment 1: v0 = v1 = 0.2, chord slope 0.2 -> linear, constant speed 0.2.
    np.testing.assert_allclose(want, [0.2], rtol=RTOL)
    np.testing.assert_allclose(out, want, rtol=RTOL)
    np.testing.assert_allclose(out, table[0, 1], rtol=RTOL)
    assert np.asarray(speed_max_np(t, q, v, 0.0, 3.0))[0] > 5.0


def test_single_segment_K1():
    rng = np.random.default_rng(8)
    with jax.enable_x64(True):
        for _ in range(20):
            t, q, v = random_traj(rng, 1, 3)
            sp = HermiteSpline.from_waypoints(t, q, v)
            assert sp.speed_table.shape == (1, 1, 3)
            a, b = np.sort(rng.uniform(t[0], t[1], 2))
            scale = speed_scale(t, q, v)
            for aa, bb in ((a, b), (t[0], t[1]), (t[0], a), (b, t[1])):
                np.testing.assert_allclose(
                    np.asarray(_speed_max_jit(sp, aa, bb)), speed_max_np(t, q, v, aa, bb),
                    rtol=RTOL, atol=RTOL * scale,
                )


def test_pad_waypoints_layout():
    rng = np.random.default_rng(9)
    t, q, v = random_traj(rng, 3, 2)
    tp, qp, vp = pad_waypoints(t, q, v, 8)
    assert tp.shape == (8,) and qp.shape == (8, 2) and vp.shape == (8, 2)
    np.testing.assert_array_equal(tp[:4], t)
    np.testing.assert_array_equal(tp[4:], t[-1] + np.arange(1.0, 5.0))
    assert np.all(np.diff(tp) > 0)
    np.testing.assert_array_equal(qp[4:], np.tile(q[-1], (4, 1)))
    np.testing.assert_array_equal(vp[:4], v)
    np.testing.assert_array_equal(vp[4:], 0.0)
    # No-op and error cases.
    tp2, _, _ = pad_waypoints(t, q, v, 4)
    np.testing.assert_array_equal(tp2, t)
    with pytest.raises(LarcInputError):
        pad_waypoints(t, q, v, 3)


def test_pad_waypoints_batch_is_pad_waypoints_stacked():
    """Each row is pad_waypoints of its trajectory bit for bit (times, positions, velocities),
    the rows after the trajectories repeat row 0, and too few knots is refused naming the trajectory."""
    rng = np.random.default_rng(19)
    trajs = [random_traj(rng, K, 3) for K in (1, 2, 5, 17, 30, 31)]
    trajs[2] = (trajs[2][0] + 1.7e9, *trajs[2][1:])  # large times: the padding knots are still increasing
    t, q, v = pad_waypoints_batch(trajs, 32, 8)
    assert t.shape == (8, 32) and q.shape == v.shape == (8, 32, 3) and t.dtype == q.dtype == np.float64
    for k, tr in enumerate(trajs):
        for got, want in zip((t[k], q[k], v[k]), pad_waypoints(*tr, 32)):
            np.testing.assert_array_equal(got, want)
    for k in (6, 7):
        np.testing.assert_array_equal(t[k], t[0])
        np.testing.assert_array_equal(q[k], q[0])
        np.testing.assert_array_equal(v[k], v[0])
    with pytest.raises(LarcInputError, match="trajectory 5"):
        pad_waypoints_batch(trajs, 31, 8)
    # Times that do not rise are blamed on the knots that do not, not on the padding.
    bad = (trajs[3][0].copy(), *trajs[3][1:])
    bad[0][4] = bad[0][3]
    with pytest.raises(LarcInputError, match=r"t\[3\], t\[4\] of trajectory 1 are not increasing"):
        pad_waypoints_batch([trajs[0], bad], 32, 2)
    huge = (2.0**53 + np.array([0.0, 2.0, 4.0]), *trajs[1][1:])  # t_K + 1 == t_K in float64: the padding's
    with pytest.raises(LarcInputError, match="padding times after t_K of trajectory 0"):
        pad_waypoints_batch([huge], 32, 1)


@pytest.mark.slow
def test_padding_does_not_change_speed_max():
    rng = np.random.default_rng(10)
    with jax.enable_x64(True):
        for K in (1, 2, 5, 16):
            t, q, v = random_traj(rng, K, 3)
            sp = HermiteSpline.from_waypoints(t, q, v)
            spp = HermiteSpline.from_waypoints(*pad_waypoints(t, q, v, K + 1 + 11))
            ivals = [random_interval(rng, t, KINDS[i % len(KINDS)]) for i in range(60)]
            ivals += [(t[0], t[-1]), (t[-1], t[-1]), (t[0], t[0]), (t[-2], t[-1])]
            A = jnp.asarray([iv[0] for iv in ivals])
            B = jnp.asarray([iv[1] for iv in ivals])
            plain = np.asarray(_speed_max_many(sp, A, B))
            padded = np.asarray(_speed_max_many(spp, A, B))
            np.testing.assert_allclose(padded, plain, rtol=1e-15, atol=0)
            # A padding segment would report |v| = 0 at its end, so also check the reference.
            for i, (a, b) in enumerate(ivals):
                np.testing.assert_allclose(
                    padded[i], speed_max_np(t, q, v, a, b), rtol=RTOL, atol=RTOL * speed_scale(t, q, v)
                )


def test_float32_inputs():
    rng = np.random.default_rng(11)
    t, q, v = random_traj(rng, 12, 6)
    ivals = [random_interval(rng, t, KINDS[i % len(KINDS)]) for i in range(30)]
    t32, q32, v32 = t.astype(np.float32), q.astype(np.float32), v.astype(np.float32)
    for x64 in (False, True):
        with jax.enable_x64(x64):
            sp = HermiteSpline.from_waypoints(t32, q32, v32)
            assert sp.t_knots.dtype == jnp.float32 and sp.speed_table.dtype == jnp.float32
            for a, b in ivals:
                out = _speed_max_jit(sp, np.float32(a), np.float32(b))
                assert out.dtype == jnp.float32
                assert np.all(np.isfinite(np.asarray(out)))
                want = speed_max_np(t32, q32, v32, np.float32(a), np.float32(b))
                np.testing.assert_allclose(np.asarray(out), want, rtol=1e-4, atol=1e-4 * speed_scale(t, q, v))
            qj, vj = _evaluate_jit(sp, np.float32(t[3]))
            assert qj.dtype == jnp.float32 and vj.dtype == jnp.float32


def test_shape_validation():
    t = np.array([0.0, 1.0])
    with pytest.raises(LarcInputError):
        HermiteSpline.from_waypoints(t, np.zeros((3, 2)), np.zeros((3, 2)))
    with pytest.raises(LarcInputError):
        HermiteSpline.from_waypoints(t, np.zeros((2, 2)), np.zeros((2, 3)))
    with pytest.raises(LarcInputError):
        HermiteSpline.from_waypoints(np.array([0.0]), np.zeros((1, 2)), np.zeros((1, 2)))


# ------------------------------------------------------------------------------------------
# Batches: jit + vmap over padded splines and many intervals
# ------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_batched_jit_vmap_matches_per_item():
    rng = np.random.default_rng(12)
    Ks = (1, 3, 8, 20, 33, 2)
    n = 6
    trajs = [random_traj(rng, K, n) for K in Ks]
    n_ivals = 40
    A = np.zeros((len(Ks), n_ivals))
    B = np.zeros((len(Ks), n_ivals))
    for i, (t, _, _) in enumerate(trajs):
        for c in range(n_ivals):
            A[i, c], B[i, c] = random_interval(rng, t, KINDS[c % len(KINDS)])
    with jax.enable_x64(True):
        batch = batch_from_waypoints([tr[0] for tr in trajs], [tr[1] for tr in trajs], [tr[2] for tr in trajs])
        N = max(Ks) + 1
        assert batch.t_knots.shape == (len(Ks), N)
        assert batch.q_knots.shape == (len(Ks), N, n)
        assert batch.speed_table.shape == (len(Ks), num_table_levels(N - 1), N - 1, n)
        got = np.asarray(_speed_max_batch(batch, jnp.asarray(A), jnp.asarray(B)))
        # Same batch built by stacking per-item padded splines.
        stacked = jax.tree_util.tree_map(
            lambda *xs: jnp.stack(xs),
            *[HermiteSpline.from_waypoints(*pad_waypoints(*tr, N)) for tr in trajs],
        )
        got_stacked = np.asarray(_speed_max_batch(stacked, jnp.asarray(A), jnp.asarray(B)))
        np.testing.assert_array_equal(got_stacked, got)
        ev_batch = jax.jit(jax.vmap(jax.vmap(evaluate, in_axes=(None, 0)), in_axes=(0, 0)))
        qb, vb = ev_batch(batch, jnp.asarray(A))
        for i, (t, q, v) in enumerate(trajs):
            sp = HermiteSpline.from_waypoints(t, q, v)  # unpadded
            scale = speed_scale(t, q, v)
            for c in range(n_ivals):
                single = np.asarray(_speed_max_jit(sp, A[i, c], B[i, c]))
                np.testing.assert_allclose(got[i, c], single, rtol=1e-15, atol=0)
                np.testing.assert_allclose(
                    got[i, c], speed_max_np(t, q, v, A[i, c], B[i, c]), rtol=RTOL, atol=RTOL * scale
                )
                qs, vs = evaluate_np(t, q, v, A[i, c])
                np.testing.assert_allclose(np.asarray(vb[i, c]), vs, rtol=0, atol=RTOL * scale)
                np.testing.assert_allclose(
                    np.asarray(qb[i, c]), qs, rtol=0, atol=RTOL * max(np.abs(q).max(), scale * (t[-1] - t[0]))
                )
