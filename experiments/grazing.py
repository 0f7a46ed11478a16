"""The cases sampling misses: trajectories that graze a thin box only between 250 Hz samples.

``python -m experiments.grazing [--n 20] [--seed 14] [--out results/grazing]`` writes a seeded
corpus: per case ``case_NN.yaml`` (a PIPER joint trajectory) and ``case_NN_scene.yaml`` (one thin
box), and ``summary.json`` (per case the witness time and FCL distance, the sampled audit's
verdict, LARC's verdict; and the counts).

Construction of one case (all random draws from ``numpy.random.default_rng(seed)``):

1. Joints 2-6 are drawn at random and held; joint 1 (the base yaw, axis z through the origin)
   sweeps at a constant speed ``omega`` (a two-waypoint Hermite curve with equal end velocities
   is exactly linear), over ``DURATION_S``.
2. A witness time ``t_w`` is drawn strictly between two 250 Hz audit samples (near the middle of
   the gap). At ``t_w`` joint 1 turns the collision-mesh vertex farthest from the z axis to
   azimuth 0 (the +x axis), at radius ``r``.
3. The box is thin along the motion (``y``, 0.5-2 mm; 1 cm high, 5 cm long), and lies radially outside the arm:
   ``x`` from ``r + d`` outwards, ``d`` drawn in ``[-2 mm, rho / 2]`` (negative: the meshes
   really intersect the box at ``t_w``), centred on the vertex in ``y`` and ``z``.

A candidate is kept only if (a) the 250 Hz FCL audit of :mod:`experiments.audit`
(:func:`~experiments.audit.audit_trajectory`, its sample times :func:`~experiments.audit.audit_times`)
finds no collision, and no audit sample has an FCL mesh-box distance within ``rho``, and (b) the
FCL distance at 20 kHz inside the sample gap that holds ``t_w`` goes below ``rho``; its smallest
value and time are the recorded witness. Then every kept case is certified with LARC (margin
``rho``), which must refuse each one (a certificate would contradict the witness).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

__all__ = ["AUDIT_HZ", "DENSE_HZ", "MARGIN_M", "DURATION_S", "make_case", "sampled_min_distance", "generate", "main"]

AUDIT_HZ = 250.0
DENSE_HZ = 20000.0
MARGIN_M = 0.005
"""rho of the corpus, m (the audit's 'within rho' and LARC's margin)."""
DURATION_S = 0.2
OMEGA_RAD_S = (10.0, 25.0)
"""Range of joint 1's sweep speed, rad/s: a link centimetres wide must cross the plate, and come
back out of rho, within one 4 ms sample gap, so the sweeps are fast (the summary gives each
case's tip speed)."""
ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "results" / "grazing"

_HELD = ((0.3, 2.0), (-2.5, -0.6), (-1.5, 1.5), (-1.1, 1.1), (-3.0, 3.0))
"""Ranges drawn for joints 2-6, rad (within PIPER's limits)."""


def _trajectory(q_other, theta_w, omega, t_w, name):
    from larc_jax.model.trajectory import Trajectory

    t = np.array([0.0, DURATION_S])
    q = np.zeros((2, 6))
    q[:, 1:] = q_other
    q[:, 0] = theta_w + omega * (t - t_w)
    qd = np.zeros((2, 6))
    qd[:, 0] = omega
    return Trajectory(t=t, q=q, qd=qd, joint_names=tuple(f"joint{j}" for j in range(1, 7)), id=name)


def sampled_min_distance(model, traj, boxes, times) -> tuple[float, float]:
    """Smallest FCL mesh-box distance over the Hermite curve at ``times``, and its time."""
    from scipy.interpolate import CubicHermiteSpline

    Q = CubicHermiteSpline(traj.t, traj.q, traj.qd, axis=0)(times)
    d = np.array([model.min_distance(q, boxes) for q in Q])
    k = int(np.argmin(d))
    return float(d[k]), float(times[k])


def make_case(rng, model, name: str):
    """One candidate: (trajectory, scene dict, facts) or None if it is not a between-samples graze."""
    from experiments.audit import audit_times, audit_trajectory
    from experiments.collision import SceneBoxes

    robot = model.robot
    q_other = np.array([rng.uniform(lo, hi) for lo, hi in _HELD])
    q0 = np.concatenate([[0.0], q_other])
    verts = np.concatenate([m.vertices for m in model.world_meshes(q0).values()])
    radius = np.hypot(verts[:, 0], verts[:, 1])
    v = verts[int(np.argmax(radius))]
    r, theta_w = float(radius.max()), -float(np.arctan2(v[1], v[0]))  # turns v to azimuth 0
    omega = float(rng.choice([-1.0, 1.0]) * rng.uniform(OMEGA_RAD_S[0], OMEGA_RAD_S[1]))
    gap = 1.0 / AUDIT_HZ
    k = int(rng.integers(20, 30))
    t_w = (k + 0.5 + rng.uniform(-0.1, 0.1)) * gap
    ends = theta_w + omega * (np.array([0.0, DURATION_S]) - t_w)
    if ends.min() < robot.q_lower[0] or ends.max() > robot.q_upper[0]:
        return None
    traj = _trajectory(q_other, theta_w, omega, t_w, name)
    d = float(rng.uniform(-0.002, MARGIN_M / 2))
    thick, length, height = float(rng.uniform(0.0005, 0.002)), 0.05, 0.01
    lo = np.array([r + d, -thick / 2, v[2] - height / 2])
    hi = np.array([r + d + length, thick / 2, v[2] + height / 2])
    boxes = SceneBoxes(lo[None], hi[None], ["plate"])
    audit = audit_trajectory(traj, boxes, model, AUDIT_HZ)
    if audit["audit_collision"]:
        return None
    sampled, _ = sampled_min_distance(model, traj, boxes, audit_times(traj.t, AUDIT_HZ))
    if sampled <= MARGIN_M:
        return None
    k_gap = int(np.floor(t_w / gap))
    dense = np.linspace(k_gap * gap, (k_gap + 1) * gap, int(DENSE_HZ * gap) + 1)
    witness_d, witness_t = sampled_min_distance(model, traj, boxes, dense)
    if witness_d >= MARGIN_M:
        return None
    from scipy.interpolate import CubicHermiteSpline

    q_w = CubicHermiteSpline(traj.t, traj.q, traj.qd, axis=0)(witness_t)
    scene = {"frame": robot.link_names[0],
             "boxes": [{"name": "plate", "min": [float(x) for x in lo], "max": [float(x) for x in hi]}]}
    facts = {"audit_states": audit["audit_states"], "audit_collision": audit["audit_collision"],
             "audit_min_distance_m": sampled, "witness_t": witness_t, "witness_distance_m": witness_d,
             "witness_collision": bool(model.scene_collision(q_w, boxes)), "omega_rad_s": omega,
             "speed_at_witness_m_s": abs(omega) * r, "plate_thickness_m": thick}
    return traj, scene, facts


def generate(n: int = 20, seed: int = 14, out: Path = OUT, max_tries: int = 400) -> dict:
    import yaml

    import larc_jax as lj
    from experiments.collision import CollisionModel
    from larc_jax.io import atomic_write_json, atomic_write_text

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    model = CollisionModel()
    rng = np.random.default_rng(seed)
    cases, tries, start = [], 0, time.perf_counter()
    while len(cases) < n and tries < max_tries:
        tries += 1
        name = f"case_{len(cases):02d}"
        made = make_case(rng, model, name)
        if made is None:
            continue
        traj, scene, facts = made
        lj.write_trajectory(out / f"{name}.yaml", traj)
        atomic_write_text(out / f"{name}_scene.yaml", yaml.safe_dump(scene, sort_keys=False))
        cases.append({"id": name, "trajectory": f"{name}.yaml", "scene": f"{name}_scene.yaml", **facts})
    robot, capsules = lj.load_robot_file()
    trajs = [lj.read_trajectory(out / c["trajectory"], robot) for c in cases]
    scenes = [lj.read_scene(out / c["scene"], frame=robot.link_names[0]) for c in cases]
    result = lj.certify(trajs, scenes, robot, capsules, margin=MARGIN_M) if cases else None
    for i, c in enumerate(cases):
        c["larc_certified"] = bool(result.certified[i])
    summary = {
        "seed": seed, "margin_m": MARGIN_M, "audit_hz": AUDIT_HZ, "dense_hz": DENSE_HZ, "candidates": tries,
        "cases": len(cases),
        "sampled_clear": sum(not c["audit_collision"] and c["audit_min_distance_m"] > MARGIN_M for c in cases),
        "within_margin_between_samples": sum(c["witness_distance_m"] < MARGIN_M for c in cases),
        "collide_between_samples": sum(c["witness_collision"] for c in cases),
        "larc_refused": sum(not c["larc_certified"] for c in cases),
        "trajectories": cases,
    }
    atomic_write_json(out / "summary.json", summary)  # no wall times: a rerun writes the same bytes
    print(f"generated in {time.perf_counter() - start:.1f} s")
    return summary


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=20, help="cases to keep")
    p.add_argument("--seed", type=int, default=14)
    p.add_argument("--out", type=Path, default=OUT)
    args = p.parse_args(argv)
    s = generate(args.n, args.seed, args.out)
    print(f"{s['cases']} cases from {s['candidates']} candidates: {s['sampled_clear']} clear at {s['audit_hz']:g} Hz, "
          f"{s['within_margin_between_samples']} within {s['margin_m'] * 1000:g} mm between samples "
          f"({s['collide_between_samples']} in collision), LARC refused {s['larc_refused']}; {args.out}/summary.json")
    return 0 if s["larc_refused"] == s["cases"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
