"""Self-collision certificate (larc_jax.leaf.self_collision): the segment-segment kernel against its NumPy
reference and dense sampling, the pair policy, the self test in both schedulers, a trajectory that
folds the gripper into the base, Stage B's OMPL paths, and soundness against FCL on the meshes."""

from __future__ import annotations

import glob
import json
import math

import jax
import numpy as np
import pytest
from scipy.interpolate import CubicHermiteSpline

from larc_jax import LarcInputError, certify
from larc_jax.drivers.cli import main
from larc_jax.enclosure import capsule_segments_np
from larc_jax.model.scene import Scene
from larc_jax.leaf.self_collision import (load_separation, segment_segment_distance, segment_segment_distance_np,
                                     self_clearance, self_clearance_np, self_pairs)
from larc_jax.model.trajectory import Trajectory
from larc_jax.model.trajectory_files import read_trajectory, write_trajectory
from tests.conftest import ROOT
from tests.test_certify import random_trajectory

FOLD = np.array([-2.138, 0.659, -0.025, 0.83, 0.898, -2.829])
"""A configuration where FCL finds link6's mesh inside base_link's, link1's and link2's."""
HOME = np.array([0.0, 0.8, -0.8, 0.0, 0.3, 0.0])


def _dense(p0, p1, q0, q1, n=801):
    s = np.linspace(0, 1, n)[:, None]
    a, b = p0 + s * (p1 - p0), q0 + s * (q1 - q0)
    return float(np.min(np.linalg.norm(a[:, None] - b[None], axis=2)))


def _kernel(P):
    with jax.enable_x64(True):
        return np.asarray(jax.jit(jax.vmap(segment_segment_distance))(P[:, 0], P[:, 1], P[:, 2], P[:, 3]))


def _cases(rng, n):
    P = rng.normal(size=(n, 4, 3)) * rng.choice([0.01, 0.3, 1.0], (n, 1, 1))
    k = n // 6
    P[:k, 1] = P[:k, 0]  # point vs segment
    P[k:2 * k, 3] = P[k:2 * k, 2]  # segment vs point
    P[2 * k:3 * k, 3] = P[2 * k:3 * k, 2] + (P[2 * k:3 * k, 1] - P[2 * k:3 * k, 0]) * rng.uniform(-2, 2, (k, 1))
    P[3 * k:4 * k, 3] = (P[3 * k:4 * k, 2] + (P[3 * k:4 * k, 1] - P[3 * k:4 * k, 0]) * rng.uniform(-2, 2, (k, 1))
                         + rng.normal(size=(k, 3)) * 1e-7)  # nearly parallel
    return P


def test_kernel_matches_reference_and_never_exceeds_it():
    rng = np.random.default_rng(0)
    P = _cases(rng, 3000)
    d = _kernel(P)
    ref = np.array([segment_segment_distance_np(*x) for x in P])
    assert np.all(np.isfinite(d))
    assert np.all(d <= ref * (1 + 1e-13) + 1e-15)  # one-sided: never above the exact distance
    # Tight up to rounding, except the documented slack of nearly parallel segments (|n| / max |d|).
    d1, d2 = P[:, 1] - P[:, 0], P[:, 3] - P[:, 2]
    slack = np.linalg.norm(np.cross(d1, d2), axis=1) / np.maximum(np.maximum(np.linalg.norm(d1, axis=1),
                                                                              np.linalg.norm(d2, axis=1)), 1e-300)
    assert np.all(ref - d <= slack * (1 + 1e-6) + 1e-12)
    assert np.mean(ref - d < 1e-12) > 0.9


def test_kernel_against_dense_sampling():
    rng = np.random.default_rng(1)
    P = _cases(rng, 300)
    d = _kernel(P)
    for x, dx in zip(P, d):
        dense = _dense(*x)
        assert dx <= dense + 1e-15  # dense sampling over-estimates the minimum: never below it
        assert dense - dx < 0.01 * np.linalg.norm(x[1] - x[0]) + 0.01 * np.linalg.norm(x[3] - x[2]) + 1e-6


