"""The enclosure cascade: kernels vs references, every scheduler takes the same decisions, the
cascade certifies at least what the capsules do, and soundness against dense sampling of the
hull meshes (python-fcl) with near misses."""

from __future__ import annotations

import math

import jax
import numpy as np
import pytest
from scipy.interpolate import CubicHermiteSpline

import larc_jax as lj
from larc_jax.leaf.cascade import Links, combine, interval_pairs, interval_pairs_np, select_pairs
from larc_jax.leaf.interval import dyadic_ends, rebase_ends, trajectory_rounding
from larc_jax.leaf.reference import leaf_enclosures
from larc_jax.enclosure.hull import hull_model
from larc_jax.enclosure.robot_file import load_robot_file
from larc_jax.model.hermite import HermiteSpline
from larc_jax.model.robot import forward_kinematics_np
from larc_jax.obstacles import stack_scenes
from larc_jax.model.scene import Scene
from larc_jax.model.trajectory import Trajectory


MARGIN = 0.01
HOLD = {"joint7": 0.0, "joint8": 0.0}


@pytest.fixture(scope="module")
def model():
    robot, capsules = load_robot_file(None, hold=HOLD)
    return robot, capsules, hull_model(robot, capsules.hull_parts, capsules.padding_m)


def near_scene(rng, robot, capsules, traj, k, n_boxes=2):
    """Boxes some 15 cm beyond a random capsule at a random time, in a random direction (then
    moved close by :meth:`HullClearance.place`)."""
    spline = CubicHermiteSpline(traj.t, traj.q, traj.qd)
    lo, hi = [], []
    for _ in range(n_boxes):
        q = spline(rng.uniform(traj.t[0], traj.t[-1]))
        pa, pb = lj.enclosure.capsule_segments_np(robot, capsules, q)
        c = int(rng.integers(capsules.n_capsules))
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        half = rng.uniform(0.01, 0.15, 3)
        centre = (pa[c] + pb[c]) / 2 + u * (capsules.radius[c] + 0.15 + np.abs(u) @ half)
        lo.append(centre - half)
        hi.append(centre + half)
    return Scene(lo=np.array(lo), hi=np.array(hi), box_names=tuple(f"b{i}" for i in range(n_boxes)), name=f"near{k}")


class HullClearance:
    """Dense python-fcl distance of the link hull meshes (which contain the link meshes) to boxes."""

    def __init__(self, robot, hulls):
        import fcl
        import trimesh

        self.fcl, self.robot, self.hulls = fcl, robot, hulls
        self.objects = []
        for p in range(hulls.n_parts):
            m = trimesh.convex.convex_hull(np.asarray(hulls.vertices[p])[: hulls.n_vertices[p]])
            bvh = fcl.BVHModel()
            bvh.beginModel(len(m.vertices), len(m.faces))
            bvh.addSubModel(np.asarray(m.vertices), np.asarray(m.faces))
            bvh.endModel()
            self.objects.append(fcl.CollisionObject(bvh, fcl.Transform()))
        self.request = fcl.DistanceRequest(enable_nearest_points=True)

    def __call__(self, traj, lo, hi, hz):
        """Smallest distance on a ``hz`` grid, and the unit vector from the box to the hull then."""
        fcl = self.fcl
        spline = CubicHermiteSpline(traj.t, traj.q, traj.qd)
        box = fcl.CollisionObject(fcl.Box(*(hi - lo)), fcl.Transform(np.eye(3), (lo + hi) / 2))
        best, towards = math.inf, np.zeros(3)
        for t in np.linspace(traj.t[0], traj.t[-1], int(traj.duration * hz) + 1):
            T = forward_kinematics_np(self.robot, spline(t))
            for p, o in enumerate(self.objects):
                Tl = T[self.hulls.link_index[p]]
                o.setTransform(fcl.Transform(Tl[:3, :3], Tl[:3, 3]))
                r = fcl.DistanceResult()
                d = fcl.distance(o, box, self.request, r)
                if d < best:
                    best, towards = d, np.asarray(r.nearest_points[0]) - np.asarray(r.nearest_points[1])
        return best, towards / max(np.linalg.norm(towards), 1e-300)

    def place(self, traj, scene, rng, lo_mm, hi_mm):
        """Move each box along the box-to-hull direction so that the hulls clear it (on a 200 Hz
        grid) by rho plus a random lo_mm..hi_mm; returns the scene and how many boxes moved."""
        lo, hi, moved = scene.lo.copy(), scene.hi.copy(), 0
        for b in range(scene.n_boxes):
            target = MARGIN + rng.uniform(lo_mm, hi_mm) / 1000
            for _ in range(4):  # the nearest points move as the box does: a few steps
                d, u = self(traj, lo[b], hi[b], 200)
                if not d > target + 1e-4:
                    break
                lo[b] += u * (d - target)
                hi[b] += u * (d - target)
            moved += int(0 < d <= target + 1e-4)
        return Scene(lo=lo, hi=hi, box_names=scene.box_names, name=scene.name), moved


def short_trajectory(rng, robot, k):
    """A 1 s move of up to 0.3 rad per joint through 3 waypoints (a local motion, as near an
    obstacle)."""
    mid = (robot.q_lower + robot.q_upper) / 2
    half = (robot.q_upper - robot.q_lower) / 2
    q0 = mid + half * rng.uniform(-0.5, 0.5, robot.n_joints)
    q = q0 + np.cumsum(rng.uniform(-0.15, 0.15, (3, robot.n_joints)), axis=0)
    qd = rng.normal(0, 0.2, q.shape)
    qd[0] = qd[-1] = 0.0
    return Trajectory(t=np.array([0.0, 0.5, 1.0]), q=q, qd=qd, joint_names=robot.active_joint_names, id=f"traj{k:03d}")


DEPTH = 6


