"""Posed convex primitives of a scene: oriented boxes, spheres, cylinders and cones.

A scene's ``boxes`` are axis-aligned; everything else it holds is a :class:`Shapes` record: per
shape a kind (:data:`SHAPE_KINDS`), a name, its dimensions and its pose in the robot base frame
(``p_world_shape``, m; ``R_world_shape``, from a unit quaternion). The geometry follows URDF and
MoveIt (``geometric_shapes``): every shape is centred on its pose; a box has full side lengths
``size``; a cylinder and a cone have their axis along the pose's z, a ``radius`` and a ``length``
(the cone's base and tip at ``z = -length/2`` and ``+length/2``, or the other way round: it is
tested as the cylinder around it, so which end is the tip never matters for soundness).

How each kind is tested (:mod:`larc_jax.obstacles.convex_shapes`): in the shape's own frame,
every shape lies in the intersection of a box ``[lo, hi]`` and, for round shapes, a capsule
(the points within ``radius`` of the z segment ``[-axis_half, axis_half]``). The distance to an
intersection is at least the larger of the distances to its two sets, so the larger of the two
lower bounds is one. For a cylinder the intersection is the cylinder itself; the bound is exact
for a box and a sphere, and for a cylinder except beyond its rim, where it is at least
``1 / sqrt 2`` of the true distance (a point ``a`` out radially and ``b`` out axially gets at
least ``max(a, b)`` of ``sqrt(a^2 + b^2)``). A cone is tested as its cylinder.
:func:`local_geometry` gives these per-shape numbers; they are exact in float64 (halving is exact).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from ..errors import LarcInputError
from ..io import check_keys, parse_number, parse_vector, short_repr

__all__ = ["SHAPE_KINDS", "Shapes", "rotation_from_quaternion", "local_geometry", "shapes_from_entries",
           "QUATERNION_NORM_TOLERANCE", "unit_quaternion", "pose_from_entry", "shape_mesh", "shape_outline", "shape_project", "outline_2d"]

SHAPE_KINDS = ("box", "sphere", "cylinder", "cone")
"""Kinds of posed shape (``obstacles:`` entry ``type``; MoveIt shape names)."""

QUATERNION_NORM_TOLERANCE = 1e-3
"""A quaternion is normalised; one whose norm is further than this from 1 is refused (MoveIt
writes 6 significant digits, so a genuine rotation is within ~1e-6)."""

_DIMENSIONS = {"box": ("size",), "sphere": ("radius",), "cylinder": ("radius", "length"), "cone": ("radius", "length")}


def rotation_from_quaternion(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a unit quaternion ``(x, y, z, w)`` (float64)."""
    x, y, z, w = np.asarray(q, np.float64)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def unit_quaternion(q, source: str, where: str) -> np.ndarray:
    """``q`` (4 numbers, x y z w) normalised; :class:`LarcInputError` if its norm is not 1
    within :data:`QUATERNION_NORM_TOLERANCE`."""
    q = np.asarray(q, np.float64)
    norm = float(np.linalg.norm(q))
    if not abs(norm - 1.0) <= QUATERNION_NORM_TOLERANCE:
        raise LarcInputError(f"{source}: {where} quaternion {q.tolist()} has norm {norm:.6g}, not 1 "
                             "(orientation is [qx, qy, qz, qw])")
    return q / norm


