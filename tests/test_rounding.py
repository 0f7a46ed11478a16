"""The floating-point error budget of larc_jax.leaf.interval: time rounding (false-safe at large start
times), every bound of the budget against measured errors, and exact soundness checks of
certified leaves (rational curve evaluation between floats, exact distances)."""

from __future__ import annotations

import math
from fractions import Fraction as F

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from larc_jax import Scene, Trajectory, certify
from larc_jax.enclosure import capsule_segments, capsule_segments_np
from larc_jax.obstacles.geometry import segment_box_distance
from larc_jax.model.hermite import HermiteSpline, evaluate, speed_max
from larc_jax.leaf.interval import (K_DIST_ABS, K_DIST_REL, K_FK, K_POS, K_SPEED, K_TIME, ROUNDING_CHUNK, rebase_ends,
                                   time_offset, time_offsets, trajectory_rounding, trajectory_roundings)
from larc_jax.errors import LarcInputError
from larc_jax.model.robot import JointType

from .exact import (accel_max_exact, hermite_exact, leaf_min_clearance, min_clearance, segment_box_sq_distance_exact,
                    speed_max_exact)

MARGIN = 0.01
U64 = np.finfo(np.float64).eps / 2
U32 = float(np.finfo(np.float32).eps) / 2
CAPSULES = dict(enclosure="capsules")
"""The checks below measure the capsules (the cascade's hulls are tighter: tests/test_cascade.py)."""


def box_ahead(robot, capsules, q_from, q_to, clearance, half=0.05):
    """An axis-aligned box ahead of the fastest-moving capsule end between two configurations,
    shifted so that the capsules at ``q_to`` have exactly ``clearance`` (dist - r) to it."""
    pa0, pb0 = capsule_segments_np(robot, capsules, q_from)
    pa1, pb1 = capsule_segments_np(robot, capsules, q_to)
    moves = np.concatenate([pa1 - pa0, pb1 - pb0])
    k = int(np.argmax(np.linalg.norm(moves, axis=1)))
    axis = int(np.argmax(np.abs(moves[k])))
    e = np.zeros(3)
    e[axis] = 1.0 if moves[k, axis] >= 0 else -1.0
    centre = np.concatenate([pa1, pb1])[k] + e * (half + 0.5)
    for _ in range(30):  # slide the box along e until the clearance is the one asked for
        scene = Scene(lo=(centre - half)[None], hi=(centre + half)[None], box_names=("box",))
        gap = min_clearance(robot, capsules, scene, q_to) - clearance
        if abs(gap) < 1e-9:
            break
        centre = centre - e * gap
    return scene


# ----------------------------------------------------------------------------------------------
# Time (budget T1-T5)
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("t0", [2.0**40, 2.1e9, 1.7e9 + 0.123])
def test_false_safe_at_large_start_time(robot, capsules, t0):
    """A move of one float spacing (0.24 ms at 2^40 s, 0.24 us at 2.1e9 s): t_m = (a + b) / 2
    rounds onto a, and an inflation of (b - a) / 2 around q(a) misses the last waypoint, which
    is inside rho (by 1 mm at 2^40 s, scaled with the spacing). Main certified these with one
    evaluation; the covering radius (T4) must not."""
    q0 = np.array([-0.018, 2.434, -2.661, 0.486, 0.522, -0.871])
    v = np.zeros(6)
    v[1] = 1000.0  # rad/s: the extreme of the class
    dt = float(np.spacing(t0))
    t = np.array([t0, t0 + dt])
    q1 = q0 + v * (t[1] - t[0])
    traj = Trajectory(t=t, q=np.stack([q0, q1]), qd=np.stack([v, v]), joint_names=robot.active_joint_names,
                      id="epoch")
    scene = box_ahead(robot, capsules, q0, q1, MARGIN - 0.001 * dt / 2.0**-12)
    end = min_clearance(robot, capsules, scene, [float(x) for x in hermite_exact(t, traj.q, traj.qd, t[1])])
    assert end < MARGIN  # the last waypoint violates the margin
    for method in ("larc", "reference"):
        res = certify(traj, scene, robot, capsules, method=method, margin=MARGIN, max_depth=4, **CAPSULES)[0]
        assert not res.certified, (method, res.evaluations, res.min_clearance_m)
        for leaf in res.leaves:
            if leaf.certified:
                assert leaf_min_clearance(robot, capsules, traj, scene, leaf.t0, leaf.t1, 8) > MARGIN


