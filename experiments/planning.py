"""Planning, time parameterisation and recording of one Stage B attempt (see
:mod:`experiments.generate` for the protocol): OMPL RRTConnect with a validity-check budget, path
simplification and MoveIt-style interpolation; TOPP-RA timing; the recorded waypoints; the
Hermite recheck grid; and the direct smoothstep control.

Every function takes the scene's context ``ctx`` (:class:`experiments.generate.SceneContext`:
the validity checker, the limits, the protocol's ``generation`` values).
"""

from __future__ import annotations

import logging
import math

import numpy as np

__all__ = ["plan_path", "time_parameterise", "record", "round_ns", "hermite_states", "smoothstep_trajectory"]


def plan_path(ctx, start, goal, ompl_seed: int):
    """OMPL RRTConnect + simplifyMax + MoveIt interpolation → ((S, n) states or None, info)."""
    from ompl import base as ob
    from ompl import geometric as og
    from ompl import util as ou

    gen = ctx.gen
    n = ctx.robot.n_joints
    ou.setLogLevel(ou.LogLevel.LOG_NONE)  # also hides "seed changed after RNG use" (harmless:
    # every RNG of this attempt is created after the reseed, so sampling is deterministic)
    ou.RNG.setSeed(int(ompl_seed))
    space = ob.RealVectorStateSpace(n)
    bounds = ob.RealVectorBounds(n)
    for i in range(n):
        bounds.setLow(i, float(ctx.limits["lo"][i]))
        bounds.setHigh(i, float(ctx.limits["hi"][i]))
    space.setBounds(bounds)
    si = ob.SpaceInformation(space)
    counter = [0]
    buf = np.empty(n)

    def is_valid(state) -> bool:
        counter[0] += 1
        for i in range(n):
            buf[i] = state[i]
        return ctx.valid(buf)

    si.setStateValidityChecker(is_valid)
    si.setStateValidityCheckingResolution(float(gen["state_validity_resolution"]))
    si.setup()
    s = space.allocState()
    g = space.allocState()
    for i in range(n):
        s[i] = float(start[i])
        g[i] = float(goal[i])
    pdef = ob.ProblemDefinition(si)
    pdef.setStartAndGoalStates(s, g)
    planner = og.RRTConnect(si)
    planner.setProblemDefinition(pdef)
    planner.setup()
    max_checks = int(gen["planner_max_validity_checks"])
    # The only limit is a count (evaluated synchronously by the planner between steps), so the
    # outcome does not depend on the machine's speed or load.
    ptc = ob.PlannerTerminationCondition(lambda: counter[0] >= max_checks)
    planner.solve(ptc)
    info = {"planner_checks": counter[0]}
    if not pdef.hasExactSolution():
        info["detail"] = "planner_check_budget"
        return None, info
    path = pdef.getSolutionPath()
    og.PathSimplifier(si).simplifyMax(path)
    seg = ctx.extent / 100.0  # MoveIt: max_solution_segment_length = extent / 100
    count = max(int(gen.get("minimum_waypoint_count", 10)), int(math.floor(0.5 + path.length() / seg)))
    path.interpolate(count)
    states = np.array([[path.getState(k)[i] for i in range(n)] for k in range(path.getStateCount())])
    info["path_length_rad"] = float(path.length())
    return states, info


def _dedupe(states: np.ndarray) -> np.ndarray:
    keep = [0]
    for k in range(1, len(states)):
        if np.linalg.norm(states[k] - states[keep[-1]]) > 1e-9:
            keep.append(k)
    return states[keep]


def _time_of_s(jnt, s_values: np.ndarray) -> np.ndarray:
    """Invert TOPP-RA's piecewise-constant-acceleration s(t) at path positions ``s_values``."""
    ss, ts, vs, us = jnt._ss, jnt._ts, jnt._velocities, jnt._us
    out = np.empty(len(s_values))
    for k, s in enumerate(s_values):
        i = int(np.clip(np.searchsorted(ss, s, side="right") - 1, 0, len(us) - 1))
        ds = max(0.0, float(s - ss[i]))
        v, u = float(vs[i]), float(us[i])
        if abs(u) < 1e-12:
            dt = ds / v if v > 0 else 0.0
        else:
            disc = max(0.0, v * v + 2.0 * u * ds)
            dt = (-v + math.sqrt(disc)) / u
        out[k] = float(np.clip(ts[i] + dt, ts[i], ts[i + 1]))
    return out


