"""The swept stage (larc_jax.leaf.swept): the Hermite acceleration maxima, the point acceleration
bound (A), the chord bound (C) against dense sampling, the kernel against its NumPy twin, both
schedulers taking the same decisions, soundness against the hull meshes (python-fcl), and the
option on every path (spec, CLI, certificate, verify)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import jax
import numpy as np
import pytest
from scipy.interpolate import CubicHermiteSpline

import larc_jax as lj
from larc_jax.drivers.cli import EXIT_OK, EXIT_REFUTED, main
from larc_jax.enclosure.hull import hull_model
from larc_jax.enclosure.robot_file import load_robot_file
from larc_jax.engine.results import STAGES
from larc_jax.errors import LarcInputError
from larc_jax.leaf.cascade import Links
from larc_jax.leaf.interval import rebase_ends, trajectory_rounding
from larc_jax.leaf.record import Stage
from larc_jax.leaf.swept import (chain_before, swept_capsule_clearance, swept_capsule_clearance_np,
                                 swept_part_clearance, swept_part_clearance_np, swept_placement, swept_placement_np,
                                 swept_radii, swept_record, swept_tables)
from larc_jax.model.hermite import HermiteSpline, accel_max, accel_max_np
from larc_jax.model.robot import forward_kinematics_np
from larc_jax.obstacles import stack_scenes

from .test_cascade import HullClearance, near_miss_dataset, near_scene, short_trajectory

MARGIN = 0.01
HOLD = {"joint7": 0.0, "joint8": 0.0}
ROOT = Path(__file__).resolve().parent.parent
EX = ROOT / "configs" / "examples"
REACH, CELL = str(EX / "reach_left.yaml"), str(EX / "cell.yaml")


@pytest.fixture(scope="module")
def model():
    robot, capsules = load_robot_file(None, hold=HOLD)
    capsules = capsules.with_padding(0.0)
    return robot, capsules, hull_model(robot, capsules.hull_parts, 0.0)


# ----------------------------------------------------------------------------------------------
# Acceleration maxima of the Hermite curve (eq. (**) of larc_jax.model.hermite)
# ----------------------------------------------------------------------------------------------


def test_accel_max_matches_reference_and_bounds_dense_samples():
    """Random curves and intervals (one segment, many, a zero-width interval at a knot): the JAX
    range query equals the NumPy twin, which is the maximum of |qddot| (SciPy's second derivative
    on 4001 samples never exceeds it and comes within 2 % of it)."""
    rng = np.random.default_rng(5)
    with jax.enable_x64(True):
        for trial in range(40):
            K = int(rng.integers(1, 12))
            t = np.cumsum(rng.uniform(0.05, 1.0, K + 1))
            q, v = rng.normal(size=(K + 1, 3)), rng.normal(size=(K + 1, 3))
            spline = HermiteSpline.from_waypoints(t, q, v)
            if trial % 10 == 0:
                a = b = t[1]  # zero width, at a knot
            else:
                a, b = np.sort(rng.uniform(t[0], t[-1], 2))
            got = np.asarray(accel_max(spline, a, b))
            ref = accel_max_np(t, q, v, a, b)
            np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-12)
            if a == b:  # one instant at a knot, where qddot jumps: the segment ending there
                np.testing.assert_allclose(got, np.abs(CubicHermiteSpline(t[:2], q[:2], v[:2])(a, 2)), rtol=1e-12)
                continue
            dense = np.abs(CubicHermiteSpline(t, q, v)(np.linspace(a, b, 4001), 2)).max(axis=0)
            assert np.all(dense <= ref * (1 + 1e-12) + 1e-12)
            assert np.all(dense >= ref * (1 - 2e-2) - 1e-9)  # the maximum may be a left limit at a knot


# ----------------------------------------------------------------------------------------------
# The point acceleration bound (A) and the chord bound (C)
# ----------------------------------------------------------------------------------------------


def _points(capsules, hulls):
    """Link-frame points of every enclosure: capsule segment ends and hull vertices, with their
    enclosure's motion constants and link."""
    out = []
    for c, li in enumerate(capsules.link_index):
        for p in (capsules.p_link_a[c], capsules.p_link_b[c]):
            out.append((np.asarray(p, float), li, np.asarray(capsules.motion_a[c]), "capsule", c))
    for p, li in enumerate(hulls.link_index):
        V = np.asarray(hulls.vertices[p])[: hulls.n_vertices[p]]
        for v in V[:: max(1, len(V) // 12)]:
            out.append((v, li, np.asarray(hulls.motion_a[p]), "part", p))
    return out


def test_point_acceleration_bound_holds_on_random_motions(model):
    """||p''|| of capsule ends and hull vertices, by central differences of forward kinematics
    along q(t) = q0 + v t + alpha t^2 / 2, never exceeds (A) with |qdot| = |v|, |qddot| = |alpha|
    (3,000 random configurations, velocities and accelerations); the bound is not idle (its
    worst ratio is above 0.3)."""
    robot, capsules, hulls = model
    before_c = chain_before(robot, capsules.link_index)
    before_p = chain_before(robot, hulls.link_index)
    rng = np.random.default_rng(7)
    lo, hi = np.asarray(robot.q_lower), np.asarray(robot.q_upper)
    pts = _points(capsules, hulls)
    worst, checked = 0.0, 0
    dt = 1e-4
    for _ in range(100):
        q0 = rng.uniform(lo, hi)
        v = rng.normal(0, 1.5, robot.n_joints) * rng.integers(0, 2, robot.n_joints)
        alpha = rng.normal(0, 4.0, robot.n_joints)
        T = [forward_kinematics_np(robot, q0 + v * s + 0.5 * alpha * s * s) for s in (-dt, 0.0, dt)]
        for x, li, a, kind, e in pts:
            p = [Ti[li][:3, :3] @ x + Ti[li][:3, 3] for Ti in T]
            acc = np.linalg.norm(p[0] - 2 * p[1] + p[2]) / dt**2
            before = (before_c if kind == "capsule" else before_p)[e]
            bound = float(np.sum(a * (np.abs(alpha) + np.abs(v) * (np.abs(v) + 2 * before @ np.abs(v)))))
            assert acc <= bound * (1 + 1e-5) + 1e-6, (kind, e, acc, bound)
            worst = max(worst, acc / bound if bound > 0 else 0.0)
            checked += 1
    assert checked > 3000 and worst > 0.3


def test_chain_order_is_the_kinematic_chain(model):
    robot, capsules, _ = model
    before = chain_before(robot, capsules.link_index)
    last = int(np.argmax([len(robot.ancestors(li)) for li in capsules.link_index]))
    # On PIPER's last link every active joint j lies above j + 1 (a serial chain).
    n = robot.n_joints
    np.testing.assert_array_equal(before[last], np.tril(np.ones((n, n)), -1))
    assert before.shape == (capsules.n_capsules, n, n) and set(np.unique(before)) <= {0.0, 1.0}


def test_every_point_stays_within_the_swept_radius_of_its_chord(model):
    """(C) with (A): on random short intervals of random trajectories, every capsule end and hull
    vertex, sampled at 400 times, lies within ``e`` (swept_radii) of the chord between its places at
    the two ends; ``e`` shrinks with the square of the interval (halving it divides ``e`` by > 3)."""
    robot, capsules, hulls = model
    rng = np.random.default_rng(11)
    before_c = chain_before(robot, capsules.link_index)
    pts = _points(capsules, hulls)
    before_p = chain_before(robot, hulls.link_index)
    ratios = []
    for k in range(8):
        traj = short_trajectory(rng, robot, k)
        bounds = trajectory_rounding(traj, robot, capsules, np.float64, hulls)
        spline = CubicHermiteSpline(traj.t, traj.q, traj.qd)
        for width in (0.25, 0.125, 0.03):
            a = rng.uniform(traj.t[0], traj.t[-1] - width)
            b = a + width
            ts = np.linspace(a, b, 400)
            with jax.enable_x64(True):
                hs = HermiteSpline.from_waypoints(traj.t, traj.q, traj.qd)
                speed = np.asarray(lj.model.hermite.speed_max(hs, a, b)) + np.asarray(bounds.omega_slack)
            accel = accel_max_np(traj.t, traj.q, traj.qd, a, b) + np.asarray(bounds.accel_slack)
            e_c = swept_radii(capsules.motion_a, before_c, b - a, float(bounds.tau_s), speed, accel)
            e_p = swept_radii(hulls.motion_a, before_p, b - a, float(bounds.tau_s), speed, accel)
            T = [forward_kinematics_np(robot, q) for q in spline(ts)]
            for x, li, _, kind, e in pts:
                P = np.array([Ti[li][:3, :3] @ x + Ti[li][:3, 3] for Ti in T])
                lam = (ts - a) / (b - a)
                chord = P[0] + lam[:, None] * (P[-1] - P[0])
                dev = np.linalg.norm(P - chord, axis=1).max()
                radius = (e_c if kind == "capsule" else e_p)[e]
                assert dev <= radius, (kind, e, dev, radius)
                if width == 0.25 and kind == "capsule":
                    ratios.append(radius)
            if width == 0.125:
                wider = swept_radii(capsules.motion_a, before_c, 0.25, float(bounds.tau_s), speed, accel)
                assert np.all(e_c * 3 <= wider) and np.all((e_c * 3 < wider)[e_c > 0])
    assert max(ratios) > 0


# ----------------------------------------------------------------------------------------------
# The kernel, its twin, the schedulers, soundness
# ----------------------------------------------------------------------------------------------


def test_kernels_match_numpy_twins(model):
    """Step 1 (swept_placement), step 1b (swept_capsule_clearance) and step 2
    (swept_part_clearance) against their NumPy float64 twins on random intervals and pairs."""
    robot, capsules, hulls = model
    rng = np.random.default_rng(3)
    tables = swept_tables(robot, capsules, hulls)
    place_k, caps_k, parts_k = (jax.jit(f) for f in (swept_placement, swept_capsule_clearance, swept_part_clearance))
    for k in range(4):
        traj = short_trajectory(rng, robot, k)
        scene = near_scene(rng, robot, capsules, traj, k, n_boxes=2)
        bounds = trajectory_rounding(traj, robot, capsules, np.float64, hulls)
        for depth in (1, 4, 7):
            i = int(rng.integers(2**depth))
            a, b = traj.t[0] + np.array([i, i + 1]) * (traj.t[-1] - traj.t[0]) / 2**depth
            ar, br = (float(x) for x in rebase_ends(a, b, float(bounds.offset_s)))
            with jax.enable_x64(True):
                spline = HermiteSpline.from_waypoints(traj.t - float(bounds.offset_s), traj.q, traj.qd)
                obstacles = stack_scenes([scene], np.float64).take(0)
                got = jax.tree.map(np.asarray, place_k(robot, capsules, hulls, tables, spline, obstacles, ar, br, MARGIN,
                                                       bounds))
                ref = swept_placement_np(robot, capsules, hulls, tables, traj, scene, ar, br, MARGIN, bounds)
                for name in ("g_capsule", "R_capsule", "t_capsule", "e_capsule", "T_mid", "R_ends", "t_ends",
                             "motion_b", "swept_e"):
                    np.testing.assert_allclose(getattr(got, name)[..., :2] if name == "g_capsule" else getattr(got, name),
                                               getattr(ref, name)[..., :2] if name == "g_capsule" else getattr(ref, name),
                                               rtol=1e-12, atol=1e-12, err_msg=name)
                item = obstacles.take(int(rng.integers(2)))
                c, p = int(rng.integers(capsules.n_capsules)), int(rng.integers(hulls.n_parts))
                g = float(caps_k(capsules, c, got.R_capsule[c], got.t_capsule[c], item, got.e_capsule[c], MARGIN))
                g_ref = swept_capsule_clearance_np(capsules, c, ref.R_capsule[c], ref.t_capsule[c], item,
                                                   float(ref.e_capsule[c]), MARGIN)
                assert abs(g - g_ref) < 1e-8
                g = float(parts_k(hulls, p, got.T_mid[p], got.R_ends[p], got.t_ends[p], item, got.motion_b[p],
                                  got.swept_e[p], MARGIN))
                g_ref = swept_part_clearance_np(hulls, p, ref.T_mid[p], ref.R_ends[p], ref.t_ends[p], item,
                                                float(ref.motion_b[p]), float(ref.swept_e[p]), MARGIN)
                assert abs(g - g_ref) < 1e-8


def test_the_record_on_named_cases():
    """Two links (capsules 0, 1 on link 0; 2 on link 1), one part each, one box: the swept test runs
    only on capsule pairs whose midpoint test fails, parts only on links whose capsules fail; a
    NaN fails the interval."""
    links = Links(of_capsule=np.array([0, 0, 1]), of_part=np.array([0, 1]), n_links=2)
    G = np.full((1, 3), 1e-6)
    g_mid = np.array([[[0.004], [-0.002], [0.03]]])  # capsule 1 fails its midpoint test
    asked = {}

    def capsules_(triples, value):
        asked["capsules"] = triples.tolist()
        return np.full(len(triples), value)

    def parts_(triples, value):
        asked["parts"] = triples.tolist()
        return np.full(len(triples), value), np.full(len(triples), 1e-6)

    g, guard, c, k, passed = swept_record(links, g_mid, G, True, lambda t: capsules_(t, 0.001), lambda t: parts_(t, 0))
    assert passed[0] and asked["capsules"] == [[0, 1, 0]] and "parts" not in asked  # the swept capsule passes
    asked.clear()
    g, guard, c, k, passed = swept_record(links, g_mid, G, True, lambda t: capsules_(t, -0.001),
                                          lambda t: parts_(t, 0.002))
    assert passed[0] and asked["parts"] == [[0, 0, 0]] and g[0] == 0.002  # link 0's part decides
    g, guard, c, k, passed = swept_record(links, g_mid, G, False, lambda t: capsules_(t, -0.001), None)
    assert not passed[0] and g[0] == -0.001 and c[0] == 1
    g, guard, c, k, passed = swept_record(links, g_mid, G, True, lambda t: capsules_(t, np.nan),
                                          lambda t: parts_(t, 0.002))
    assert not passed[0] and math.isnan(g[0])


@pytest.fixture(scope="module")
def near_misses(model):
    """12 one-second trajectories, each with a box the hulls clear by rho + 0.3..6 mm."""
    return near_miss_dataset(*model, 12, 0.3, 6)


DEPTH = 6


def test_schedulers_agree_and_the_swept_stage_only_adds(model, near_misses):
    """Batched LARC and the NumPy reference take the same decisions with the swept stage, for the
    capsules and for the cascade; with it every trajectory certified without it still is, with no
    more evaluations, and the swept stage decides leaves."""
    robot, capsules, _ = model
    for enclosure in ("capsules", "hull"):
        runs = {}
        for swept in (False, True):
            runs[swept] = lj.certify(*near_misses, robot, capsules, method="larc", margin=MARGIN, max_depth=DEPTH,
                                     enclosure=enclosure, padding=0.0, swept=swept)
        ref = lj.certify(*near_misses, robot, capsules, method="reference", margin=MARGIN, max_depth=DEPTH,
                         enclosure=enclosure, padding=0.0, swept=True)
        on, off = runs[True], runs[False]
        assert (ref.certified == on.certified).all() and (ref.frontier == on.frontier).all()
        assert (ref.leaves.stage == on.leaves.stage).all()
        np.testing.assert_allclose(ref.leaves.clearance_m, on.leaves.clearance_m, rtol=0, atol=1e-8)
        assert ((~off.certified) | on.certified).all() and (on.evaluations <= off.evaluations).all()
        assert (on.leaves.stage == Stage.SWEPT).sum() > 5 and on.evaluations.sum() < off.evaluations.sum()
        assert on.spec.swept and not off.spec.swept
        assert "swept" in STAGES and set(on.to_dataframe()["certified"]) <= {True, False}


def test_soundness_against_dense_sampling_of_the_hulls(model, near_misses):
    """Whenever a leaf is passed by the swept stage, the link hulls (which contain the meshes) stay
    more than rho from the box at 4 kHz on that leaf (python-fcl on the hull meshes)."""
    import fcl

    robot, capsules, hulls = model
    measure = HullClearance(robot, hulls)
    res = lj.certify(*near_misses, robot, capsules, method="larc", margin=MARGIN, max_depth=DEPTH, padding=0.0,
                     swept=True)
    lv = res.leaves
    rows = np.flatnonzero(lv.stage == Stage.SWEPT)
    assert len(rows) > 5
    trajs, scenes = near_misses
    for j in rows[:40]:
        traj, scene = trajs[lv.traj[j]], scenes[lv.traj[j]]
        spline = CubicHermiteSpline(traj.t, traj.q, traj.qd)
        lo, hi = scene.lo[0], scene.hi[0]
        box = fcl.CollisionObject(fcl.Box(*(hi - lo)), fcl.Transform(np.eye(3), (lo + hi) / 2))
        n = max(8, int((lv.t1[j] - lv.t0[j]) * 4000))
        for t in np.linspace(lv.t0[j], lv.t1[j], n + 1):
            T = forward_kinematics_np(robot, spline(t))
            for p, o in enumerate(measure.objects):
                Tl = T[hulls.link_index[p]]
                o.setTransform(fcl.Transform(Tl[:3, :3], Tl[:3, 3]))
                assert fcl.distance(o, box, fcl.DistanceRequest(), fcl.DistanceResult()) > MARGIN


def test_the_option_on_every_path(tmp_path, capsys):
    """RunSpec.swept is validated and round-trips; ``larc certify --swept`` records it in the
    certificate, ``larc verify`` re-checks the swept leaves with it, and a certificate whose
    ``swept`` is forged to false is refuted (its swept leaves fail the midpoint tests)."""
    assert lj.RunSpec(swept=True).swept and not lj.RunSpec().swept
    assert lj.RunSpec.from_json(lj.RunSpec(swept=True).to_json()).swept
    with pytest.raises(LarcInputError, match=r"^swept 'yes': must be true or false"):
        lj.RunSpec(swept="yes")
    path = tmp_path / "c.json"
    rc = main(["certify", REACH, "--scene", CELL, "--max-depth", "5", "--swept", "--hold", "joint7=0",
               "--hold", "joint8=0", "--certificate", str(path), "-q"])
    assert rc in (EXIT_OK, 1)
    doc = json.loads(path.read_text())
    assert doc["parameters"]["swept"] is True
    stages = [s for t in doc["trajectories"] for s in t["leaves"]["stage"]]
    assert int(Stage.SWEPT) in stages
    assert main(["verify", str(path)]) == EXIT_OK
    capsys.readouterr()
    forged = tmp_path / "forged.json"
    forged.write_text(json.dumps(dict(doc, parameters=dict(doc["parameters"], swept=False))))
    assert main(["verify", str(forged)]) == EXIT_REFUTED


def test_union_of_placements_bound_is_below_every_placed_point(model):
    """The polytope bound on the hull of two placements (larc_jax.obstacles.polytope, several
    poses) never exceeds the box distance of any placed vertex of either placement, nor of points
    on the segments joining them; JAX and NumPy agree."""
    from larc_jax.obstacles.polytope import polytope_box_lower_bound, polytope_box_lower_bound_np
    from scipy.spatial.transform import Rotation

    _, _, hulls = model
    rng = np.random.default_rng(9)
    kernel = jax.jit(polytope_box_lower_bound)
    for trial in range(60):
        p = int(rng.integers(hulls.n_parts))
        V = np.asarray(hulls.vertices[p])[: hulls.n_vertices[p]]
        R = Rotation.random(2, random_state=trial).as_matrix()
        t = rng.normal(0, 0.05, (2, 3)) + rng.normal(0, 0.2, 3)
        lo = rng.normal(0, 0.3, 3)
        hi = lo + rng.uniform(0.01, 0.2, 3)
        with jax.enable_x64(True):
            got = float(kernel(np.asarray(hulls.vertices), p, np.asarray(hulls.centre[p]), R, t, lo, hi))
        ref = polytope_box_lower_bound_np(V, np.asarray(hulls.centre[p]), R, t, lo, hi)
        assert abs(got - ref) < 1e-8
        placed = np.concatenate([V @ R[i].T + t[i] for i in range(2)])
        lam = rng.uniform(0, 1, (200, 1))
        j = rng.integers(len(V), size=200)
        between = (1 - lam) * placed[j] + lam * placed[len(V) + j]
        pts = np.concatenate([placed, between])
        dist = np.linalg.norm(pts - np.clip(pts, lo, hi), axis=1).min()
        assert ref <= dist + 1e-12 and got <= dist + 1e-12
