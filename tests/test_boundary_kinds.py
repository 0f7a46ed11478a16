"""The boundary driver (experiments.boundary_kinds): a window written moved is read where the
original is plus the offset, the direction points from the obstacle toward the arm, and the flip search
brackets a threshold to its resolution."""

from __future__ import annotations

import numpy as np
import pytest

from experiments import boundary_kinds as bk
from experiments import tightness_kinds as tk


@pytest.fixture(scope="module")
def windows(tmp_path_factory):
    return tk.write_scenes(tmp_path_factory.mktemp("windows"), tk.KINDS)


def test_a_moved_window_is_the_window_moved(windows, tmp_path):
    """Every obstacle of the moved file is where the original's is plus the offset: shapes exactly
    (centre, turn and size), every mesh vertex and cloud point within 1e-12 m."""
    import larc_jax as lj

    off = np.array([0.013, -0.021, 0.007])
    for kind, path in windows.items():
        scene, moved = lj.read_scene(path), lj.read_scene(bk.write_moved(path, off, tmp_path))
        assert moved.shapes.kinds == scene.shapes.kinds and moved.point_sets.count == scene.point_sets.count
        np.testing.assert_allclose(moved.shapes.p_world_shape, scene.shapes.p_world_shape + off, rtol=0, atol=1e-15)
        np.testing.assert_array_equal(moved.shapes.R_world_shape, scene.shapes.R_world_shape)
        np.testing.assert_array_equal(moved.shapes.dims, scene.shapes.dims)
        assert moved.point_sets.radius == scene.point_sets.radius
        if scene.point_sets.count:
            a, b = (np.unique(np.concatenate(s.point_sets.pieces).round(12), axis=0) for s in (moved, scene))
            assert len(a) == len(b)
            np.testing.assert_allclose(a, b + off, rtol=0, atol=1e-12)
        assert moved.n_obstacles == scene.n_obstacles > 0


def test_the_direction_points_from_the_box_to_the_nearest_point():
    lo, hi = np.array([-1.0, -1.0, -1.0]), np.array([1.0, 1.0, 1.0])
    W = np.array([[3.0, 0.5, 0.0], [0.0, 5.0, 0.0]])
    np.testing.assert_allclose(bk.toward_arm(W, lo, hi), [1.0, 0.0, 0.0], atol=1e-15)
    # The same box turned 90 degrees about z and moved: the direction is the world's.
    Rz = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    p = np.array([10.0, 0.0, 0.0])
    np.testing.assert_allclose(bk.toward_arm(W @ Rz.T + p, lo, hi, Rz, p), [0.0, 1.0, 0.0], atol=1e-15)
    # A point inside the box: from its centre to the points' mean.
    np.testing.assert_allclose(bk.toward_arm(np.array([[0.5, 0.0, 0.0], [0.1, 0.0, 0.0]]), lo, hi), [1.0, 0.0, 0.0])


@pytest.mark.parametrize("threshold", [0.0005, 0.0123, 0.2])
def test_the_flip_is_bracketed_to_the_resolution(threshold):
    seen = []

    def ok(s):
        seen.append(s)
        return s < threshold

    lo, hi, calls = bk.find_flip(ok)
    assert ok(lo) and not ok(hi) and hi - lo <= bk.RESOLUTION_M and calls == len(seen) - 2
    assert lo < threshold <= hi


def test_no_flip_within_the_limit():
    lo, hi, calls = bk.find_flip(lambda s: True)
    assert hi is None and lo == bk.MAX_SHIFT_M and calls == 8  # 2 mm doubled up to 256 mm


def test_piece_obstacles_are_the_pieces_hulls():
    """A flat piece (a square's corners and centre) and a solid one (a cube's corners): FCL's
    distance from a ball to each is the distance to the hull, the flat one's polygon included."""
    import types

    import fcl

    square = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0.5, 0.5, 0]], float)
    cube = np.array([[x, y, z] for x in (3, 4) for y in (0, 1) for z in (0, 1)], float)
    ps = types.SimpleNamespace(pieces=(square, cube), owner=(0, 0), names=("cloud",))
    obs = bk.piece_obstacles(types.SimpleNamespace(point_sets=ps))
    assert len(obs.names) == 2
    np.testing.assert_allclose(obs.lo[1], [3, 0, 0])
    np.testing.assert_allclose(obs.hi[0], [1, 1, 0])
    ball = fcl.CollisionObject(fcl.Sphere(0.1), fcl.Transform(np.eye(3), [0.25, 0.75, 1.0]))  # over no vertex
    d = [fcl.distance(ball, o[0], fcl.DistanceRequest(), fcl.DistanceResult()) for o in obs.objects]
    np.testing.assert_allclose(d, [0.9, 2.65], atol=1e-6)  # the square below; the cube's face x = 3
