"""Motion constants a_lj (paper eq. 6): a bound on how fast any point of an enclosure moves.

The derivation is in :func:`motion_constants`. The interval test inflates each capsule by
``b_l(I) = h * sum_j a_lj * max_I |qdot_j|`` (eq. 6): every point of capsule ``l`` moves with
speed at most ``sum_j a_lj |qdot_j(t)|``, so over ``I = [t_m - h, t_m + h]`` it stays within
``b_l(I)`` of where it is at ``t_m``.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ..defaults import POSITION_TOLERANCE
from ..robot import JointType, Robot

__all__ = ["motion_constants"]


def motion_constants(
    robot: Robot, link_index: Sequence[int], p_link_a: np.ndarray, p_link_b: np.ndarray,
    radius: np.ndarray,
) -> np.ndarray:
    """Sound a_lj for every capsule l and active joint j: (C, n), float64.

    Every point p of capsule l moves with velocity ``sum_j qd_j * v_j(p)`` where
    ``v_j = axis_j x (p - o_j)`` for a revolute joint (``|v_j| = dist(p, axis_j)``) and
    ``v_j = axis_j`` for a prismatic joint (``|v_j| = 1``). Hence ``|p_dot| <= sum_j a_lj |qd_j|``
    whenever ``a_lj >= dist(p, axis_j)`` for all configurations, which is what we bound:

    * joint j not an ancestor of the capsule's link: a_lj = 0;
    * prismatic j: a_lj = 1;
    * revolute j with no active joint between it and the link: the capsule is rigid in the frame
      F_j of j's child link, so ``dist(p, axis_j) <= max_{e in {a,b}} |P_j e_Fj| + r`` exactly
      (``P_j = I - axis axis^T``; distance to a line is convex along the segment, and a ball of
      radius r adds at most r);
    * otherwise (triangle inequality along the chain): let k_1 be the next active joint, with
      joint-frame origin c_1 in F_j (constant: only fixed/held joints lie between). Then
      ``dist(p, axis_j) <= |P_j c_1| + |p - o_{k1}|`` (for a prismatic k_1 the first term is the
      max over the stroke ends of ``|P_j (c_1 + q R_1 axis_k1)|``, convex in q). The norm
      ``|p - o_{k1}|`` is invariant to k_1's rotation, and is bounded the same way, link by link,
      with ``|c_i|`` in place of ``|P_j c_i|``, ending with ``max_e |e_F| + r`` at the last
      active joint.
    """
    n = robot.n_joints
    T_pj = np.asarray(robot.T_parent_joint, np.float64)
    axis = np.asarray(robot.axis, np.float64)
    q_held = np.asarray(robot.q_held, np.float64)
    lower = np.asarray(robot.q_lower, np.float64)
    upper = np.asarray(robot.q_upper, np.float64)

    def held_motion(i: int) -> np.ndarray:
        M = np.eye(4)
        if robot.joint_type[i] == JointType.REVOLUTE:
            from scipy.spatial.transform import Rotation

            M[:3, :3] = Rotation.from_rotvec(axis[i] * q_held[i]).as_matrix()
        elif robot.joint_type[i] == JointType.PRISMATIC:
            M[:3, 3] = axis[i] * q_held[i]
        return M

    def is_active(i: int) -> bool:
        return robot.q_index[i] >= 0

    out = np.zeros((len(link_index), n))
    for c, li in enumerate(link_index):
        path = robot.ancestors(li)[1:]  # link indices whose joint lies on the way to li
        ends = np.stack([np.asarray(p_link_a[c], float), np.asarray(p_link_b[c], float)])
        r = float(radius[c])
        for pos, i in enumerate(path):
            if not is_active(i):
                continue
            j = robot.q_index[i]
            if robot.joint_type[i] == JointType.PRISMATIC:
                out[c, j] = 1.0
                continue
            P = np.eye(3) - np.outer(axis[i], axis[i])
            proj = P  # first step measures perpendicular distance, later steps full norms
            total = 0.0
            A = np.eye(4)  # frame of the current active joint's child link -> walked frame
            for k in path[pos + 1:]:
                if not is_active(k):
                    A = A @ T_pj[k] @ held_motion(k)
                    continue
                J = A @ T_pj[k]
                c1, ax = J[:3, 3], J[:3, :3] @ axis[k]
                if robot.joint_type[k] == JointType.PRISMATIC:
                    qk = robot.q_index[k]
                    # the stroke as validated: limits widened by the tolerance (twice, for rounding)
                    lo_k, hi_k = lower[qk] - 2 * POSITION_TOLERANCE, upper[qk] + 2 * POSITION_TOLERANCE
                    total += max(np.linalg.norm(proj @ (c1 + lo_k * ax)), np.linalg.norm(proj @ (c1 + hi_k * ax)))
                else:
                    total += np.linalg.norm(proj @ c1)
                proj = np.eye(3)
                A = np.eye(4)
            e = ends @ A[:3, :3].T + A[:3, 3]
            total += float(np.linalg.norm(e @ proj.T, axis=1).max()) + r
            out[c, j] = total
    return out