@pytest.mark.parametrize("name, p0, p1, q0, q1, expected", [
    ("crossing", [-1, 0, 0], [1, 0, 0], [0, -1, 0.5], [0, 1, 0.5], 0.5),
    ("touching crossing", [-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], 0.0),
    ("parallel offset", [0, 0, 0], [1, 0, 0], [0.5, 0.3, 0], [1.5, 0.3, 0], 0.3),
    ("parallel apart along the line", [0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0], 1.0),
    ("collinear overlapping", [0, 0, 0], [1, 0, 0], [0.5, 0, 0], [2, 0, 0], 0.0),
    ("antiparallel", [0, 0, 0], [1, 0, 0], [1.5, 0.2, 0], [0.5, 0.2, 0], 0.2),
    ("two points", [0, 0, 0], [0, 0, 0], [0, 3, 4], [0, 3, 4], 5.0),
    ("point on segment", [0.5, 0, 0], [0.5, 0, 0], [0, 0, 0], [1, 0, 0], 0.0),
    ("end to end", [0, 0, 0], [1, 0, 0], [1, 0, 0], [1, 1, 1], 0.0),
    ("skew, closest at ends", [0, 0, 0], [1, 0, 0], [2, 1, 1], [2, 2, 3], math.sqrt(3.0)),
    ("T shape", [0, 0, 0], [2, 0, 0], [1, 0.25, 0], [1, 2, 0], 0.25),
])
def test_named_cases(name, p0, p1, q0, q1, expected):
    P = np.array([[p0, p1, q0, q1]], float)
    got = float(_kernel(P)[0])
    assert got <= expected + 1e-15, name
    assert got == pytest.approx(expected, abs=1e-12), name
    assert segment_segment_distance_np(*P[0]) == pytest.approx(expected, abs=1e-12)


def test_pair_policy(robot, capsules):
    pairs = self_pairs(robot, capsules)
    names = {tuple(sorted((capsules.link_names[a], capsules.link_names[b]))) for a, b in zip(pairs.first, pairs.second)}
    skipped = {(a, b): why for a, b, why in pairs.skipped}
    for adjacent in [("base_link", "link1"), ("link1", "link2"), ("link5", "link6"), ("link6", "link7")]:
        assert skipped[adjacent] == "adjacent" and adjacent not in names
    assert skipped[("link7", "link8")] == "rigid"  # fingers held closed on link6: fixed relative pose
    # Pairs the allowed list calls "never" (sampling) are checked: not a proof.
    for never in [("base_link", "link3"), ("link3", "link6"), ("link2", "link4"), ("link5", "link7")]:
        assert never in names
    assert ("base_link", "link6") in names
    a = np.asarray(capsules.motion_a)
    assert np.all(pairs.motion_a <= a[pairs.first] + a[pairs.second])  # never more than b_1 + b_2
    # Relative motion: link5/link8 move apart only through joint6; base_link/link6 through all six.
    k = next(p for p, (a, b) in enumerate(zip(pairs.first, pairs.second))
             if (capsules.names[a], capsules.names[b]) == ("link5", "link8"))
    c8 = capsules.names.index("link8")
    np.testing.assert_array_equal(pairs.motion_a[k], np.r_[np.zeros(5), capsules.motion_a[c8, 5]])
    k = next(p for p, (a, b) in enumerate(zip(pairs.first, pairs.second))
             if (capsules.names[a], capsules.names[b]) == ("base_link", "link6"))
    np.testing.assert_array_equal(pairs.motion_a[k], capsules.motion_a[capsules.names.index("link6")])
    proven = {("base_link", "link2"): (0.002, {"joint1": (-2.0, 2.0), "joint2": (0.0, 3.0)})}
    p2 = self_pairs(robot, capsules, 0.001, proven=proven)
    assert any(a == "base_link" and b == "link2" and why.startswith("proven apart by 2.00 mm")
               for a, b, why in p2.skipped)
    k = [capsules.names[c] for c in p2.first].index("base_link")  # base_link / link2_a
    inside, outside = np.zeros(6), np.zeros(6)
    outside[0] = 2.5
    assert p2.skip_mask(inside, inside)[k] and not p2.skip_mask(inside, outside)[k]
    assert p2.skip_mask(inside, inside).sum() == 2  # both capsules of link2, nothing else
    p3 = self_pairs(robot, capsules, 0.003, proven=proven)  # the proof is too weak for this margin
    assert not any(a == "base_link" and b == "link2" for a, b, _ in p3.skipped)
    assert not p3.skip_mask(inside, inside).any()
    p4 = self_pairs(robot, capsules, skip=["link1:link6"])
    assert ("link1", "link6", "skipped") in p4.skipped and p4.n_pairs == pairs.n_pairs - 1
    for bad in (["link1:nolink"], ["link1"], ["link1:link1"]):
        with pytest.raises(LarcInputError, match="self-collision skip"):
            self_pairs(robot, capsules, skip=bad)
    for bad in (-0.001, math.nan, math.inf, "0.1"):
        with pytest.raises(LarcInputError, match="self_margin"):
            self_pairs(robot, capsules, bad)


