"""An FCL audit of a robot's capsules along a curve, for the obstacle-kind tests: the smallest
distance FCL finds between any capsule (an ``fcl.Capsule`` on its placed segment) and any of the
given FCL objects over ``n`` states. Sampling makes it an upper bound of the true minimum, which
is the side a soundness check needs (a certified move must still clear the margin here)."""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation


def _placed(robot, capsules, traj, n: int):
    """``(a, b, r)`` of every capsule segment at ``n`` states along the curve."""
    from larc_jax.enclosure.capsule import capsule_segments_np
    from larc_jax.model.hermite_reference import evaluate_np

    for time in np.linspace(traj.t[0], traj.t[-1], n):
        q, _ = evaluate_np(traj.t, traj.q, traj.qd, time)
        p_a, p_b = capsule_segments_np(robot, capsules, q)[:2]
        yield from zip(p_a, p_b, np.asarray(capsules.radius))


def capsule_clearance(robot, capsules, traj, objects, n: int = 300) -> float:
    import fcl

    best = math.inf
    for a, b, r in _placed(robot, capsules, traj, n):
        axis = b - a
        length = float(np.linalg.norm(axis))
        R = Rotation.align_vectors([axis / length], [[0, 0, 1.0]])[0].as_matrix() if length > 0 else np.eye(3)
        cap = fcl.CollisionObject(fcl.Capsule(float(r), length), fcl.Transform(R, (a + b) / 2))
        for obj in objects:
            best = min(best, fcl.distance(cap, obj, fcl.DistanceRequest(), fcl.DistanceResult()))
    return best


def point_clearance(robot, capsules, traj, points: np.ndarray, n: int = 300) -> float:
    """The least distance between any capsule and any of ``points`` (M, 3) over ``n`` states (an
    upper bound of the true minimum, as :func:`capsule_clearance`)."""
    best = math.inf
    for a, b, r in _placed(robot, capsules, traj, n):
        ab = b - a
        s = np.clip((points - a) @ ab / max(float(ab @ ab), 1e-300), 0.0, 1.0)
        best = min(best, float(np.linalg.norm(points - (a + s[:, None] * ab), axis=1).min()) - r)
    return best


def bracket_fcl(examples, shift) -> "fcl.CollisionObject":  # noqa: F821
    """The camera cell's bracket (``bracket.stl`` posed as in ``cell_camera.yaml``) moved by
    ``shift`` (3,), as an FCL BVH of its triangles."""
    import fcl
    import trimesh

    from larc_jax.model.shapes import rotation_from_quaternion

    mesh = trimesh.load(examples / "bracket.stl")
    R = rotation_from_quaternion([0.0, 0.0, 0.9238795325112867, -0.3826834323650898])
    V = np.asarray(mesh.vertices) @ R.T + [-0.275, 0.325, 0.0] + np.asarray(shift)
    bvh = fcl.BVHModel()
    bvh.beginModel(len(V), len(mesh.faces))
    bvh.addSubModel(V, np.asarray(mesh.faces))
    bvh.endModel()
    return fcl.CollisionObject(bvh, fcl.Transform())


def last_certified(ok, lo: float, hi: float, steps: int) -> float:
    """Bisection for the boundary test: ``ok(lo)`` holds and ``ok(hi)`` does not (asserted);
    returns the largest tested ``s`` with ``ok(s)`` after ``steps`` halvings."""
    assert ok(lo) and not ok(hi)
    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if ok(mid) else (lo, mid)
    return lo
