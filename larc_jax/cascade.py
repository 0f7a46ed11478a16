"""The enclosure cascade: the capsule test first, the convex-hull test on what it leaves open.

An interval passes the cascade when, for every link ``l`` and box ``k``, *either* all of the
link's capsules clear the box (paper eq. 7) *or* all of its hull parts
(:mod:`larc_jax.enclosure.hull`) do: each of the two unions contains the link's geometry, so
either proof shows the link more than rho from the box on the whole interval. The hull test
of one part against one box is::

    g_h = lb(part at q(t_m), box) - (radius_p + b_p(I) + rho)

with ``lb`` the proven lower bound of :func:`larc_jax.polytope.polytope_box_lower_bound`,
``radius_p`` the padding (plus the containment slack) and ``b_p(I) = h * sum_j a_pj *
omega_max_j(I)`` the part's motion radius from its own motion constants (eq. 6). The part is
placed at the same midpoint ``q(t_m)``, with the same ``h`` and speed maxima, as the capsules:
both stages read them from one :class:`~larc_jax.interval.IntervalEval`, so the hull stage
inherits the capsule stage's time handling, and its clearance is compared with the same
rounding guard (the bound's own rounding is derived in :mod:`larc_jax.polytope`).

Order of work (all of it deterministic, so every scheduler takes the same decisions):

1. the capsule test on every interval (:mod:`larc_jax.interval`); intervals with
   ``g > guard`` pass ("capsule" stage); NaN fails;
2. for the others, one compacted call (:func:`interval_pairs`) gives every capsule-box
   clearance, the parts' link poses and motion radii, and for each part-box pair an *upper*
   bound of its hull clearance from 14 of its vertices (a point of the part is at least as far
   as the part);
3. a (link, box) pair is sent to the hull test when its capsules fail (``<= guard``) and every
   one of its parts could still pass (upper bound ``> guard``): otherwise the hull test could
   not change the outcome, and is skipped;
4. one compacted call on those (interval, part, box) triples (:func:`hull_pair_clearance`);
5. the interval's clearance is ``min over (l, k) of max(g_capsules(l, k), g_hull(l, k))``
   (``g_hull`` only where tested); it passes ("hull" stage) when that exceeds the guard.

:func:`combine` is step 5 (NumPy, shared by every scheduler); :func:`cascade_np` runs steps 1-5
on one interval with the NumPy float64 references (:func:`interval_pairs_np`,
:func:`~larc_jax.polytope.polytope_box_lower_bound_np`) for the reference scheduler.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from .enclosure.capsule import CapsuleModel
from .enclosure.hull import HullModel
from .geometry import segment_box_distance, segment_box_distance_np
from .interval import evaluate_interval, evaluate_interval_np
from .polytope import polytope_box_lower_bound, polytope_box_lower_bound_np
from .robot import Robot, forward_kinematics, forward_kinematics_np

__all__ = ["PairDetails", "interval_pairs", "interval_pairs_np", "hull_pair_clearance",
           "hull_pair_clearance_np", "Links", "select_pairs", "combine", "cascade_np"]

@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class PairDetails:
    """What step 2 computes on one interval (JAX or NumPy arrays)."""

    g_capsule: jax.Array
    """(C, B) capsule-box clearances (eq. 7), m; +inf for padding boxes."""
    T_part: jax.Array
    """(P, 3, 4) pose of each part's link at q(t_m): rotation | translation."""
    motion_b: jax.Array
    """(P,) motion radius of each part, m."""
    g_upper: jax.Array
    """(P, B) upper bound of each part-box hull clearance, m; +inf for padding boxes."""
    g: jax.Array
    """The capsule stage's clearance of the interval (as step 1), m."""


def _point_box_distance(p, lo, hi):
    gap = jnp.maximum(jnp.maximum(lo - p, p - hi), 0)
    return jnp.sqrt(jnp.sum(gap * gap, axis=-1))