def near_miss_dataset(robot, capsules, hulls, n: int, lo_mm: float, hi_mm: float, seed: int = 12):
    """``n`` one-second trajectories, each with a box the hulls clear by rho + lo_mm..hi_mm (or, in
    a few, a box the arm sweeps through)."""
    rng = np.random.default_rng(seed)
    measure = HullClearance(robot, hulls)
    trajs, scenes = [], []
    for k in range(n):
        t = short_trajectory(rng, robot, k)
        trajs.append(t)
        scenes.append(measure.place(t, near_scene(rng, robot, capsules, t, k, n_boxes=1), rng, lo_mm, hi_mm)[0])
    return trajs, scenes


@pytest.fixture(scope="module")
def dataset(model):
    """20 trajectories, boxes at rho + 0.5..12 mm from the hulls."""
    return near_miss_dataset(*model, 20, 0.5, 12)


@pytest.fixture(scope="module", autouse=True)
def host_frontier():
    """This module tests the cascade as the host frontier and fixed-fine run it (steps 2-5 of
    :mod:`larc_jax.engine.batch`), so ``certify``'s LARC runs its 20 trajectories there, not on the
    device tree (whose hull stage ``tests/test_tree_hull.py`` compares with these steps)."""
    import larc_jax.engine.tree_pool as pool_module

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(pool_module, "TREE_FROM_TRAJECTORIES", 10**9)
        yield


@pytest.fixture(scope="module")
def larc(dataset, model):
    robot, capsules, _ = model
    return lj.certify(*dataset, robot, capsules, method="larc", margin=MARGIN, max_depth=DEPTH)


def test_reference_larc_and_fine_agree(dataset, model, larc):
    """The NumPy reference (Algorithm 1 with the cascade) and batched LARC evaluate the same
    intervals and take the same decision on each; a trajectory fine certifies LARC certifies."""
    robot, capsules, _ = model
    ref = lj.certify(*dataset, robot, capsules, method="reference", margin=MARGIN, max_depth=DEPTH)
    assert 3 < larc.certified.sum() < 20
    assert (larc.leaves.stage == 2).sum() > 20  # the hull stage decided many leaves
    assert (ref.certified == larc.certified).all()
    assert (ref.frontier == larc.frontier).all()
    assert (ref.leaves.stage == larc.leaves.stage).all()
    np.testing.assert_allclose(ref.leaves.clearance_m, larc.leaves.clearance_m, rtol=0, atol=1e-9)
    fine = lj.certify(*dataset, robot, capsules, method="fine", margin=MARGIN, max_depth=DEPTH)
    assert ((~fine.certified) | larc.certified).all()


def test_cascade_certifies_what_the_capsules_do_and_more(dataset, model, larc):
    robot, capsules, _ = model
    caps = lj.certify(*dataset, robot, capsules, method="larc", margin=MARGIN, max_depth=DEPTH, enclosure="capsules")
    assert ((~caps.certified) | larc.certified).all()
    assert larc.certified.sum() > caps.certified.sum()
    assert (caps.leaves.stage <= 1).all() and caps.enclosure == "capsules" and larc.enclosure == "hull"
    assert (larc.evaluations <= caps.evaluations).all()  # a leaf passing either test stops bisecting


def test_interval_pairs_matches_reference(dataset, model):
    robot, capsules, hulls = model
    trajs, scenes = dataset
    obstacles = stack_scenes(scenes[:10], np.float64)
    rng = np.random.default_rng(1)
    for k in range(10):
        traj = trajs[k]
        a, b = np.sort(rng.uniform(traj.t[0], traj.t[-1], 2))
        bounds = trajectory_rounding(traj, robot, capsules, np.float64, hulls)
        ar, br = rebase_ends(a, b, float(bounds.offset_s))
        with jax.enable_x64(True):
            spline = HermiteSpline.from_waypoints(traj.t - float(bounds.offset_s), traj.q, traj.qd)
            d = interval_pairs(robot, capsules, hulls, spline, obstacles.take(k), ar, br, MARGIN, bounds)
        r = interval_pairs_np(robot, capsules, hulls, traj, scenes[k], a, b, MARGIN, bounds)
        nb = scenes[k].n_boxes
        np.testing.assert_allclose(np.asarray(d.g_capsule)[:, :nb], r.g_capsule[:, :nb], atol=1e-12)
        np.testing.assert_allclose(np.asarray(d.g_upper)[:, :nb], r.g_upper[:, :nb], atol=1e-12)
        np.testing.assert_allclose(np.asarray(d.T_part), r.T_part, atol=1e-12)
        np.testing.assert_allclose(np.asarray(d.motion_b), r.motion_b, atol=1e-15)


def test_bounded_step_two_is_exact_where_it_matters(dataset, model):
    """interval_pairs_bounded against the NumPy float64 reference: the k pairs of least lower
    excess exact, every other pair at or below its exact clearance (one-sided), ``rest`` at or below
    the least ``g - G`` of those pairs; the parts' numbers as step 2's. Random intervals, every
    pair exact (k = C * B: ``rest`` +inf), one pair exact, and a zero-width interval."""
    from larc_jax.leaf.cascade import interval_pairs_bounded

    robot, capsules, hulls = model
    trajs, scenes = dataset
    obstacles = stack_scenes(scenes[:10], np.float64)
    rng = np.random.default_rng(4)
    for n in range(12):
        k = n % 10
        traj = trajs[k]
        a, b = np.sort(rng.uniform(traj.t[0], traj.t[-1], 2)) if n != 11 else (traj.t[1], traj.t[1])
        nb = scenes[k].n_boxes
        n_exact = {9: capsules.n_capsules * obstacles.n_items, 10: 1}.get(n, 8)
        bounds = trajectory_rounding(traj, robot, capsules, np.float64, hulls)
        ar, br = rebase_ends(a, b, float(bounds.offset_s))
        with jax.enable_x64(True):
            spline = HermiteSpline.from_waypoints(traj.t - float(bounds.offset_s), traj.q, traj.qd)
            d, rest = interval_pairs_bounded(robot, capsules, hulls, spline, obstacles.take(k), ar, br, MARGIN, bounds,
                                             n_exact)
        r = interval_pairs_np(robot, capsules, hulls, traj, scenes[k], a, b, MARGIN, bounds)
        g, want = np.asarray(d.g_capsule)[:, :nb], r.g_capsule[:, :nb]
        exact = np.abs(g - want) <= 1e-12
        assert (g <= want + 1e-12).all() and exact.sum() >= min(n_exact, g.size), n
        assert (np.asarray(d.g_capsule)[:, nb:] == np.inf).all()
        G = np.asarray(bounds.guard_m)[:, None]
        assert float(rest) <= ((want - G)[~exact]).min(initial=np.inf) + 1e-12, n
        assert (float(rest) == np.inf) == (n == 9)
        np.testing.assert_allclose(np.asarray(d.g_upper)[:, :nb], r.g_upper[:, :nb], atol=1e-12)
        np.testing.assert_allclose(np.asarray(d.T_part), r.T_part, atol=1e-12)