def test_time_offset_and_rebase_are_exact():
    for t in ([2.0**40, 2.0**40 + 2**-12, 2.0**40 + 1.0], [1.7e9 + 0.123, 1.7e9 + 0.623, 1.7e9 + 3.5],
              [0.1, 10.3, 20.7], [-5.0, 1e-17, 3.0], [0.0, 1.0]):
        t = np.array(t)
        o = time_offset(t)
        if o != 0.0:
            assert all(F(float(x - o)) == F(float(x)) - F(o) for x in t)
        rng = np.random.default_rng(0)
        a = np.sort(rng.uniform(t[0], t[-1], 50))
        b = np.minimum(a + rng.uniform(0, t[-1] - t[0], 50), t[-1])
        ar, br = rebase_ends(a, b, o)
        for x, y, xr, yr in zip(a, b, ar, br):
            assert F(float(xr)) <= F(float(x)) - F(o) and F(float(yr)) >= F(float(y)) - F(o)
            assert xr >= t[0] - o and yr <= t[-1] - o
    assert time_offset(np.array([0.1, 10.3])) == 0.0  # 10.3 - 0.1 is not exact: times used as given
    assert time_offset(np.array([2.1e9, 2.1e9 + 5.0])) == 2.1e9  # Sterbenz


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_roundings_together_are_each_alone(robot, capsules, dtype):
    """trajectory_roundings of trajectories of many lengths (more than one chunk, padded to the
    longest in each) gives each one's trajectory_rounding, alone, bit for bit; the offset is
    time_offset's and the horizon the rebased first and last knots."""
    rng = np.random.default_rng(23)
    n = len(robot.active_joint_names)
    trajs = []
    for k in range(2 * ROUNDING_CHUNK + 3):
        m = int(rng.integers(2, 40))
        t = np.cumsum(rng.uniform(0.01, 1.0, m)) + [0.0, 1.7e9 + 0.125, -3.3, 1e-9, 2.0**40][k % 5]
        q = rng.normal(size=(m, n)) * 10.0 ** rng.uniform(-3, 1)
        qd = rng.normal(size=(m, n)) * 10.0 ** rng.uniform(-3, 2)
        trajs.append(Trajectory(t=t, q=q, qd=qd, joint_names=robot.active_joint_names, id=f"r{k}"))
    together = trajectory_roundings(trajs, robot, capsules, dtype)
    assert len(together) == len(trajs)
    for traj, got in zip(trajs, together):
        want = trajectory_rounding(traj, robot, capsules, dtype)
        for field in ("offset_s", "t_start", "t_end", "tau_s", "omega_slack", "accel_slack", "guard_m",
                      "hull_guard_m"):
            a, b = np.asarray(getattr(got, field)), np.asarray(getattr(want, field))
            assert a.shape == b.shape and a.dtype == b.dtype and np.array_equal(a, b), (traj.id, field)
        o = time_offset(traj.t)
        assert float(got.offset_s) == o and float(got.t_start) == traj.t[0] - o and float(got.t_end) == traj.t[-1] - o
    # The speed slack of a trajectory alone, from its own formula (P2): the padding masked out.
    traj = trajs[0]
    h = np.diff(traj.t - float(together[0].offset_s))[:, None]
    v = np.abs(traj.qd)
    V = (v[:-1] + v[1:] + 1.5 * (np.abs(np.diff(traj.q, axis=0)) / h)).max(axis=0)
    np.testing.assert_array_equal(together[0].omega_slack, K_SPEED * U64 * V)


def test_roundings_refuse_a_trajectory_without_a_segment(robot, capsules):
    """A trajectory of one knot (only a duck-typed object gets one past validation) has no
    segment: its maxima would be -inf and its guards negative, so it is refused, by index."""
    n = len(robot.active_joint_names)
    one = type("OneKnot", (), {"t": np.zeros(1), "q": np.zeros((1, n)), "qd": np.zeros((1, n))})()
    two = Trajectory(t=np.array([0.0, 1.0]), q=np.zeros((2, n)), qd=np.zeros((2, n)),
                     joint_names=robot.active_joint_names, id="two")
    with pytest.raises(LarcInputError, match="trajectory 1 has 1 knot"):
        trajectory_roundings([two, one], robot, capsules)