def interval_pairs(robot: Robot, capsules: CapsuleModel, hulls: HullModel, spline, box_lo, box_hi, box_mask,
                   a, b, margin) -> PairDetails:
    """Step 2 on one interval ``[a, b]`` of one trajectory (kernel; batch with ``jax.vmap``)."""
    ev = evaluate_interval(robot, capsules, spline, box_lo, box_hi, box_mask, a, b, margin)
    per_box = jax.vmap(segment_box_distance, in_axes=(None, None, 0, 0))
    dist = jax.vmap(per_box, in_axes=(0, 0, None, None))(ev.p_world_a, ev.p_world_b, box_lo, box_hi)
    g_capsule = dist - (capsules.radius + ev.motion_b + margin)[:, None]
    g_capsule = jnp.where(box_mask[None, :], g_capsule, jnp.inf)
    T = forward_kinematics(robot, ev.q_mid)[jnp.asarray(hulls.link_index)][:, :3, :]  # (P, 3, 4)
    motion_b = ev.h * (hulls.motion_a.astype(T.dtype) @ ev.omega_max)  # eq. 6, the parts' own a_pj
    probes = jnp.einsum("pij,pqj->pqi", T[:, :, :3], hulls.probes.astype(T.dtype)) + T[:, None, :, 3]
    d = _point_box_distance(probes[:, :, None, :], box_lo[None, None], box_hi[None, None])  # (P, Q, B)
    g_upper = d.min(axis=1) - (hulls.radius.astype(T.dtype) + motion_b + margin)[:, None]
    g_upper = jnp.where(box_mask[None, :], g_upper, jnp.inf)
    return PairDetails(g_capsule=g_capsule, T_part=T, motion_b=motion_b, g_upper=g_upper, g=ev.g)


def hull_pair_clearance(hulls: HullModel, part, T_part, lo, hi, motion_b, margin) -> jax.Array:
    """Step 4 on one (part, box) pair: ``g_h`` of the module docstring (kernel; ``vmap`` it).

    Args:
      part: index of the part; T_part: (3, 4) its link's pose at q(t_m); lo, hi: (3,) the box;
      motion_b: the part's motion radius b_p(I), m; margin: rho, m.
    """
    lb = polytope_box_lower_bound(hulls.vertices, part, hulls.centre[part], T_part[:, :3], T_part[:, 3], lo, hi)
    return lb - (hulls.radius[part] + motion_b + margin)


# ----------------------------------------------------------------------------------------------
# NumPy float64 references
# ----------------------------------------------------------------------------------------------


def interval_pairs_np(robot: Robot, capsules: CapsuleModel, hulls: HullModel, traj, scene, a: float, b: float,
                      margin: float, ev=None) -> PairDetails:
    """NumPy float64 reference of :func:`interval_pairs` (``traj``: a Trajectory, ``scene``: a
    Scene; ``ev``: the interval's :func:`~larc_jax.interval.evaluate_interval_np`, if computed)."""
    ev = ev if ev is not None else evaluate_interval_np(robot, capsules, traj, scene, a, b, margin)
    radius = np.asarray(capsules.radius, np.float64)
    G = np.full((capsules.n_capsules, max(scene.n_boxes, 1)), np.inf)
    for c in range(capsules.n_capsules):
        for k in range(scene.n_boxes):
            G[c, k] = segment_box_distance_np(ev.p_world_a[c], ev.p_world_b[c], scene.lo[k], scene.hi[k]) - (
                radius[c] + ev.motion_b[c] + margin)
    T_all = forward_kinematics_np(robot, ev.q_mid)
    T = np.stack([T_all[li][:3, :] for li in hulls.link_index])
    motion_b = ev.h * (np.asarray(hulls.motion_a, np.float64) @ ev.omega_max)
    U = np.full((hulls.n_parts, max(scene.n_boxes, 1)), np.inf)
    probes = np.asarray(hulls.probes, np.float64)
    for p in range(hulls.n_parts):
        world = probes[p] @ T[p, :, :3].T + T[p, :, 3]
        for k in range(scene.n_boxes):
            gap = np.maximum(np.maximum(scene.lo[k] - world, world - scene.hi[k]), 0)
            U[p, k] = np.sqrt((gap * gap).sum(axis=1)).min() - (float(hulls.radius[p]) + motion_b[p] + margin)
    return PairDetails(g_capsule=G, T_part=T, motion_b=motion_b, g_upper=U, g=ev.g)


def hull_pair_clearance_np(hulls: HullModel, part: int, T_part, lo, hi, motion_b: float, margin: float) -> float:
    """NumPy float64 reference of :func:`hull_pair_clearance`."""
    V = np.asarray(hulls.vertices[part], np.float64)
    T_part = np.asarray(T_part, np.float64)
    lb = polytope_box_lower_bound_np(V, np.asarray(hulls.centre[part]), T_part[:, :3], T_part[:, 3], lo, hi)
    return lb - (float(hulls.radius[part]) + motion_b + margin)


