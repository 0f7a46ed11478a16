"""Continuous-time self-collision certificate: which capsule pairs are checked, the segment-segment
distance kernel (one pair) with its NumPy reference, and the self test of one interval.

The test. On a leaf ``I`` the interval test (:mod:`larc_jax.leaf.interval`) places every capsule at the
midpoint configuration ``q(t')``. Both links of a pair move; the issue's test inflates each by its
own motion radius, ``r_1 + r_2 + b_1 + b_2 + rho_self``. We use a tighter bound that is just as
sound: the distance between two links does not change when both move rigidly together, so only
the *relative* motion counts. Let ``c`` be the deepest common ancestor link of ``l1`` and ``l2``;
in ``c``'s frame, link ``l1`` moves only through the active joints on the tree path from ``c``
to ``l1`` (``P_1``), link ``l2`` only through those from ``c`` to ``l2`` (``P_2``, disjoint from
``P_1``; for a chain, ``l1 = c`` and ``P_1`` is empty). A point ``p`` of capsule ``l`` moves in
that frame with velocity ``sum_{j in P} qd_j v_j(p)``, ``|v_j(p)| = dist(p, axis_j) <= a_lj``
(motion constants, valid at every configuration; a distance to an axis is frame-invariant). So
over ``I`` the pair's relative displacement is at most::

    b_p = h_cov * sum_j A_pj (omega_j + slack_j) * (1 + (n + 64) eps),   A_pj = a_{l1,j} [j in P_1] + a_{l2,j} [j in P_2]

(the same covering radius, speed maxima, slack and rounding as ``b_l``, budget T4-P3; ``A_pj``
is a copy of one motion constant, exact), and ``b_p <= b_1 + b_2``. The certificate clearance
of a pair ``p = (l1, l2)`` is::

    g_p = dist(seg_l1, seg_l2) * (1 - K_DIST_REL eps_g) - (r_1 + r_2 + b_p + rho_self) * (1 + 4 eps)

and the pair passes iff ``g_p > G_l1 + G_l2`` (the per-capsule guards of the trajectory,
:func:`larc_jax.leaf.interval.trajectory_rounding`). An interval passes the self test iff every
checked pair passes; with ``certify(self_collision=True)`` a leaf passes iff the box test and
the self test pass, and it records the pair (box or capsule pair) with the smallest
``g - guard``.

Why the guard ``G_l1 + G_l2`` covers the rounding. ``G_l`` bounds (budget P1, G1) how far the
computed segment of capsule ``l`` is from the exact one, plus ``2 K_DIST_ABS u_g R_l`` for the
absolute error of a distance evaluated at points of magnitude ``R_l``. The segment-segment
distance below is the minimum of candidates of two kinds: point-segment distances (a
projection, a clip and a norm: the same error terms as budget G2, ``16 u_g`` relative and
``32 u_g`` times the end point magnitudes absolute, so ``K_DIST_ABS u_g (R_1 + R_2)`` covers the
absolute part) and lower bounds of the interior minimum whose own rounding is subtracted in the
kernel (below). Moving a segment end by ``e`` changes the distance by at most ``e``, so the
placement errors of both capsules add: ``G_l1 + G_l2``. ``fl(G_l1 + G_l2)`` may be ``u`` low and
the comparison costs another ``u`` (G4): both within the ``(1 + 8u)`` factor of each guard.
The placed segments are at the rounded configuration ``q^``: budget P3 already puts every point
within ``sum_j a_lj E_j`` (in ``G_l``) of where it is at ``q(t')``. The shell is a sum of four
non-negative float64 terms: ``(1 + 4 eps)`` bounds its rounding.

Segment-segment distance (:func:`segment_segment_distance`). ``f(s, t) = |P(s) - Q(t)|^2`` is a
convex quadratic on ``[0, 1]^2``; its minimum lies on the boundary (the four point-segment
distances of the end points, evaluated exactly up to rounding) or at the interior stationary
point of the two lines, where it equals the line-line distance ``|w . n| / |n|`` (``n = d1 x
d2``, ``w = q0 - p0``). The line distance is a lower bound of the segment distance, so using it
is always safe; the kernel uses it whenever the *computed* stationary point lies within
``tau`` of the square, ``tau = 64 u_g kappa (1 + |w| / min(|d1|, |d2|))``, ``kappa = (|d1|
|d2| / |n|)^2``, which exceeds the error of the computed ``(s*, t*)`` (Cramer's rule on the
cross products: ``~ 32 u_g kappa (1 + |w| / min |d|)``), so a true interior minimum is never
missed. The line distance's own rounding (``<= 20 u_g |w| sqrt(kappa)``) is subtracted as
``64 u_g |w| sqrt(kappa)``. When ``tau >= 1/4`` (nearly parallel or degenerate segments) the
stationary point is not trusted; then, if the true minimum ``(s*, t*)`` is interior, moving
``t`` (say ``d2`` is the shorter) to the boundary while ``s`` follows along ``d1`` changes
``P - Q`` by the component of ``d2`` orthogonal to ``d1`` only: the boundary minimum is at most
``dist* + min(|d1|, |d2|) sin(theta) = dist* + |n| / max(|d1|, |d2|)``. The kernel subtracts
that (rounded up) from the boundary minimum. Both lower bounds only lose tightness, never
soundness; exactly parallel and point segments reduce to the boundary candidates (``n = 0``).

Pairs (:func:`self_pairs`). Every pair of capsules on different links is checked, except pairs of
links joined by one joint (parent and child in the kinematic tree: their capsules overlap at the
joint by construction) and pairs of links whose relative pose never changes (no active joint on
the tree path between them, e.g. PIPER's two fingers, held closed on link6: they always touch,
by design). The robot's allowed-collision list (MoveIt's ``disable_collisions``) is *not* used
to skip pairs: its "never" pairs only record that 10^4 random samples saw no contact, which is
not a proof; they are checked like any other pair, unless a pair is *proven* never to come
closer than a clearance larger than the self margin over a box of joint values (the limits
widened by 0.05 rad; :func:`load_separation`: a branch and bound with FCL mesh distances and the
motion constants, ``experiments/self_separation.py``; for PIPER base_link/link2 and link3/link5,
whose capsules overlap at every configuration though the meshes never touch). Such a pair is
skipped for a trajectory only if a sound enclosure of its curve (:func:`curve_ranges`, widened
by the tracking tolerance) lies inside that box, else it is checked. Pairs can also be skipped
explicitly (``certify(self_skip=...)``). The result names every pair not checked, and why.
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import math
import numbers

import numpy as np

from ..enclosure.capsule import CapsuleModel
from ..errors import LarcInputError
from .interval import K_DIST_REL
from .record import LeafRecord, self_record
from .placement import motion_radii
from ..lazy_jax import jax, jnp
from ..model.robot import Robot

__all__ = [
    "SelfPairs",
    "self_pairs",
    "segment_segment_distance",
    "segment_segment_distance_np",
    "self_clearance",
    "self_clearance_np",
    "self_stage",
    "self_stage_np",
    "curve_ranges",
    "check_self_margin",
    "path_joints",
    "link_geometry_sha256",
    "load_separation",
    "K_SEG_TAU",
    "K_SEG_LINE",
]

K_SEG_TAU = 64
"""tau of the inside test, in u_g kappa (1 + |w| / min |d|) (module docstring)."""
K_SEG_LINE = 64
"""Rounding of the line-line distance subtracted, in u_g |w| sqrt(kappa)."""


@dataclasses.dataclass(frozen=True)
class SelfPairs:
    """The capsule pairs a self-collision certificate checks (static: NumPy and tuples)."""

    first: np.ndarray
    """(P,) int32 capsule index of each pair's first capsule."""
    second: np.ndarray
    """(P,) int32 capsule index of the second capsule."""
    motion_a: np.ndarray
    """(P, n) float64 ``A_pj``: the motion constants of the pair's relative motion (module docstring)."""
    proven_lower: np.ndarray
    """(P, n) joint values the pair is proven apart above (-inf: any; +inf for every joint: not proven)."""
    proven_upper: np.ndarray
    """(P, n) joint values the pair is proven apart below (+inf: any; -inf for every joint: not proven)."""
    margin_m: float
    """rho_self, m: the required distance between the links of a pair (0: touching fails)."""
    skipped: tuple[tuple[str, str, str], ...] = ()
    """(link, link, why) for every pair of links not checked."""

    @property
    def n_pairs(self) -> int:
        return len(self.first)

    def skip_mask(self, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
        """(P,) bool: pairs proven apart over a box containing the joint ranges ``[lower, upper]``
        (n,) of a trajectory's curve (:func:`curve_ranges`): the self test need not check them."""
        return np.all((self.proven_lower <= lower[None]) & (upper[None] <= self.proven_upper), axis=1)


def check_self_margin(value, what: str = "certify: self_margin") -> float:
    """rho_self as a float: finite and >= 0; else :class:`LarcInputError` naming ``what``."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not (math.isfinite(value) and value >= 0):
        raise LarcInputError(f"{what} {value!r}: must be a finite number >= 0 m (the self-collision margin)")
    return float(value)


def path_joints(robot: Robot, a: int, b: int) -> list[int]:
    """Link indices whose joint lies on the tree path between links ``a`` and ``b``."""
    up_a, up_b = robot.ancestors(a), robot.ancestors(b)
    common = max(set(up_a) & set(up_b), key=lambda i: up_a.index(i))
    return [i for i in up_a[up_a.index(common) + 1:]] + [i for i in up_b[up_b.index(common) + 1:]]


def link_geometry_sha256(robot: Robot, link: str, geometry: dict | None = None) -> str:
    """SHA-256 of what ``link``'s collision geometry is (mesh files hashed afresh, origins, scales,
    primitives: ``geometry``, default :func:`~larc_jax.enclosure.meshes.collision_geometry`)."""
    from ..enclosure.meshes import collision_geometry

    geometry = collision_geometry(robot) if geometry is None else geometry
    text = json.dumps(geometry.get(link, []), sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


def load_separation(robot: Robot, path=None) -> dict[tuple[str, str], tuple[float, dict]]:
    """Link pairs proven never to touch (``experiments/self_separation.py``), as ``{(link, link):
    (clearance_m, {joint: (lower, upper)})}`` (the joint box the proof covers), from ``path``
    (default: the package's PIPER file). Only proofs made for this robot count: the URDF's
    SHA-256 and both links' collision geometry must match (else the pair is not listed, and is
    checked)."""
    import yaml

    from ..data import PIPER_SELF_SEPARATION, data_path

    path = data_path(PIPER_SELF_SEPARATION) if path is None else path
    try:
        doc = yaml.safe_load(open(path).read())
    except OSError as exc:
        raise LarcInputError(f"{path}: cannot read the self-separation proofs ({exc.strerror or exc})") from None
    if not isinstance(doc, dict) or doc.get("urdf_sha256") != robot.urdf_sha256:
        return {}
    from ..enclosure.meshes import collision_geometry

    out = {}
    geometry = collision_geometry(robot) if doc.get("pairs") else {}
    for p in doc.get("pairs") or []:
        if not isinstance(p, dict) or not isinstance(p.get("joints"), dict):
            continue  # not a proof this version can read: the pair is checked
        a, b = str(p["a"]), str(p["b"])
        if a in robot.link_names and b in robot.link_names and all(
                p.get("geometry_sha256", {}).get(x) == link_geometry_sha256(robot, x, geometry) for x in (a, b)):
            box = {str(j): (float(lo), float(hi)) for j, (lo, hi) in dict(p["joints"]).items()}
            if all(j in robot.active_joint_names for j in box):
                out[tuple(sorted((a, b)))] = (float(p["clearance_m"]), box)
    return out


def self_pairs(robot: Robot, capsules: CapsuleModel, margin_m: float = 0.0, skip=(), proven=None) -> SelfPairs:
    """The checked pairs (module docstring): capsules on different links, minus links joined by
    one joint, links whose relative pose never changes, link pairs proven apart by more than
    ``margin_m`` (``proven``: :func:`load_separation`), and the link pairs in ``skip``
    (``(link, link)`` tuples or ``"link:link"`` strings; LarcInputError if not links with capsules).
    A proven pair is kept in the list with its proof's joint box (:meth:`SelfPairs.skip_mask`)."""
    margin_m = check_self_margin(margin_m)
    proven = dict(proven or {})
    n = robot.n_joints
    plo, phi = [], []
    names = set(capsules.link_names)
    wanted = set()
    for item in skip:
        pair = tuple(item.split(":")) if isinstance(item, str) else tuple(item)
        if len(pair) != 2 or not all(isinstance(x, str) and x in names for x in pair) or pair[0] == pair[1]:
            raise LarcInputError(f"self-collision skip {item!r}: expected two different links with capsules "
                                 f"({', '.join(sorted(names))}) as 'LINK:LINK'")
        wanted.add(tuple(sorted(pair)))
    first, second, skipped, rows = [], [], {}, []
    a = np.asarray(capsules.motion_a, np.float64)
    for c1, c2 in itertools.combinations(range(capsules.n_capsules), 2):
        l1, l2 = capsules.link_index[c1], capsules.link_index[c2]
        if l1 == l2:
            continue
        key = tuple(sorted((capsules.link_names[c1], capsules.link_names[c2])))
        path = path_joints(robot, l1, l2)
        if len(path) == 1:
            skipped[key] = "adjacent"
        elif all(robot.q_index[i] < 0 for i in path):
            skipped[key] = "rigid"
        elif key in wanted:
            skipped[key] = "skipped"
        else:
            lo, hi = np.full(n, np.inf), np.full(n, -np.inf)
            if key in proven and proven[key][0] > margin_m:
                clearance, box = proven[key]
                skipped[key] = (f"proven apart by {clearance * 1000:.2f} mm where the curve stays within "
                                + ", ".join(f"{j} [{lo_j:.3f}, {hi_j:.3f}]" for j, (lo_j, hi_j) in box.items())
                                + "; checked elsewhere")
                lo, hi = np.full(n, -np.inf), np.full(n, np.inf)
                for j, (a_j, b_j) in box.items():
                    lo[robot.active_joint_names.index(j)] = a_j
                    hi[robot.active_joint_names.index(j)] = b_j
            plo.append(lo)
            phi.append(hi)
            first.append(c1)
            second.append(c2)
            row = np.zeros(robot.n_joints)
            for c, link in ((c1, l1), (c2, l2)):
                for i in path:
                    if robot.q_index[i] >= 0 and i in robot.ancestors(link):  # a joint on link's side
                        row[robot.q_index[i]] = a[c, robot.q_index[i]]
            rows.append(row)
    return SelfPairs(first=np.array(first, np.int32), second=np.array(second, np.int32),
                     motion_a=np.array(rows, np.float64).reshape(len(rows), n),
                     proven_lower=np.array(plo, np.float64).reshape(len(rows), n),
                     proven_upper=np.array(phi, np.float64).reshape(len(rows), n), margin_m=margin_m,
                     skipped=tuple((a, b, why) for (a, b), why in sorted(skipped.items())))