def test_time_offsets_are_time_offset_row_by_row():
    """The batch rule of the rebase offset (T1) is the one-trajectory rule on each row."""
    rng = np.random.default_rng(5)
    t = np.cumsum(rng.uniform(1e-3, 1.0, (40, 9)), axis=1) + rng.choice([0.0, 0.1, 1.7e9 + 0.3, 2.0**52, -7.7], (40, 1))
    np.testing.assert_array_equal(time_offsets(t), [time_offset(row) for row in t])
    assert np.any(time_offsets(t) == 0.0) and np.any(time_offsets(t) != 0.0)


def test_evaluation_time_error_is_within_tau(robot, capsules):
    """T3: the time the curve is really evaluated at, t' = t_k + s H_k, is within 6u T of t_m,
    and tau = K_TIME u T covers it; the speed query [a - tau, b + tau] contains [a, b] (T5)."""
    rng = np.random.default_rng(3)
    worst = 0.0
    for _ in range(300):
        T = 10.0 ** rng.uniform(-3, 4)
        t = np.sort(np.r_[0.0, rng.uniform(0, T, 4), T])
        t = np.unique(t)
        tm = rng.uniform(t[0], t[-1])
        k = int(np.searchsorted(t, tm, side="right") - 1)
        k = min(k, len(t) - 2)
        s = (tm - t[k]) / (t[k + 1] - t[k])  # what hermite.evaluate computes
        t_eff = F(float(t[k])) + F(float(s)) * (F(float(t[k + 1])) - F(float(t[k])))
        worst = max(worst, float(abs(t_eff - F(tm))) / (U64 * max(abs(t[0]), abs(t[-1]))))
    assert worst <= 6 and K_TIME >= 16 and worst > 0


# ----------------------------------------------------------------------------------------------
# Curve values (P1, P2) against exact rational evaluation
# ----------------------------------------------------------------------------------------------


def _random_curve(rng, K, n, speed):
    T = 10.0 ** rng.uniform(-3, 4)
    t = np.unique(np.sort(np.r_[0.0, rng.uniform(0, T, K - 1), T]))
    q = rng.uniform(-3, 3, (len(t), n))
    v = rng.normal(0, speed, (len(t), n))
    return t, q, v


def test_position_and_speed_errors_are_within_budget():
    rng = np.random.default_rng(4)
    worst_q = worst_w = 0.0
    with jax.enable_x64(True):
        ev = jax.jit(evaluate)
        sm = jax.jit(speed_max)
        for case in range(60):
            t, q, v = _random_curve(rng, int(rng.integers(1, 6)), 3, 10.0 ** rng.uniform(-1, 3))
            sp = HermiteSpline.from_waypoints(t, q, v)
            H = np.diff(t)[:, None]
            Q = (np.abs(q[:-1]) + np.abs(q[1:]) + H * (np.abs(v[:-1]) + np.abs(v[1:]))).max(axis=0)
            V = (np.abs(v[:-1]) + np.abs(v[1:]) + 1.5 * np.abs(np.diff(q, axis=0)) / H).max(axis=0)
            for tm in rng.uniform(t[0], t[-1], 5):
                got = np.asarray(ev(sp, tm)[0])
                k = min(int(np.searchsorted(t, tm, side="right") - 1), len(t) - 2)
                s = (tm - t[k]) / (t[k + 1] - t[k])
                t_eff = F(float(t[k])) + F(float(s)) * (F(float(t[k + 1])) - F(float(t[k])))
                want = hermite_exact(t, q, v, t_eff)  # the curve at the time really evaluated
                err = np.array([float(abs(F(float(g)) - w)) for g, w in zip(got, want)])
                worst_q = max(worst_q, float((err / (U64 * Q)).max()))
            for _ in range(3):
                a, b = np.sort(rng.uniform(t[0], t[-1], 2))
                got = np.asarray(sm(sp, a, b))
                want = speed_max_exact(t, q, v, a, b)
                under = np.array([float(w - F(float(g))) for g, w in zip(got, want)])
                worst_w = max(worst_w, float((under / (U64 * V)).max()))
    assert worst_q * 8 <= K_POS, worst_q  # measured error well inside the budget
    assert worst_w * 8 <= K_SPEED, worst_w


