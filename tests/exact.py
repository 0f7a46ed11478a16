"""Exact (rational) evaluations for the soundness tests, independent of larc_jax's kernels.

* :func:`hermite_exact`: the piecewise-cubic Hermite curve through the waypoints, evaluated in
  :class:`fractions.Fraction` arithmetic at a rational time (every float is a rational), so
  times between two floats of a 2^40 s axis are evaluated exactly too.
* :func:`speed_max_exact`: the exact maximum of ``|qdot_j|`` over a rational interval;
  :func:`accel_max_exact` the same of ``|qddot_j|``.
* :func:`segment_box_sq_distance_exact`: the exact squared distance between a segment and an
  axis-aligned box with rational (float) coordinates.
* :func:`min_clearance`: capsule-box clearance ``dist - r`` at a configuration, with the NumPy
  float64 forward-kinematics reference (error ~1e-16 m, far below what the tests look for).
"""

from __future__ import annotations

import math
from fractions import Fraction as F

import numpy as np

from larc_jax.enclosure import capsule_segments_np
from larc_jax.obstacles.geometry import segment_box_distance_np


def _segment(t, tt: F) -> int:
    K = len(t) - 1
    k = 0
    while k < K - 1 and tt >= F(float(t[k + 1])):
        k += 1
    return k


def _coeffs(t, q, qd, k: int, j: int):
    """Power-form coefficients of q_j(t_k + tau) and the segment duration, exact."""
    h = F(float(t[k + 1])) - F(float(t[k]))
    y0, y1 = F(float(q[k, j])), F(float(q[k + 1, j]))
    m0, m1 = F(float(qd[k, j])), F(float(qd[k + 1, j]))
    slope = (y1 - y0) / h
    return y0, m0, (3 * slope - 2 * m0 - m1) / h, (m0 + m1 - 2 * slope) / (h * h), h


def hermite_exact(t, q, qd, tt) -> list[F]:
    """Exact q(tt) (list of Fractions, one per joint) for a rational time in [t_0, t_K]."""
    tt = F(tt)
    k = _segment(t, tt)
    tau = tt - F(float(t[k]))
    out = []
    for j in range(q.shape[1]):
        a0, a1, a2, a3, _ = _coeffs(t, q, qd, k, j)
        out.append(a0 + tau * (a1 + tau * (a2 + tau * a3)))
    return out


def speed_max_exact(t, q, qd, a, b) -> list[F]:
    """Exact max over [a, b] of |qdot_j| (rational ends inside [t_0, t_K])."""
    a, b = F(a), F(b)
    n = q.shape[1]
    best = [F(0)] * n
    for k in range(len(t) - 1):
        lo, hi = F(float(t[k])), F(float(t[k + 1]))
        if hi < a or lo > b:
            continue
        for j in range(n):
            _, a1, a2, a3, _ = _coeffs(t, q, qd, k, j)
            cands = [max(a, lo) - lo, min(b, hi) - lo]
            if a3 != 0:
                tv = -a2 / (3 * a3)
                if cands[0] < tv < cands[1]:
                    cands.append(tv)
            for tau in cands:
                best[j] = max(best[j], abs(a1 + tau * (2 * a2 + tau * 3 * a3)))
    return best


def accel_max_exact(t, q, qd, a, b) -> list[F]:
    """Exact max over [a, b] (a < b, rational, inside [t_0, t_K]) of |qddot_j|, which is linear on
    each segment: the segments overlapping [a, b] in more than a point, at their clipped ends."""
    a, b = F(a), F(b)
    best = [F(0)] * q.shape[1]
    for k in range(len(t) - 1):
        lo, hi = F(float(t[k])), F(float(t[k + 1]))
        if not (lo < b and hi > a):
            continue
        for j in range(q.shape[1]):
            _, _, a2, a3, _ = _coeffs(t, q, qd, k, j)
            for tau in (max(a, lo) - lo, min(b, hi) - lo):
                best[j] = max(best[j], abs(2 * a2 + 6 * a3 * tau))
    return best


def segment_box_sq_distance_exact(p0, p1, lo, hi) -> F:
    """Exact squared distance between segment [p0, p1] and box [lo, hi] (float coordinates)."""
    p0, p1, lo, hi = ([F(float(x)) for x in v] for v in (p0, p1, lo, hi))
    d = [y - x for x, y in zip(p0, p1)]

    def f(s: F) -> F:
        total = F(0)
        for i in range(3):
            x = p0[i] + s * d[i]
            g = max(lo[i] - x, x - hi[i], F(0))
            total += g * g
        return total

    knots = {F(0), F(1)}
    for i in range(3):
        if d[i] != 0:
            for bound in (lo[i], hi[i]):
                s = (bound - p0[i]) / d[i]
                if 0 < s < 1:
                    knots.add(s)
    knots = sorted(knots)
    best = min(f(s) for s in knots)
    for u, v in zip(knots[:-1], knots[1:]):
        mid = (u + v) / 2
        num = den = F(0)
        for i in range(3):
            x = p0[i] + mid * d[i]
            e = lo[i] - p0[i] if x < lo[i] else (hi[i] - p0[i] if x > hi[i] else None)
            if e is not None:
                num += d[i] * e
                den += d[i] * d[i]
        if den > 0:
            best = min(best, f(min(max(num / den, u), v)))
    return best


def min_clearance(robot, capsules, scene, q) -> float:
    """min over capsules and boxes of dist(segment, box) - radius at configuration q (float64)."""
    pa, pb = capsule_segments_np(robot, capsules, np.asarray(q, np.float64))
    best = math.inf
    for c in range(capsules.n_capsules):
        for k in range(scene.n_boxes):
            best = min(best, segment_box_distance_np(pa[c], pb[c], scene.lo[k], scene.hi[k]) - float(capsules.radius[c]))
    return best


def leaf_min_clearance(robot, capsules, traj, scene, t0: float, t1: float, n: int = 16) -> float:
    """Smallest clearance over the real leaf [t0, t1]: its ends and n - 1 rational times
    between them, each with the exact curve."""
    a, b = F(t0), F(t1)
    times = [a + (b - a) * F(i, n) for i in range(n + 1)]
    return min(min_clearance(robot, capsules, scene, [float(x) for x in hermite_exact(traj.t, traj.q, traj.qd, tt)])
               for tt in times)
