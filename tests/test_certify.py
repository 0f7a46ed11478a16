"""The certifier: reference vs batched LARC, fixed baselines, soundness against dense sampling."""

from __future__ import annotations

import math

import jax
import numpy as np
import pytest
from scipy.interpolate import CubicHermiteSpline

from larc_jax import LarcInputError
from larc_jax.enclosure import capsule_segments_np
from larc_jax.engine.certify import certify
from larc_jax.leaf.interval import interval_clearance, interval_clearance_np, rebase_ends, trajectory_rounding
from larc_jax.obstacles.geometry import segment_box_distance_np
from larc_jax.model.hermite import HermiteSpline
from larc_jax.obstacles import AlignedBoxes, stack_scenes
from larc_jax.model.scene import Scene
from larc_jax.model.trajectory import Trajectory

MARGIN = 0.01


def random_trajectory(rng, robot, k, max_waypoints=10, speed=0.4):
    K = int(rng.integers(2, max_waypoints + 1))
    t = np.cumsum(np.r_[rng.uniform(0, 0.5), rng.uniform(0.1, 1.0, K - 1)])
    mid = (robot.q_lower + robot.q_upper) / 2
    half = (robot.q_upper - robot.q_lower) / 2
    q = mid + half * rng.uniform(-0.6, 0.6, (K, robot.n_joints))
    qd = rng.normal(0, speed, (K, robot.n_joints))
    qd[0] = qd[-1] = 0.0 if rng.random() < 0.5 else qd[0]
    return Trajectory(t=t, q=q, qd=qd, joint_names=robot.active_joint_names, id=f"traj{k:03d}")


def random_scene(rng, k, max_boxes=4):
    B = int(rng.integers(0, max_boxes + 1))
    c = rng.uniform([-0.6, -0.6, -0.1], [0.6, 0.6, 0.7], (B, 3))
    s = rng.uniform(0.02, 0.2, (B, 3))
    return Scene(lo=c - s, hi=c + s, box_names=tuple(f"box{i}" for i in range(B)), name=f"scene{k}")


def dense_clearance(robot, capsules, traj, scene, hz=10_000):
    """Exact capsule-box distance (segment-box distance minus radius) on a >= 10 kHz grid of the
    trajectory, with SciPy's Hermite spline (independent of larc_jax.model.hermite)."""
    spline = CubicHermiteSpline(traj.t, traj.q, traj.qd)
    n = max(2, int(math.ceil(traj.duration * hz)) + 1)
    ts = np.linspace(traj.t[0], traj.t[-1], n)
    best = math.inf
    radius = np.asarray(capsules.radius)
    for q in spline(ts):
        pa, pb = capsule_segments_np(robot, capsules, q)
        for c in range(capsules.n_capsules):
            for k in range(scene.n_boxes):
                best = min(best, segment_box_distance_np(pa[c], pb[c], scene.lo[k], scene.hi[k]) - radius[c])
    return best


@pytest.fixture(scope="module")
def dataset(robot):
    rng = np.random.default_rng(2024)
    trajs = [random_trajectory(rng, robot, k) for k in range(200)]
    scenes = [random_scene(rng, k) for k in range(200)]
    return trajs, scenes


# These tests exercise the capsule test (the paper's model); the cascade has tests/test_cascade.py.
CAPSULES = dict(enclosure="capsules")


@pytest.fixture(scope="module")
def larc_result(dataset, robot, capsules):
    return certify(*dataset, robot, capsules, method="larc", margin=MARGIN, **CAPSULES)


@pytest.mark.slow
def test_reference_and_larc_agree_on_200(dataset, robot, capsules, larc_result):
    ref = certify(*dataset, robot, capsules, method="reference", margin=MARGIN, **CAPSULES)
    n_cert = sum(r.certified for r in ref)
    assert 20 < n_cert < 190, n_cert  # the random set exercises both outcomes
    for r, l in zip(ref, larc_result):
        assert r.certified == l.certified, r.id
        assert r.evaluations == l.evaluations, r.id
        assert r.frontier_sizes == l.frontier_sizes, r.id
        assert len(r.leaves) == len(l.leaves)
        np.testing.assert_allclose([x.clearance_m for x in r.leaves], [x.clearance_m for x in l.leaves],
                                   rtol=1e-9, atol=1e-12)
    assert ref.frontier_sizes == larc_result.frontier_sizes


@pytest.mark.slow
def test_leaves_cover_horizon(dataset, larc_result):
    for traj, res in zip(dataset[0], larc_result):
        leaves = res.leaves
        assert leaves[0].t0 == traj.t[0] and leaves[-1].t1 == traj.t[-1]
        for x, y in zip(leaves, leaves[1:]):
            assert x.t1 == y.t0  # exact, no gaps
        assert res.certified == all(x.certified for x in leaves)
        assert (res.min_clearance_m > 0) == res.certified or not np.isfinite(res.min_clearance_m)


