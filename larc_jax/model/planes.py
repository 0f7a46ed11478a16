"""Infinite planes (MoveIt's ``plane a b c d``) as the square of them the robot can reach.

A MoveIt plane is the set ``{x : n . x + offset = 0}`` (``n = (a, b, c) / |(a, b, c)|``, ``offset =
d / |(a, b, c)|``, in the shape's frame; :func:`plane_from_coefficients` carries it to the base
frame), of zero thickness: a link on either side is clear of it, one crossing it collides (FCL's
``Plane``, which MoveIt builds for it). Nothing in the obstacle protocol is infinite, so a plane is
held as a posed box of zero thickness: the square ``S`` of half-side ``L`` (:data:`PLANE_HALF_SIDE_M`)
in the plane, centred on ``c``, the plane's point nearest the base origin, thickened to ``2 delta``
(``delta`` bounds how far float64 puts the stored square's plane from the user's, below).

Why that is enough. A certificate proves that every point of every enclosure is more than the
margin from ``S`` at every time, and the robot's geometry lies in its enclosures; it holds for the
plane if every robot point ``p`` is at least as far from ``S`` as from the plane, i.e. if the
plane's point nearest ``p``, ``y = P(p)``, lies in ``S``. ``P`` (projection onto the user's
plane) is 1-Lipschitz, so ``|y - P(0)| <= |p| <= R`` for a robot whose every point is within ``R``
of the base origin. The stored numbers differ from exact ones by rounding: ``c`` is within
``delta`` of ``P(0)``, the user's plane within ``delta`` of the stored one over the square
(``delta = 32 eps (1.5 L + 2 |offset| + |d| / |(a, b, c)| + |p_shape|_1)``, ``eps`` float64's
epsilon: the products and normalisations that make ``n`` and ``offset`` err by a few ``eps`` of
their terms, times distances up to ``|c| + 1.5 L``), and ``e = |c - P_stored(0)|`` (computed,
rounded up). So ``y`` lies within ``delta`` of the stored plane, and its projection onto it within
``R + 2 delta + e`` of ``c``: inside the square when ``R + e + 2 delta <= L``, so ``y`` is in ``S``.
:func:`check_plane_reach` checks ``R + e + 2 delta <= L`` for the run's enclosures before anything
compiles (``certify``) and again in ``larc verify``; ``R`` is the capsules' reach bound
(:func:`capsule_reach_m`: each capsule's farthest point from its link origin, its radius grown by
the padding and the tracking tolerance, plus its chain's joint offsets, held prismatic values and
active prismatic limits, which trajectories are checked to keep between waypoints too).

The square is stored as the scene's other shapes are (:class:`~larc_jax.model.shapes.Shapes`, kind
``box``, size ``(2 L, 2 L, 2 delta)``); a ``.scene`` plane whose normal is exactly ``±z`` in the
base frame is an axis-aligned box, every other plane (a YAML one always) a posed box. Its
rotation is built from ``n`` in float64 (third column ``n``), its rounding
defect counted like any posed shape's (R1 of :mod:`larc_jax.obstacles.convex_shapes`). Every
stage's rounding terms are measured on the numbers as computed: the capsule stage's in the
shape frame grow with the robot's distance from ``c``, not with ``L``; the hull and swept stages'
GJK terms grow with the support vertices, up to ``L`` (a few micrometres in float32 at 5 m):
sound, a little looser than for a small box.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..errors import LarcInputError
from ..defaults import POSITION_TOLERANCE
from .robot import Robot, chain_terms

__all__ = ["PLANE_HALF_SIDE_M", "Plane", "plane_from_coefficients", "capsule_reach_m", "check_plane_reach"]

PLANE_HALF_SIDE_M = 5.0
"""Half-side ``L`` of the square a plane is held as, m: the robot's reach bound must not exceed it
(module docstring). 5 m holds any arm whose capsules reach less far from its base."""


@dataclasses.dataclass(frozen=True)
class Plane:
    """One plane of a scene, base frame: ``normal_world . x + offset_m = 0``, and the square it is
    held as (the scene's shape or box named ``name``; module docstring)."""

    name: str
    normal_world: tuple[float, float, float]
    """Unit normal, base frame."""
    offset_m: float
    centre_world: tuple[float, float, float]
    """``c``: the square's centre, the plane's point nearest the base origin, m."""
    R_world_square: tuple[tuple[float, float, float], ...]
    """The square's orientation (its third column the normal)."""
    half_side_m: float = PLANE_HALF_SIDE_M
    half_thickness_m: float = 0.0
    """``delta`` (module docstring), m."""

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise LarcInputError(f"Plane.name must be a non-empty string, got {self.name!r}")
        n, c, R = (np.asarray(v, np.float64) for v in (self.normal_world, self.centre_world, self.R_world_square))
        if n.shape != (3,) or c.shape != (3,) or R.shape != (3, 3) or not all(
                np.isfinite(v).all() for v in (n, c, R)) or not math.isfinite(self.offset_m):
            raise LarcInputError(f"plane '{self.name}': normal, centre and rotation must be finite 3-vectors and a 3x3")
        if not 0 < self.half_side_m < math.inf or not 0 <= self.half_thickness_m < self.half_side_m:
            raise LarcInputError(f"plane '{self.name}': half_side_m must be positive and half_thickness_m smaller, got "
                                 f"{self.half_side_m!r}, {self.half_thickness_m!r}")

    @property
    def size_m(self) -> np.ndarray:
        """The square's full sides in its frame: ``(2 L, 2 L, 2 delta)``."""
        return 2 * np.array([self.half_side_m, self.half_side_m, self.half_thickness_m])

    @property
    def reach_limit_m(self) -> float:
        """``L - e - 2 delta``: how far from the base origin the robot may reach (module docstring)."""
        return self.half_side_m - self.inplane_offset_m - 2 * self.half_thickness_m

    @property
    def inplane_offset_m(self) -> float:
        """``e``: the stored centre's distance from the base origin's projection onto the stored
        plane (through ``c``, normal the rotation's third column), rounded up."""
        c, n = np.asarray(self.centre_world), np.asarray(self.R_world_square)[:, 2]
        e = float(np.linalg.norm(c - n * float(n @ c)))
        return (e + 8 * np.finfo(np.float64).eps * float(np.abs(c).sum())) * (1 + 1e-12)

    def assumption(self) -> str:
        """What a certificate over this plane assumes of it, in words."""
        n = ", ".join(repr(float(x)) for x in self.normal_world)
        sign = "-" if self.offset_m < 0 else "+"
        return (f"{self.name}: plane [{n}] . x {sign} {abs(float(self.offset_m))!r} = 0 (base frame), held as the square of "
                f"half-side {self.half_side_m!r} m centred on its point nearest the base origin: the plane itself for "
                f"every robot point within {self.reach_limit_m!r} m of the base origin (the square "
                f"{2 * self.half_thickness_m:.3g} m thick to hold float64 rounding), checked for the run's capsules")


def plane_from_coefficients(name: str, coefficients, p_world_shape, R_world_shape, where: str,
                            half_side_m: float | None = None) -> Plane:
    """The plane ``a x + b y + c z + d = 0`` of a shape frame placed at ``p_world_shape,
    R_world_shape`` (MoveIt: the object pose composed with the shape pose), base frame, held as
    the square of half-side ``half_side_m`` (default :data:`PLANE_HALF_SIDE_M`)."""
    half_side_m = PLANE_HALF_SIDE_M if half_side_m is None else half_side_m
    abc, d = np.asarray(coefficients[:3], np.float64), float(coefficients[3])
    norm = float(np.linalg.norm(abc))
    if not norm > 0 or not math.isfinite(norm):
        raise LarcInputError(f"{where}: plane {list(map(float, coefficients))} has no normal ((a, b, c) is zero)")
    R = np.asarray(R_world_shape, np.float64)
    n = R @ (abc / norm)
    n = n / np.linalg.norm(n)
    p = np.asarray(p_world_shape, np.float64)
    offset = d / norm - float(n @ p)
    eps = float(np.finfo(np.float64).eps)
    delta = 32 * eps * (1.5 * half_side_m + 2 * abs(offset) + abs(d) / norm + float(np.abs(p).sum()))
    centre = -offset * n
    if abs(n[0]) == 0 and abs(n[1]) == 0:  # exactly +-z: an axis-aligned square (the same set either way)
        R_sq = np.eye(3)
        centre = np.array([0.0, 0.0, -offset * n[2]])
    else:
        helper = np.eye(3)[int(np.argmin(np.abs(n)))]  # the axis least along n
        x = helper - n * float(n @ helper)
        x = x / np.linalg.norm(x)
        R_sq = np.stack([x, np.cross(n, x), n], axis=1)
    return Plane(name=name, normal_world=tuple(map(float, n)), offset_m=float(offset),
                 centre_world=tuple(map(float, centre)), R_world_square=tuple(tuple(map(float, r)) for r in R_sq),
                 half_side_m=float(half_side_m), half_thickness_m=delta)


def capsule_reach_m(robot: Robot, capsules) -> float:
    """An upper bound on the distance from the base origin of every point of every capsule of
    ``capsules`` (a :class:`~larc_jax.enclosure.capsule.CapsuleModel`) at every configuration a
    checked trajectory takes (prismatic joints within their limits widened by the position
    tolerance), m, rounded up."""
    a, b = (np.linalg.norm(np.asarray(v, np.float64), axis=1) for v in (capsules.p_link_a, capsules.p_link_b))
    ends = np.maximum(a, b) + np.asarray(capsules.radius, np.float64)
    _, fixed, prismatic = chain_terms(robot, capsules.link_index, ends)
    travel = np.maximum(np.abs(np.asarray(robot.q_lower, np.float64)),
                        np.abs(np.asarray(robot.q_upper, np.float64))) + POSITION_TOLERANCE
    reach = [f + sum(float(travel[j]) for j in js) for f, js in zip(fixed, prismatic)]
    terms = 2 + max((len(robot.ancestors(int(li))) for li in capsules.link_index), default=0)
    return max(reach, default=0.0) * (1 + 4 * terms * float(np.finfo(np.float64).eps))  # the sums' rounding


def check_plane_reach(scenes, robot: Robot, capsules, error=LarcInputError) -> None:
    """Raise ``error`` (``larc verify``: its ``Refuted``) if a plane of ``scenes`` is not the plane
    itself wherever the robot can be (module docstring), naming the scene, the plane and both distances."""
    planes = [(s, p) for s in {id(s): s for s in scenes}.values() for p in s.planes]
    if not planes:
        return
    reach = capsule_reach_m(robot, capsules)
    for s, p in planes:
        if not reach <= p.reach_limit_m:
            raise error(
                f"{s.source or s.name or 'Scene'}: plane '{p.name}' is held as the square of half-side "
                f"{p.half_side_m} m about the base origin (exact within {p.reach_limit_m:.6g} m of it), but the "
                f"robot's capsules reach up to {reach:.4g} m from it: give the part of the plane the robot can reach "
                "as a thin box")
