"""Static obstacle scenes: axis-aligned boxes and posed shapes in the robot base frame.

Scene YAML::

    frame: base_link            # must be the robot's root link
    units: m                    # optional; only metres are accepted
    name: cell                  # optional
    boxes:                      # axis-aligned boxes
      - {name: wall_left, min: [x, y, z], max: [x, y, z]}
    obstacles:                  # posed shapes (larc_jax.model.shapes); pose and orientation optional
      - {name: board, type: box, size: [sx, sy, sz],
         pose: {position: [x, y, z], orientation: [qx, qy, qz, qw]}}
      - {name: ball, type: sphere, radius: r, pose: {position: [x, y, z]}}
      - {name: post, type: cylinder, radius: r, length: l, pose: ...}   # axis along the pose's z
      - {name: cone, type: cone, radius: r, length: l, pose: ...}
      - {name: floor, type: plane, normal: [a, b, c], offset: d, pose: ...}   # a x + b y + c z + d = 0

A scene needs ``boxes`` or ``obstacles`` (or both; ``[]`` for none). Any other field, in the
scene or in an entry, is an error naming it (a typo such as ``obstacle:`` or ``box:`` must not
read as a scene with fewer obstacles).

MoveIt ``.scene`` text (``PlanningScene::saveGeometryToStream``, MoveIt 1 and 2), read when the
file name ends in ``.scene``::

    scene name
    * object name
    px py pz                    # object pose: present in the newer layout only
    qx qy qz qw
    1                           # number of shapes
    box
    sx sy sz                    # full side lengths, m
    px py pz                    # shape pose, relative to the object pose
    qx qy qz qw
    r g b a                     # colour (ignored)
    0                           # subframes: newer layout only (name + pose each; ignored)
    .

As in MoveIt, the newer layout is recognised by the line after the first ``*`` line holding
several numbers (a position) rather than one (the shape count). Coordinates are metres in the
MoveIt planning frame, which is taken to be the robot base frame (PIPER: ``base_link``): a scene
saved in another planning frame must be re-expressed first. A box whose orientation (object
pose composed with shape pose) is exactly the identity becomes an axis-aligned box; any other
box, and every sphere, cylinder and cone (``sphere`` r; ``cylinder`` / ``cone`` r l), becomes a
posed shape with its rotation kept (:class:`~larc_jax.model.shapes.Shapes`). A mesh (``mesh``, then
``V T``, V vertices ``x y z`` in the shape's frame, T triangles ``i j k`` indexing them, as
``shapes::saveAsText`` writes it) becomes a mesh obstacle placed by the composed pose, exactly as
a YAML ``type: mesh`` entry of the same triangles (:mod:`larc_jax.model.point_sets`: a convex
watertight mesh is a solid, any other its surface; its file is the ``.scene`` file). A plane
(``plane``, then ``a b c d``: the infinite plane ``a x + b y + c z + d = 0`` of the shape's frame) is
held as its square of half-side 5 m about the base origin, a box of rounding thickness, which holds
the plane wherever the robot can be: ``certify`` and ``larc verify`` check the robot's reach
(:mod:`larc_jax.model.planes`), and certificates state it (``scenes[].assumes``). MoveIt does not
write octrees to ``.scene`` files; the word is refused.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import math
import re
from pathlib import Path
from typing import Sequence

import numpy as np
import yaml

from ..errors import LarcInputError
from ..io import (check_keys, decode_text, deferred_log, parse_vector, parse_yaml, read_input_bytes, read_input_text,
                  real_array, short_repr)
from .planes import Plane, plane_from_coefficients
from .point_sets import MAX_POINTS, PointSets, mesh_from_arrays, posed_mesh_pieces
from .shapes import QUATERNION_NORM_TOLERANCE, Shapes, rotation_from_quaternion, shapes_from_entries

__all__ = ["Scene", "read_scene", "read_moveit_scene", "scene_from_dict", "pad_scenes"]

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class Scene:
    """Obstacles of one scene: axis-aligned boxes, and posed shapes (``shapes``).

    The constructor accepts array-likes (``[[x, y, z], ...]``; ``[]`` for no boxes) and stores
    read-only float64 copies; a wrong type or shape (a single box given as ``[x, y, z]``, say),
    a non-finite corner, ``min > max``, or a wrong number of names raises
    :class:`LarcInputError` naming the field and box.
    """

    lo: np.ndarray
    """(B, 3) box minimum corners in the base frame, m."""
    hi: np.ndarray
    """(B, 3) box maximum corners in the base frame, m (hi >= lo componentwise)."""
    box_names: tuple[str, ...] = ()
    """B names (default ``box0``, ``box1``, ...)."""
    name: str = ""
    frame: str = ""
    """The frame the boxes are in: the robot's root link; "" (default) means exactly that."""
    source: str = ""
    shapes: Shapes = dataclasses.field(default_factory=Shapes)
    """Posed shapes (oriented boxes, spheres, cylinders, cones); none by default."""
    point_sets: PointSets = dataclasses.field(default_factory=PointSets)
    """Meshes and point clouds, as convex pieces; none by default."""
    planes: tuple[Plane, ...] = ()
    """Planes (:mod:`larc_jax.model.planes`), each held as the box or shape of its name."""

    def __post_init__(self):
        for field in ("name", "frame", "source"):
            if not isinstance(getattr(self, field), str):
                raise LarcInputError(f"Scene.{field} must be a string, got {short_repr(getattr(self, field))}")
        src = self.source or self.name or "Scene"
        lo, hi = (_boxes_array(getattr(self, f), f"{src}: Scene.{f}") for f in ("lo", "hi"))
        if lo.shape != hi.shape:
            raise LarcInputError(f"{src}: Scene.lo has {len(lo)} boxes but Scene.hi has {len(hi)}")
        for f, arr in (("lo", lo), ("hi", hi)):
            if not np.isfinite(arr).all():
                k, i = map(int, np.argwhere(~np.isfinite(arr))[0])
                raise LarcInputError(f"{src}: Scene.{f}[{k}][{i}] is not finite ({float(arr[k, i])!r})")
        if (lo > hi).any():
            k, i = map(int, np.argwhere(lo > hi)[0])
            raise LarcInputError(f"{src}: box {k}: Scene.lo[{k}][{i}] = {float(lo[k, i])!r} exceeds "
                                 f"Scene.hi[{k}][{i}] = {float(hi[k, i])!r}")
        names = self.box_names
        if isinstance(names, str) or not isinstance(names, (list, tuple)) or not all(isinstance(n, str) for n in names):
            raise LarcInputError(f"{src}: Scene.box_names must be a list of names, got {short_repr(names)}")
        if names and len(names) != len(lo):
            raise LarcInputError(f"{src}: Scene.box_names has {len(names)} names for {len(lo)} boxes")
        if not isinstance(self.shapes, Shapes):
            raise LarcInputError(f"{src}: Scene.shapes must be a Shapes record, got {short_repr(self.shapes)}")
        if not isinstance(self.point_sets, PointSets):
            raise LarcInputError(f"{src}: Scene.point_sets must be a PointSets record, got {short_repr(self.point_sets)}")
        for field, value in (("lo", lo), ("hi", hi), ("box_names", tuple(names) or tuple(f"box{k}" for k in range(len(lo))))):
            object.__setattr__(self, field, value)
        if not isinstance(self.planes, (list, tuple)) or not all(isinstance(p, Plane) for p in self.planes):
            raise LarcInputError(f"{src}: Scene.planes must be a list of Plane records, got {short_repr(self.planes)}")
        held = tuple(self.box_names) + self.shapes.names
        for p in self.planes:
            if p.name not in held:
                raise LarcInputError(f"{src}: plane '{p.name}' has no box or shape of its name (its square)")
        object.__setattr__(self, "planes", tuple(self.planes))

    def assumptions(self) -> tuple[str, ...]:
        """What a certificate over this scene assumes of its meshes, clouds and planes, in words
        (certificates state them; ``larc verify`` checks them against the files)."""
        return self.point_sets.assumptions() + tuple(p.assumption() for p in self.planes)

    @property
    def n_boxes(self) -> int:
        """Axis-aligned boxes."""
        return len(self.lo)

    @property
    def n_obstacles(self) -> int:
        """Obstacle items: the boxes, then the shapes, then the pieces of the meshes and point
        clouds (a result's obstacle index counts these)."""
        return len(self.lo) + self.shapes.count + self.point_sets.count

    @property
    def obstacle_names(self) -> tuple[str, ...]:
        """Names of the boxes, then of the shapes, then of the pieces."""
        return tuple(self.box_names) + self.shapes.names + self.point_sets.piece_names

    @property
    def posed(self) -> bool:
        """Whether the scene holds anything but axis-aligned boxes."""
        return bool(self.shapes.count or self.point_sets.count)

    @staticmethod
    def empty(name: str = "empty") -> "Scene":
        return Scene(lo=np.zeros((0, 3)), hi=np.zeros((0, 3)), name=name)


