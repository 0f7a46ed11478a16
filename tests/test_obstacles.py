"""The obstacle protocol's first kind, axis-aligned boxes: the JAX kernels equal their NumPy
twins, named edge cases, padding, outward rounding, and one-sided soundness against dense
sampling (NumPy; one small jitted call)."""

from __future__ import annotations

import math

import jax
import numpy as np
import pytest

from larc_jax.obstacles import AlignedBoxes, ObstacleSet, scene_obstacles, stack_scenes
from larc_jax.model.scene import Scene


def random_boxes(rng, n):
    lo = rng.uniform(-0.6, 0.6, (n, 3))
    return AlignedBoxes(lo=lo, hi=lo + rng.uniform(0.0, 0.4, (n, 3)), mask=np.ones(n, bool))


def _set_kernels(boxes, p_a, p_b):
    """Every set-level helper on one box set, in one jitted call (the polytope kernel against its
    twin: tests/test_polytope.py)."""
    return boxes.segment_distances(p_a, p_b), boxes.segment_lower_bounds(p_a, p_b), boxes.point_distances(p_a)


def test_aligned_boxes_kernels_equal_numpy_twins_and_padding_is_inf():
    rng = np.random.default_rng(0)
    boxes = random_boxes(rng, 7)
    boxes = AlignedBoxes(boxes.lo, boxes.hi, np.array([True] * 6 + [False]))  # one padding box
    p_a = rng.uniform(-0.8, 0.8, (9, 3))
    p_b = p_a + rng.normal(0, 0.2, (9, 3))
    p_b[0] = p_a[0]  # a degenerate segment
    with jax.enable_x64(True):
        dist, lb, point = (np.asarray(x) for x in jax.jit(_set_kernels)(boxes, p_a, p_b))
    for k in range(boxes.n_items):
        item = boxes.take(k)
        if not boxes.mask[k]:  # padding is never nearer than anything
            assert (dist[:, k] == np.inf).all() and (lb[:, k] == np.inf).all() and (point[:, k] == np.inf).all()
            continue
        for s in range(len(p_a)):
            assert dist[s, k] == pytest.approx(item.segment_distance_np(p_a[s], p_b[s]), abs=1e-12)
            assert lb[s, k] == pytest.approx(item.segment_lower_bound_np(p_a[s], p_b[s]), abs=1e-15)
            assert lb[s, k] <= dist[s, k]
        np.testing.assert_allclose(point[:, k], item.point_distance_np(p_a), atol=1e-15)


def test_nearest_point_distances_bit_for_bit():
    """AlignedBoxes' set-level ``nearest_point_distances`` (square root after the least square,
    sums axis by axis) gives the protocol's default (every ``point_distance``, then the least) bit
    for bit, in float64 and float32: points inside, on faces and corners, far; a padding box is
    +inf; each value is the NumPy twin's least distance."""
    rng = np.random.default_rng(5)
    boxes = random_boxes(rng, 6)
    boxes = AlignedBoxes(boxes.lo, boxes.hi, np.array([True] * 5 + [False]))
    pts = rng.uniform(-1.0, 1.0, (11, 14, 3))
    pts[0, :6] = boxes.lo  # corners
    pts[1, :6] = (boxes.lo + boxes.hi) / 2  # inside
    pts[2, :6, 0], pts[2, :6, 1:] = boxes.hi[:, 0], (boxes.lo[:, 1:] + boxes.hi[:, 1:]) / 2  # on a face
    for dtype in (np.float64, np.float32):
        with jax.enable_x64(dtype == np.float64):
            b = AlignedBoxes(boxes.lo.astype(dtype), boxes.hi.astype(dtype), boxes.mask)
            p = pts.astype(dtype)
            fast, default = (np.asarray(x) for x in jax.jit(
                lambda b, p: (b.nearest_point_distances(p), ObstacleSet.nearest_point_distances(b, p)))(b, p))
        assert fast.dtype == dtype and fast.shape == (11, 6)
        np.testing.assert_array_equal(fast, default)
        assert (fast[:, 5] == np.inf).all() and (fast[:2, :5] == 0).all() and (fast[2, :5] == 0).all()
        for k in range(5):
            twin = np.array([boxes.take(k).point_distance_np(pts[i]).min() for i in range(len(pts))])
            np.testing.assert_allclose(fast[:, k], twin, rtol=1e-6 if dtype == np.float32 else 1e-15, atol=1e-7)