def test_acceleration_maxima_error_is_within_budget():
    """P2' (larc_jax.leaf.interval): accel_max never falls below the exact rational maximum of
    |qddot_j| by more than a small fraction of accel_slack = K_SPEED u A_j, over curves whose
    times span 1 ms to 10^4 s and whose speeds span 0.1 to 1000."""
    from larc_jax.model.hermite import accel_max

    rng = np.random.default_rng(6)
    worst = 0.0
    with jax.enable_x64(True):
        am = jax.jit(accel_max)
        for case in range(60):
            t, q, v = _random_curve(rng, int(rng.integers(1, 6)), 3, 10.0 ** rng.uniform(-1, 3))
            sp = HermiteSpline.from_waypoints(t, q, v)
            H = np.diff(t)[:, None]
            A = ((4 * np.abs(v[:-1]) + 4 * np.abs(v[1:]) + 6 * np.abs(np.diff(q, axis=0)) / H) / H).max(axis=0)
            for _ in range(3):
                a, b = np.sort(rng.uniform(t[0], t[-1], 2))
                if not a < b:
                    continue
                got = np.asarray(am(sp, a, b))
                want = accel_max_exact(t, q, v, a, b)
                under = np.array([float(w - F(float(g))) for g, w in zip(got, want)])
                worst = max(worst, float((under / (U64 * A)).max()))
    assert worst * 8 <= K_SPEED, worst


# ----------------------------------------------------------------------------------------------
# Geometry (G1, G2): placement and distance, float64 and float32
# ----------------------------------------------------------------------------------------------


def _fk_longdouble(robot, capsules, q):
    """Capsule segment ends with numpy.longdouble arithmetic (x87 80-bit on x86-64)."""
    ld = np.longdouble
    T_pj = np.asarray(robot.T_parent_joint).astype(ld)
    axis = np.asarray(robot.axis).astype(ld)
    held = np.asarray(robot.q_held).astype(ld)
    out = [np.eye(4, dtype=ld)]
    for i in range(1, robot.n_links):
        k = robot.q_index[i]
        val = ld(q[k]) if k >= 0 else held[i]
        M = np.eye(4, dtype=ld)
        if robot.joint_type[i] == JointType.REVOLUTE:
            x, y, z = axis[i]
            Kx = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]], dtype=ld)
            M[:3, :3] = np.eye(3, dtype=ld) + np.sin(val) * Kx + (1 - np.cos(val)) * (Kx @ Kx)
        elif robot.joint_type[i] == JointType.PRISMATIC:
            M[:3, 3] = axis[i] * val
        out.append(out[robot.parent[i]] @ T_pj[i] @ M)
    a = np.array([out[li][:3, :3] @ np.asarray(capsules.p_link_a[c]).astype(ld) + out[li][:3, 3]
                  for c, li in enumerate(capsules.link_index)])
    b = np.array([out[li][:3, :3] @ np.asarray(capsules.p_link_b[c]).astype(ld) + out[li][:3, 3]
                  for c, li in enumerate(capsules.link_index)])
    return a, b


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_placement_error_is_within_budget(robot, capsules, dtype):
    if np.finfo(np.longdouble).eps >= np.finfo(np.float64).eps:
        pytest.skip("no extended precision on this platform")
    ug = float(np.finfo(dtype).eps) / 2
    rng = np.random.default_rng(5)
    zero = np.zeros((1, robot.n_joints + 1))
    traj = Trajectory(t=np.array([0.0, 1.0]), q=zero[:, :-1].repeat(2, 0), qd=zero[:, :-1].repeat(2, 0),
                      joint_names=robot.active_joint_names)
    guard = trajectory_rounding(traj, robot, capsules, dtype).guard_m  # no curve error at rest
    cast = lambda x: np.asarray(x, dtype) if np.issubdtype(np.asarray(x).dtype, np.floating) else x  # noqa: E731
    robot_g = jax.tree.map(cast, robot)
    caps_g = jax.tree.map(cast, capsules)
    worst = 0.0
    with jax.enable_x64(True):
        place = jax.jit(capsule_segments)
        for _ in range(200):
            q = rng.uniform(-1, 1, robot.n_joints) * 10.0 ** rng.uniform(0, 3)  # angles up to 1000 rad
            a, b = (np.asarray(x).astype(np.longdouble) for x in place(robot_g, caps_g, np.asarray(q, dtype)))
            # the exact placement at the configuration the kernel really used (q rounded to dtype)
            ea, eb = _fk_longdouble(robot, capsules, np.asarray(q, dtype).astype(np.float64))
            err = np.maximum(np.linalg.norm(a - ea, axis=1), np.linalg.norm(b - eb, axis=1)).astype(np.float64)
            worst = max(worst, float((err / guard).max()))
    assert worst < 0.25, worst
    assert K_FK * ug > 0