def test_bounded_step_two_changes_no_decision(dataset, model, larc, monkeypatch):
    """LARC with step 2 bounded (the default) and with every interval's step 2 all-exact
    (exact_enough always False) walk the same intervals and record the same leaves: the same
    stages, pairs and guards, clearances equal to the last bits (a pair's distance computed in
    another compiled program)."""
    import dataclasses

    import larc_jax.engine.batch as batch_module

    robot, capsules, _ = model
    seen = []
    real = batch_module.exact_enough

    def spy(*args):
        seen.append(real(*args))
        return seen[-1]

    monkeypatch.setattr(batch_module, "exact_enough", spy)
    bounded = lj.certify(*dataset, robot, capsules, method="larc", margin=MARGIN, max_depth=DEPTH)
    assert sum(int(s.sum()) for s in seen) > 0.8 * sum(len(s) for s in seen) > 0  # the bounded values served
    monkeypatch.setattr(batch_module, "exact_enough", lambda links, cap, *rest: np.zeros(len(cap), bool))
    exact = lj.certify(*dataset, robot, capsules, method="larc", margin=MARGIN, max_depth=DEPTH)
    for r in (bounded, larc):
        assert (r.certified == exact.certified).all() and (r.frontier == exact.frontier).all()
        for f in dataclasses.fields(exact.leaves):
            got, want = getattr(r.leaves, f.name), getattr(exact.leaves, f.name)
            if f.name == "clearance_m":
                np.testing.assert_allclose(got, want, rtol=1e-14, atol=1e-16)
            else:
                np.testing.assert_array_equal(got, want, err_msg=f.name)


def test_exact_enough_on_named_cases():
    """exact_enough: the interval's excess bounded from above below ``rest > 0`` -> True; a failing
    capsule pair counts its parts' upper excess, a passing one its capsule excess; rest <= 0, NaN,
    or the bound reaching ``rest`` -> False."""
    from larc_jax.leaf.cascade import exact_enough

    links = Links(np.array([0, 0, 1]), np.array([0, 1]), 2)
    cap = np.array([[[0.5], [0.7], [0.9]]] * 6)  # (F, C, B): every capsule passes
    upper = np.full((6, 2, 1), 2.0)
    rest = np.array([0.6, 0.5, 0.0, np.nan, 0.6, 0.6])
    cap[4, 0, 0] = -0.1  # link 0 fails: its parts' upper excess 2.0 counts, not rest-bound
    cap[5, 0, 0], upper[5, 0, 0] = -0.1, 0.3  # the upper excess 0.3 < rest
    np.testing.assert_array_equal(exact_enough(links, cap, upper, rest), [True, False, False, False, False, True])


def test_select_and_combine_on_named_cases():
    """Two links (capsules 0, 1 on link 0; capsule 2 on link 1), one part each, two boxes."""
    links = Links(of_capsule=np.array([0, 0, 1]), of_part=np.array([0, 1]), n_links=2)
    inf = np.inf
    g_cap = np.array([[[0.004, inf], [-0.002, 0.010], [0.020, 0.030]],   # link 0 fails box 0
                      [[0.004, inf], [-0.002, 0.010], [0.020, np.nan]],  # ... and a NaN
                      [[-0.05, 0.01], [-0.04, 0.01], [0.02, 0.02]]])     # link 0 fails; hull cannot pass
    g_up = np.array([[[0.01, inf], [0.5, 0.5]], [[0.01, inf], [0.5, 0.5]], [[-0.001, 0.5], [0.5, 0.5]]])
    guard_c, guard_p = np.zeros((3, 3)), np.zeros(2)
    tried, triples = select_pairs(links, g_cap, g_up)
    assert tried[0, 0, 0] and not tried[0, 0, 1] and not tried[0, 1].any()
    assert not tried[2].any()  # the upper bound says the hull cannot pass: skipped
    assert triples.tolist() == [[0, 0, 0], [1, 0, 0]]
    g, guard, cap, box, passed = combine(links, g_cap, guard_c, tried, triples, np.array([0.003, 0.003]),
                                         guard_p[triples[:, 1]])
    assert passed.tolist() == [True, False, False]
    assert g[0] == pytest.approx(0.003) and math.isnan(g[1])  # NaN never certifies
    assert cap[2] == 0 and box[2] == 0 and g[2] == pytest.approx(-0.05)
    # Guards: the hull passes only above its own guard; the recorded (g, guard) decide the leaf.
    g, guard, _, _, passed = combine(links, g_cap, guard_c, tried, triples, np.array([0.003, 0.003]),
                                     np.array([0.004, 0.0]))
    assert not passed[0] and g[0] == pytest.approx(0.003) and guard[0] == pytest.approx(0.004)
    g, guard, _, _, passed = combine(links, g_cap, guard_c, tried, triples, np.array([-0.001, 0.003]),
                                     guard_p[triples[:, 1]])
    assert not passed[0] and g[0] == pytest.approx(-0.001)  # the hull fails too: max of the two excesses


