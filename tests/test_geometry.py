"""Tests for larc_jax.obstacles.geometry: exact segment-box distance (JAX kernel, NumPy reference, batch)."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import minimize_scalar

from larc_jax.obstacles.geometry import (
    segment_box_distance,
    segment_box_distance_np,
    segment_box_distances,
)

# One compiled batched kernel per dtype; every test goes through these (jit once, vmap big).
_kernel_vmapped = jax.jit(jax.vmap(segment_box_distance))
_kernel_single = jax.jit(segment_box_distance)


def jax_f64(p0, p1, lo, hi) -> np.ndarray:
    """Kernel in float64 on (N, 3) arrays (or (3,) for one item)."""
    with jax.enable_x64(True):
        args = [jnp.asarray(np.asarray(v, np.float64)) for v in (p0, p1, lo, hi)]
        fn = _kernel_single if args[0].ndim == 1 else _kernel_vmapped
        out = fn(*args)
        assert out.dtype == jnp.float64
        return np.asarray(out)


def jax_f32(p0, p1, lo, hi) -> np.ndarray:
    """Kernel in float32 on (N, 3) arrays (or (3,) for one item)."""
    args = [jnp.asarray(np.asarray(v, np.float32)) for v in (p0, p1, lo, hi)]
    fn = _kernel_single if args[0].ndim == 1 else _kernel_vmapped
    out = fn(*args)
    assert out.dtype == jnp.float32
    return np.asarray(out)


def ref_np(p0, p1, lo, hi) -> np.ndarray:
    p0, p1, lo, hi = (np.atleast_2d(np.asarray(v, np.float64)) for v in (p0, p1, lo, hi))
    return np.array([segment_box_distance_np(*row) for row in zip(p0, p1, lo, hi)])


def point_box_distance(x, lo, hi) -> np.ndarray:
    """Distance from points x (..., 3) to the box [lo, hi]; independent of the kernels."""
    gap = np.maximum(np.maximum(lo - x, x - hi), 0.0)
    return np.sqrt(np.sum(gap * gap, axis=-1))


def random_cases(seed: int, n: int):
    """(p0, p1, lo, hi), each (n, 3) float64: varied scales, placements and exact ties."""
    rng = np.random.default_rng(seed)
    scale = 10.0 ** rng.uniform(-2, 1, size=(n, 1))
    centre = rng.uniform(-1, 1, size=(n, 3)) * scale
    half = rng.uniform(0, 1, size=(n, 3)) * scale
    flat = rng.random(n) < 0.15  # some boxes flat on one axis (lo == hi)
    half[flat, rng.integers(0, 3, size=flat.sum())] = 0.0
    lo, hi = centre - half, centre + half

    def in_box(m):
        return lo[:m] + rng.random((m, 3)) * (hi[:m] - lo[:m])

    p0 = centre + rng.uniform(-4, 4, size=(n, 3)) * scale
    p1 = centre + rng.uniform(-4, 4, size=(n, 3)) * scale
    mode = rng.integers(0, 8, size=n)
    q = lo + rng.random((n, 3)) * (hi - lo)  # a point in each box
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    a = rng.uniform(0.1, 4, size=(n, 1)) * scale
    b = rng.uniform(0.1, 4, size=(n, 1)) * scale
    cross = mode == 1  # through a point of the box: distance 0
    p0[cross], p1[cross] = (q - a * u)[cross], (q + b * u)[cross]
    inside = mode == 2  # both ends inside
    p0[inside], p1[inside] = in_box(n)[inside], in_box(n)[inside]
    one_in = mode == 3
    p0[one_in] = in_box(n)[one_in]
    par = mode == 4  # parallel to some faces: d_i = 0 on random axes
    keep = rng.random((n, 3)) < 0.5
    p1[par] = np.where(keep, p0, p1)[par]
    zero = mode == 5  # zero-length
    p1[zero] = p0[zero]
    snap = mode == 6  # coordinates snapped onto the box planes: ties between breakpoints
    planes = np.where(rng.random((n, 3)) < 0.5, lo, hi)
    p0[snap] = np.where(rng.random((n, 3)) < 0.5, planes, p0)[snap]
    p1[snap] = np.where(rng.random((n, 3)) < 0.5, planes, p1)[snap]
    grid = mode == 7  # small dyadic grid: exact arithmetic, edge/vertex contacts and ties
    g = lambda: rng.integers(-3, 4, size=(n, 3)) * 0.25  # noqa: E731
    g1, g2 = g(), g()
    lo[grid], hi[grid] = np.minimum(g1, g2)[grid], np.maximum(g1, g2)[grid]
    p0[grid], p1[grid] = g()[grid], g()[grid]
    return p0, p1, lo, hi


# ---------------------------------------------------------------------------------------------
# Random agreement: kernel vs reference vs sampling vs scipy
# ---------------------------------------------------------------------------------------------


def test_kernel_matches_numpy_reference_float64():
    p0, p1, lo, hi = random_cases(0, 4000)
    got = jax_f64(p0, p1, lo, hi)
    want = ref_np(p0, p1, lo, hi)
    assert np.all(np.isfinite(got))
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
    # The generator really covers intersecting and separated cases.
    assert np.mean(want == 0) > 0.2 and np.mean(want > 0) > 0.3


def test_dense_sampling_and_scipy_bound_the_exact_value():
    p0, p1, lo, hi = random_cases(1, 300)
    exact = jax_f64(p0, p1, lo, hi)
    ref = ref_np(p0, p1, lo, hi)
    t = np.linspace(0.0, 1.0, 10_000)
    h = t[1] - t[0]
    for k in range(len(p0)):
        seg_len = float(np.linalg.norm(p1[k] - p0[k]))
        x = p0[k] + t[:, None] * (p1[k] - p0[k])
        sampled = point_box_distance(x, lo[k], hi[k]).min()
        # A true minimum is never above a sampled value; the distance is seg_len-Lipschitz in t,
        # so the sample nearest the minimiser is within seg_len * h / 2 of it.
        for val in (exact[k], ref[k]):
            assert val <= sampled + 1e-12
            assert sampled - val <= seg_len * h / 2 + 1e-12

        res = minimize_scalar(
            lambda s: float(point_box_distance(p0[k] + s * (p1[k] - p0[k]), lo[k], hi[k])),
            bounds=(0.0, 1.0),
            method="bounded",
            options={"xatol": 1e-10},
        )
        assert exact[k] <= res.fun + 1e-12
        assert res.fun - exact[k] <= 1e-8 * (1.0 + seg_len)


def test_float32_close_to_float64():
    p0, p1, lo, hi = (v.astype(np.float32) for v in random_cases(2, 3000))
    d32 = jax_f32(p0, p1, lo, hi)
    d64 = jax_f64(p0, p1, lo, hi)  # same (float32-representable) inputs, in float64
    assert d32.dtype == np.float32 and np.all(np.isfinite(d32))
    # Relative 1e-5, except where the distance is far below the coordinates' magnitude: there
    # float32 rounding of positions (eps32 * |coordinate|) is the floor.
    mag = np.max(np.abs(np.concatenate([p0, p1, lo, hi], axis=1)), axis=1)
    err = np.abs(d32.astype(np.float64) - d64)
    assert np.all(err <= 1e-5 * d64 + 8 * np.finfo(np.float32).eps * mag)


def test_never_nan_on_extreme_inputs():
    rng = np.random.default_rng(3)
    n = 500
    base = rng.uniform(-1, 1, size=(n, 3))
    lo = rng.uniform(-1, 0, size=(n, 3))
    hi = lo + rng.uniform(0, 1, size=(n, 3))
    nudge = np.nextafter(base, np.inf)  # one-ulp segments
    for dtype, big in ((np.float32, 1e30), (np.float64, 1e200)):
        cases = [
            (base, nudge, lo, hi),
            (base * big, -base * big, lo, hi),  # huge segment across a small box
            (base, base, lo * big, hi * big),  # huge box
            (base * 1e-30, nudge * 1e-30, lo * 1e-30, hi * 1e-30),  # subnormal-ish
        ]
        for args in cases:
            args = [np.asarray(a, dtype) for a in args]
            out = jax_f32(*args) if dtype == np.float32 else jax_f64(*args)
            assert not np.any(np.isnan(out)), dtype


# ---------------------------------------------------------------------------------------------
# Named edge cases with known answers (box [0, 1]^3 unless stated)
# ---------------------------------------------------------------------------------------------

UNIT_LO, UNIT_HI = np.zeros(3), np.ones(3)


def check(p0, p1, expected, lo=UNIT_LO, hi=UNIT_HI, exact_zero=False):
    """Assert the float64 kernel, the reference and the float32 kernel give `expected`."""
    p0, p1, lo, hi = (np.asarray(v, np.float64) for v in (p0, p1, lo, hi))
    mag = max(np.max(np.abs(v)) for v in (p0, p1, lo, hi))
    d64 = float(jax_f64(p0, p1, lo, hi))
    dnp = segment_box_distance_np(p0, p1, lo, hi)
    d32 = jax_f32(p0, p1, lo, hi)
    assert d32.dtype == np.float32
    d32 = float(d32)
    for d in (d64, dnp, d32):
        assert math.isfinite(d)
    if exact_zero:
        assert d64 == 0.0 and dnp == 0.0 and d32 == 0.0
    tol64 = 1e-12 * max(expected, mag)
    assert abs(d64 - expected) <= tol64
    assert abs(dnp - expected) <= tol64
    assert abs(d32 - expected) <= 1e-5 * expected + 4 * np.finfo(np.float32).eps * mag
    # Reversing the segment must not change anything.
    assert abs(float(jax_f64(p1, p0, lo, hi)) - d64) <= tol64


def test_zero_length_outside():
    check([2, 3, 0.5], [2, 3, 0.5], math.sqrt(5))


def test_zero_length_on_surface():
    check([1, 0.5, 0.5], [1, 0.5, 0.5], 0.0, exact_zero=True)
    check([0, 0, 0], [0, 0, 0], 0.0, exact_zero=True)  # on a vertex


def test_zero_length_inside():
    check([0.5, 0.25, 0.75], [0.5, 0.25, 0.75], 0.0, exact_zero=True)


def test_parallel_to_face_outside():
    check([-1, 0.5, 1.5], [2, 0.5, 1.5], 0.5)  # over the top face
    check([2, 0.5, 3], [5, 0.5, 3], math.sqrt(1 + 4))  # parallel and beside, nearest an edge


def test_touching_an_edge():
    check([2, 0, 0.5], [0, 2, 0.5], 0.0, exact_zero=True)  # crosses the x=1,y=1 edge
    check([2, 2, 0.25], [1, 1, 0.25], 0.0, exact_zero=True)  # ends on it


def test_touching_a_vertex():
    check([2, 2, 2], [1, 1, 1], 0.0, exact_zero=True)  # ends on the vertex
    check([2, 0, 0], [0, 2, 2], 0.0, exact_zero=True)  # passes through (1, 1, 1) only


def test_crossing_through_two_faces():
    check([-1, 0.5, 0.5], [2, 0.3, 0.6], 0.0)
    check([0.5, -3, 0.2], [0.4, 4, 0.9], 0.0)


def test_fully_inside():
    check([0.1, 0.2, 0.3], [0.9, 0.8, 0.7], 0.0, exact_zero=True)


def test_along_edge_line_beyond_box():
    check([2, 0, 0], [5, 0, 0], 1.0)
    check([-3, 1, 1], [-0.5, 1, 1], 0.5)


def test_diagonal_approach_to_vertex():
    k = 0.25
    v = np.ones(3)
    check(v + 3 * k, v + k, math.sqrt(3) * k)
    # Passing beside the vertex, perpendicular to the diagonal: interior minimiser at t = 1/2.
    s = 0.1 * np.array([1.0, -1.0, 0.0])
    check(v + k - s, v + k + s, math.sqrt(3) * k)


def test_leaving_a_face_obliquely():
    # Starts on the face x = 0 and moves away from it: at t = 0 the x-breakpoint ties with the
    # start, and only the "moving below lo" state of (0, 0+) gives the true minimum at t = 1/4:
    # f(t) = (2t)^2 + (1 - 2t)^2 -> 1/2. Classifying by x(0) < lo would miss it (answer 1).
    check([0, 2, 0.5], [-2, 0, 0.5], math.sqrt(0.5))


def test_flat_box():
    lo, hi = np.array([0, 0, 0.5]), np.array([1, 1, 0.5])
    check([0.5, 0.5, -1], [0.5, 0.5, 2], 0.0, lo, hi)  # pierces the plate
    check([-1, 0.5, 0.75], [2, 0.5, 0.75], 0.25, lo, hi)  # parallel above it
    check([2, 0.5, 0.5], [3, 0.5, 0.5], 1.0, lo, hi)  # in its plane, beyond an edge
    check([2, 0.5, 0.5], [0.5, 0.5, 0.5], 0.0, lo, hi, exact_zero=True)  # in-plane, into it
    p = np.array([0.5, 0.5, 0.5])
    check([1.5, 0.5, 0.5], [0.5, 1.5, 0.5], math.sqrt(0.5), p, p)  # point box


def test_huge_coordinates():
    off = 1000.0
    k = 0.25
    check(off + 1 + 3 * k + np.zeros(3), off + 1 + k + np.zeros(3), math.sqrt(3) * k,
          UNIT_LO + off, UNIT_HI + off)
    check([off - 1, off + 0.5, off + 1.5], [off + 2, off + 0.5, off + 1.5], 0.5,
          UNIT_LO + off, UNIT_HI + off)


def test_tiny_coordinates():
    s = 1e-6
    k = 0.25 * s
    check(s + 3 * k + np.zeros(3), s + k + np.zeros(3), math.sqrt(3) * k, UNIT_LO * s, UNIT_HI * s)
    check(np.array([0, 2, 0.5]) * s, np.array([-2, 0, 0.5]) * s, math.sqrt(0.5) * s,
          UNIT_LO * s, UNIT_HI * s)


def test_kernel_is_sort_free_and_traceable():
    args = [jnp.zeros(3, jnp.float32)] * 2 + [jnp.zeros(3, jnp.float32), jnp.ones(3, jnp.float32)]
    jaxpr = str(jax.make_jaxpr(segment_box_distance)(*args))
    assert "sort" not in jaxpr
    assert "cond" not in jaxpr and "while" not in jaxpr


# ---------------------------------------------------------------------------------------------
# Batched wrapper
# ---------------------------------------------------------------------------------------------


def test_batched_wrapper_shape_and_values():
    p0, p1, lo, hi = random_cases(4, 2 * 5 * 4)
    P0, P1 = p0[:10].reshape(2, 5, 3), p1[:10].reshape(2, 5, 3)
    LO, HI = lo[:8].reshape(2, 4, 3), hi[:8].reshape(2, 4, 3)
    with jax.enable_x64(True):
        out = np.asarray(segment_box_distances(*(jnp.asarray(v) for v in (P0, P1, LO, HI))))
        # Segments without leading dims broadcast against batched boxes.
        out_b = np.asarray(segment_box_distances(*(jnp.asarray(v) for v in (P0[0], P1[0], LO, HI))))
    assert out.shape == (2, 5, 4) and out.dtype == np.float64
    assert out_b.shape == (2, 5, 4)
    for n in range(2):
        for s in range(5):
            for b in range(4):
                single = float(jax_f64(P0[n, s], P1[n, s], LO[n, b], HI[n, b]))
                np.testing.assert_allclose(out[n, s, b], single, rtol=1e-14, atol=1e-15)
                np.testing.assert_allclose(
                    out[n, s, b], segment_box_distance_np(P0[n, s], P1[n, s], LO[n, b], HI[n, b]),
                    rtol=0, atol=1e-12)
                single0 = float(jax_f64(P0[0, s], P1[0, s], LO[n, b], HI[n, b]))
                np.testing.assert_allclose(out_b[n, s, b], single0, rtol=1e-14, atol=1e-15)

    # float32 in, float32 out; no leading dims.
    out32 = segment_box_distances(*(jnp.asarray(v[0], jnp.float32) for v in (P0, P1, LO, HI)))
    assert out32.shape == (5, 4) and out32.dtype == jnp.float32