@dataclasses.dataclass(frozen=True)
class Shapes:
    """Posed convex shapes (module docstring); the arrays are read-only float64 copies."""

    kinds: tuple[str, ...] = ()
    """P kinds, each in :data:`SHAPE_KINDS`."""
    names: tuple[str, ...] = ()
    dims: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3)))
    """(P, 3), m: a box's full side lengths; a sphere's ``(radius, 0, 0)``; a cylinder's or cone's
    ``(radius, length, 0)``."""
    p_world_shape: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3)))
    """(P, 3) shape centres in the robot base frame, m."""
    R_world_shape: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3, 3)))
    """(P, 3, 3) shape orientations (rotation matrices)."""

    def __post_init__(self):
        n = len(self.kinds)
        arrays = {}
        for field, shape in (("dims", (n, 3)), ("p_world_shape", (n, 3)), ("R_world_shape", (n, 3, 3))):
            value = np.array(getattr(self, field), dtype=np.float64)
            if value.shape != shape:
                raise LarcInputError(f"Shapes.{field} must have shape {shape}, got {value.shape}")
            if not np.isfinite(value).all():
                raise LarcInputError(f"Shapes.{field}[{int(np.argwhere(~np.isfinite(value))[0][0])}] is not finite")
            value.setflags(write=False)
            arrays[field] = value
        if len(self.names) != n:
            raise LarcInputError(f"Shapes: {len(self.names)} names for {n} shapes")
        for k, kind in enumerate(self.kinds):
            if kind not in SHAPE_KINDS:
                raise LarcInputError(f"Shapes.kinds[{k}] = {short_repr(kind)} is not one of {', '.join(SHAPE_KINDS)}")
        if (arrays["dims"] < 0).any():
            raise LarcInputError(f"Shapes.dims[{int(np.argwhere(arrays['dims'] < 0)[0][0])}] is negative")
        for field, value in arrays.items():
            object.__setattr__(self, field, value)
        object.__setattr__(self, "kinds", tuple(self.kinds))
        object.__setattr__(self, "names", tuple(str(s) for s in self.names))

    @property
    def count(self) -> int:
        return len(self.kinds)


def local_geometry(shapes: Shapes):
    """Per shape, in its own frame: the box ``lo, hi`` (P, 3), and the capsule ``axis_half``,
    ``radius`` (P,) with ``rounded`` (P,) saying whether the capsule applies (module docstring).
    Exact in float64: only halving and sign changes."""
    n = shapes.count
    lo, hi = np.zeros((n, 3)), np.zeros((n, 3))
    axis_half, radius, rounded = np.zeros(n), np.zeros(n), np.zeros(n, bool)
    for k, (kind, d) in enumerate(zip(shapes.kinds, shapes.dims)):
        if kind == "box":
            half = d / 2
        elif kind == "sphere":
            half = np.full(3, d[0])
            radius[k], rounded[k] = d[0], True
        else:  # cylinder, cone (tested as its cylinder)
            half = np.array([d[0], d[0], d[1] / 2])
            axis_half[k], radius[k], rounded[k] = d[1] / 2, d[0], True
        lo[k], hi[k] = -half, half
    return lo, hi, axis_half, radius, rounded


_ENTRY_KEYS = {"box": ("name", "type", "size", "pose"), "sphere": ("name", "type", "radius", "pose"),
               "cylinder": ("name", "type", "radius", "length", "pose"),
               "cone": ("name", "type", "radius", "length", "pose")}
_POINT_SET_KEYS = {"mesh": ("name", "type", "file", "scale", "pose"), "points": ("name", "type", "file", "radius", "pose")}
_PLANE_KEYS = ("name", "type", "normal", "offset", "pose")
_ALL_KINDS = SHAPE_KINDS + tuple(_POINT_SET_KEYS) + ("plane",)