def test_separation_proofs_are_for_this_robot(robot, tmp_path):
    proofs = load_separation(robot)
    assert set(proofs) >= {("base_link", "link2"), ("link3", "link5")}
    assert all(c > 0.001 and box for c, box in proofs.values())
    assert proofs[("base_link", "link2")][1]["joint1"][1] > robot.q_upper[0]  # the limits, widened
    other = tmp_path / "proofs.yaml"
    other.write_text((ROOT / "larc_jax/data/piper_self_separation.yaml").read_text().replace(
        robot.urdf_sha256, "0" * 64))
    assert load_separation(robot, other) == {}  # another URDF: no proof counts


def test_self_clearance_kernel_matches_reference(robot, capsules):
    rng = np.random.default_rng(4)
    pairs = self_pairs(robot, capsules, 0.002)
    radius = np.asarray(capsules.radius, np.float64)
    for q in rng.uniform(robot.q_lower, robot.q_upper, (20, robot.n_joints)):
        pa, pb = capsule_segments_np(robot, capsules, q)
        h, speed = rng.uniform(0, 0.01), rng.uniform(0, 2, robot.n_joints)
        guard = rng.uniform(0, 1e-12, capsules.n_capsules)
        with jax.enable_x64(True):
            skip = rng.random(pairs.n_pairs) < 0.2
            g, gd, c1, c2 = (np.asarray(x) for x in jax.jit(self_clearance)(
                pa, pb, radius, h, speed, guard, pairs.first, pairs.second, pairs.motion_a, np.float64(pairs.margin_m),
                skip))
        g_np, gd_np, c1_np, c2_np = self_clearance_np(pa, pb, radius, h, speed, guard, pairs, skip)
        assert not skip[list(zip(pairs.first, pairs.second)).index((c1_np, c2_np))]
        assert float(g) <= g_np + 1e-15 and float(g) == pytest.approx(g_np, abs=1e-9)
        assert float(gd) == pytest.approx(gd_np, rel=1e-15)


def _fold_trajectory(robot, start=HOME, end=FOLD, duration=2.0, name="fold"):
    return Trajectory(t=np.array([0.0, duration]), q=np.stack([start, end]), qd=np.zeros((2, robot.n_joints)),
                      joint_names=robot.active_joint_names, id=name)


@pytest.fixture(scope="module")
def fcl_model(robot):
    pytest.importorskip("fcl")
    from experiments.collision import CollisionModel

    return CollisionModel(robot)


def _checked_link_pairs(robot, capsules):
    pairs = self_pairs(robot, capsules)
    return sorted({tuple(sorted((capsules.link_names[a], capsules.link_names[b])))
                   for a, b in zip(pairs.first, pairs.second)} | {(a, b) for a, b, why in pairs.skipped
                                                                  if why.startswith("proven")})