def _boxes_array(value, where: str) -> np.ndarray:
    """(B, 3) corners; an empty list or array means no boxes."""
    if (isinstance(value, (list, tuple)) and len(value) == 0) or (isinstance(value, np.ndarray) and value.shape == (0,)):
        return real_array(np.zeros((0, 3)), where, 2, 3)
    return real_array(value, where, 2, 3)


_SCENE_KEYS = ("frame", "units", "name", "boxes", "obstacles")
_BOX_KEYS = ("name", "min", "max")


def scene_from_dict(doc, *, source: str = "<scene>", name: str = "", frame: str | None = None) -> Scene:
    """Build a scene from a parsed YAML mapping; ``frame`` (if given) is the required frame."""
    if not isinstance(doc, dict):
        raise LarcInputError(f"{source}: expected a mapping with 'frame' and 'boxes'")
    check_keys(doc, _SCENE_KEYS, source)
    scene_frame = doc.get("frame", "base_link")
    if not isinstance(scene_frame, str):
        raise LarcInputError(f"{source}: frame must be a link name, got {short_repr(scene_frame)}")
    if frame is not None and scene_frame != frame:
        raise LarcInputError(
            f"{source}: frame '{scene_frame}' is not the robot base frame '{frame}'"
        )
    units = doc.get("units", "m")
    if not isinstance(units, str) or units not in ("m", "meter", "meters", "metre", "metres"):
        raise LarcInputError(
            f"{source}: units {short_repr(units)} are not supported (boxes are in metres: use m)")
    if "boxes" not in doc and "obstacles" not in doc:  # a typo ('box:') must not read as an empty scene
        raise LarcInputError(
            f"{source}: missing field 'boxes' or 'obstacles' (found fields {short_repr(sorted(map(str, doc)))}); "
            f"write 'boxes: []' for a scene without obstacles")
    base = Path(source).parent if source and not source.startswith("<") else Path(".")
    shapes, point_sets, planes = shapes_from_entries(doc.get("obstacles"), source, base)
    boxes = doc.get("boxes")
    if boxes is None:
        boxes = []
    if not isinstance(boxes, list):
        raise LarcInputError(f"{source}: boxes must be a list, got {short_repr(boxes)}")
    lo, hi, names = [], [], []
    for k, box in enumerate(boxes):
        where = f"boxes[{k}]"
        if not isinstance(box, dict):
            raise LarcInputError(f"{source}: {where} must be a mapping with min and max")
        check_keys(box, _BOX_KEYS, source, where)
        for key in ("min", "max"):
            if key not in box:
                raise LarcInputError(f"{source}: {where}.{key} is missing")
        b_lo = parse_vector(box["min"], 3, source, f"{where}.min", finite=True)
        b_hi = parse_vector(box["max"], 3, source, f"{where}.max", finite=True)
        if (b_lo > b_hi).any():
            i = int(np.flatnonzero(b_lo > b_hi)[0])
            raise LarcInputError(
                f"{source}: {where}.min[{i}] = {b_lo[i]} exceeds {where}.max[{i}] = {b_hi[i]}"
            )
        lo.append(b_lo)
        hi.append(b_hi)
        box_name = box.get("name", f"box{k}")
        if isinstance(box_name, bool) or not isinstance(box_name, (str, int, float)):
            raise LarcInputError(f"{source}: {where}.name must be a string, got {short_repr(box_name)}")
        names.append(str(box_name))
    return Scene(
        lo=np.array(lo).reshape(-1, 3), hi=np.array(hi).reshape(-1, 3), box_names=tuple(names),
        name=name or str(doc.get("name", "")), frame=scene_frame, source=source, shapes=shapes,
        point_sets=point_sets, planes=planes,
    )