def shapes_from_entries(entries, source: str, base: Path | None = None):
    """The ``obstacles:`` list of a scene YAML (:mod:`larc_jax.model.scene`): its shapes as
    :class:`Shapes`, its meshes and point clouds as :class:`~larc_jax.model.point_sets.PointSets`
    (files relative to ``base``, default the current folder) and its planes
    (:class:`~larc_jax.model.planes.Plane`, each also a shape: its square); every error names the
    file and the entry."""
    from .planes import plane_from_coefficients
    from .point_sets import PointSets, point_set_entry

    base = Path(".") if base is None else base
    if entries is None:
        entries = []
    if not isinstance(entries, list):
        raise LarcInputError(f"{source}: obstacles must be a list, got {short_repr(entries)}")
    kinds, names, dims, positions, rotations, planes = [], [], [], [], [], []
    sets: dict = {"kinds": [], "names": [], "files": [], "file_sha256": [], "radius": [], "pieces": [], "owner": [],
                  "solid": []}
    for k, entry in enumerate(entries):
        where = f"obstacles[{k}]"
        if not isinstance(entry, dict):
            raise LarcInputError(f"{source}: {where} must be a mapping with a type, got {short_repr(entry)}")
        kind = entry.get("type")
        if kind not in _ALL_KINDS:
            raise LarcInputError(f"{source}: {where}.type must be one of {', '.join(_ALL_KINDS)}, got {short_repr(kind)}")
        name = entry.get("name", f"{kind}{k}")
        if isinstance(name, bool) or not isinstance(name, (str, int, float)):
            raise LarcInputError(f"{source}: {where}.name must be a string, got {short_repr(name)}")
        if kind == "plane":  # normal . x + offset = 0 in the pose's frame (MoveIt's a b c d)
            check_keys(entry, _PLANE_KEYS, source, where)
            if "normal" not in entry or "offset" not in entry:
                raise LarcInputError(f"{source}: {where}: a plane needs normal and offset (normal . x + offset = 0)")
            abc = parse_vector(entry["normal"], 3, source, f"{where}.normal", finite=True)
            d = parse_number(entry["offset"], source, f"{where}.offset", finite=True)
            p, R = pose_from_entry(entry.get("pose"), source, f"{where}.pose")
            plane = plane_from_coefficients(str(name), [*abc, d], p, R, f"{source}: {where}")
            planes.append(plane)
            kinds.append("box"), names.append(plane.name), dims.append(plane.size_m)
            positions.append(np.asarray(plane.centre_world)), rotations.append(np.asarray(plane.R_world_square))
            continue
        if kind in _POINT_SET_KEYS:
            check_keys(entry, _POINT_SET_KEYS[kind], source, where)
            p, R = pose_from_entry(entry.get("pose"), source, f"{where}.pose")
            scale = parse_vector(entry.get("scale", [1, 1, 1]), 3, source, f"{where}.scale", finite=True)
            if (scale <= 0).any():
                raise LarcInputError(f"{source}: {where}.scale must be positive, got {scale.tolist()}")
            radius = parse_number(entry.get("radius", 0.0), source, f"{where}.radius", finite=True)
            if radius < 0:
                raise LarcInputError(f"{source}: {where}.radius must not be negative, got {radius}")
            file, sha, pieces, solid = point_set_entry(kind, entry, base, source, where, p, R, scale, radius)
            owner = len(sets["names"])
            for key, value in (("kinds", kind), ("names", str(name)), ("files", file), ("file_sha256", sha),
                               ("radius", radius), ("solid", solid)):
                sets[key].append(value)
            sets["pieces"] += pieces
            sets["owner"] += [owner] * len(pieces)
            continue
        check_keys(entry, _ENTRY_KEYS[kind], source, where)
        d = np.zeros(3)
        for i, field in enumerate(_DIMENSIONS[kind]):
            if field not in entry:
                raise LarcInputError(f"{source}: {where}.{field} is missing (a {kind} needs {', '.join(_DIMENSIONS[kind])})")
            if field == "size":
                d = parse_vector(entry[field], 3, source, f"{where}.size", finite=True)
            else:
                d[i] = parse_number(entry[field], source, f"{where}.{field}", finite=True)
        if (d < 0).any():
            raise LarcInputError(f"{source}: {where}: {'/'.join(_DIMENSIONS[kind])} must not be negative, got "
                                 f"{d[:3 if kind == 'box' else len(_DIMENSIONS[kind])].tolist()}")
        p, R = pose_from_entry(entry.get("pose"), source, f"{where}.pose")
        kinds.append(kind), names.append(str(name)), dims.append(d), positions.append(p), rotations.append(R)
    shapes = Shapes(kinds=tuple(kinds), names=tuple(names), dims=np.array(dims).reshape(-1, 3),
                    p_world_shape=np.array(positions).reshape(-1, 3), R_world_shape=np.array(rotations).reshape(-1, 3, 3))
    return shapes, PointSets(**{key: tuple(value) for key, value in sets.items()}), tuple(planes)