def test_combine_picks_the_deciding_part_as_a_loop_does():
    """Random intervals with two parts per link, ties and NaN: the recorded (g, guard) of a leaf
    the hull decides are those of its (link, box)'s part with the least excess, the first in triple
    order on a tie, the first NaN if any (np.argmin over that pair's triples, written as a loop)."""
    rng = np.random.default_rng(7)
    links = Links(of_capsule=np.array([0, 0, 1, 2]), of_part=np.array([0, 1, 1, 2, 2, 0]), n_links=3)
    F, B = 300, 3
    g_cap = rng.choice([-0.004, -0.002, 0.001, 0.02], (F, 4, B))
    g_up = np.full((F, 6, B), 0.5)
    guard_c = np.full((F, 4), 1e-4)
    tried, triples = select_pairs(links, g_cap - guard_c[:, :, None], g_up)
    g_hull = rng.choice([-0.003, 0.001, 0.002, 0.002, 0.005, np.nan], len(triples), p=[.2, .2, .2, .2, .15, .05])
    guard_hull = rng.choice([1e-4, 2e-4], len(triples))
    g, guard, cap, box, passed = combine(links, g_cap, guard_c, tried, triples, g_hull, guard_hull)
    # The loop: the deciding (link, box) from the rule, then its parts' least excess.
    i, p, k = triples.T
    ex = g_hull - guard_hull
    checked = 0
    for f in range(F):
        sel = np.flatnonzero(i == f)
        if not len(sel):
            continue
        for l in range(3):
            for kb in range(B):
                on = sel[(links.of_part[p[sel]] == l) & (k[sel] == kb)]
                if len(on) and box[f] == kb and links.of_capsule[cap[f]] == l and not math.isnan(g[f]):
                    t = on[np.argmin(ex[on])]
                    if ex[t] > (g_cap[f, cap[f], kb] - guard_c[f, cap[f]]):  # the hull decided
                        assert (g[f], guard[f]) == (g_hull[t], guard_hull[t]), f
                        checked += 1
    assert checked > 50
    assert np.array_equal(passed, g > guard)


def test_vertex_classes_evaluate_each_pair_as_the_whole_table(model):
    """Pairs run a call per group of vertex classes, on the table cut to the group's columns:
    every part's vertices are in its call's columns, the clearances equal the whole table's bit
    for bit (first axis and full search), and come back in the pairs' order."""
    from larc_jax.engine import batch as batch_module
    from larc_jax.enclosure.hull import by_vertex_class

    robot, capsules, hulls = model
    classes = hulls.vertex_classes()
    K = hulls.vertices.shape[1]
    assert classes[-1] == K and list(classes) == sorted(set(classes)) and len(classes) <= 3
    assert len(classes) > 1  # PIPER's parts have 122..691 vertices
    rng = np.random.default_rng(5)
    n = 300
    part = rng.integers(0, hulls.n_parts, n)
    T = np.concatenate([np.linalg.qr(rng.normal(size=(n, 3, 3)))[0], rng.uniform(-0.3, 0.3, (n, 3, 1))], axis=2)
    lo = rng.uniform(-0.5, 0.3, (n, 3))
    boxes = lj.AlignedBoxes(lo=lo, hi=lo + rng.uniform(0.01, 0.2, (n, 3)), mask=np.ones(n, bool))
    mb = rng.uniform(0, 0.01, n)
    calls = []

    def run(kernel):
        def call(h, idx):
            calls.append(h.vertices.shape[1])
            assert all(hulls.n_vertices[p] <= h.vertices.shape[1] for p in part[idx])
            items = jax.tree.map(lambda x: x[idx], boxes)
            return np.asarray(kernel(h, part[idx], T[idx], items, mb[idx], np.float64(MARGIN)))
        return call

    with jax.enable_x64(True):
        for kernel in (batch_module.hull_first_axis, batch_module.hull_early, batch_module.hull_pairs):
            whole = np.asarray(kernel(hulls, part, T, boxes, mb, np.float64(MARGIN)))
            calls.clear()
            split = by_vertex_class(hulls, part, run(kernel), (64, 256, 1024))
            assert len(calls) > 1 and min(calls) < K
            np.testing.assert_array_equal(split, whole)
        # Few pairs of a small class ride with a larger class's call (one call of 64 is cheaper).
        calls.clear()
        small = np.array([int(np.argmin(hulls.n_vertices)), int(np.argmax(hulls.n_vertices))])
        by_vertex_class(hulls, small, run(batch_module.hull_first_axis), (64, 256, 1024))
        assert calls == [K]


def test_soundness_against_dense_sampling_of_the_hulls(model, dataset, larc):
    """Whenever the cascade certifies, the link hulls (which contain the meshes) stay more than
    rho from every box at 2 kHz (python-fcl distance of the hull meshes). The boxes are near
    misses: the hulls pass rho + 0.2..3 mm from them, where the capsules fail."""
    robot, capsules, hulls = model
    measure = HullClearance(robot, hulls)
    rng = np.random.default_rng(21)
    checked = near = 0
    for k in range(8):
        traj = short_trajectory(rng, robot, 100 + k)
        scene, moved = measure.place(traj, near_scene(rng, robot, capsules, traj, k, n_boxes=1), rng, 0.2, 3)
        near += moved
        res = lj.certify(traj, scene, robot, capsules, margin=MARGIN, max_depth=10)[0]
        if res.certified:
            checked += 1
            assert measure(traj, scene.lo[0], scene.hi[0], 2000)[0] > MARGIN, traj.id
    # The dataset's certificates too (rho + 0.5..12 mm).
    for traj, scene, ok in zip(*dataset, larc.certified):
        if ok:
            checked += 1
            assert measure(traj, scene.lo[0], scene.hi[0], 2000)[0] > MARGIN, traj.id
    assert checked >= 6 and near >= 5