def read_scene(path: str | Path, *, frame: str | None = None) -> Scene:
    """Read a scene file: MoveIt ``.scene`` text if the name ends in ``.scene``, else YAML.

    ``frame`` (if given) is the robot base frame the scene must be in. A YAML scene states its
    frame and is checked; a ``.scene`` file has none and is taken to be in it (module docstring).
    """
    path = Path(path)
    if path.suffix.lower() == ".scene":
        with deferred_log(log):  # a refused file gives its error line only, not warnings too
            return read_moveit_scene(path, frame=frame)
    doc = parse_yaml(read_input_text(path, "scene file"), str(path))
    if doc is None:
        raise LarcInputError(f"{path}: scene file is empty")
    return scene_from_dict(doc, source=str(path), name=path.stem, frame=frame)


class _Tokens:
    """Whitespace-separated tokens of a ``.scene`` file with their line numbers (MoveIt reads
    the file as a stream, so line breaks between numbers do not matter)."""

    def __init__(self, lines: list[str], start: int, source: str):
        self.items: list[tuple[str, int, str]] = []   # (token, line number, rest of line after '*')
        for lineno in range(start, len(lines)):
            line = lines[lineno]
            for m in re.finditer(r"\S+", line):
                rest = line[m.end():].strip() if m.group() == "*" else ""
                self.items.append((m.group(), lineno + 1, rest))
        self.pos = 0
        self.source = source
        self.last_line = len(lines)

    def error(self, line: int, message: str) -> LarcInputError:
        return LarcInputError(f"{self.source}:{line}: {message}")

    def next(self, what: str) -> tuple[str, int, str]:
        if self.pos >= len(self.items):
            raise self.error(self.last_line, f"file ends where {what} was expected (no '.' end line?)")
        item = self.items[self.pos]
        self.pos += 1
        return item

    def skip_line(self, line: int) -> None:
        while self.pos < len(self.items) and self.items[self.pos][1] == line:
            self.pos += 1

    def number(self, what: str) -> tuple[float, int]:
        tok, line, _ = self.next(what)
        try:
            value = float(tok)
        except ValueError:
            raise self.error(line, f"{what}: '{tok}' is not a number") from None
        if not math.isfinite(value):
            raise self.error(line, f"{what}: '{tok}' is not finite")
        return value, line

    def count(self, what: str) -> tuple[int, int]:
        tok, line, _ = self.next(what)
        if not (tok.isascii() and tok.isdigit()):
            raise self.error(line, f"{what}: '{tok}' is not a non-negative integer")
        return int(tok), line

    def pose(self, what: str) -> tuple[np.ndarray, np.ndarray]:
        """Position and rotation matrix of ``px py pz qx qy qz qw``."""
        p = np.array([self.number(f"{what} position")[0] for _ in range(3)])
        q = np.empty(4)
        for i in range(4):
            q[i], line = self.number(f"{what} orientation")
        norm = float(np.linalg.norm(q))
        if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
            raise self.error(line, f"{what} orientation quaternion {q.tolist()} has norm {norm:.6g}, not 1")
        return p, rotation_from_quaternion(q / norm)


