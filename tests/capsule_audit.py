"""An FCL audit of a robot's capsules along a curve, for the obstacle-kind tests: the smallest
distance FCL finds between any capsule (an ``fcl.Capsule`` on its placed segment) and any of the
given FCL objects over ``n`` states. Sampling makes it an upper bound of the true minimum, which
is the side a soundness check needs (a certified move must still clear the margin here)."""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation


def capsule_clearance(robot, capsules, traj, objects, n: int = 300) -> float:
    import fcl

    from larc_jax.enclosure.capsule import capsule_segments_np
    from larc_jax.model.hermite_reference import evaluate_np

    best = math.inf
    for time in np.linspace(traj.t[0], traj.t[-1], n):
        q, _ = evaluate_np(traj.t, traj.q, traj.qd, time)
        p_a, p_b = capsule_segments_np(robot, capsules, q)[:2]
        for a, b, r in zip(p_a, p_b, np.asarray(capsules.radius)):
            axis = b - a
            length = float(np.linalg.norm(axis))
            R = Rotation.align_vectors([axis / length], [[0, 0, 1.0]])[0].as_matrix() if length > 0 else np.eye(3)
            cap = fcl.CollisionObject(fcl.Capsule(float(r), length), fcl.Transform(R, (a + b) / 2))
            for obj in objects:
                best = min(best, fcl.distance(cap, obj, fcl.DistanceRequest(), fcl.DistanceResult()))
    return best


def last_certified(ok, lo: float, hi: float, steps: int) -> float:
    """Bisection for the boundary test: ``ok(lo)`` holds and ``ok(hi)`` does not (asserted);
    returns the largest tested ``s`` with ``ok(s)`` after ``steps`` halvings."""
    assert ok(lo) and not ok(hi)
    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if ok(mid) else (lo, mid)
    return lo