def test_named_edge_cases_and_nan():
    box = AlignedBoxes(lo=np.zeros(3), hi=np.ones(3), mask=np.bool_(True))
    touching = ([1.0, 0.5, 0.5], [2.0, 0.5, 0.5])  # starts on a face and leaves it
    inside = ([0.2, 0.3, 0.4], [0.6, 0.6, 0.6])
    degenerate = ([2.0, 0.5, 0.5], [2.0, 0.5, 0.5])  # a point 1 m from the +x face
    assert box.segment_distance_np(*touching) == 0.0 and box.segment_lower_bound_np(*touching) <= 0.0
    assert box.segment_distance_np(*inside) == 0.0 and box.segment_lower_bound_np(*inside) <= 0.0
    assert box.segment_distance_np(*degenerate) == 1.0
    assert 1.0 - 1e-12 < box.segment_lower_bound_np(*degenerate) <= 1.0
    assert box.point_distance_np(np.array([2.0, 0.5, 0.5])) == 1.0
    nan = [math.nan, 0.0, 0.0]
    V = np.eye(3)
    for value in (box.segment_distance_np(nan, [0.0, 0.0, 0.0]), box.segment_lower_bound_np(nan, [0.0, 0.0, 0.0]),
                  box.point_distance_np(np.array(nan)), box.polytope_lower_bound_np(V, np.zeros(3), np.eye(3), nan)):
        assert not value > 0 and math.isnan(value)  # NaN never certifies


def test_lower_bounds_never_exceed_dense_sampled_distance():
    rng = np.random.default_rng(1)
    boxes = random_boxes(rng, 40)
    s = np.linspace(0.0, 1.0, 2001)[:, None]
    V = rng.normal(0, 0.05, (8, 3))
    w = rng.dirichlet(np.ones(len(V)), 3000)  # points of conv(V)
    for k in range(boxes.n_items):
        item = boxes.take(k)
        p0, p1 = rng.uniform(-0.9, 0.9, 3), rng.uniform(-0.9, 0.9, 3)
        sampled = item.point_distance_np((1 - s) * p0 + s * p1).min()
        assert item.segment_lower_bound_np(p0, p1) <= sampled
        assert item.segment_distance_np(p0, p1) <= sampled + 1e-12
        t = rng.uniform(-0.9, 0.9, 3)
        R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        placed = np.concatenate([V, w @ V]) @ R.T + t
        assert item.polytope_lower_bound_np(V, V.mean(0), R, t) <= item.point_distance_np(placed).min()


def test_scenes_become_padded_outward_rounded_sets():
    a = Scene(lo=[[0.1, 0.2, 0.3]], hi=[[0.4, 0.5, 0.6]])
    b = Scene(lo=[[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]], hi=[[0.1, 0.1, 0.1], [1.3, 1.3, 1.3]])
    one = scene_obstacles(b)
    assert isinstance(one, ObstacleSet) and scene_obstacles(one) is one and one.n_items == 2
    stacked = stack_scenes([a, b, Scene.empty()], np.float32)
    assert stacked.lo.shape == (3, 2, 3) and stacked.lo.dtype == np.float32 and stacked.n_items == 2
    assert stacked.mask.tolist() == [[True, False], [True, True], [False, False]]
    assert (stacked.lo[0, 0] <= a.lo[0]).all() and (stacked.hi[0, 0] >= a.hi[0]).all()  # G3: contains the user's
    assert (stacked.lo[0, 0] < a.lo[0]).any()  # 0.1 is not a float32: rounded down
    exact = stack_scenes([a, b], np.float64)
    assert np.array_equal(exact.lo[1], b.lo) and np.array_equal(exact.take(1).take(1).hi, b.hi[1])