def test_gripper_folded_into_the_base_is_refused(robot, capsules, fcl_model):
    contacts = fcl_model.self_contacts(FOLD, allowed_pairs=[])
    assert {("base_link", "link6"), ("link1", "link6")} <= set(contacts)  # FCL: the meshes intersect
    assert not fcl_model.self_contacts(HOME, allowed_pairs=[(a, b) for a, b, _ in self_pairs(robot, capsules).skipped])
    traj = _fold_trajectory(robot)
    for method in ("larc", "reference"):
        res = certify(traj, Scene.empty(), robot, capsules, method=method, self_collision=True, max_depth=5)
        assert not res.certified[0], method
        bad = res[0].first_inconclusive
        assert bad.other_capsule and bad.box == "", bad
        assert res.self_margin_m == 0.0
    # Without the self test the same trajectory certifies (no boxes): the new test is what refuses it.
    assert certify(traj, Scene.empty(), robot, capsules).certified[0]


def test_proven_pair_is_checked_where_the_curve_leaves_the_proof(robot, capsules):
    """base_link/link2 is proven apart for joint1 within its limits widened by 0.05 rad. A curve that
    overshoots joint1's limit between its waypoints leaves that box: the pair is then checked (and its
    capsules overlap), so the trajectory is refused; the same waypoints at rest are certified."""
    q = np.array([2.6, 0.8, -0.8, 0.0, 0.3, 0.0])
    qd = np.zeros((2, 6))
    qd[0, 0], qd[1, 0] = 1.0, -1.0  # q1(s) = 2.6 + s (1 - s): up to 2.85 rad
    over = Trajectory(t=np.array([0.0, 1.0]), q=np.stack([q, q]), qd=qd, joint_names=robot.active_joint_names,
                      id="overshoot")
    still = Trajectory(t=np.array([0.0, 1.0]), q=np.stack([q, q]), qd=np.zeros((2, 6)),
                       joint_names=robot.active_joint_names, id="still")
    res = certify([over, still], Scene.empty(), robot, capsules, self_collision=True, max_depth=3)
    assert res.certified.tolist() == [False, True]
    bad = res[0].first_inconclusive
    assert bad.capsule == "base_link" and bad.other_capsule.startswith("link2")


def test_default_results_unchanged_by_the_option(robot, capsules):
    rng = np.random.default_rng(9)
    trajs = [random_trajectory(rng, robot, k, max_waypoints=4) for k in range(4)]
    scene = Scene(lo=np.array([[0.2, -0.1, 0.0]]), hi=np.array([[0.3, 0.1, 0.4]]), box_names=("post",))
    plain = certify(trajs, scene, robot, capsules)
    assert np.all(plain.leaves.other_capsule == -1) and plain.self_margin_m is None
    both = certify(trajs, scene, robot, capsules, self_collision=True, self_margin=0.001)
    assert not np.any(both.certified & ~plain.certified)  # the self test only adds conditions
    box_leaves = both.leaves.other_capsule < 0
    assert np.all(both.leaves.box[box_leaves] >= 0) and np.all(both.leaves.box[~box_leaves] == -1)