def _random_segment_box(rng, far):
    p0 = rng.uniform(-0.8, 0.8, 3)
    p1 = p0 + rng.normal(0, 0.2, 3) * (rng.random() < 0.9)
    if far == "far":
        c = rng.normal(size=3)
        c *= 10.0 ** rng.uniform(2, 6) / np.linalg.norm(c)
        half = rng.uniform(0.01, 10.0, 3)
    elif far == "huge":  # a floor slab reaching far beyond the arm, close to it
        c = np.array([0.0, 0.0, rng.uniform(-1.0, -0.0)])
        half = np.array([10.0 ** rng.uniform(3, 6), 10.0 ** rng.uniform(3, 6), rng.uniform(0.001, 0.5)])
        c[2] -= half[2]
    else:
        c = rng.uniform(-0.8, 0.8, 3)
        half = rng.uniform(0.0, 0.2, 3)
    return p0, p1, c - half, c + half


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("kind", ["near", "far", "huge"])
def test_distance_error_is_within_budget(dtype, kind):
    """G2: computed <= (1 + 16 u) dist + 32 u (|p0| + |p1|), whatever the box's size or distance;
    the kernel removes K_DIST_REL eps relative and the guard holds K_DIST_ABS u per metre."""
    ug = float(np.finfo(dtype).eps) / 2
    rng = np.random.default_rng({"near": 1, "far": 2, "huge": 3}[kind])
    worst = 0.0
    with jax.enable_x64(True):
        dist = jax.jit(segment_box_distance)
        for _ in range(300):
            p0, p1, lo, hi = (np.asarray(x, dtype) for x in _random_segment_box(rng, kind))
            got = F(float(dist(p0, p1, lo, hi)))
            exact_sq = segment_box_sq_distance_exact(p0, p1, lo, hi)
            scale = float(np.linalg.norm(p0.astype(float)) + np.linalg.norm(p1.astype(float)))
            exact = math.sqrt(float(exact_sq))  # float64 sqrt of the exact square: relative 1e-16
            allowed = 16 * ug * exact + 32 * ug * scale
            over = float(got) - exact
            worst = max(worst, over / allowed)
    assert worst <= 0.5, worst
    assert K_DIST_REL * 2 >= 32 and K_DIST_ABS >= 32


def test_xla_sin_cos_accurate_for_large_arguments():
    """G1 assumes sin/cos accurate to 2 ulp for every finite argument (XLA's CPU kernels do full
    range reduction; CUDA's libdevice documents it)."""
    rng = np.random.default_rng(6)
    with jax.enable_x64(True):
        for dtype in (np.float32, np.float64):
            x = (rng.uniform(-1, 1, 4000) * 10.0 ** rng.uniform(0, 9, 4000)).astype(dtype)
            s = np.asarray(jax.jit(jnp.sin)(x)).astype(np.longdouble)
            c = np.asarray(jax.jit(jnp.cos)(x)).astype(np.longdouble)
            xs = x.astype(np.longdouble)
            eps = float(np.finfo(dtype).eps)
            assert float(np.abs(s - np.sin(xs)).max()) <= 2 * eps
            assert float(np.abs(c - np.cos(xs)).max()) <= 2 * eps