def test_rounds_decide_as_the_full_search(dataset, model, larc, monkeypatch):
    """Step 4's early rounds (the first GJK axis alone; the middle round, which also stops a triple
    whose upper bound cannot pass) change no decision: with the full search on every triple (the
    first round replaced by it) the same intervals are evaluated and every leaf has the same stage;
    a leaf an early round decided records a bound no larger than the full search's, and still above
    its guard."""
    import larc_jax.engine.batch as batch_module

    robot, capsules, _ = model
    monkeypatch.setattr(batch_module, "hull_first_axis", batch_module.hull_pairs)
    full = lj.certify(*dataset, robot, capsules, method="larc", margin=MARGIN, max_depth=DEPTH)
    assert (full.certified == larc.certified).all()
    assert (full.frontier == larc.frontier).all()
    assert (full.leaves.stage == larc.leaves.stage).all()
    hull = larc.leaves.stage == 2
    excess, excess_full = (r.leaves.clearance_m - r.leaves.guard_m for r in (larc, full))
    assert (excess[hull] > 0).all()
    assert (excess[hull] <= excess_full[hull] + 1e-12).all()
    assert (excess[hull] < excess_full[hull] - 1e-6).any()  # some leaves were decided by the first axis
    capsule = larc.leaves.stage == 1
    assert (larc.leaves.clearance_m[capsule] == full.leaves.clearance_m[capsule]).all()


def test_hull_rounds_rule():
    """Named cases of :func:`hull_rounds` with a middle round: a first value above its guard is
    kept (steps 0); else the middle value is kept (steps 6) when it is above the guard or its upper
    bound is at or below ``guard - slack``; an upper bound inside the slack, or NaN, goes on to the
    full search (steps 12); each round is asked only for what the previous one left."""
    from larc_jax.leaf.rounds import EARLY_ITERATIONS, hull_rounds
    from larc_jax.obstacles.polytope import GJK_ITERATIONS

    first = np.array([0.5, 0.0, -1.0, -1.0, -1.0, np.nan, -2.0])
    guard = np.full(7, 0.1)
    slack = 0.01
    asked = []

    def early(redo):
        asked.append(("early", list(redo)))
        lower = np.array([0.2, -1.0, -1.0, -1.0, np.nan, -1.0])
        upper = np.array([0.3, 0.09, 0.095, np.nan, np.nan, 0.1 - slack])
        return lower[: len(redo)], upper[: len(redo)]

    def full(redo):
        asked.append(("full", list(redo)))
        return np.full(len(redo), 7.0)

    g, steps = hull_rounds(first, guard, full, early, slack)
    assert asked == [("early", [1, 2, 3, 4, 5, 6]), ("full", [3, 4, 5])]
    np.testing.assert_array_equal(g, [0.5, 0.2, -1.0, 7.0, 7.0, 7.0, -1.0])
    F, E = GJK_ITERATIONS, EARLY_ITERATIONS
    np.testing.assert_array_equal(steps, [0, E, E, F, F, F, E])


def test_two_rounds_rule():
    """Named cases of :func:`hull_rounds` without a middle round (``early=None``; no scheduler
    passes it since every obstacle kind takes the middle round, but the rule stays defined): a
    first value above its guard is kept; at the guard, below it or NaN, the full search's value
    replaces it (and only those are asked for)."""
    from larc_jax.leaf.rounds import hull_rounds

    def two_rounds(first, guard, full):
        return hull_rounds(first, guard, full)[0]

    first = np.array([0.5, 0.1, 0.2, np.nan, -1.0])
    guard = np.array([0.1, 0.1, 0.3, 0.0, 0.0])
    asked = []

    def full(redo):
        asked.append(list(redo))
        return np.array([7.0, 8.0, 9.0, 10.0])[: len(redo)]

    g = two_rounds(first, guard, full)
    assert asked == [[1, 2, 3, 4]]
    np.testing.assert_array_equal(g, [0.5, 7.0, 8.0, 9.0, 10.0])
    assert len(two_rounds(np.array([1.0]), np.array([0.0]), lambda redo: 1 / 0)) == 1  # never asked


def test_point_round_rule():
    """Named cases of :func:`point_round`: only triples at or below their guard whose obstacle is
    made of separate points are asked for; each gets the larger of its two values (a lower
    per-point value never lowers it); NaN is kept and never asked for."""
    from larc_jax.leaf.rounds import point_round

    g = np.array([0.5, 0.1, 0.2, np.nan, -1.0, -1.0, 0.0])
    guard = np.array([0.1, 0.1, 0.3, 0.0, 0.0, 0.0, 0.1])
    separate = np.array([True, True, True, True, True, False, True])
    asked = []

    def points(redo):
        asked.append(list(redo))
        return np.array([0.4, 0.1, -2.0, np.nan])[: len(redo)]

    out = point_round(g, guard, separate, points)
    assert asked == [[1, 2, 4, 6]]
    np.testing.assert_array_equal(out, [0.5, 0.4, 0.2, np.nan, -1.0, -1.0, np.nan])
    assert len(point_round(g[:1], guard[:1], separate[:1], lambda redo: 1 / 0)) == 1  # never asked


