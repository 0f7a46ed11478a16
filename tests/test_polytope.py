"""The polytope-box lower bound: kernel vs NumPy reference, one-sided against FCL and sampling,
named edge cases."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from larc_jax.obstacles.polytope import polytope_box_lower_bound, polytope_box_lower_bound_np


def _kernel(V, centre, R, t, lo, hi, dtype=np.float64):
    with jax.enable_x64(dtype == np.float64):
        table = jnp.asarray(np.asarray(V, dtype)[None])
        out = jax.jit(polytope_box_lower_bound)(table, 0, *(jnp.asarray(np.asarray(x, dtype)) for x in (centre, R, t, lo, hi)))
        return float(out)


@pytest.fixture(scope="module")
def link_hulls(robot):
    from larc_jax.enclosure.hull import build_parts

    return {p.name: p.vertices for p in build_parts(robot, links=["link2", "link6", "link7"])}


def _placement(rng, V, gap):
    """A random pose of V and a random box beyond the supporting plane of the placed polytope in
    a random direction, at least ``gap`` away from it (the true distance comes from FCL)."""
    R = Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix()
    t = rng.normal(0, 0.05, 3)
    W = V @ R.T + t
    u = rng.normal(size=3)
    u /= np.linalg.norm(u)
    half = rng.uniform(0.001, 0.2, 3)
    centre = W[np.argmax(W @ u)] + u * (gap + np.abs(u) @ half)  # the box's support toward -u is gap away
    return R, t, centre - half, centre + half


def _fcl_distance(V, R, t, lo, hi) -> float:
    import fcl
    import trimesh

    hull = trimesh.convex.convex_hull(V)
    bvh = fcl.BVHModel()
    bvh.beginModel(len(hull.vertices), len(hull.faces))
    bvh.addSubModel(np.asarray(hull.vertices), np.asarray(hull.faces))
    bvh.endModel()
    a = fcl.CollisionObject(bvh, fcl.Transform(R, t))
    b = fcl.CollisionObject(fcl.Box(*(hi - lo)), fcl.Transform(np.eye(3), (lo + hi) / 2))
    return float(fcl.distance(a, b, fcl.DistanceRequest(), fcl.DistanceResult()))


def test_never_above_fcl_and_tight(link_hulls):
    """On PIPER link hulls near random boxes (1 mm .. 30 mm), the bound never exceeds python-fcl's
    distance of the hull mesh, and is within 0.1 mm of it in at least 90 % of the cases."""
    rng = np.random.default_rng(3)
    gaps = []
    for name, V in link_hulls.items():
        c = (V.min(0) + V.max(0)) / 2
        for _ in range(60):
            R, t, lo, hi = _placement(rng, V, rng.uniform(0.001, 0.03))
            d = _fcl_distance(V, R, t, lo, hi)
            if not d > 0:
                continue
            lb = polytope_box_lower_bound_np(V, c, R, t, lo, hi)
            assert lb <= d + 1e-9, (name, lb, d)
            gaps.append(d - lb)
    gaps = np.array(gaps)
    assert len(gaps) > 150
    assert np.mean(gaps < 1e-4) >= 0.9, np.percentile(gaps, [50, 90, 99])


def test_never_above_sampled_distances():
    """Random polytopes and boxes, some overlapping: the bound never exceeds the distance from
    the box to any sampled point of the polytope (convex combinations of its vertices)."""
    rng = np.random.default_rng(4)
    for k in range(300):
        V = rng.normal(0, rng.uniform(0.005, 0.1), (int(rng.integers(1, 30)), 3))
        R = Rotation.random(random_state=k).as_matrix()
        t = rng.normal(0, 0.1, 3)
        lo = rng.uniform(-0.3, 0.3, 3)
        hi = lo + rng.uniform(0, 0.3, 3)
        lb = polytope_box_lower_bound_np(V, V.mean(0), R, t, lo, hi)
        w = rng.dirichlet(np.ones(len(V)) * 0.3, size=400)
        P = (w @ V) @ R.T + t
        P = np.concatenate([P, V @ R.T + t])
        gap = np.maximum(np.maximum(lo - P, P - hi), 0)
        assert lb <= np.sqrt((gap * gap).sum(1)).min() + 1e-12, k


def test_kernel_matches_reference():
    rng = np.random.default_rng(5)
    table = rng.normal(0, 0.05, (3, 64, 3))
    table[2, 20:] = table[2, 0]  # a padded row: repeated vertex
    parts = rng.integers(0, 3, 200)
    R = Rotation.random(200, random_state=1).as_matrix()
    t = rng.normal(0, 0.05, (200, 3))
    lo = rng.uniform(-0.3, 0.3, (200, 3))
    hi = lo + rng.uniform(0, 0.2, (200, 3))
    centre = table.mean(axis=1)
    with jax.enable_x64(True):
        f = jax.jit(jax.vmap(polytope_box_lower_bound, in_axes=(None, 0, 0, 0, 0, 0, 0)))
        out = np.asarray(f(jnp.asarray(table), parts, centre[parts], R, t, lo, hi))
    ref = np.array([polytope_box_lower_bound_np(table[p], centre[p], R[i], t[i], lo[i], hi[i])
                    for i, p in enumerate(parts)])
    # Where a bound is positive (the only case a decision can depend on) the two agree to
    # rounding; when the sets overlap both are <= 0 (the search paths may then differ).
    pos = np.maximum(out, ref) > 0
    assert pos.sum() > 100
    np.testing.assert_allclose(out[pos], ref[pos], rtol=0, atol=1e-9)
    assert (out[~pos] <= 0).all() and (ref[~pos] <= 0).all()


@pytest.mark.parametrize("case", ["inside", "touching_face", "single_point", "collinear", "flat_polytope",
                                  "flat_box", "far"])
def test_named_cases(case):
    I = np.eye(3)
    zero = np.zeros(3)
    cube = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float) * 0.1
    lo, hi = np.array([0.2, 0.0, 0.0]), np.array([0.3, 0.1, 0.1])
    if case == "inside":
        V, lo, hi, exact = cube * 0.1 + np.array([0.21, 0.01, 0.01]), lo, hi, 0.0
    elif case == "touching_face":
        V, lo, hi, exact = cube + np.array([0.1, 0, 0]), lo, hi, 0.0
    elif case == "single_point":
        V, exact = np.array([[0.0, 0.05, 0.05]]), 0.2
    elif case == "collinear":
        V, exact = np.array([[0.0, 0.0, 0.05], [0.1, 0.0, 0.05], [0.05, 0.0, 0.05]]), 0.1
    elif case == "flat_polytope":
        V, exact = cube[cube[:, 0] == 0] + np.array([0.15, 0, 0]), 0.05
    elif case == "flat_box":
        V, lo, hi, exact = cube, np.array([0.2, 0.05, 0.05]), np.array([0.2, 0.05, 0.05]), 0.1
    else:
        V, lo, hi, exact = cube, lo + 100.0, hi + 100.0, None
    for fn in (polytope_box_lower_bound_np, _kernel):
        lb = fn(V, V.mean(0), I, zero, lo, hi)
        assert math.isfinite(lb)
        if case == "inside":
            assert lb <= 0.0  # overlapping sets: no positive bound (its value is meaningless)
        elif exact is not None:
            assert lb <= exact + 1e-12 and lb >= exact - 1e-9, (case, lb)
        else:
            assert lb > 99.0


def test_rotation_and_translation_are_applied():
    V = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]])
    R = Rotation.from_euler("z", 90, degrees=True).as_matrix()  # the segment now points along +y
    lo, hi = np.array([-0.01, 0.3, -0.01]), np.array([0.01, 0.4, 0.01])
    for fn in (polytope_box_lower_bound_np, _kernel):
        # exact up to the tie term, 2 TIE v_max (v_max = 0.1 here; module docstring)
        assert fn(V, V.mean(0), R, np.array([0.0, 0.1, 0.0]), lo, hi) == pytest.approx(0.1, abs=1e-9)


def test_nan_gives_nan_and_float32_is_close():
    V = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]])
    lo, hi = np.array([0.3, -0.1, -0.1]), np.array([0.4, 0.1, 0.1])
    bad = np.array([np.nan, 0.0, 0.0])
    assert math.isnan(_kernel(V, V.mean(0), np.eye(3), bad, lo, hi))
    assert math.isnan(polytope_box_lower_bound_np(V, V.mean(0), np.eye(3), bad, lo, hi))
    assert _kernel(V, V.mean(0), np.eye(3), np.zeros(3), lo, hi, np.float32) == pytest.approx(0.2, abs=1e-6)


def _equations(jaxpr):
    """Every equation of a jaxpr, those of its sub-jaxprs (loop bodies, conditionals) included."""
    import jax.extend

    for eqn in jaxpr.eqns:
        yield eqn
        for value in eqn.params.values():
            for sub in value if isinstance(value, (list, tuple)) else (value,):
                if isinstance(sub, jax.extend.core.ClosedJaxpr):
                    yield from _equations(sub.jaxpr)
                elif isinstance(sub, jax.extend.core.Jaxpr):
                    yield from _equations(sub)


def test_every_product_is_ieee_in_float32():
    """The rounding bounds assume IEEE products; a float32 product on a GPU defaults to TF32 (a
    10-bit mantissa). Every product of the kernel (bound and search) and of forward kinematics
    asks for HIGHEST, checked on the traced program (no GPU needed)."""
    from larc_jax.model.robot import forward_kinematics
    from larc_jax.model.urdf import load_robot

    f32 = np.float32
    args = (np.zeros((2, 4, 3), f32), 0, np.zeros(3, f32), np.eye(3, dtype=f32), np.zeros(3, f32),
            np.zeros(3, f32), np.ones(3, f32))
    robot = jax.tree.map(lambda x: x.astype(f32) if isinstance(x, np.ndarray) and x.dtype == np.float64 else x,
                         load_robot())
    for jaxpr in (jax.make_jaxpr(polytope_box_lower_bound)(*args),
                  jax.make_jaxpr(lambda q: forward_kinematics(robot, q))(np.zeros(len(robot.active_joint_names), f32))):
        dots = [e for e in _equations(jaxpr.jaxpr) if e.primitive.name == "dot_general"]
        assert dots
        for e in dots:
            assert e.params["precision"] == (jax.lax.Precision.HIGHEST,) * 2, e


def test_first_max_picks_what_argmax_picks():
    """The support vertex by two plain reductions is ``jnp.argmax``'s, ties (equal scores, +0 and
    -0) included; NaN scores give no winner (the bound is then -inf, below)."""
    from larc_jax.obstacles.polytope import first_max

    rng = np.random.default_rng(3)
    rows = [rng.normal(size=691), rng.integers(-3, 4, 57).astype(float),  # many ties
            np.array([0.0, -0.0, -1.0]), np.array([-0.0, 0.0]), np.full(8, 2.5), np.array([-np.inf, -np.inf, 1.0])]
    with jax.enable_x64(True):
        for row in rows:
            k, found = jax.jit(first_max)(jnp.asarray(row))
            assert bool(found) and int(k) == int(jnp.argmax(jnp.asarray(row))) == int(np.argmax(row))
        batch = rng.integers(0, 5, (64, 40)).astype(float)
        k, found = jax.jit(jax.vmap(first_max))(jnp.asarray(batch))
        np.testing.assert_array_equal(np.asarray(k), batch.argmax(axis=1))
        assert np.asarray(found).all()
        k, found = jax.jit(first_max)(jnp.asarray([1.0, np.nan, 2.0]))
        assert not bool(found) and int(k) == 0


def test_no_winner_gives_no_bound(monkeypatch):
    """Where the support search finds no vertex scoring the maximum (NaN scores, or XLA computing the
    scores twice with different roundings), the kernel gives -inf (no bound), never a bound from an
    arbitrary vertex; non-finite input still gives NaN."""
    import larc_jax.obstacles.polytope as polytope

    V = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]])
    lo, hi = np.array([0.3, -0.1, -0.1]), np.array([0.4, 0.1, 0.1])

    def bound(t):  # traced anew on every call (a new function), so the patch below is seen
        with jax.enable_x64(True):
            fn = jax.jit(lambda *a: polytope_box_lower_bound(*a))
            return float(fn(jnp.asarray(V[None]), 0, *(jnp.asarray(x) for x in (V.mean(0), np.eye(3), t, lo, hi))))

    assert bound(np.zeros(3)) == pytest.approx(0.2, abs=1e-9)  # up to the tie term, 2 TIE v_max
    monkeypatch.setattr(polytope, "first_max", lambda scores, tol=0.0: (jnp.zeros((), jnp.int32), jnp.asarray(False)))
    assert bound(np.zeros(3)) == -math.inf
    assert math.isnan(bound(np.array([np.nan, 0.0, 0.0])))


def test_one_path_upper_bound_and_lower_bounds_below_it(link_hulls):
    """After every number of steps the kernel and its NumPy reference give the same lower bound and
    the same upper bound (:func:`polytope_box_bounds`; they take the same path: module docstring,
    "One path"), and no lower bound, at any number of steps, exceeds any upper bound: a pair
    stopped because its upper bound is below a threshold could not have passed it. The upper bound
    is never below python-fcl's distance of the hull mesh less FCL's own tolerance (its GJK stops
    within about 1e-6 m, above the true distance)."""
    from larc_jax.obstacles.polytope import GJK_ITERATIONS, polytope_box_bounds, polytope_box_bounds_np

    rng = np.random.default_rng(8)
    kernel = jax.jit(polytope_box_bounds, static_argnames="iterations")
    checked = 0
    for name, V in link_hulls.items():
        c = (V.min(0) + V.max(0)) / 2
        for n in range(25):
            R, t, lo, hi = _placement(rng, V, rng.uniform(-0.01, 0.03))  # some overlap
            d = _fcl_distance(V, R, t, lo, hi)
            lbs, ubs = [], []
            for steps in (*range(GJK_ITERATIONS + 1), 2 * GJK_ITERATIONS):
                lb, ub = polytope_box_bounds_np(V, c, R, t, lo, hi, steps)
                assert lb == polytope_box_lower_bound_np(V, c, R, t, lo, hi, steps)
                assert ub >= max(d, 0.0) - 1e-5, (name, n, steps, ub, d)
                with jax.enable_x64(True):
                    out = kernel(jnp.asarray(V[None]), 0, *(jnp.asarray(x) for x in (c, R, t, lo, hi)), iterations=steps)
                np.testing.assert_allclose([float(out[0]), float(out[1])], [lb, ub], rtol=1e-9, atol=1e-12)
                lbs.append(lb)
                ubs.append(ub)
                checked += 1
            assert max(lbs) <= min(ubs) + 1e-12, (name, n, max(lbs), min(ubs))
    assert checked == 14 * 25 * len(link_hulls)


@pytest.mark.parametrize("case", ["inside", "first_axis", "nan"])
def test_upper_bound_named_cases(case):
    """Named cases of the upper bound: a box holding the polytope gives 0 (the simplex holds the
    origin) or less than the box's reach; with no step it is the first support point's norm; NaN
    input gives NaN for both bounds (never stops a search early on NaN: ``NaN <= x`` is false)."""
    from larc_jax.obstacles.polytope import polytope_box_bounds_np

    V = np.array([[0.0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1]])
    c, R, t = V.mean(0), np.eye(3), np.zeros(3)
    if case == "inside":
        lb, ub = polytope_box_bounds_np(V, c, R, t, -np.ones(3), np.ones(3))
        assert lb <= 0 and ub <= 1e-12
    elif case == "first_axis":
        lo, hi = np.array([1.0, -1, -1]), np.array([2.0, 1, 1])
        lb, ub = polytope_box_bounds_np(V, c, R, t, lo, hi, 0)
        assert lb <= 0.9 <= ub and math.isfinite(ub)
    else:
        lb, ub = polytope_box_bounds_np(V, c, R, t, np.array([np.nan, 0, 0]), np.ones(3))
        assert math.isnan(lb) and math.isnan(ub)
