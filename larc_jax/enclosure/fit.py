"""Fitting capsules to the link meshes, and the containment proof.

Containment (paper eq. 2 at zero motion). A capsule is the set of points within ``radius`` of a
segment, hence convex. The collision geometry of a link is split into elements
(:func:`~larc_jax.enclosure.meshes.link_elements`: mesh triangles, or primitives replaced by a
circumscribed polyhedron). An element lies in a capsule iff each of its vertices does
(convexity), so checking every vertex (:func:`verify_containment`) proves that the whole mesh
lies in the union of the link's capsules. Fitting and checking use ``radius - padding``: the
stored radius carries ``padding_m`` of extra margin on top. Radii are rounded *up* to the
micrometre from the endpoints the file will hold, so the file itself is what is proven.

Fitting (:func:`fit_capsules`): a minimum-volume capsule around the convex hull of each link's
vertices (Nelder-Mead from the three principal directions); optionally two capsules per link,
its elements split whole (never clipped) along the principal axis at the cut that minimises the
total volume. A link whose geometry cannot be split into two non-empty parts (a single
primitive, a single triangle, elements with one centroid) keeps one capsule.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from typing import Mapping, Sequence

import numpy as np

from ..errors import LarcInputError
from ..model.robot import Robot
from .capsule import CapsuleModel
from .meshes import link_elements, stroke_shifts

__all__ = ["FittedCapsule", "fit_capsules", "fit_stated_capsules", "verify_containment", "point_segment_distance",
           "inside_capsule"]

log = logging.getLogger(__name__)

_SPLIT_FRACTIONS = (0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8)

_ROUND = 1e-6  # radii are rounded *up* to the micrometre (endpoints are stored to it).
_DIST_SLACK = 32 * float(np.finfo(np.float64).eps)
"""Float64 rounding of :func:`point_segment_distance`, per metre of |p| + |a| + |b| (a handful
of operations, each off by at most u): containment is claimed only with this much to spare."""


def inside_capsule(points: np.ndarray, a: np.ndarray, b: np.ndarray, core: float) -> np.ndarray:
    """Which points (..., 3) are within ``core`` of segment [a, b], float64 rounding included."""
    scale = np.linalg.norm(points, axis=-1) + np.linalg.norm(a) + np.linalg.norm(b)
    return point_segment_distance(points, a, b) + _DIST_SLACK * scale <= core


def point_segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances of points ``p`` (..., 3) to the segment [a, b], float64."""
    d = b - a
    dd = float(d @ d)
    t = np.zeros(p.shape[:-1]) if dd == 0.0 else np.clip(((p - a) @ d) / dd, 0.0, 1.0)
    return np.linalg.norm(p - a - t[..., None] * d, axis=-1)


def _capsule_volume(length: float, r: float) -> float:
    return math.pi * r * r * length + 4.0 / 3.0 * math.pi * r**3


def _hull_points(points: np.ndarray) -> np.ndarray:
    from scipy.spatial import ConvexHull, QhullError

    pts = np.unique(points.reshape(-1, 3), axis=0)
    try:
        return pts[ConvexHull(pts).vertices]
    except (QhullError, ValueError):
        return pts  # degenerate (flat) sets: every point is kept, still exact


def _hull_volume(points: np.ndarray) -> float:
    from scipy.spatial import ConvexHull, QhullError

    try:
        return float(ConvexHull(np.unique(points.reshape(-1, 3), axis=0)).volume)
    except (QhullError, ValueError):
        return 0.0


def _fit_one(points: np.ndarray, maxiter: int = 3000) -> tuple[np.ndarray, np.ndarray, float]:
    """Minimum-volume capsule (core radius, no padding) around ``points`` (hull vertices)."""
    from scipy.optimize import minimize

    centre = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centre, full_matrices=False)

    def volume(x: np.ndarray) -> float:
        a, b = x[:3], x[3:]
        return _capsule_volume(float(np.linalg.norm(b - a)), float(point_segment_distance(points, a, b).max()))

    best = None
    for u in vt:  # a start along each principal direction
        s = (points - centre) @ u
        r0 = float(np.linalg.norm((points - centre) - np.outer(s, u), axis=1).max())
        half = max(0.0, (s.max() - s.min()) / 2 - r0 * 0.5)
        mid = centre + u * (s.max() + s.min()) / 2
        x0 = np.concatenate([mid - half * u, mid + half * u])
        res = minimize(volume, x0, method="Nelder-Mead",
                       options=dict(maxiter=maxiter, xatol=1e-6, fatol=1e-12))
        if best is None or res.fun < best.fun:
            best = res
    return best.x[:3], best.x[3:], volume(best.x)