def test_screen_matches_reference(dataset, model):
    """The screen ahead of step 2 (:func:`link_upper_excess`) against its NumPy float64 reference
    on random intervals, links and items, and on named cases: a zero-width interval, the whole
    horizon, a box far away (large positive), a box on the arm (negative), no part on the link (inf)."""
    from larc_jax.leaf.cascade import link_upper_excess, link_upper_excess_np

    robot, capsules, hulls = model
    trajs, scenes = dataset
    links = Links.of(capsules, hulls)
    rng = np.random.default_rng(3)
    cases = []
    for k in range(8):
        traj = trajs[k]
        a, b = np.sort(rng.uniform(traj.t[0], traj.t[-1], 2))
        cases.append((k, a, b, scenes[k], rng.integers(links.n_links)))
    t = trajs[0].t
    far = Scene(lo=np.array([[5.0, 5.0, 5.0]]), hi=np.array([[5.5, 5.5, 5.5]]), box_names=("far",), name="far")
    on_arm = Scene(lo=np.array([[-2.0, -2.0, -2.0]]), hi=np.array([[2.0, 2.0, 2.0]]), box_names=("all",), name="all")
    cases += [(0, t[1], t[1], scenes[0], 1), (0, t[0], t[-1], scenes[0], 2), (0, t[0], t[-1], far, 0),
              (0, t[0], t[1], on_arm, 3), (0, t[0], t[1], scenes[0], -1)]
    seen = []
    for k, a, b, scene, link in cases:
        traj = trajs[k]
        bounds = trajectory_rounding(traj, robot, capsules, np.float64, hulls)
        ar, br = rebase_ends(a, b, float(bounds.offset_s))
        on_link = links.of_part == link
        with jax.enable_x64(True):
            spline = HermiteSpline.from_waypoints(traj.t - float(bounds.offset_s), traj.q, traj.qd)
            item = stack_scenes([scene], np.float64).take((0, 0))
            got = float(link_upper_excess(robot, capsules, hulls, spline, item, ar, br, MARGIN, bounds, on_link))
        want = link_upper_excess_np(robot, capsules, hulls, traj, scene, a, b, MARGIN, bounds, 0, on_link)
        assert got == want or abs(got - want) <= 1e-12, (k, a, b, scene.name, link)
        seen.append(got)
    assert seen[-3] > 4 and seen[-2] < 0 and seen[-1] == np.inf


def test_screen_from_step_one_is_the_screen(dataset, model):
    """:func:`screened_interval` (step 1 and the screen from one placement, only the recorded
    link's parts bounded) gives the capsule test's record and the screen's value on the pair it
    records: against :func:`evaluate_interval` and :func:`link_upper_excess` (each placing the
    interval itself), and the NumPy float64 reference, on random intervals (passing and failing,
    broad phase and all pairs) and a zero-width one; ``part_table`` lists each link's parts."""
    from larc_jax.leaf.cascade import link_upper_excess, link_upper_excess_np, screened_interval
    from larc_jax.leaf.clearance import BROAD_PHASE_K
    from larc_jax.leaf.interval import evaluate_interval

    robot, capsules, hulls = model
    trajs, scenes = dataset
    links = Links.of(capsules, hulls)
    table = links.part_table
    for l in range(links.n_links):
        row = table[l][table[l] >= 0]
        np.testing.assert_array_equal(row, np.flatnonzero(links.of_part == l))
        assert (table[l][len(row):] == -1).all()
    link_of = (links.of_capsule, table)
    rng = np.random.default_rng(8)
    cases = [(k % len(trajs), *np.sort(rng.uniform(trajs[k % len(trajs)].t[0], trajs[k % len(trajs)].t[-1], 2)))
             for k in range(12)] + [(0, trajs[0].t[1], trajs[0].t[1])]
    failing = 0
    for n, (k, a, b) in enumerate(cases):
        traj = trajs[k]
        bounds = trajectory_rounding(traj, robot, capsules, np.float64, hulls)
        ar, br = rebase_ends(a, b, float(bounds.offset_s))
        kb = BROAD_PHASE_K if n % 2 else None
        with jax.enable_x64(True):
            spline = HermiteSpline.from_waypoints(traj.t - float(bounds.offset_s), traj.q, traj.qd)
            obstacles = stack_scenes([scenes[k]], np.float64).take((0,))
            ev, excess = screened_interval(robot, capsules, hulls, link_of, spline, obstacles, ar, br, MARGIN, bounds, kb)
            want = evaluate_interval(robot, capsules, spline, obstacles, ar, br, MARGIN, bounds, kb)
            assert (int(ev.capsule), int(ev.box)) == (int(want.capsule), int(want.box))
            assert abs(float(ev.g) - float(want.g)) <= 1e-12 and float(ev.guard) == float(want.guard)
            on_link = links.of_part == links.of_capsule[int(ev.capsule)]
            alone = float(link_upper_excess(robot, capsules, hulls, spline, obstacles.take(int(ev.box)), ar, br, MARGIN,
                                            bounds, on_link))
        ref = link_upper_excess_np(robot, capsules, hulls, traj, scenes[k], a, b, MARGIN, bounds, int(ev.box), on_link)
        assert abs(float(excess) - alone) <= 1e-12 and abs(float(excess) - ref) <= 1e-12, (k, a, b)
        failing += not float(ev.g) > float(ev.guard)
    assert 0 < failing < len(cases)


def _spied_screen(monkeypatch):
    """Record what :meth:`Batch._hopeless` returns (a list of bool arrays)."""
    import larc_jax.engine.batch as batch_module

    seen, real = [], batch_module.Batch._hopeless

    def spy(self, *args):
        seen.append(real(self, *args))
        return seen[-1]

    monkeypatch.setattr(batch_module.Batch, "_hopeless", spy)
    return seen


def _no_screen(monkeypatch):
    """Every interval the capsules fail through steps 2-5, whatever the screen would find."""
    import larc_jax.engine.batch as batch_module

    monkeypatch.setattr(batch_module.Batch, "_hopeless", lambda self, tr, *args: np.zeros(len(tr), bool))


def _same_leaves(r, whole):
    """``r`` walks the intervals ``whole`` walks and takes its decisions; its leaves record the
    same stages, pairs and guards, and clearances equal to 1e-12 m (a screened leaf keeps step 1's
    clearance, larc_jax.leaf.cascade "The screen": step 2 computes it again in another program)."""
    import dataclasses

    assert (r.certified == whole.certified).all() and (r.frontier == whole.frontier).all()
    for f in dataclasses.fields(whole.leaves):
        if f.name != "clearance_m":
            np.testing.assert_array_equal(getattr(r.leaves, f.name), getattr(whole.leaves, f.name), err_msg=f.name)
    np.testing.assert_allclose(r.leaves.clearance_m, whole.leaves.clearance_m, rtol=0, atol=1e-12)
    passed = whole.leaves.stage > 0  # decided by steps 1-5 alike: bit-identical
    np.testing.assert_array_equal(r.leaves.clearance_m[passed], whole.leaves.clearance_m[passed])


