"""Joint tracking-error tolerance (larc_jax.enclosure.tracking): validation, kernel vs reference, monotonicity,
and soundness against perturbed executions sampled within the tolerance."""

from __future__ import annotations

import json
import math

import jax
import numpy as np
import pytest
from scipy.interpolate import CubicHermiteSpline

from larc_jax import LarcInputError, certify
from larc_jax.drivers.cli import main
from larc_jax.enclosure import capsule_segments_np
from larc_jax.obstacles.geometry import segment_box_distance_np, segment_box_distances
from larc_jax.model.hermite import HermiteSpline
from larc_jax.leaf.interval import interval_clearance, interval_clearance_np, rebase_ends, trajectory_rounding
from larc_jax.obstacles import stack_scenes
from larc_jax.model.scene import Scene
from larc_jax.enclosure.tracking import check_tracking_tolerance, parse_tracking_tolerance, tracked_capsules, tracking_radius
from larc_jax.model.trajectory import Trajectory
from larc_jax.model.trajectory_files import write_trajectory
from tests.test_certify import random_scene, random_trajectory

MARGIN = 0.01


def test_validation(robot):
    n = robot.n_joints
    assert check_tracking_tolerance(None, robot) is None
    np.testing.assert_array_equal(check_tracking_tolerance(0.01, robot), np.full(n, 0.01))
    np.testing.assert_array_equal(check_tracking_tolerance({"joint2": 0.02}, robot), np.eye(n)[1] * 0.02)
    np.testing.assert_array_equal(check_tracking_tolerance(np.arange(n) * 0.01, robot), np.arange(n) * 0.01)
    for bad, match in [(-0.01, "-0.01"), (math.nan, "nan"), (math.inf, "inf"), ([0.01] * (n - 1), "5 values for 6"),
                       ({"joint9": 0.01}, "'joint9' is not an active joint"), ([0.0, 0.0, -1.0, 0.0, 0.0, 0.0],
                                                                              r"\[2\] \(joint3\)"),
                       ("0.01", "expected a number"), (True, "True")]:
        with pytest.raises(LarcInputError, match=match):
            check_tracking_tolerance(bad, robot)
    assert parse_tracking_tolerance("0.02") == 0.02
    assert parse_tracking_tolerance("joint1=0.01, joint3=0.5") == {"joint1": 0.01, "joint3": 0.5}
    for bad in ("abc", "joint1=x", "=0.1", "joint1=0.1,joint2", "joint1=0.1, joint1=0.2"):
        with pytest.raises(LarcInputError, match="--tracking-tolerance"):
            parse_tracking_tolerance(bad)


def test_radius_grows_by_motion_constants(capsules):
    delta = np.array([0.01, 0.02, 0.0, 0.03, 0.0, 0.05])
    grown = tracked_capsules(capsules, delta)
    exact = np.asarray(capsules.radius) + np.asarray(capsules.motion_a) @ delta
    assert np.all(np.asarray(grown.radius) >= exact)
    assert np.all(np.asarray(grown.radius) - exact < 1e-15)
    np.testing.assert_array_equal(np.asarray(grown.motion_a), np.asarray(capsules.motion_a))
    grow = tracking_radius(capsules, delta)
    assert grow[0] == 0 and np.all(grow[1:] > 0)  # the base never moves; every other capsule moves with joint1
    zero = tracked_capsules(capsules, np.zeros(6))
    np.testing.assert_array_equal(np.asarray(zero.radius), np.asarray(capsules.radius))


@pytest.fixture(scope="module")
def dataset(robot):
    rng = np.random.default_rng(77)
    return [random_trajectory(rng, robot, k, max_waypoints=6) for k in range(12)], \
        [random_scene(rng, k) for k in range(12)]


def _same(r1, r2):
    assert r1.certified.tolist() == r2.certified.tolist()
    assert r1.frontier.tolist() == r2.frontier.tolist()
    for f in ("t0", "t1", "clearance_m", "guard_m", "capsule", "box"):
        np.testing.assert_array_equal(getattr(r1.leaves, f), getattr(r2.leaves, f))