def time_parameterise(ctx, states: np.ndarray):
    """TOPP-RA over the (deduplicated) path states → (jnt, t at each state, states); jnt and t
    are None when TOPP-RA fails."""
    import toppra as ta
    import toppra.algorithm as algo
    import toppra.constraint as constraint

    logging.getLogger("toppra").setLevel(logging.ERROR)
    states = _dedupe(states)
    if len(states) < 2:
        return None, None, states
    ss = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(states, axis=0), axis=1))])
    path = ta.SplineInterpolator(ss, states)
    pc_vel = constraint.JointVelocityConstraint(np.stack([-ctx.vlim, ctx.vlim], axis=1))
    pc_acc = constraint.JointAccelerationConstraint(np.stack([-ctx.alim, ctx.alim], axis=1))
    instance = algo.TOPPRA([pc_vel, pc_acc], path, parametrizer="ParametrizeConstAccel")
    jnt = instance.compute_trajectory()
    if jnt is None:
        return None, None, states
    t_states = _time_of_s(jnt, ss)
    t_states[0], t_states[-1] = 0.0, float(jnt.duration)
    return jnt, t_states, states


def round_ns(t: np.ndarray) -> np.ndarray:
    return np.round(np.asarray(t, dtype=np.float64) * 1e9) / 1e9


def record(ctx, jnt, t_states: np.ndarray, states: np.ndarray):
    """Recorded waypoints (t, q, qd) and the largest clip applied to positions."""
    gen = ctx.gen
    T = float(jnt.duration)
    dt = float(gen["record_dt_s"])
    gap = float(gen.get("record_min_gap_s", 0.02))
    grid = np.arange(1, int(math.floor(T / dt)) + 1) * dt
    grid = grid[grid < T - gap]
    near = np.min(np.abs(grid[:, None] - t_states[None, :]), axis=1) < gap if len(grid) else np.zeros(0, bool)
    t = np.union1d(t_states, grid[~near])
    t = round_ns(t)
    t = np.unique(t)
    q = np.asarray(jnt(t), dtype=np.float64)
    qd = np.asarray(jnt(t, 1), dtype=np.float64)
    q[0], q[-1] = states[0], states[-1]
    qd[0] = 0.0
    qd[-1] = 0.0
    clipped = np.clip(q, ctx.limits["lo"], ctx.limits["hi"])
    max_clip = float(np.max(np.abs(clipped - q)))
    return t, clipped, qd, max_clip


def hermite_states(t: np.ndarray, q: np.ndarray, qd: np.ndarray, hz: float,
                   include_waypoints: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Times and states of the Hermite reconstruction on a ``hz`` grid from t[0] (plus the last
    time; plus every waypoint time if ``include_waypoints``)."""
    from scipy.interpolate import CubicHermiteSpline

    t = np.asarray(t, dtype=np.float64)
    spline = CubicHermiteSpline(t, q, qd, axis=0)
    n = int(math.floor((t[-1] - t[0]) * hz + 1e-9))
    ts = t[0] + np.arange(n + 1) / hz
    ts = ts[ts <= t[-1]]
    ts = np.union1d(ts, [t[-1]])
    if include_waypoints:
        ts = np.union1d(ts, t)
    states = spline(ts)
    if include_waypoints:  # exact recorded positions at the waypoints
        idx = np.searchsorted(ts, t)
        states[idx] = q
    return ts, states


def smoothstep_trajectory(q0, q1, T: float, n_waypoints: int, joint_names, traj_id: str = ""):
    """The direct control: q(t) = q0 + (q1 - q0) (3u^2 - 2u^3), u = t / T, exact velocities."""
    from larc_jax.model.trajectory import Trajectory

    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    t = round_ns(np.linspace(0.0, T, int(n_waypoints)))
    t[-1] = T
    u = t / T
    s = 3 * u**2 - 2 * u**3
    sd = (6 * u - 6 * u**2) / T
    q = q0 + np.outer(s, q1 - q0)
    qd = np.outer(sd, q1 - q0)
    q[0], q[-1] = q0, q1
    qd[0] = 0.0
    qd[-1] = 0.0
    return Trajectory(t=t, q=q, qd=qd, joint_names=tuple(joint_names), id=traj_id,
                      source="direct_smoothstep")