def test_screen_changes_no_decision(dataset, model, larc, monkeypatch):
    """LARC and fixed-fine with the screen (the default: LARC's from step 1's kernel, fine's from
    a call of its own) and without it (every interval through steps 2-5) walk the same intervals,
    take the same decisions and write the same leaves (:func:`_same_leaves`); the screen spared
    steps 2-4 on many intervals, fine's deepest (failing) leaves included."""
    robot, capsules, _ = model
    runs = {}
    for method in ("larc", "fine"):
        seen = _spied_screen(monkeypatch)
        runs[method] = lj.certify(*dataset, robot, capsules, method=method, margin=MARGIN, max_depth=DEPTH)
        assert sum(int(s.sum()) for s in seen) > 20, method  # the screen spared steps 2-4 on many intervals
    _no_screen(monkeypatch)
    for method, r in runs.items():
        whole = lj.certify(*dataset, robot, capsules, method=method, margin=MARGIN, max_depth=DEPTH)
        assert (~whole.certified).any()  # failing leaves, where the screen keeps the capsule record
        _same_leaves(r, whole)
    _same_leaves(larc, lj.certify(*dataset, robot, capsules, method="larc", margin=MARGIN, max_depth=DEPTH))


def test_screened_intervals_fail_the_cascade(dataset, model, monkeypatch):
    """One-sided: every interval of depths 0-5 gets the same verdict from the leaf test with the
    screen, computed in step 1 (``may_bisect``, LARC) or in a call of its own (fine), as from the
    whole cascade; in particular every interval the screen calls hopeless fails steps 2-5, and
    the screen was asked about some that then passed. The NumPy reference with the screen and
    without agrees on the intervals it spared."""
    import larc_jax.leaf.cascade as cascade_module
    from larc_jax.engine import batch as B
    from larc_jax.leaf.cascade import cascade_np

    robot, capsules, hulls = model
    trajs, scenes = dataset
    bounds = [trajectory_rounding(t, robot, capsules, np.float64, hulls) for t in trajs]
    b = B.prepare(trajs, scenes, robot, capsules, MARGIN, np.float64, bounds, hulls=hulls)
    depth = np.concatenate([np.full(2**d, d) for d in range(6)])
    index = np.concatenate([np.arange(2**d) for d in range(6)])
    traj = np.repeat(np.arange(len(trajs)), len(depth))
    depth, index = np.tile(depth, len(trajs)), np.tile(index, len(trajs))
    runs = []
    for may_bisect in (np.ones(len(traj), bool), None):
        seen = _spied_screen(monkeypatch)
        runs.append(b.evaluate_cascade(traj, depth, index, may_bisect=may_bisect)[2])
        hopeless = sum(int(s.sum()) for s in seen)
        assert hopeless > 50 and sum(len(s) for s in seen) > hopeless  # it spared some, not all
    with monkeypatch.context() as m:
        _no_screen(m)
        whole = b.evaluate_cascade(traj, depth, index)[2]
    for screened in runs:
        np.testing.assert_array_equal(screened.stage > 0, whole.stage > 0)
        passed = whole.stage == 2
        np.testing.assert_array_equal(screened.clearance_m[passed], whole.clearance_m[passed])
        excess = lambda r: r.clearance_m - r.guard_m  # noqa: E731
        np.testing.assert_allclose(excess(screened), excess(whole), rtol=0, atol=1e-12)
    steps = []  # one entry per reference call that reached step 3 (not screened)
    real = cascade_module.select_pairs
    monkeypatch.setattr(cascade_module, "select_pairs", lambda *a: steps.append(1) or real(*a))
    enc, screened_here = leaf_enclosures(robot, capsules, "hull"), 0
    for i in np.flatnonzero(~(whole.stage > 0) & np.isfinite(whole.clearance_m))[::41][:8]:
        t = trajs[traj[i]]
        a, bb = (float(x) for x in dyadic_ends(t.t[0], t.t[-1], depth[i], index[i]))
        args = (robot, enc.capsules, enc.hulls, enc.links, t, scenes[traj[i]], a, bb, MARGIN, bounds[traj[i]])
        before = len(steps)
        got = cascade_np(*args)
        screened_here += len(steps) == before
        full = cascade_np(*args, screen=False)
        assert got[4] == full[4] == 0 and abs((got[0] - got[1]) - (full[0] - full[1])) <= 1e-12, (i, got, full)
    assert screened_here >= 2


def test_larc_compiles_one_step_one(dataset, model, monkeypatch):
    """LARC's cascade runs step 1 through the screened kernel at every level, its deepest included
    (one compiled program, not two); its deepest-level leaves are the leaves fixed-fine writes for
    the same intervals (fine runs the plain kernel): same verdicts, stages and pairs, clearances
    equal to 1e-12 m."""
    import larc_jax.engine.batch as batch_module

    robot, capsules, _ = model
    kernels, real = [], batch_module.Batch._over

    def spy(self, kernel, *args, **kw):
        kernels.append(getattr(kernel, "__name__", ""))
        return real(self, kernel, *args, **kw)

    monkeypatch.setattr(batch_module.Batch, "_over", spy)
    larc = lj.certify(*dataset, robot, capsules, method="larc", margin=MARGIN, max_depth=DEPTH)
    step_one = {k for k in kernels if k.startswith("evaluate_intervals")}
    assert step_one and all(k.startswith("evaluate_intervals_screened") for k in step_one), step_one
    kernels.clear()
    fine = lj.certify(*dataset, robot, capsules, method="fine", margin=MARGIN, max_depth=DEPTH)
    assert not any(k.startswith("evaluate_intervals_screened") for k in kernels)
    deep = np.flatnonzero(larc.leaves.depth == DEPTH)
    assert len(deep) > 20 and (~larc.leaves.certified[deep]).any()  # failing and passing deepest leaves
    key = lambda r, rows: r.leaves.traj[rows] * 2**DEPTH + r.leaves.index[rows]  # noqa: E731
    at = np.searchsorted(key(fine, slice(None)), key(larc, deep))
    np.testing.assert_array_equal(key(fine, at), key(larc, deep))
    for name in ("certified", "stage", "capsule", "box", "guard_m"):
        np.testing.assert_array_equal(getattr(larc.leaves, name)[deep], getattr(fine.leaves, name)[at], err_msg=name)
    np.testing.assert_allclose(larc.leaves.clearance_m[deep], fine.leaves.clearance_m[at], rtol=0, atol=1e-12)