def curve_ranges(traj, delta=None):
    """(lower, upper), (n,) each: joint values enclosing the trajectory's whole Hermite curve, widened by
    the tracking tolerance ``delta`` (n,) if given. On a segment ``q(s) = h00 q_k + h01 q_k+1 + H
    (h10 v_k + h11 v_k+1)`` with ``h00 + h01 = 1``, ``h00, h01 >= 0`` and ``|h10|, |h11| <= 4/27``,
    so ``q`` stays within ``4/27 H (|v_k| + |v_k+1|)`` of ``[min, max](q_k, q_k+1)``; the result is
    padded by ``1e-9 (1 + |x|)`` for its own rounding."""
    q = np.asarray(traj.q, np.float64)
    v = np.abs(np.asarray(traj.qd, np.float64))
    H = np.diff(np.asarray(traj.t, np.float64))[:, None]
    over = 4.0 / 27.0 * H * (v[:-1] + v[1:])
    lo = (np.minimum(q[:-1], q[1:]) - over).min(axis=0)
    hi = (np.maximum(q[:-1], q[1:]) + over).max(axis=0)
    if delta is not None:
        lo, hi = lo - delta, hi + delta
    return lo - 1e-9 * (1 + np.abs(lo)), hi + 1e-9 * (1 + np.abs(hi))