# ----------------------------------------------------------------------------------------------
# Steps 3 and 5 (host side, NumPy; shared by every scheduler)
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Links:
    """Which link each capsule and each part belongs to (links numbered 0..L-1)."""

    of_capsule: np.ndarray
    """(C,) link number of each capsule."""
    of_part: np.ndarray
    """(P,) link number of each part."""
    n_links: int

    @staticmethod
    def of(capsules: CapsuleModel, hulls: HullModel) -> "Links":
        links = list(dict.fromkeys(capsules.link_names))
        missing = sorted(set(hulls.link_names) ^ set(links))
        if missing:
            from .errors import LarcInputError

            raise LarcInputError(f"capsules and hull parts cover different links: {missing}")
        return Links(np.array([links.index(l) for l in capsules.link_names]),
                     np.array([links.index(l) for l in hulls.link_names]), len(links))

    def reduce_min(self, values: np.ndarray, owner: np.ndarray) -> np.ndarray:
        """(..., E, B) values per capsule or part -> (..., L, B) minimum per link."""
        out = np.full(values.shape[:-2] + (self.n_links, values.shape[-1]), np.inf)
        for e, l in enumerate(owner):
            out[..., l, :] = np.minimum(out[..., l, :], values[..., e, :])  # NaN propagates
        return out


def select_pairs(links: Links, g_capsule: np.ndarray, g_upper: np.ndarray, guard) -> tuple[np.ndarray, np.ndarray]:
    """Step 3. ``g_capsule`` (F, C, B), ``g_upper`` (F, P, B), ``guard`` scalar or (F,).

    Returns ``tried`` (F, L, B), the (interval, link, box) pairs sent to the hull test, and the
    triples ``(interval, part, box)`` (T, 3) to evaluate (every part of every tried link)."""
    guard = np.asarray(guard, np.float64).reshape(-1, 1, 1)
    cap = links.reduce_min(g_capsule, links.of_capsule)
    upper = links.reduce_min(g_upper, links.of_part)
    tried = ~(cap > guard) & (upper > guard) & ~np.isnan(cap)
    i, l, k = np.nonzero(tried)
    triples = [np.stack([i[links.of_part[p] == l], np.full(np.sum(links.of_part[p] == l), p),
                         k[links.of_part[p] == l]], axis=1) for p in range(len(links.of_part))]
    triples = np.concatenate(triples) if triples else np.zeros((0, 3), np.int64)
    order = np.lexsort((triples[:, 2], triples[:, 1], triples[:, 0]))
    return tried, triples[order].astype(np.int64)


def combine(links: Links, g_capsule: np.ndarray, tried: np.ndarray, triples: np.ndarray, g_hull: np.ndarray,
            guard):
    """Step 5: per interval ``(g, capsule, box, passed)`` from the capsule matrix ``g_capsule``
    (F, C, B), the tried pairs and the hull clearances ``g_hull`` (T,) of the triples.
    ``capsule`` is the capsule of the blocking link nearest the blocking box."""
    F, C, B = g_capsule.shape
    cap = links.reduce_min(g_capsule, links.of_capsule)  # (F, L, B)
    hull = np.full(cap.shape, np.inf)
    if len(triples):
        i, p, k = triples.T
        np.minimum.at(hull, (i, links.of_part[p], k), g_hull)  # a NaN hull clearance propagates
    value = np.where(tried, np.maximum(cap, hull), cap)
    flat = value.reshape(F, -1)
    nan = np.isnan(flat).any(axis=1)
    best = np.argmin(np.where(np.isnan(flat), -np.inf, flat), axis=1)
    g = np.where(nan, np.nan, flat[np.arange(F), best])
    link, box = best // B, best % B
    on_link = links.of_capsule[None, :] == link[:, None]  # (F, C)
    per_cap = np.where(on_link, g_capsule[np.arange(F), :, box], np.inf)
    capsule = np.argmin(per_cap, axis=1)
    guard = np.asarray(guard, np.float64)
    return g, capsule, box, g > guard


def cascade_np(robot: Robot, capsules: CapsuleModel, hulls: HullModel, links: Links, traj, scene, a: float,
               b: float, margin: float, guard: float):
    """Steps 1-5 on one interval with the NumPy references: ``(g, capsule, box, stage)``."""
    ev = evaluate_interval_np(robot, capsules, traj, scene, a, b, margin)
    if ev.g > guard or math.isnan(ev.g):
        return ev.g, ev.capsule, ev.box, int(ev.g > guard)
    d = interval_pairs_np(robot, capsules, hulls, traj, scene, a, b, margin, ev)
    tried, triples = select_pairs(links, d.g_capsule[None], d.g_upper[None], guard)
    g_hull = np.array([hull_pair_clearance_np(hulls, p, d.T_part[p], scene.lo[k], scene.hi[k], d.motion_b[p], margin)
                       for _, p, k in triples])
    g, c, bx, passed = combine(links, d.g_capsule[None], tried, triples, g_hull, guard)
    return float(g[0]), int(c[0]), int(bx[0]), 2 if passed[0] else 0