# ----------------------------------------------------------------------------------------------
# Property: a passed leaf keeps every capsule point more than rho from every box (exactly)
# ----------------------------------------------------------------------------------------------


@st.composite
def timed_trajectories(draw):
    """(offset, duration, speed, steady, box_at_end, seed): the issue's ranges, with durations of
    a few float spacings of the offset too (where the midpoint rounds onto an end)."""
    offset = draw(st.one_of(st.sampled_from([0.0, 2.1e9, 2.0**40, 2.0**40, 1.7e9 + 0.37]), st.floats(1.0, 2.0**40)))
    if draw(st.booleans()):
        duration = 10.0 ** draw(st.floats(-3.0, 4.0))
    else:
        duration = draw(st.integers(1, 4)) * float(np.spacing(offset))
    speed = 10.0 ** draw(st.floats(-1.0, 3.0))  # rad/s: the limits (1 rad/s) and far beyond
    steady, at_end = draw(st.sampled_from([(True, True), (True, True), (True, False), (False, True), (False, False)]))
    return offset, duration, speed, steady, at_end, draw(st.integers(0, 2**32 - 1))


def _make_case(robot, capsules, offset, duration, speed, steady, box_at_end, seed):
    rng = np.random.default_rng(seed)
    n_seg = int(rng.integers(1, 4))
    t = np.unique(offset + duration * np.sort(np.r_[0.0, rng.uniform(0.1, 0.9, n_seg - 1), 1.0]))
    if len(t) < 2:
        t = np.array([offset, offset + np.spacing(offset)])
    T = t[-1] - t[0]
    lo, hi = np.asarray(robot.q_lower), np.asarray(robot.q_upper)
    q = lo + (hi - lo) * rng.uniform(0.1, 0.9, (len(t), robot.n_joints))
    if steady:  # one joint at constant speed (as far as the limits allow); the others still
        v = np.zeros(robot.n_joints)
        v[rng.integers(robot.n_joints)] = speed * rng.choice([-1.0, 1.0])
        step = np.clip(v * T, lo - q[0] + 0.01, hi - q[0] - 0.01)
        q = q[0] + (t - t[0])[:, None] / T * step
        qd = np.tile(step / T, (len(t), 1))
    else:
        qd = rng.normal(0, speed, q.shape)
    traj = Trajectory(t=t, q=q, qd=qd, joint_names=robot.active_joint_names, id="prop")
    # A box grazing the motion: ahead of the fastest capsule end, at the last waypoint or at a
    # random time, with clearance rho - 3 mm .. rho + 4 mm there.
    t0, t1 = F(float(t[0])), F(float(t[-1]))
    tb = t1 if box_at_end else t0 + (t1 - t0) * F(int(rng.integers(0, 33)), 32)
    qb = np.array([float(x) for x in hermite_exact(t, q, qd, tb)])
    q_prev = np.array([float(x) for x in hermite_exact(t, q, qd, max(t0, tb - (t1 - t0) / 4))])
    if np.abs(qb - q_prev).max() < 1e-9:
        q_prev = qb - 0.05
    pa0, pb0 = capsule_segments_np(robot, capsules, q_prev)
    pa1, pb1 = capsule_segments_np(robot, capsules, qb)
    travel = float(np.linalg.norm(np.concatenate([pa1 - pa0, pb1 - pb0]), axis=1).max())
    delta = float(np.clip(rng.uniform(-0.1, 0.1) * travel, -0.003, 0.004))
    return traj, box_ahead(robot, capsules, q_prev, qb, MARGIN + delta)


@pytest.mark.slow
@settings(max_examples=60, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow,
          HealthCheck.function_scoped_fixture])
