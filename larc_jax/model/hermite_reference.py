"""NumPy float64 references of the Hermite kernels (:mod:`larc_jax.model.hermite`).

Independent of the JAX kernels: the curve in power form in ``tau = t - t_k`` on each segment,
``q = a0 + a1 tau + a2 tau^2 + a3 tau^3``, and plain loops over the segments an interval touches.
The tests compare each kernel with its reference on random inputs and named edge cases.
"""

from __future__ import annotations

import numpy as np

__all__ = ["evaluate_np", "speed_max_np", "accel_max_np"]


def _power_coeffs_np(t_knots, q_knots, qd_knots, k):
    """Coefficients of q(t_k + tau) = a0 + a1 tau + a2 tau^2 + a3 tau^3 on segment k."""
    h = float(t_knots[k + 1] - t_knots[k])
    y0, y1 = q_knots[k], q_knots[k + 1]
    m0, m1 = qd_knots[k], qd_knots[k + 1]
    slope = (y1 - y0) / h
    a2 = (3.0 * slope - 2.0 * m0 - m1) / h
    a3 = (m0 + m1 - 2.0 * slope) / (h * h)
    return y0, m0, a2, a3, h


def evaluate_np(t_knots, q_knots, qd_knots, t):
    """NumPy float64 reference of :func:`evaluate`: ``(q (n,), qd (n,))`` at scalar ``t``."""
    t_knots = np.asarray(t_knots, dtype=np.float64)
    q_knots = np.asarray(q_knots, dtype=np.float64)
    qd_knots = np.asarray(qd_knots, dtype=np.float64)
    K = t_knots.shape[0] - 1
    t = float(t)
    k = 0
    while k < K - 1 and t >= t_knots[k + 1]:
        k += 1
    a0, a1, a2, a3, _ = _power_coeffs_np(t_knots, q_knots, qd_knots, k)
    tau = t - t_knots[k]
    q = a0 + tau * (a1 + tau * (a2 + tau * a3))
    qd = a1 + tau * (2.0 * a2 + tau * 3.0 * a3)
    return q, qd


def speed_max_np(t_knots, q_knots, qd_knots, a, b):
    """NumPy float64 reference of :func:`speed_max` (paper eq. 5), for ``t_0 <= a <= b <= t_K``.

    Loops over every segment ``[t_k, t_{k+1}]`` that intersects ``[a, b]`` (a zero-width
    interval at a knot touches both neighbours) and takes, per joint, the largest ``|qdot|`` at
    the clipped ends and at the vertex of the quadratic ``qdot`` when it lies inside.
    """
    t_knots = np.asarray(t_knots, dtype=np.float64)
    q_knots = np.asarray(q_knots, dtype=np.float64)
    qd_knots = np.asarray(qd_knots, dtype=np.float64)
    a = float(a)
    b = float(b)
    K = t_knots.shape[0] - 1
    n = q_knots.shape[1]
    best = np.zeros(n)
    for k in range(K):
        lo, hi = t_knots[k], t_knots[k + 1]
        if hi < a or lo > b:
            continue
        _, a1, a2, a3, h = _power_coeffs_np(t_knots, q_knots, qd_knots, k)
        tau0 = max(a, lo) - lo
        tau1 = min(b, hi) - lo
        for j in range(n):
            cands = [tau0, tau1]
            if a3[j] != 0.0:
                tv = -a2[j] / (3.0 * a3[j])  # root of qddot_j = 2 a2 + 6 a3 tau
                if tau0 < tv < tau1:
                    cands.append(tv)
            for tau in cands:
                val = abs(a1[j] + tau * (2.0 * a2[j] + tau * 3.0 * a3[j]))
                best[j] = max(best[j], val)
    return best


def accel_max_np(t_knots, q_knots, qd_knots, a, b):
    """NumPy float64 reference of :func:`accel_max`: the power form's ``qddot = 2 a2 + 6 a3 tau``
    at the clipped ends (linear in between) of every segment overlapping ``[a, b]`` in more than a
    point. ``qddot`` jumps at the knots, so a segment that only touches ``[a, b]`` at a knot is left
    out, as :func:`accel_max` does (the value at one instant does not enter the chord bound of
    :mod:`larc_jax.leaf.swept`); a zero-width interval takes the segment ending at it (the first
    segment at ``t_0``)."""
    t_knots = np.asarray(t_knots, dtype=np.float64)
    q_knots = np.asarray(q_knots, dtype=np.float64)
    qd_knots = np.asarray(qd_knots, dtype=np.float64)
    a, b = float(a), float(b)
    best = np.zeros(q_knots.shape[1])
    K = t_knots.shape[0] - 1
    for k in range(K):
        lo, hi = t_knots[k], t_knots[k + 1]
        if a < b and not (lo < b and hi > a):
            continue
        if a == b and not (lo < a <= hi or (k == 0 and a <= lo) or (k == K - 1 and a > hi)):
            continue
        _, _, a2, a3, _ = _power_coeffs_np(t_knots, q_knots, qd_knots, k)
        for tau in (max(a, lo) - lo, min(b, hi) - lo):
            best = np.maximum(best, np.abs(2.0 * a2 + 6.0 * a3 * tau))
    return best