@pytest.mark.slow
def test_zero_tolerance_is_the_plain_certificate_and_larger_never_certifies_more(dataset, robot, capsules):
    plain = certify(*dataset, robot, capsules, margin=MARGIN, enclosure="capsules")
    zero = certify(*dataset, robot, capsules, margin=MARGIN, tracking_tolerance=0.0, enclosure="capsules")
    _same(plain, zero)
    assert zero.tracking_tolerance == tuple((j, 0.0) for j in robot.active_joint_names)
    assert plain.tracking_tolerance == ()
    prev = plain
    for delta in (0.002, 0.01, 0.05):
        res = certify(*dataset, robot, capsules, margin=MARGIN, tracking_tolerance=delta, enclosure="capsules")
        assert not np.any(res.certified & ~prev.certified)
        prev = res
    assert prev.certified.sum() < plain.certified.sum()  # the tolerance costs something here
    # On the same intervals (fixed depth), every leaf's clearance shrinks as the tolerance grows.
    small = certify(*dataset, robot, capsules, margin=MARGIN, method="coarse", tracking_tolerance=0.002,
                    enclosure="capsules")
    large = certify(*dataset, robot, capsules, margin=MARGIN, method="coarse", tracking_tolerance=0.01,
                    enclosure="capsules")  # recorded clearances compare within one enclosure
    np.testing.assert_array_equal(small.leaves.t0, large.leaves.t0)
    ok = np.isfinite(small.leaves.clearance_m)
    assert np.all(large.leaves.clearance_m[ok] < small.leaves.clearance_m[ok])


def test_kernel_matches_reference_with_tolerance(dataset, robot, capsules):
    trajs, scenes = dataset
    rng = np.random.default_rng(3)
    caps = tracked_capsules(capsules, rng.uniform(0, 0.03, robot.n_joints))
    obstacles = stack_scenes(scenes, np.float64)
    for k in range(12):
        traj, scene = trajs[k], scenes[k]
        bounds = trajectory_rounding(traj, robot, caps)
        with jax.enable_x64(True):
            spline = HermiteSpline.from_waypoints(traj.t - bounds.offset_s, traj.q, traj.qd)
            for _ in range(3):
                a, b = np.sort(rng.uniform(traj.t[0], traj.t[-1], 2))
                ar, br = rebase_ends(a, b, float(bounds.offset_s))
                g, guard, c, bx = interval_clearance(robot, caps, spline, obstacles.take(k), ar, br, MARGIN, bounds)
                g_np, guard_np, c_np, b_np = interval_clearance_np(robot, caps, traj, scene, a, b, MARGIN, bounds)
                assert float(guard) == guard_np
                if scene.n_boxes:
                    assert abs(float(g) - g_np) < 1e-12
                    g0 = interval_clearance_np(robot, capsules, traj, scene, a, b, MARGIN, bounds)[0]
                    assert g_np < g0  # the grown radius enters the test


@pytest.mark.slow
def test_reference_agrees_with_larc_under_tolerance(dataset, robot, capsules):
    trajs, scenes = dataset
    kw = dict(margin=MARGIN, tracking_tolerance={"joint1": 0.01, "joint2": 0.02, "joint5": 0.05})
    ref = certify(trajs[:4], scenes[:4], robot, capsules, method="reference", **kw)
    lar = certify(trajs[:4], scenes[:4], robot, capsules, method="larc", **kw)
    assert ref.certified.tolist() == lar.certified.tolist()
    assert ref.frontier.tolist() == lar.frontier.tolist()
    np.testing.assert_allclose(ref.leaves.clearance_m, lar.leaves.clearance_m, rtol=1e-9, atol=1e-12)


def _min_clearance(robot, capsules, Q, scene):
    """Smallest capsule-box distance (exact segment-box distance minus radius) over configurations Q,
    and where: the JAX distance over all pairs, the closest pair recomputed with the NumPy reference."""
    segs = [capsule_segments_np(robot, capsules, q) for q in Q]
    pa = np.stack([s[0] for s in segs])
    pb = np.stack([s[1] for s in segs])
    with jax.enable_x64(True):
        d = np.asarray(segment_box_distances(pa, pb, scene.lo[None], scene.hi[None]))  # (T, C, B)
    g = d - np.asarray(capsules.radius)[None, :, None]
    t, c, k = np.unravel_index(np.argmin(g), g.shape)
    exact = segment_box_distance_np(pa[t, c], pb[t, c], scene.lo[k], scene.hi[k]) - float(capsules.radius[c])
    assert abs(exact - g[t, c, k]) < 1e-9
    return min(exact, float(g.min())), g.min(axis=(1, 2))


def _worst_signs(robot, capsules, q, scene, delta):
    """Per configuration, the corner of the tolerance box that lowers the clearance most to first order
    (sign of the finite-difference gradient), and that corner itself."""
    base = _min_clearance(robot, capsules, q[None], scene)[0]
    grad = np.zeros(len(delta))
    for j in range(len(delta)):
        dq = np.zeros(len(delta))
        dq[j] = 1e-6
        grad[j] = (_min_clearance(robot, capsules, (q + dq)[None], scene)[0] - base) / 1e-6
    return -np.sign(grad) * delta