@given(case=timed_trajectories())
def test_passed_leaves_keep_the_margin_exactly(robot, capsules, case):
    """Start offsets 0 .. 2^40 s, durations 1 ms .. 1e4 s (and a few float spacings), speeds
    0.1 .. 1000 rad/s, a box grazing the motion: every passed leaf, checked at its ends and 7 rational times inside with the
    exact curve, keeps every capsule more than rho from the box."""
    traj, scene = _make_case(robot, capsules, *case)
    res = certify(traj, scene, robot, capsules, margin=MARGIN, **CAPSULES)[0]
    passed = [leaf for leaf in res.leaves if leaf.certified]
    # The leaves closest to the box first; at most 40 leaves are checked densely.
    passed.sort(key=lambda leaf: leaf.clearance_m)
    for leaf in passed[:40]:
        assert leaf_min_clearance(robot, capsules, traj, scene, leaf.t0, leaf.t1, 8) > MARGIN, (case, leaf)
    for leaf in passed[40:]:
        ends = [min_clearance(robot, capsules, scene, [float(x) for x in hermite_exact(traj.t, traj.q, traj.qd, t)])
                for t in (leaf.t0, leaf.t1)]
        assert min(ends) > MARGIN, (case, leaf)


# ----------------------------------------------------------------------------------------------
# One scene must not change another's result (the guard depends only on what a test touches)
# ----------------------------------------------------------------------------------------------


def _leaf_tuples(result):
    return [[(x.depth, x.index, x.t0, x.t1, x.clearance_m, x.guard_m, x.certified, x.capsule, x.box)
             for x in r.leaves] for r in result]


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_far_box_in_another_scene_changes_nothing(robot, capsules, dtype):
    """A scene with a box 1e4 m away (and a 1e5 m floor slab) certified in the same call must
    leave every other trajectory's certificate bit for bit unchanged; main computed one guard
    from the largest coordinate of all scenes (float32: 4.9 m, nothing certified)."""
    from .test_certify import random_scene, random_trajectory

    rng = np.random.default_rng(77)
    trajs = [random_trajectory(rng, robot, k) for k in range(40)]
    scenes = [random_scene(rng, k) for k in range(40)]
    far = Scene(lo=np.array([[1e4, 1e4, 0.0], [-1e5, -1e5, -1.0]]), hi=np.array([[1e4 + 1, 1e4 + 1, 1.0], [1e5, 1e5, -0.3]]),
                box_names=("far", "slab"))
    kw = dict(margin=MARGIN, max_depth=4)
    alone = certify(trajs, scenes, robot, capsules, dtype=dtype, **kw)
    both = certify(trajs + trajs[:1], scenes + [far], robot, capsules, dtype=dtype, **kw)
    assert _leaf_tuples(alone) == _leaf_tuples(both)[:40]
    n64 = sum(r.certified for r in certify(trajs, scenes, robot, capsules, **kw)) if dtype == np.float32 else None
    if n64 is not None:
        assert sum(r.certified for r in alone) >= n64 - 2  # float32 geometry certifies (nearly) as much
    assert both[40].certified  # the far scene itself: the slab is 0.3 m below the base


def test_far_box_in_the_same_scene_affects_only_its_own_pairs(robot, capsules):
    from .test_certify import random_trajectory

    rng = np.random.default_rng(78)
    trajs = [random_trajectory(rng, robot, k) for k in range(6)]
    near = Scene(lo=np.array([[0.3, -0.2, 0.0]]), hi=np.array([[0.5, 0.2, 0.3]]), box_names=("near",))
    with_far = Scene(lo=np.array([[0.3, -0.2, 0.0], [1e4, 0.0, 0.0]]), hi=np.array([[0.5, 0.2, 0.3], [1e4 + 1, 1.0, 1.0]]),
                     box_names=("near", "far"))
    for method, dtype in (("reference", np.float64), ("larc", np.float32)):
        a = certify(trajs, near, robot, capsules, method=method, dtype=dtype, margin=MARGIN, max_depth=3)
        b = certify(trajs, with_far, robot, capsules, method=method, dtype=dtype, margin=MARGIN, max_depth=3)
        assert [r.guard_m for r in a] == [r.guard_m for r in b]
        for ra, rb in zip(_leaf_tuples(a), _leaf_tuples(b)):
            # Same leaves, decisions, pairs and guards; the clearances may differ in the last bit
            # (XLA compiles another shape), far below the guard.
            assert [x[:4] + x[5:] for x in ra] == [x[:4] + x[5:] for x in rb]
            assert all(abs(x[4] - y[4]) <= max(1e-15, 1e-6 * x[5]) for x, y in zip(ra, rb))