# ----------------------------------------------------------------------------------------------
# Segment-segment distance: one pair (JAX) and its NumPy reference
# ----------------------------------------------------------------------------------------------


def _dot(x, y):
    return x[0] * y[0] + x[1] * y[1] + x[2] * y[2]


def _cross(x, y):
    return jnp.stack([x[1] * y[2] - x[2] * y[1], x[2] * y[0] - x[0] * y[2], x[0] * y[1] - x[1] * y[0]])


def _point_segment(p, a, b):
    """|p - x| for x the clipped projection of p on [a, b] (a real point of the segment)."""
    d = b - a
    dd = _dot(d, d)
    t = jnp.where(dd > 0, _dot(p - a, d) / jnp.where(dd > 0, dd, 1), 0)
    t = jnp.where(t > 0, jnp.where(t < 1, t, 1), 0)  # comparisons: NaN falls back to 0
    x = (1 - t) * a + t * b
    return jnp.sqrt(_dot(p - x, p - x))


def segment_segment_distance(p0, p1, q0, q1) -> jax.Array:
    """A lower bound of the distance between segments ``[p0, p1]`` and ``[q0, q1]`` (m), tight up to
    rounding except for nearly parallel segments (module docstring: at most ``|n| / max |d|``
    low). One pair; batch with ``jax.vmap``. Never NaN for finite inputs."""
    p0, p1, q0, q1 = (jnp.asarray(v) for v in (p0, p1, q0, q1))
    dtype = jnp.result_type(p0, p1, q0, q1, 0.0)
    p0, p1, q0, q1 = (v.astype(dtype) for v in (p0, p1, q0, q1))
    u = float(jnp.finfo(dtype).eps) / 2
    boundary = jnp.minimum(jnp.minimum(_point_segment(p0, q0, q1), _point_segment(p1, q0, q1)),
                           jnp.minimum(_point_segment(q0, p0, p1), _point_segment(q1, p0, p1)))
    d1, d2, w = p1 - p0, q1 - q0, q0 - p0
    n = _cross(d1, d2)
    nn = _dot(n, n)
    l1, l2, lw = jnp.sqrt(_dot(d1, d1)), jnp.sqrt(_dot(d2, d2)), jnp.sqrt(_dot(w, w))
    safe_nn = jnp.where(nn > 0, nn, 1)
    kappa = (l1 * l2) ** 2 / safe_nn
    short = jnp.minimum(l1, l2)
    tau = K_SEG_TAU * u * kappa * (1 + lw / jnp.where(short > 0, short, 1))
    reliable = (nn > 0) & (short > 0) & (tau < 0.25)
    s = _dot(_cross(w, d2), n) / safe_nn
    t = _dot(_cross(w, d1), n) / safe_nn
    inside = (s >= -tau) & (s <= 1 + tau) & (t >= -tau) & (t <= 1 + tau)
    line = jnp.abs(_dot(w, n)) / jnp.sqrt(safe_nn) - K_SEG_LINE * u * lw * jnp.sqrt(kappa)
    long = jnp.maximum(l1, l2)
    slack = (jnp.sqrt(nn) + 8 * u * l1 * l2) / jnp.where(long > 0, long, 1) * (1 + 8 * u)
    interior = jnp.where(reliable, jnp.where(inside, line, jnp.inf), boundary - slack)
    return jnp.maximum(jnp.minimum(boundary, interior), 0)