def test_a_box_only_scene_batched_with_a_posed_one_records_what_it_records_alone(dataset, model, larc):
    """A batch holding any posed scene stacks every scene as posed shapes (whose upper bound, R8,
    subtracts R4's term: a failing triple may stop in another round), while the reference and
    ``larc verify`` read a box-only scene as aligned boxes. A passing triple must still go through
    the same rounds in both (a pass stops every kind in the same round), so a certified trajectory's leaves record the same clearances batched with a posed
    scene as alone, and as the reference records them (``larc verify`` refutes a stored clearance
    above the recomputed one by more than rounding)."""
    from pathlib import Path

    robot, capsules, _ = model
    trajs, scenes = dataset
    shapes = lj.read_scene(str(Path(__file__).resolve().parents[1] / "configs" / "examples" / "cell_shapes.yaml"))
    assert shapes.posed and not any(s.posed for s in scenes)
    kw = dict(method="larc", margin=MARGIN, max_depth=DEPTH)
    mixed = lj.certify(list(trajs) + [trajs[0]], list(scenes) + [shapes], robot, capsules, **kw)
    ref = lj.certify(list(trajs) + [trajs[0]], list(scenes) + [shapes], robot, capsules,
                     **dict(kw, method="reference"))
    n = len(trajs)
    assert (mixed.certified[:n] == larc.certified).all() and (ref.certified == mixed.certified).all()
    ours = mixed.leaves.traj < n
    certified = larc.certified[larc.leaves.traj]
    assert ((larc.leaves.stage == 2) & certified).sum() > 5  # hull-decided leaves of certified trajectories
    np.testing.assert_array_equal(mixed.leaves.stage[ours], larc.leaves.stage)
    np.testing.assert_allclose(mixed.leaves.clearance_m[ours][certified], larc.leaves.clearance_m[certified],
                               rtol=0, atol=1e-12)
    mine = ref.leaves.traj < n
    np.testing.assert_allclose(ref.leaves.clearance_m[mine][certified], mixed.leaves.clearance_m[ours][certified],
                               rtol=0, atol=1e-9)


def _posed(scene: Scene, rng) -> Scene:
    """The scene's boxes as posed boxes, each turned by up to 0.3 rad about its centre."""
    from scipy.spatial.transform import Rotation

    from larc_jax.model.shapes import Shapes

    n = scene.n_boxes
    turns = Rotation.from_rotvec(rng.normal(size=(n, 3)) * 0.3 / math.sqrt(3)).as_matrix()
    shapes = Shapes(kinds=("box",) * n, names=tuple(f"p{i}" for i in range(n)), dims=scene.hi - scene.lo,
                    p_world_shape=(scene.lo + scene.hi) / 2, R_world_shape=turns)
    return Scene(lo=np.zeros((0, 3)), hi=np.zeros((0, 3)), shapes=shapes, name=scene.name + "_posed")


def test_posed_middle_round_stops_failing_triples_and_decides_as_the_full_search(dataset, model, monkeypatch):
    """Against posed shapes the middle round also stops triples that cannot pass (their upper
    bound, R8 of larc_jax.obstacles.convex_shapes, at or below the guard less the slack), and that
    changes no decision: with the full search on every triple the same intervals are evaluated and
    every leaf has the same stage (a hull leaf recording a bound no larger than the full search's);
    and the NumPy reference, with its own bounds, decides as the batched rounds do."""
    import larc_jax.engine.batch as batch_module

    robot, capsules, _ = model
    trajs, scenes = dataset
    rng = np.random.default_rng(11)
    posed = [_posed(s, rng) for s in scenes]
    seen = {"stopped": 0, "middle": 0}
    rounds = batch_module.hull_rounds

    def counting(g_first, guard, full, early=None, slack=0.0):
        def early_counted(redo):
            lower, upper = early(redo)
            seen["middle"] += len(redo)
            seen["stopped"] += int(((upper <= guard[redo] - slack) & ~(lower > guard[redo])).sum())
            return lower, upper
        return rounds(g_first, guard, full, early_counted, slack)

    kw = dict(method="larc", margin=MARGIN, max_depth=DEPTH)
    monkeypatch.setattr(batch_module, "hull_rounds", counting)
    larc = lj.certify(trajs, posed, robot, capsules, **kw)
    assert seen["stopped"] > 20 and seen["middle"] > seen["stopped"], seen
    assert 0 < larc.certified.sum() < len(trajs) and (larc.leaves.stage == 2).sum() > 20
    monkeypatch.setattr(batch_module, "hull_first_axis", batch_module.hull_pairs)
    full = lj.certify(trajs, posed, robot, capsules, **kw)
    assert (full.certified == larc.certified).all()
    assert (full.frontier == larc.frontier).all()
    assert (full.leaves.stage == larc.leaves.stage).all()
    hull = larc.leaves.stage == 2
    excess, excess_full = (r.leaves.clearance_m - r.leaves.guard_m for r in (larc, full))
    assert (excess[hull] <= excess_full[hull] + 1e-12).all()
    few = slice(0, 6)
    ref = lj.certify(trajs[few], posed[few], robot, capsules, **dict(kw, method="reference"))
    mine = larc.leaves.traj < 6
    assert (ref.certified == larc.certified[few]).all()
    assert (ref.leaves.stage == larc.leaves.stage[mine]).all()
    np.testing.assert_allclose(ref.leaves.clearance_m, larc.leaves.clearance_m[mine], rtol=0, atol=1e-9)