@pytest.mark.slow
def test_fine_certified_implies_larc_certified(dataset, robot, capsules, larc_result):
    fine = certify(*dataset, robot, capsules, method="fine", margin=MARGIN, **CAPSULES)
    coarse = certify(*dataset, robot, capsules, method="coarse", margin=MARGIN, **CAPSULES)
    assert all(r.evaluations == 512 for r in fine) and all(r.evaluations == 16 for r in coarse)
    for f, l, c in zip(fine, larc_result, coarse):
        if f.certified:
            assert l.certified, f.id
        if c.certified:
            assert l.certified, c.id  # a passing depth-4 interval covers its depth-9 descendants
    assert sum(r.evaluations for r in larc_result) < sum(r.evaluations for r in fine)


@pytest.mark.slow
def test_soundness_against_dense_sampling(robot, capsules):
    """Whenever LARC certifies, the sampled (10 kHz) capsule-box distance stays above rho.
    Includes near misses: a box is moved so the swept capsules pass within a few mm of rho."""
    rng = np.random.default_rng(11)
    checked = near = 0
    for k in range(16):
        traj = random_trajectory(rng, robot, k, max_waypoints=5, speed=0.3)
        traj = Trajectory(t=traj.t / traj.duration * 1.0, q=traj.q, qd=traj.qd * traj.duration,
                          joint_names=traj.joint_names, id=traj.id)  # 1 s long
        scene = random_scene(rng, k, max_boxes=3)
        if k % 2 == 0:
            # Near miss: a small box placed just outside the swept volume of capsule c.
            spline = CubicHermiteSpline(traj.t, traj.q, traj.qd)
            q = spline(rng.uniform(traj.t[0], traj.t[-1]))
            pa, pb = capsule_segments_np(robot, capsules, q)
            c = int(rng.integers(capsules.n_capsules))
            direction = rng.normal(size=3)
            direction /= np.linalg.norm(direction)
            centre = (pa[c] + pb[c]) / 2 + direction * (capsules.radius[c] + MARGIN + 0.03)
            box = Scene(lo=(centre - 0.01)[None], hi=(centre + 0.01)[None], box_names=("near",))
            d = dense_clearance(robot, capsules, traj, box, hz=2000)
            shift = d - MARGIN - rng.uniform(0.0005, 0.004)  # target clearance rho + 0.5..4 mm
            box = Scene(lo=box.lo + direction * -shift, hi=box.hi + direction * -shift, box_names=("near",))
            scene = box
            near += 1
        res = certify(traj, scene, robot, capsules, method="larc", margin=MARGIN, **CAPSULES)[0]
        if res.certified:
            checked += 1
            assert dense_clearance(robot, capsules, traj, scene) > MARGIN, traj.id
    assert checked >= 4 and near >= 8


@pytest.mark.slow
def test_interval_kernel_matches_reference(dataset, robot, capsules):
    trajs, scenes = dataset
    rng = np.random.default_rng(5)
    obstacles = stack_scenes(scenes[:40], np.float64)
    for k in range(40):
        traj, scene = trajs[k], scenes[k]
        bounds = trajectory_rounding(traj, robot, capsules)
        with jax.enable_x64(True):
            spline = HermiteSpline.from_waypoints(traj.t - bounds.offset_s, traj.q, traj.qd)
            for _ in range(5):
                a, b = np.sort(rng.uniform(traj.t[0], traj.t[-1], 2))
                if rng.random() < 0.2:
                    b = a  # zero-width interval
                ar, br = rebase_ends(a, b, float(bounds.offset_s))
                g, guard, c, bx = interval_clearance(robot, capsules, spline, obstacles.take(k), ar, br, MARGIN,
                                                     bounds)
                g_np, guard_np, c_np, b_np = interval_clearance_np(robot, capsules, traj, scene, a, b, MARGIN, bounds)
                assert float(guard) == guard_np == bounds.guard_m[c_np]
                if scene.n_boxes == 0:
                    assert float(g) == math.inf and g_np == math.inf
                else:
                    assert abs(float(g) - g_np) < 1e-12
                    assert (int(c), int(bx)) == (c_np, b_np) or abs(float(g) - g_np) < 1e-12


def test_no_boxes_passes_at_root(robot, capsules, dataset):
    res = certify(dataset[0][:3], Scene.empty(), robot, capsules, **CAPSULES)
    assert all(r.certified and r.evaluations == 1 and r.frontier_sizes[0] == 1 for r in res)


def test_zero_speed_trajectory_has_zero_inflation(robot, capsules):
    q = np.array([0.0, 1.0, -1.0, 0.0, 0.0, 0.0])
    traj = Trajectory(t=np.array([0.0, 2.0]), q=np.stack([q, q]), qd=np.zeros((2, 6)),
                      joint_names=robot.active_joint_names, id="still")
    pa, pb = capsule_segments_np(robot, capsules, q)
    # A box at exactly clearance rho + 1 mm of the closest capsule surface.
    c = capsules.names.index("link6")
    centre = pb[c] + np.array([0.0, 0.0, 1.0]) * (capsules.radius[c] + MARGIN + 0.001 + 0.05)
    scene = Scene(lo=(centre - 0.05)[None], hi=(centre + 0.05)[None], box_names=("lid",))
    g_exact = dense_clearance(robot, capsules, traj, scene, hz=10) - MARGIN
    res = certify(traj, scene, robot, capsules, **CAPSULES)[0]
    assert res.certified and res.evaluations == 1
    assert res.min_clearance_m == pytest.approx(g_exact, abs=1e-12)  # b = 0 at zero speed


