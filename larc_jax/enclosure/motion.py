"""Motion constants a_lj (paper eq. 6): a bound on how fast any point of an enclosure moves.

The interval test inflates each enclosure by ``b_l(I) = h * sum_j a_lj * max_I |qdot_j|``
(eq. 6): every point of enclosure ``l`` moves with speed at most ``sum_j a_lj |qdot_j(t)|``, so
over ``I = [t_m - h, t_m + h]`` it stays within ``b_l(I)`` of where it is at ``t_m``.

An enclosure is given as a finite point set ``X`` in its link frame plus a radius ``r``: the set
``conv(X) + B(0, r)`` (a capsule: its two segment ends and its radius; a hull part: its vertices
and its padding). Every bound below is a maximum of a *convex* function of the point (a distance
to a line or to a point), so its maximum over ``conv(X) + B(0, r)`` is its maximum over ``X``
plus ``r``: checking the generating points is exact.

Why a_lj bounds the speed. Every point p of the enclosure moves with velocity
``sum_j qd_j v_j(p)``, ``v_j = axis_j x (p - o_j)`` for a revolute joint (``|v_j| = dist(p,
axis_j)``), ``v_j = axis_j`` for a prismatic one (``|v_j| = 1``). Hence ``|p_dot| <= sum_j a_lj
|qd_j|`` whenever ``a_lj >= dist(p, axis_j)`` for every configuration, which is what we bound:

* j not an ancestor of the link: a_lj = 0; prismatic j: a_lj = 1;
* revolute j, no active joint between it and the link: the enclosure is rigid in the frame of
  j's child link, and ``max_x |P_j x| + r`` (``P_j = I - axis axis^T``) is exact;
* otherwise two sound bounds, and a_lj is the smaller:

  **(A) triangle inequality along the chain** (the paper's calibration): with ``k_1`` the next
  active joint, ``c_1`` its joint origin in j's child frame, ``dist(p, axis_j) <= |P_j c_1| +
  |p - o_k1|``; ``|p - o_k1|`` does not change when ``k_1`` turns and is bounded the same way,
  with ``|c_i|`` in place of ``|P_j c_i|``, ending with ``max_x |x| + r`` at the last active
  joint (a prismatic ``k_1`` contributes the larger of its two stroke ends).

  **(B) balls centred on the axes**, walked up from the link. Suppose the enclosure, in the
  frame of an active revolute joint k (before its rotation), lies in a ball ``B(h a_k, rho)``
  whose centre is *on* k's axis. Turning k leaves that ball where it is, so it encloses the
  enclosure at every value of k; mapped into the parent frame it is ``B(T (h a_k), rho)``.
  The first such ball (at the active joint nearest the link) is centred at the height ``h``
  that minimises ``rho = max_x |x - h a_k| + r`` (any ``h`` is sound; the minimum is found by
  golden-section search, a convex 1-D problem); at each further active revolute joint k the
  ball ``B(c, rho)`` is replaced by ``B((c . a_k) a_k, |P_k c| + rho)``, which holds it at every
  angle of k. A prismatic joint turns the ball into the two balls at its stroke ends (their hull
  holds the sweep; the bounds stay convex). At j: ``a_lj <= max |P_j c| + rho``.

  (A) charges every joint offset at its full length; (B) charges only the part of the offset
  perpendicular to the next axis, and the enclosure's extent from an axis rather than from a
  joint origin, so it is smaller wherever the chain runs along its axes (PIPER's wrist);
  taking the minimum keeps whichever is tighter, link by link and joint by joint.

Sampled check: tests compare ``sum_j a_lj |qd_j|`` with FK-Jacobian point speeds of 10^4 random
configurations and velocities (tests/test_capsules.py, tests/test_hull.py).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ..defaults import POSITION_TOLERANCE
from ..model.robot import JointType, Robot

__all__ = ["motion_constants", "motion_constants_points"]


def motion_constants(
    robot: Robot, link_index: Sequence[int], p_link_a: np.ndarray, p_link_b: np.ndarray,
    radius: np.ndarray,
) -> np.ndarray:
    """Sound a_lj for every capsule l and active joint j: (C, n), float64 (module docstring)."""
    points = [np.stack([np.asarray(a, float), np.asarray(b, float)]) for a, b in zip(p_link_a, p_link_b)]
    return motion_constants_points(robot, link_index, points, radius)


def motion_constants_points(robot: Robot, link_index: Sequence[int], points: Sequence[np.ndarray],
                            radius: Sequence[float]) -> np.ndarray:
    """Sound a_lj for enclosures ``conv(points[l]) + B(0, radius[l])`` in the frames of links
    ``link_index[l]``: (E, n), float64, the minimum of bounds (A) and (B) of the module docstring."""
    chain = _Chain(robot)
    out = np.zeros((len(link_index), robot.n_joints))
    for e, li in enumerate(link_index):
        X = np.asarray(points[e], np.float64).reshape(-1, 3)
        r = float(radius[e])
        path = robot.ancestors(li)[1:]  # link indices whose joint lies on the way to li
        for pos, i in enumerate(path):
            if robot.q_index[i] < 0:
                continue
            j = robot.q_index[i]
            if robot.joint_type[i] == JointType.PRISMATIC:
                out[e, j] = 1.0
                continue
            below = path[pos + 1:]
            out[e, j] = min(chain.triangle_bound(i, below, X, r), chain.ball_bound(i, below, X, r))
    return out


class _Chain:
    """Joint data of ``robot`` as float64 arrays, and the two bounds."""

    def __init__(self, robot: Robot):
        self.robot = robot
        self.T_pj = np.asarray(robot.T_parent_joint, np.float64)
        self.axis = np.asarray(robot.axis, np.float64)
        self.q_held = np.asarray(robot.q_held, np.float64)
        self.lower = np.asarray(robot.q_lower, np.float64)
        self.upper = np.asarray(robot.q_upper, np.float64)

    def active(self, i: int) -> bool:
        return self.robot.q_index[i] >= 0

    def held_motion(self, i: int) -> np.ndarray:
        M = np.eye(4)
        if self.robot.joint_type[i] == JointType.REVOLUTE:
            from scipy.spatial.transform import Rotation

            M[:3, :3] = Rotation.from_rotvec(self.axis[i] * self.q_held[i]).as_matrix()
        elif self.robot.joint_type[i] == JointType.PRISMATIC:
            M[:3, 3] = self.axis[i] * self.q_held[i]
        return M

    def stroke(self, i: int) -> tuple[float, float]:
        """The stroke of active prismatic joint ``i`` as validated: its limits widened by the
        position tolerance (twice, for rounding; trajectories within it are accepted)."""
        k = self.robot.q_index[i]
        return float(self.lower[k]) - 2 * POSITION_TOLERANCE, float(self.upper[k]) + 2 * POSITION_TOLERANCE

    def triangle_bound(self, j: int, below: Sequence[int], X: np.ndarray, r: float) -> float:
        """Bound (A) for revolute joint ``j`` (link index) over the links ``below`` it."""
        P = np.eye(3) - np.outer(self.axis[j], self.axis[j])
        proj = P  # the first step measures perpendicular distance, later steps full norms
        total = 0.0
        A = np.eye(4)  # frame of the current active joint's child link -> walked frame
        for k in below:
            if not self.active(k):
                A = A @ self.T_pj[k] @ self.held_motion(k)
                continue
            J = A @ self.T_pj[k]
            c1, ax = J[:3, 3], J[:3, :3] @ self.axis[k]
            if self.robot.joint_type[k] == JointType.PRISMATIC:
                lo, hi = self.stroke(k)
                total += max(np.linalg.norm(proj @ (c1 + lo * ax)), np.linalg.norm(proj @ (c1 + hi * ax)))
            else:
                total += np.linalg.norm(proj @ c1)
            proj = np.eye(3)
            A = np.eye(4)
        e = X @ A[:3, :3].T + A[:3, 3]
        return total + float(np.linalg.norm(e @ proj.T, axis=1).max()) + r

    def ball_bound(self, j: int, below: Sequence[int], X: np.ndarray, r: float) -> float:
        """Bound (B) for revolute joint ``j`` (link index) over the links ``below`` it."""
        pts, rho = X, r  # enclosure: conv(pts) + B(0, rho), in the frame of the link being walked
        for k in reversed(below):
            if not self.active(k):
                pts = _apply(self.T_pj[k] @ self.held_motion(k), pts)
                continue
            a = self.axis[k]
            if self.robot.joint_type[k] == JointType.PRISMATIC:
                lo, hi = self.stroke(k)
                pts = np.concatenate([pts + lo * a, pts + hi * a])
            else:
                h, rho = _axis_ball(pts, rho, a)
                pts = (h * a)[None]  # B(h a, rho) holds the enclosure at every angle of k
            pts = _apply(self.T_pj[k], pts)
        P = np.eye(3) - np.outer(self.axis[j], self.axis[j])
        return float(np.linalg.norm(pts @ P.T, axis=1).max()) + rho


def _apply(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return pts @ T[:3, :3].T + T[:3, 3]


def _axis_ball(pts: np.ndarray, rho: float, a: np.ndarray) -> tuple[float, float]:
    """A ball centred on the line ``R a`` holding ``conv(pts) + B(0, rho)``: (h, radius) with
    radius ``max |x - h a| + rho`` at the ``h`` found by golden-section search (the maximum of
    distances to ``h a`` is convex in h; whatever h the search returns, the radius is computed
    for that h, so the ball is sound)."""
    s = pts @ a
    perp2 = np.maximum((pts * pts).sum(axis=1) - s * s, 0.0)

    def radius(h: float) -> float:
        return float(np.sqrt(perp2 + (s - h) ** 2).max())

    lo, hi = float(s.min()), float(s.max())
    g = (np.sqrt(5.0) - 1.0) / 2.0
    for _ in range(60):
        m1, m2 = hi - g * (hi - lo), lo + g * (hi - lo)
        if radius(m1) <= radius(m2):
            hi = m2
        else:
            lo = m1
    h = 0.5 * (lo + hi)
    # Recompute the radius directly from the points (not from perp2, which lost the sign
    # information of rounding): |x - h a| with x - h a formed explicitly.
    return h, float(np.linalg.norm(pts - h * a, axis=1).max()) + rho