@pytest.mark.slow
def test_soundness_against_perturbed_executions(robot, capsules):
    """Certified with tolerance delta => every execution q(t) + e(t), |e_j(t)| <= delta_j (constant corners,
    smooth random errors, the per-instant worst corner), keeps every capsule more than rho from every box
    at 2 kHz. Boxes are placed for near misses so the tolerance matters."""
    rng = np.random.default_rng(8)
    delta = np.array([0.02, 0.02, 0.02, 0.03, 0.03, 0.05])
    checked = tight = 0
    for k in range(10):
        traj = random_trajectory(rng, robot, k, max_waypoints=4, speed=0.3)
        traj = Trajectory(t=traj.t / traj.duration, q=traj.q, qd=traj.qd * traj.duration,
                          joint_names=traj.joint_names, id=traj.id)  # 1 s long
        spline = CubicHermiteSpline(traj.t, traj.q, traj.qd)
        ts = np.linspace(traj.t[0], traj.t[-1], 2001)
        Q = spline(ts)
        # A small box just outside the swept capsules, rho + grown radius + 1..6 mm from them.
        q = Q[rng.integers(len(Q))]
        pa, pb = capsule_segments_np(robot, capsules, q)
        c = int(rng.integers(capsules.n_capsules))
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        centre = (pa[c] + pb[c]) / 2 + u * 0.3
        box = Scene(lo=(centre - 0.02)[None], hi=(centre + 0.02)[None], box_names=("near",))
        d, _ = _min_clearance(robot, capsules, Q, box)
        grow = float(tracking_radius(capsules, delta).max())
        shift = d - MARGIN - grow - rng.uniform(0.001, 0.006)
        scene = Scene(lo=box.lo - u * shift, hi=box.hi - u * shift, box_names=("near",))
        res = certify(traj, scene, robot, capsules, margin=MARGIN, tracking_tolerance=delta)[0]
        if not res.certified:
            continue
        checked += 1
        planned, _ = _min_clearance(robot, capsules, Q, scene)
        worst = np.inf
        for s in range(8):  # constant corners of the tolerance box
            signs = rng.choice([-1.0, 1.0], robot.n_joints)
            worst = min(worst, _min_clearance(robot, capsules, Q + signs * delta, scene)[0])
        for s in range(4):  # smooth errors within the tolerance
            w, ph = rng.uniform(1, 40, robot.n_joints), rng.uniform(0, 2 * np.pi, robot.n_joints)
            E = np.sin(ts[:, None] * w + ph) * delta
            worst = min(worst, _min_clearance(robot, capsules, Q + E, scene)[0])
        # The worst corner near the closest instants of the plan.
        _, per_t = _min_clearance(robot, capsules, Q, scene)
        for i in np.argsort(per_t)[:20]:
            e = _worst_signs(robot, capsules, Q[i], scene, delta)
            worst = min(worst, _min_clearance(robot, capsules, (Q[i] + e)[None], scene)[0])
        assert worst > MARGIN, (traj.id, worst)
        tight += worst < planned - 0.002  # the perturbations do move the robot towards the box
    assert checked >= 4 and tight >= 2, (checked, tight)


def test_cli_tracking_tolerance(tmp_path, robot, capsules, capsys):
    q = np.array([0.0, 1.0, -1.0, 0.0, 0.0, 0.0])
    traj = Trajectory(t=np.array([0.0, 1.0]), q=np.stack([q, q + 0.1]), qd=np.zeros((2, 6)),
                      joint_names=robot.active_joint_names, id="move")
    path = tmp_path / "move.yaml"
    write_trajectory(path, traj)
    scene = tmp_path / "scene.yaml"
    scene.write_text("frame: base_link\nboxes:\n  - {name: far, min: [2, 2, 2], max: [2.1, 2.1, 2.1]}\n")
    out = tmp_path / "r.json"
    rc = main(["certify", str(path), "--scene", str(scene), "--tracking-tolerance", "joint1=0.01,joint6=0.05",
               "--json", str(out)])
    assert rc == 0
    assert "tracking error of joint1 0.01" in capsys.readouterr().out
    doc = json.loads(out.read_text())
    assert doc["tracking_tolerance"] == {"joint1": 0.01, "joint2": 0.0, "joint3": 0.0, "joint4": 0.0,
                                         "joint5": 0.0, "joint6": 0.05}
    for bad, msg in (("-0.1", "-0.1"), ("joint9=0.1", "joint9"), ("nan", "nan"), ("x", "expected a number")):
        assert main(["certify", str(path), "--scene", str(scene), "--tracking-tolerance", bad]) == 2
        err = capsys.readouterr().err
        assert "--tracking-tolerance" in err and msg in err, err