def segment_segment_distance_np(p0, p1, q0, q1) -> float:
    """NumPy float64 reference: the exact minimum of ``|P(s) - Q(t)|`` over ``[0, 1]^2``, written
    independently (the four edges by clipped projection, the interior by solving the 2x2 normal
    equations with ``numpy.linalg.solve`` and evaluating the distance there)."""
    p0, p1, q0, q1 = (np.asarray(v, np.float64).reshape(3) for v in (p0, p1, q0, q1))
    d1, d2 = p1 - p0, q1 - q0

    def point_seg(p, a, d):
        dd = d @ d
        t = 0.0 if dd == 0 else min(max(float((p - a) @ d) / dd, 0.0), 1.0)
        return float(np.linalg.norm(p - (a + t * d)))

    best = min(point_seg(p0, q0, d2), point_seg(p1, q0, d2), point_seg(q0, p0, d1), point_seg(q1, p0, d1))
    A = np.array([[d1 @ d1, -(d1 @ d2)], [-(d1 @ d2), d2 @ d2]])
    if np.linalg.det(A) > 1e-12 * A[0, 0] * A[1, 1]:
        s, t = np.linalg.solve(A, np.array([d1 @ (q0 - p0), -(d2 @ (q0 - p0))]))
        if 0 <= s <= 1 and 0 <= t <= 1:
            best = min(best, float(np.linalg.norm(p0 + s * d1 - q0 - t * d2)))
    return best