def pose_from_entry(pose, source: str, where: str):
    """``{position: [x, y, z], orientation: [qx, qy, qz, qw]}`` (both optional) as a position and
    a rotation matrix."""
    if pose is None:
        return np.zeros(3), np.eye(3)
    if not isinstance(pose, dict):
        raise LarcInputError(f"{source}: {where} must be a mapping with position and orientation, got {short_repr(pose)}")
    check_keys(pose, ("position", "orientation"), source, where)
    p = parse_vector(pose.get("position", [0, 0, 0]), 3, source, f"{where}.position", finite=True)
    if "orientation" not in pose:
        return p, np.eye(3)
    q = parse_vector(pose["orientation"], 4, source, f"{where}.orientation", finite=True)
    return p, rotation_from_quaternion(unit_quaternion(q, source, f"{where}.orientation"))


def shape_mesh(shapes: Shapes, k: int, sections: int = 32):
    """Shape ``k`` as a ``trimesh.Trimesh`` in the base frame (for drawing: a sphere, cylinder or
    cone is faceted, which the certifier never uses)."""
    import trimesh

    kind, d = shapes.kinds[k], shapes.dims[k]
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = shapes.R_world_shape[k], shapes.p_world_shape[k]
    if kind == "box":
        mesh = trimesh.creation.box(extents=np.maximum(d, 1e-6))
    elif kind == "sphere":
        mesh = trimesh.creation.icosphere(subdivisions=2, radius=max(d[0], 1e-6))
    elif kind == "cylinder":
        mesh = trimesh.creation.cylinder(radius=max(d[0], 1e-6), height=max(d[1], 1e-6), sections=sections)
    else:  # cone: base at -length/2, tip at +length/2 (geometric_shapes)
        mesh = trimesh.creation.cone(radius=max(d[0], 1e-6), height=max(d[1], 1e-6), sections=sections)
        mesh.apply_translation([0.0, 0.0, -d[1] / 2])
    mesh.apply_transform(T)
    return mesh


def shape_outline(shapes: Shapes, k: int, axes: tuple[int, int]) -> np.ndarray:
    """(M, 2) the convex outline of shape ``k`` projected on the base-frame ``axes`` (drawing)."""
    return outline_2d(np.asarray(shape_mesh(shapes, k).vertices)[:, list(axes)])


def outline_2d(points: np.ndarray) -> np.ndarray:
    """(M, 2) the convex hull of 2-D ``points``, counter-clockwise (Andrew's monotone chain)."""
    pts = np.unique(np.round(np.asarray(points, np.float64), 12), axis=0)  # sorted by x then y
    if len(pts) < 3:
        return pts

    def turn(o, a, b) -> float:  # z of the 2-D cross product (a - o) x (b - o)
        return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))

    def half(points):
        out: list = []
        for p in points:
            while len(out) >= 2 and turn(out[-2], out[-1], p) <= 0:
                out.pop()
            out.append(p)
        return out[:-1]

    return np.array(half(pts) + half(pts[::-1]))


def shape_project(shapes: Shapes, k: int, p_world: np.ndarray) -> np.ndarray:
    """The point of shape ``k`` nearest ``p_world`` (3,) (drawing; a cone as its cylinder, the
    set it is tested as)."""
    R, c, d = shapes.R_world_shape[k], shapes.p_world_shape[k], shapes.dims[k]
    x = R.T @ (np.asarray(p_world, np.float64) - c)
    kind = shapes.kinds[k]
    if kind == "box":
        y = np.clip(x, -d / 2, d / 2)
    elif kind == "sphere":
        n = float(np.linalg.norm(x))
        y = x if n <= d[0] else x * (d[0] / n)
    else:
        rho = float(np.hypot(x[0], x[1]))
        xy = x[:2] if rho <= d[0] else x[:2] * (d[0] / rho)
        y = np.array([xy[0], xy[1], np.clip(x[2], -d[1] / 2, d[1] / 2)])
    return c + R @ y