_REFUSED_SHAPES = ("octree",)
_SHAPE_NUMBERS = {"box": 3, "sphere": 1, "cylinder": 2, "cone": 2}
"""Dimensions MoveIt writes per shape: box sx sy sz; sphere r; cylinder and cone r l."""


def read_moveit_scene(path: str | Path, *, frame: str | None = None) -> Scene:
    """Read a MoveIt ``.scene`` text file (old and new layouts; see the module docstring).

    Errors are ``file:line: message``. Boxes, spheres, cylinders, cones and meshes are accepted,
    their rotations kept (an exactly axis-aligned box is an axis-aligned box). The scene's frame is
    ``frame`` (default ``base_link``): the file itself names none.
    """
    path = Path(path)
    source = str(path)
    data = read_input_bytes(path, "scene file")  # missing, directory, permissions; read once, hashed below
    text = decode_text(data, path)  # binary
    lines = text.splitlines()
    if not text.strip():
        raise LarcInputError(f"{path}: scene file is empty")
    toks = _Tokens(lines, 1, source)
    # Layout detection as in MoveIt: the line after the first '*' line has spaces in the new one.
    new_layout = False
    for i in range(1, len(lines)):
        if lines[i].startswith("*"):
            following = lines[i + 1].strip() if i + 1 < len(lines) else ""
            new_layout = len(following.split()) > 1
            break
    lo, hi, names = [], [], []
    shape_rows: list = []  # (kind, name, dims, p_world_shape, R_world_shape)
    mesh_rows: list = []  # (name, pieces, solid)
    planes: list[Plane] = []
    seen: set[str] = set()
    while True:
        marker, line, rest = toks.next("'* object name' or the end line '.'")
        if marker == ".":
            break
        if marker != "*":
            raise toks.error(line, f"expected '* object name' or the end line '.', found '{marker}'")
        obj = rest
        if not obj:
            raise toks.error(line, "object has no name after '*'")
        if obj in seen:
            raise toks.error(line, f"object '{obj}' appears twice")
        seen.add(obj)
        toks.skip_line(line)
        if new_layout:
            p_obj, r_obj = toks.pose(f"object '{obj}' pose")
        else:
            p_obj, r_obj = np.zeros(3), np.eye(3)
        n_shapes, _ = toks.count(f"object '{obj}' shape count")
        for k in range(n_shapes):
            shape, sline, _ = toks.next(f"object '{obj}' shape {k} type")
            shape_name = obj if n_shapes == 1 else f"{obj}[{k}]"
            if shape == "mesh":
                mesh_rows.append((shape_name, *_moveit_mesh(toks, obj, k, sline, p_obj, r_obj)))
                continue
            if shape == "plane":  # its square (larc_jax.model.planes): axis-aligned if its normal is +-z exactly
                plane = _moveit_plane(toks, obj, k, shape_name, p_obj, r_obj)
                planes.append(plane)
                centre, R_sq = np.asarray(plane.centre_world), np.asarray(plane.R_world_square)
                if bool((R_sq == np.eye(3)).all()):
                    half = plane.size_m / 2
                    lo.append(centre - half), hi.append(centre + half), names.append(shape_name)
                else:
                    shape_rows.append(("box", shape_name, plane.size_m, centre, R_sq))
                continue
            if shape not in _SHAPE_NUMBERS:
                kind = shape if shape in _REFUSED_SHAPES else f"unknown shape type '{shape}'"
                raise toks.error(
                    sline, f"object '{obj}' shape {k} is a {kind}: only boxes, spheres, cylinders, cones, meshes and "
                    f"planes are supported (replace it by one that encloses it)")
            numbers = np.empty(_SHAPE_NUMBERS[shape])
            for i in range(len(numbers)):
                numbers[i], dline = toks.number(f"object '{obj}' {shape} size")
            if (numbers < 0).any():
                raise toks.error(dline, f"object '{obj}' {shape} size {numbers.tolist()} is negative")
            p_shape, r_shape = toks.pose(f"object '{obj}' shape {k} pose")
            for _ in range(4):
                toks.number(f"object '{obj}' shape {k} colour")
            center = p_obj + r_obj @ p_shape
            rot = r_obj @ r_shape
            if shape == "box" and bool((rot == np.eye(3)).all()):  # exactly axis-aligned
                lo.append(center - numbers / 2.0)
                hi.append(center + numbers / 2.0)
                names.append(shape_name)
            else:  # the rotation kept (larc_jax.model.shapes)
                dims = numbers if shape == "box" else np.concatenate([numbers, np.zeros(3 - len(numbers))])
                shape_rows.append((shape, shape_name, dims, center, rot))
        if new_layout:
            n_sub, _ = toks.count(f"object '{obj}' subframe count")
            for k in range(n_sub):
                toks.next(f"object '{obj}' subframe {k} name")
                toks.pose(f"object '{obj}' subframe {k} pose")
    if toks.pos < len(toks.items):
        tok, line, _ = toks.items[toks.pos]
        raise toks.error(line, f"'{tok}' after the end line '.' (one scene per file)")
    shapes = Shapes(kinds=tuple(r[0] for r in shape_rows), names=tuple(r[1] for r in shape_rows),
                    dims=np.array([r[2] for r in shape_rows]).reshape(-1, 3),
                    p_world_shape=np.array([r[3] for r in shape_rows]).reshape(-1, 3),
                    R_world_shape=np.array([r[4] for r in shape_rows]).reshape(-1, 3, 3))
    sha = hashlib.sha256(data).hexdigest() if mesh_rows else ""  # the bytes parsed
    point_sets = PointSets(kinds=("mesh",) * len(mesh_rows), names=tuple(r[0] for r in mesh_rows),
                           files=(source,) * len(mesh_rows), file_sha256=(sha,) * len(mesh_rows),
                           radius=(0.0,) * len(mesh_rows), pieces=tuple(x for r in mesh_rows for x in r[1]),
                           owner=tuple(o for o, r in enumerate(mesh_rows) for _ in r[1]),
                           solid=tuple(r[2] for r in mesh_rows))
    return Scene(
        lo=np.array(lo).reshape(-1, 3), hi=np.array(hi).reshape(-1, 3), box_names=tuple(names),
        name=path.stem, frame=frame or "", source=source, shapes=shapes, point_sets=point_sets,
        planes=tuple(planes),
    )