# ----------------------------------------------------------------------------------------------
# The self test of one interval
# ----------------------------------------------------------------------------------------------


def self_clearance(p_world_a, p_world_b, radius, h_cov, speed, guard_m, first, second, motion_a, margin_m, skip):
    """``(g, guard, capsule1, capsule2)`` of the checked pair with the smallest ``g - guard`` on one
    interval (module docstring), from the interval test's placed segments, covering radius and
    speeds (:class:`~larc_jax.leaf.interval.IntervalEval`; ``speed = omega_max + omega_slack``).
    ``first``, ``second``: (P,) capsule indices (P >= 1), ``motion_a``: (P, n) ``A_pj``, ``skip``:
    (P,) pairs proven apart for this trajectory (their ``g`` is +inf); NaN ``g`` if anything is
    not finite."""
    eps = float(jnp.finfo(speed.dtype).eps)
    eps_g = float(jnp.finfo(p_world_a.dtype).eps)
    first, second = jnp.asarray(first), jnp.asarray(second)
    dist = jax.vmap(segment_segment_distance)(p_world_a[first], p_world_b[first], p_world_a[second],
                                              p_world_b[second])
    dist = dist.astype(speed.dtype) * (1 - K_DIST_REL * eps_g)
    shell = (radius[first] + radius[second] + motion_radii(motion_a, h_cov, speed) + margin_m) * (1 + 4 * eps)
    g = jnp.where(skip, jnp.inf, dist - shell)
    guard = guard_m[first] + guard_m[second]
    k = jnp.argmin(g - guard)  # a NaN is picked first (NumPy semantics) and never certifies
    return g[k], guard[k], first[k], second[k]