@pytest.mark.slow
def test_reference_and_larc_agree_with_self_test(robot, capsules):
    rng = np.random.default_rng(12)
    trajs = [random_trajectory(rng, robot, k, max_waypoints=4) for k in range(3)] + [_fold_trajectory(robot)]
    scene = Scene(lo=np.array([[0.25, -0.1, 0.0]]), hi=np.array([[0.35, 0.1, 0.4]]), box_names=("post",))
    kw = dict(self_collision=True, self_margin=0.002, max_depth=6)
    ref = certify(trajs, scene, robot, capsules, method="reference", **kw)
    lar = certify(trajs, scene, robot, capsules, method="larc", **kw)
    assert ref.certified.tolist() == lar.certified.tolist()
    assert ref.frontier.tolist() == lar.frontier.tolist()
    np.testing.assert_allclose(ref.leaves.clearance_m, lar.leaves.clearance_m, rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(ref.leaves.other_capsule, lar.leaves.other_capsule)


def _stage_b_paths(robot, n):
    files = sorted(glob.glob(str(ROOT / "results/stageB/dataset/trajectories/*/*ompl_planned.yaml")))
    if not files:
        pytest.skip("no Stage B dataset in results/")
    return [read_trajectory(f, robot) for f in files[::max(1, len(files) // n)][:n]]


@pytest.mark.slow
def test_stage_b_ompl_paths_pass_the_self_test(robot, capsules):
    trajs = _stage_b_paths(robot, 8)
    res = certify(trajs, Scene.empty(), robot, capsules, self_collision=True)
    assert res.certified.sum() >= 7, res.to_dataframe()[["id", "certified", "blocked_capsule", "blocked_other_capsule"]]


@pytest.mark.slow
def test_soundness_against_fcl_on_the_meshes(robot, capsules, fcl_model):
    """Certified with the self test (margin 1 mm) => at 1 kHz, every checked link pair's meshes (and
    the pairs proven apart) stay more than 1 mm apart (FCL distance). Trajectories head from a home
    pose part of the way towards folds, so some pass close and some are refused."""
    import fcl

    margin = 0.001  # below the proven clearance of base_link/link2 and link3/link5 (1.6 mm)
    link_pairs = _checked_link_pairs(robot, capsules)
    objs = {}
    for o, li in zip(fcl_model.objects, fcl_model.object_link):
        objs.setdefault(robot.link_names[li], []).append(o)
    rng = np.random.default_rng(21)
    trajs = []
    for k in range(10):
        frac = rng.uniform(0.3, 0.9)
        end = HOME + frac * (FOLD - HOME) + rng.normal(0, 0.1, robot.n_joints)
        end = np.clip(end, robot.q_lower, robot.q_upper)
        trajs.append(_fold_trajectory(robot, end=end, duration=1.0, name=f"towards_fold_{k}"))
    res = certify(trajs, Scene.empty(), robot, capsules, self_collision=True, self_margin=margin)
    assert 2 <= res.certified.sum() <= 8, res.certified
    closest = np.inf
    for traj, ok in zip(trajs, res.certified):
        if not ok:
            continue
        spline = CubicHermiteSpline(traj.t, traj.q, traj.qd)
        for q in spline(np.linspace(traj.t[0], traj.t[-1], 501)):
            fcl_model.set_configuration(q)
            for a, b in link_pairs:
                d = min(fcl.distance(x, y, fcl.DistanceRequest(), fcl.DistanceResult())
                        for x in objs.get(a, ()) for y in objs.get(b, ()))
                assert d > margin, (traj.id, a, b, d)
                closest = min(closest, d)
    assert closest < 0.01  # certified trajectories do pass close to a self-contact


def test_cli_self_collision(tmp_path, robot, capsys):
    path = tmp_path / "fold.yaml"
    write_trajectory(path, _fold_trajectory(robot))
    scene = tmp_path / "scene.yaml"
    scene.write_text("frame: base_link\nboxes: []\n")
    out, leaves = tmp_path / "r.json", tmp_path / "leaves.csv"
    rc = main(["certify", str(path), "--scene", str(scene), "--self-collision", "--self-margin", "0.001",
               "--max-depth", "4", "--json", str(out), "--leaves", str(leaves)])
    assert rc == 1
    text = capsys.readouterr().out
    assert "(self)" in text and "self-collision checked (margin 1 mm)" in text
    doc = json.loads(out.read_text())
    assert doc["self_collision"]["margin_m"] == 0.001
    assert {"a": "link7", "b": "link8", "reason": "rigid"} in doc["self_collision"]["skipped_pairs"]
    assert doc["trajectories"][0]["first_inconclusive"]["other_capsule"]
    import pandas as pd

    df = pd.read_csv(leaves, keep_default_na=False)
    assert (df["other_capsule"] != "").any()
    for args, msg in ((["--self-margin", "-1", "--self-collision"], "--self-margin"),
                      (["--self-margin", "0.01"], "need --self-collision"),
                      (["--self-collision", "--self-skip", "link1:nope"], "self-collision skip")):
        assert main(["certify", str(path), "--scene", str(scene), *args]) == 2
        assert msg in capsys.readouterr().err