def _moveit_plane(toks: _Tokens, obj: str, k: int, name: str, p_obj, r_obj) -> Plane:
    """A ``.scene`` plane after its ``plane`` word: ``a b c d``, the shape pose, the colour."""
    what = f"object '{obj}' shape {k} (plane)"
    coefficients = [toks.number(f"{what} coefficients") for _ in range(4)]
    p_shape, r_shape = toks.pose(f"{what} pose")
    for _ in range(4):
        toks.number(f"{what} colour")
    return plane_from_coefficients(name, [c for c, _ in coefficients], p_obj + r_obj @ p_shape, r_obj @ r_shape,
                                   f"{toks.source}:{coefficients[0][1]}: {what}")


def _moveit_mesh(toks: _Tokens, obj: str, k: int, line: int, p_obj, r_obj):
    """A ``.scene`` mesh after its ``mesh`` word (module docstring): its pieces in the base frame and
    whether it is a solid (convex and watertight)."""
    what = f"object '{obj}' shape {k} (mesh)"
    n_v, vline = toks.count(f"{what} vertex count")
    n_t, tline = toks.count(f"{what} triangle count")
    if n_v > MAX_POINTS:
        raise toks.error(vline, f"{what} has {n_v} vertices, more than {MAX_POINTS}")
    if n_t == 0:
        raise toks.error(tline, f"{what} has no triangles")
    V = np.array([toks.number(f"{what} vertex")[0] for _ in range(3 * n_v)]).reshape(-1, 3)
    F = np.empty(3 * n_t, np.int64)
    for i in range(len(F)):
        F[i], iline = toks.count(f"{what} triangle")
        if F[i] >= n_v:
            raise toks.error(iline, f"{what} triangle {i // 3} names vertex {F[i]}, but the mesh has {n_v} vertices")
    p_shape, r_shape = toks.pose(f"{what} pose")
    for _ in range(4):
        toks.number(f"{what} colour")
    V, F, solid = mesh_from_arrays(V, F.reshape(-1, 3), f"{toks.source}:{line}: {what}")
    return posed_mesh_pieces(V, F, solid, p_obj + r_obj @ p_shape, r_obj @ r_shape), solid


def pad_scenes(scenes: Sequence[Scene], n_boxes: int | None = None):
    """Stack scenes into padded arrays.

    Returns ``lo (S, B, 3)``, ``hi (S, B, 3)``, ``mask (S, B)`` with B = ``n_boxes`` or the
    largest scene (at least 1). Padding boxes are degenerate at the origin and masked out.
    """
    B = max([s.n_boxes for s in scenes] + [1]) if n_boxes is None else n_boxes
    lo = np.zeros((len(scenes), B, 3))
    hi = np.zeros((len(scenes), B, 3))
    mask = np.zeros((len(scenes), B), bool)
    for i, s in enumerate(scenes):
        lo[i, : s.n_boxes] = s.lo
        hi[i, : s.n_boxes] = s.hi
        mask[i, : s.n_boxes] = True
    return lo, hi, mask