def self_clearance_np(p_world_a, p_world_b, radius, h_cov, speed, guard_m, pairs: SelfPairs, skip=None):
    """NumPy float64 reference of :func:`self_clearance` (the exact segment distance)."""
    eps = float(np.finfo(np.float64).eps)
    speed = np.asarray(speed, np.float64)
    b = motion_radii(pairs.motion_a, h_cov, speed)  # the relative motion of each pair
    best, out = math.inf, (math.inf, 0.0, -1, -1)
    for p, (c1, c2) in enumerate(zip(pairs.first, pairs.second)):
        dist = segment_segment_distance_np(p_world_a[c1], p_world_b[c1], p_world_a[c2], p_world_b[c2])
        dist *= 1 - K_DIST_REL * eps
        shell = (radius[c1] + radius[c2] + b[p] + pairs.margin_m) * (1 + 4 * eps)
        g, guard = (math.inf if skip is not None and skip[p] else dist - shell), float(guard_m[c1] + guard_m[c2])
        if g - guard < best or (math.isnan(g) and not math.isnan(best)):
            best, out = g - guard, (g, guard, int(c1), int(c2))
    return out


def self_stage(pl, radius, bounds, first, second, motion_a, margin_m, skip):
    """The self stage of the leaf test (:mod:`larc_jax.leaf.record`) on one placed interval
    (:class:`~larc_jax.leaf.placement.Placement`): :func:`self_clearance`'s ``(g, guard, capsule1,
    capsule2)``, ``g`` NaN where the placement is not finite. ``radius``: (C,) float64."""
    g, guard, c1, c2 = self_clearance(pl.p_world_a, pl.p_world_b, radius, pl.h_cov, pl.speed, bounds.guard_m,
                                      first, second, motion_a, margin_m, skip)
    return jnp.where(pl.finite, g, jnp.nan), guard, c1, c2


def self_stage_np(pl, radius, bounds, pairs: SelfPairs, skip=None) -> LeafRecord:
    """NumPy float64 twin of :func:`self_stage`, as a :class:`~larc_jax.leaf.record.LeafRecord`."""
    g, guard, c1, c2 = self_clearance_np(pl.p_world_a, pl.p_world_b, np.asarray(radius, np.float64), pl.h_cov,
                                         pl.speed, bounds.guard_m, pairs, skip)
    return self_record(g if pl.finite else math.nan, guard, c1, c2)