def _best_split(elements: np.ndarray) -> float | None:
    """The cut fraction giving the smallest total volume of two capsules, or None when no cut
    leaves both parts non-empty (a single primitive, elements sharing one centroid)."""
    best = None
    for frac in _SPLIT_FRACTIONS:
        m1, m2 = _split_parts(elements, frac)
        if not (m1.any() and m2.any()):
            continue
        f1 = _fit_one(_hull_points(elements[m1]), maxiter=600)
        f2 = _fit_one(_hull_points(elements[m2]), maxiter=600)
        if best is None or f1[2] + f2[2] < best[0]:
            best = (f1[2] + f2[2], frac)
    return None if best is None else best[1]


def _split_parts(elements: np.ndarray, cut_fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """Split elements (whole, never clipped) by their centroid along the principal axis."""
    c = elements.mean(axis=1)
    centre = c.mean(axis=0)
    _, _, vt = np.linalg.svd(c - centre, full_matrices=False)
    s = (c - centre) @ vt[0]
    cut = np.quantile(s, cut_fraction)
    mask = s <= cut
    return mask, ~mask


@dataclasses.dataclass
class FittedCapsule:
    name: str
    link: str
    a: np.ndarray
    b: np.ndarray
    radius: float
    volume_m3: float
    hull_volume_m3: float
    n_elements: int


def _finalise(name, link, elems, a, b, padding) -> FittedCapsule:
    # Store endpoints to the micrometre, then take the radius from the *stored* endpoints so the
    # file itself is what containment is proven for; round the radius up, never down.
    a = np.array([round(float(x), 6) for x in a])  # exactly the values the file will hold
    b = np.array([round(float(x), 6) for x in b])
    core = float(point_segment_distance(elems.reshape(-1, 3), a, b).max())
    radius = round(math.ceil((core + padding) / _ROUND) * _ROUND, 6)
    while not inside_capsule(elems.reshape(-1, 3), a, b, radius - padding).all():  # the file must not undercut the proof
        radius = round(radius + _ROUND, 6)
    return FittedCapsule(
        name, link, a, b, radius,
        _capsule_volume(float(np.linalg.norm(b - a)), radius),
        _hull_volume(elems), len(elems),
    )


def fit_capsules(
    robot: Robot,
    *,
    n_capsules: int | None = None,
    capsules_per_link: Mapping[str, int] | None = None,
    padding_m: float = 0.001,
    links: Sequence[str] | None = None,
    progress=None,
) -> list[FittedCapsule]:
    """Fit minimum-volume capsules to every link with collision geometry.

    Each link gets one capsule; links listed in ``capsules_per_link`` with 2 get two, as do the
    links that gain most volume from a split until ``n_capsules`` is reached. With two capsules
    the link's elements (triangles) are split whole along the principal axis, at the cut that
    minimises the total volume.
    """
    per_link = dict(capsules_per_link or {})
    for k, v in per_link.items():
        if v not in (1, 2):
            raise LarcInputError(f"capsules_per_link: link '{k}' asks for {v} capsules (1 or 2)")
    names = list(links) if links is not None else list(robot.link_names)
    elements = {}
    for link in names:
        e = link_elements(robot, link)
        if len(e):
            elements[link] = e
    if not elements:
        raise LarcInputError(f"{robot.urdf_path}: no link has collision geometry")
    unknown = [k for k in per_link if k not in elements]
    if unknown:
        raise LarcInputError(f"capsules_per_link: link '{unknown[0]}' is not a link with collision geometry "
                             f"(links: {', '.join(elements)})")

    single, double = {}, {}
    for link, e in elements.items():
        if progress:
            progress(f"fitting {link}")
        single[link] = _fit_one(_hull_points(e))
        if per_link.get(link, 2 if n_capsules else 1) == 2:
            best = _best_split(e)
            if best is None:
                if per_link.get(link) == 2:
                    log.warning("link '%s' has %d collision element%s that cannot be split in two: it keeps one "
                                "capsule", link, len(e), "" if len(e) == 1 else "s")
                continue
            m1, m2 = _split_parts(e, best)
            double[link] = (m1, m2, _fit_one(_hull_points(e[m1])), _fit_one(_hull_points(e[m2])))

    split = {l for l, v in per_link.items() if v == 2 and l in double}
    if n_capsules is not None:
        free = [l for l in double if l not in split and per_link.get(l) != 1]
        budget = n_capsules - len(elements) - len(split)
        if budget < 0 or budget > len(free):
            fixed = sorted(set(elements) - set(double))
            raise LarcInputError(
                f"cannot fit {n_capsules} capsules to {len(elements)} links with collision geometry: between "
                f"{len(elements) + len(split)} and {len(elements) + len(split) + len(free)}"
                + (f" (cannot be split: {', '.join(fixed)})" if fixed else ""))
        gains = sorted(((single[l][2] - double[l][2][2] - double[l][3][2], l) for l in free), reverse=True)
        split |= {l for _, l in gains[:budget]}

    out = []
    for link, e in elements.items():
        if link in split:
            m1, m2, f1, f2 = double[link]
            out.append(_finalise(f"{link}_a", link, e[m1], f1[0], f1[1], padding_m))
            out.append(_finalise(f"{link}_b", link, e[m2], f2[0], f2[1], padding_m))
        else:
            a, b, _ = single[link]
            out.append(_finalise(link, link, e, a, b, padding_m))
    return out


def fit_stated_capsules(robot: Robot, *, padding_m: float = 0.001, progress=None) -> list[FittedCapsule]:
    """Capsules of the links whose enclosure covers a stroke (below an unstated held prismatic
    joint, e.g. PIPER's fingers), fitted to each link alone in its own frame: what the robot
    file's ``stated_capsules`` hold, used when the gripper opening is stated."""
    links = [l for l in robot.link_names if len(stroke_shifts(robot, l)) > 1 and len(link_elements(robot, l))]
    if not links:
        return []
    stated = dataclasses.replace(robot, stated_joints=robot.stated_joints + robot.stroke_joints)
    return fit_capsules(stated, links=links, padding_m=padding_m, progress=progress)


# ----------------------------------------------------------------------------------------------
# Containment check
# ----------------------------------------------------------------------------------------------


def verify_containment(robot: Robot, capsules: CapsuleModel, *, source: str = "capsule file",
                       progress=None) -> dict:
    """Prove that every collision element of every link lies inside one of its link's capsules
    shrunk by the padding (float64 rounding of the distances included). Raises
    :class:`LarcInputError` naming the link and element otherwise; ``progress(link)`` is called
    before each link.

    Returns ``{link: number of elements checked}``.
    """
    checked = {}
    for link in dict.fromkeys(capsules.link_names):
        if progress:
            progress(link)
        elems = link_elements(robot, link)
        idx = [c for c, l in enumerate(capsules.link_names) if l == link]
        inside = np.zeros(len(elems), bool)
        for c in idx:
            a = np.asarray(capsules.p_link_a[c], np.float64)
            b = np.asarray(capsules.p_link_b[c], np.float64)
            core = float(capsules.radius[c]) - capsules.padding_m
            inside |= inside_capsule(elems, a, b, core).all(axis=1)
        if not inside.all():
            bad = int(np.flatnonzero(~inside)[0])
            raise LarcInputError(
                f"{source}: link '{link}' element {bad} (of {len(elems)}) is not inside any of "
                f"its capsules {[capsules.names[c] for c in idx]} shrunk by the padding"
            )
        checked[link] = len(elems)
    for i, link in enumerate(robot.link_names):
        if link not in checked and len(link_elements(robot, link)):
            raise LarcInputError(f"{source}: link '{link}' has collision geometry but no capsule")
    return checked