@pytest.mark.slow
def test_nan_never_certifies(robot, capsules):
    q = np.zeros((2, 6)) + np.array([0, 1.0, -1.0, 0, 0, 0])
    q[1, 2] = np.nan
    bad = Trajectory(t=np.array([0.0, 1.0]), q=q, qd=np.zeros((2, 6)), joint_names=robot.active_joint_names)
    with pytest.raises(LarcInputError, match=r"points\[1\]\.positions\[2\] is not finite"):
        certify(bad, Scene.empty(), robot, capsules)
    # Kernel level: NaN in the curve gives a NaN clearance, which fails `g > guard`,
    # even when there are no boxes at all.
    with jax.enable_x64(True):
        spline = HermiteSpline.from_waypoints(np.array([0.0, 1.0]), bad.q, bad.qd)
        bounds = trajectory_rounding(bad, robot, capsules)
        none = AlignedBoxes(np.zeros((1, 3)), np.zeros((1, 3)), np.array([False]))
        g, _, _, _ = interval_clearance(robot, capsules, spline, none, 0.0, 1.0, MARGIN, bounds)
    assert math.isnan(float(g)) and not float(g) > 0


@pytest.mark.slow
def test_float32_is_conservative(dataset, robot, capsules, larc_result):
    trajs, scenes = dataset
    r32 = certify(trajs[:60], scenes[:60], robot, capsules, method="larc", dtype=np.float32, **CAPSULES)
    for a, b in zip(r32, larc_result):
        if a.certified:
            assert b.certified, a.id
        assert a.guard_m > 100 * b.guard_m  # float32 geometry has its own (larger) guard
    # The float32 clearance never exceeds the float64 one by more than a quarter of its guard,
    # and is lower by little more than its deliberate deflation (budget G2) on every leaf both
    # runs have.
    checked = 0
    for a, b in zip(r32, larc_result):
        ref = {(x.depth, x.index): x for x in b.leaves}
        for x in a.leaves:
            y = ref.get((x.depth, x.index))
            if y is not None and np.isfinite(y.clearance_m) and (x.capsule, x.box) == (y.capsule, y.box):
                assert x.clearance_m - y.clearance_m < x.guard_m / 4, (a.id, x, y)
                assert x.clearance_m - y.clearance_m > -1e-5, (a.id, x, y)
                checked += 1
    assert checked >= 100


@pytest.mark.parametrize("kwargs,msg", [
    (dict(margin=0.0), "margin"),
    (dict(margin=float("nan")), "margin"),
    (dict(max_depth=-1), "max_depth"),
    (dict(method="exact"), "unknown method"),
])
def test_bad_arguments(robot, capsules, dataset, kwargs, msg):
    with pytest.raises(LarcInputError, match=msg):
        certify(dataset[0][:1], Scene.empty(), robot, capsules, **kwargs)


def test_speculated_levels_change_nothing(dataset, robot, capsules, monkeypatch):
    """A small frontier evaluated a few levels ahead in one call (certify.SPECULATE_INTERVALS) gives
    the leaves, decisions and per-depth evaluation counts of one call per level, bit for bit: one
    trajectory alone (speculated from the root) and six together."""
    import dataclasses

    import larc_jax.engine.certify as certify_module

    trajs, scenes = dataset
    cases = [(trajs[:1], scenes[:1]), (trajs[3:4], scenes[3:4]), (trajs[:6], scenes[:6])]
    ahead = [certify(t, s, robot, capsules, margin=MARGIN, enclosure="capsules") for t, s in cases]
    monkeypatch.setattr(certify_module, "SPECULATE_INTERVALS", 0)
    for (t, s), got in zip(cases, ahead):
        want = certify(t, s, robot, capsules, margin=MARGIN, enclosure="capsules")
        assert (got.frontier == want.frontier).all() and (got.certified == want.certified).all()
        for f in dataclasses.fields(want.leaves):
            np.testing.assert_array_equal(getattr(got.leaves, f.name), getattr(want.leaves, f.name), err_msg=f.name)


def test_speculated_levels_bound():
    """How many levels a frontier is evaluated ahead: within SPECULATE_INTERVALS intervals, never
    past the maximum depth."""
    from larc_jax.engine.certify import SPECULATE_INTERVALS, speculated_levels

    assert SPECULATE_INTERVALS == 256
    assert speculated_levels(1, 0, 9) == 7  # 255 intervals: depths 0-7
    assert speculated_levels(1, 7, 9) == 2  # not past depth 9
    assert speculated_levels(85, 3, 9) == 1  # 255 intervals
    assert speculated_levels(86, 3, 9) == 0  # 258 > 256
    assert speculated_levels(1, 9, 9) == 0
