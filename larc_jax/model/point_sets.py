"""Obstacles given by their points: triangle meshes and point clouds, split into convex pieces.

A scene's ``obstacles:`` entry of ``type: mesh`` (a triangle mesh file: STL, OBJ, PLY, or DAE,
read by trimesh, scaled per axis, then posed) or ``type: points`` (an ``.npy`` file holding an
(N, 3) array, or a ``.ply`` point cloud; posed; optionally a ``radius`` per cloud: every point is
then a ball) becomes one or more *pieces*, each given by its vertices in the base frame and
tested as their convex hull (:mod:`larc_jax.obstacles.convex_shapes`).

Why the pieces contain the obstacle. A piece is the hull of a group of the obstacle's points;
for a mesh, the groups are groups of whole triangles and a piece holds all three corners of
each of its triangles, so each triangle lies in its piece's hull. The union of the pieces
therefore holds every point of the cloud, and every point of the mesh's surface: the distance
to the obstacle is at least the smallest distance to a piece. A mesh that trimesh finds convex
and watertight is one piece, which holds its solid too. A non-convex mesh is its surface, as in
FCL and MoveIt: a robot part entirely inside a closed non-convex mesh is not detected (split the
mesh into convex files, or use a convex one, to certify against its solid).

How the points are grouped (:func:`convex_pieces`): recursive median splits along the longest
side of the group's bounding box, down to :data:`MESH_PIECE_TRIANGLES` triangles or
:data:`CLOUD_PIECE_POINTS` points per piece. Neighbours end up together, so a piece of a
surface is thin and its hull hugs the surface; the cost is one polytope bound per piece.

A cloud's piece is also its points: the hull fills the gaps between them, so where a link
part's bound against the hull fails, the hull stage bounds the part's distance to each point
alone (R7 of :mod:`larc_jax.obstacles.convex_shapes`, a third round of
:mod:`larc_jax.leaf.cascade`'s step 4). A mesh's piece is not: its triangles fill the hull's
faces between its vertices.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
from pathlib import Path

import numpy as np

from ..errors import LarcInputError
from ..io import read_input_bytes, real_array, short_repr

__all__ = ["PointSets", "convex_pieces", "load_mesh_points", "load_cloud_points", "MESH_PIECE_TRIANGLES",
           "CLOUD_PIECE_POINTS", "POINT_SET_KINDS"]

POINT_SET_KINDS = ("mesh", "points")
MESH_PIECE_TRIANGLES = 16
"""Triangles per mesh piece at most (a non-convex mesh)."""
CLOUD_PIECE_POINTS = 64
"""Points per cloud piece at most."""
MAX_POINTS = 1_000_000
"""Points (or mesh vertices) per obstacle at most."""


@dataclasses.dataclass(frozen=True)
class PointSets:
    """The mesh and point-cloud obstacles of a scene, as convex pieces (module docstring)."""

    kinds: tuple[str, ...] = ()
    """Per obstacle: ``mesh`` or ``points``."""
    names: tuple[str, ...] = ()
    files: tuple[str, ...] = ()
    """Per obstacle: the file read (as resolved)."""
    file_sha256: tuple[str, ...] = ()
    """Per obstacle: SHA-256 of the file's bytes (certificates state them)."""
    radius: tuple[float, ...] = ()
    """Per obstacle: the radius of every point, m (0 for a mesh)."""
    pieces: tuple[np.ndarray, ...] = ()
    """Per piece: its vertices (k, 3) in the base frame, m (read-only float64)."""
    owner: tuple[int, ...] = ()
    """Per piece: the obstacle it belongs to."""
    solid: tuple[bool, ...] = ()
    """Per obstacle: whether it is certified against as a solid (a mesh that trimesh finds convex
    and watertight, one piece: its hull is the solid); else its surface (a non-convex mesh) or its
    points. Empty: none is (the API's default)."""

    def __post_init__(self):
        n = len(self.names)
        for field in ("kinds", "files", "file_sha256", "radius"):
            if len(getattr(self, field)) != n:
                raise LarcInputError(f"PointSets.{field} has {len(getattr(self, field))} entries for {n} obstacles")
        if len(self.owner) != len(self.pieces):
            raise LarcInputError(f"PointSets.owner has {len(self.owner)} entries for {len(self.pieces)} pieces")
        for k, kind in enumerate(self.kinds):
            if kind not in POINT_SET_KINDS:
                raise LarcInputError(f"PointSets.kinds[{k}] = {short_repr(kind)} is not one of {', '.join(POINT_SET_KINDS)}")
        if len(self.solid) not in (0, n):
            raise LarcInputError(f"PointSets.solid has {len(self.solid)} entries for {n} obstacles (give one per "
                                 "obstacle, or none)")
        for k, solid in enumerate(self.solid):
            if not isinstance(solid, (bool, np.bool_)) or (solid and self.kinds[k] != "mesh"):
                raise LarcInputError(f"PointSets.solid[{k}] must be True or False (True only for a mesh), got "
                                     f"{short_repr(solid)}")
            if solid and list(self.owner).count(k) != 1:
                raise LarcInputError(f"PointSets.solid[{k}]: a solid mesh is one piece (its convex hull)")
        for k, r in enumerate(self.radius):
            if isinstance(r, bool) or not isinstance(r, (int, float)) or not 0 <= r < math.inf:
                raise LarcInputError(f"PointSets.radius[{k}] must be a finite non-negative number, got {short_repr(r)}")
        pieces = []
        for g, (piece, o) in enumerate(zip(self.pieces, self.owner)):
            if isinstance(o, bool) or not isinstance(o, (int, np.integer)) or not 0 <= o < n:
                raise LarcInputError(f"PointSets.owner[{g}] = {short_repr(o)} is not an obstacle index (0..{n - 1})")
            arr = real_array(piece, f"PointSets.pieces[{g}]", 2, 3)
            if len(arr) == 0 or not np.isfinite(arr).all():
                raise LarcInputError(f"PointSets.pieces[{g}] must hold at least one point, all finite")
            pieces.append(arr)
        object.__setattr__(self, "pieces", tuple(pieces))
        object.__setattr__(self, "owner", tuple(int(o) for o in self.owner))
        object.__setattr__(self, "radius", tuple(float(r) for r in self.radius))

    def assumptions(self) -> tuple[str, ...]:
        """What a certificate over these obstacles assumes of each, in words (certificates and
        ``larc verify`` state them)."""
        out = []
        for k, (kind, name, r) in enumerate(zip(self.kinds, self.names, self.radius)):
            if kind == "points":
                out.append(f"{name}: points, each a ball of radius {r!r} m")
            elif self.solid and self.solid[k]:
                out.append(f"{name}: mesh, a solid (convex and watertight: its hull)")
            else:
                out.append(f"{name}: mesh, its surface only (not a convex watertight mesh: a link wholly inside "
                           "it is not seen)")
        return tuple(out)

    @property
    def count(self) -> int:
        """Pieces (each is one obstacle item of a result)."""
        return len(self.pieces)

    @property
    def piece_names(self) -> tuple[str, ...]:
        """``name`` for an obstacle of one piece, ``name[g]`` for its pieces otherwise."""
        counts = np.bincount(np.asarray(self.owner, int), minlength=len(self.names)) if self.owner else []
        seen: dict[int, int] = {}
        out = []
        for o in self.owner:
            g = seen.get(o, 0)
            seen[o] = g + 1
            out.append(self.names[o] if counts[o] == 1 else f"{self.names[o]}[{g}]")
        return tuple(out)

    def arrays(self):
        """``(vertices, sizes, owner)``: every piece's vertices stacked (M, 3), the vertex count per
        piece, the owner per piece (for hashing)."""
        if not self.pieces:
            return np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0, np.int64)
        return (np.concatenate(self.pieces), np.array([len(p) for p in self.pieces], np.int64),
                np.asarray(self.owner, np.int64))


def convex_pieces(points: np.ndarray, groups: np.ndarray | None, limit: int) -> list[np.ndarray]:
    """Split ``points`` into pieces of neighbours (module docstring). ``groups``: (T, 3) vertex
    indices of triangles (a mesh: whole triangles stay together, at most ``limit`` per piece), or
    None (a cloud: at most ``limit`` points per piece). Returns each piece's vertices."""
    items = points[groups].mean(axis=1) if groups is not None else points  # the positions split on
    out: list[np.ndarray] = []
    stack = [np.arange(len(items))]
    while stack:
        idx = stack.pop()
        if len(idx) <= limit:
            if groups is None:
                out.append(points[idx])
            else:
                out.append(points[np.unique(groups[idx].reshape(-1))])
            continue
        box = items[idx].max(axis=0) - items[idx].min(axis=0)
        axis = int(np.argmax(box))
        order = idx[np.argsort(items[idx, axis], kind="stable")]
        half = len(order) // 2
        stack += [order[half:], order[:half]]
    return out


def _read(path: Path, source: str, where: str, kind: str) -> bytes:
    """The file's bytes; its errors (missing, a directory, too large) name the scene and entry too."""
    try:
        return read_input_bytes(path, f"{kind} file")
    except LarcInputError as exc:
        raise LarcInputError(f"{source}: {where}.file: {exc}") from None


def _pose_points(points: np.ndarray, p, R) -> np.ndarray:
    return points @ np.asarray(R).T + np.asarray(p)


def load_mesh_points(path: Path, scale: np.ndarray, source: str, where: str):
    """Vertices (V, 3) (scaled, mesh frame), triangles (T, 3), whether convex, and the file's
    SHA-256; :class:`LarcInputError` naming the file and entry for anything unreadable."""
    import trimesh

    data = _read(path, source, where, "mesh")
    try:
        mesh = trimesh.load(trimesh.util.wrap_as_stream(data), file_type=path.suffix.lstrip(".").lower(), force="mesh",
                            process=True)
    except Exception as exc:  # trimesh raises many kinds for a bad file
        raise LarcInputError(f"{source}: {where}.file {path}: not a readable mesh ({type(exc).__name__}: "
                             f"{' '.join(str(exc).split())[:200]})") from None
    V = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), np.float64)
    F = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), np.int64)
    if len(F) == 0 or len(V) == 0:
        raise LarcInputError(f"{source}: {where}.file {path}: the mesh has no triangles")
    if len(V) > MAX_POINTS:
        raise LarcInputError(f"{source}: {where}.file {path}: {len(V)} vertices, more than {MAX_POINTS}")
    if not np.isfinite(V).all():
        raise LarcInputError(f"{source}: {where}.file {path}: a vertex is not finite")
    convex = bool(mesh.is_watertight and mesh.is_convex)
    return V * scale, F, convex, hashlib.sha256(data).hexdigest()


def load_cloud_points(path: Path, source: str, where: str):
    """Points (N, 3) of an ``.npy`` or ``.ply`` file, and the file's SHA-256."""
    suffix = path.suffix.lower()
    data = _read(path, source, where, "points")
    if suffix == ".npy":
        import io

        try:
            P = np.load(io.BytesIO(data), allow_pickle=False)
        except Exception as exc:
            raise LarcInputError(f"{source}: {where}.file {path}: not a readable .npy array ({type(exc).__name__})") from None
    elif suffix == ".ply":
        import trimesh

        try:
            P = np.asarray(trimesh.load(trimesh.util.wrap_as_stream(data), file_type="ply").vertices)
        except Exception as exc:
            raise LarcInputError(f"{source}: {where}.file {path}: not a readable .ply ({type(exc).__name__})") from None
    else:
        raise LarcInputError(f"{source}: {where}.file {path}: points are read from .npy (an (N, 3) array) or .ply "
                             f"files, not {short_repr(suffix or path.name)} (convert a .pcd with your PCL tools)")
    if P.dtype.kind not in "iuf" or P.ndim != 2 or P.shape[1] != 3 or len(P) == 0:
        raise LarcInputError(f"{source}: {where}.file {path}: expected an (N, 3) array of numbers with N >= 1, "
                             f"got shape {P.shape} of dtype {P.dtype}")
    if len(P) > MAX_POINTS:
        raise LarcInputError(f"{source}: {where}.file {path}: {len(P)} points, more than {MAX_POINTS}")
    P = P.astype(np.float64)
    if not np.isfinite(P).all():
        k = int(np.argwhere(~np.isfinite(P))[0][0])
        raise LarcInputError(f"{source}: {where}.file {path}: point {k} is not finite")
    return P, hashlib.sha256(data).hexdigest()


def point_set_entry(kind: str, entry: dict, base: Path, source: str, where: str, p, R, scale, radius: float):
    """One ``mesh`` / ``points`` entry: ``(file, sha256, pieces, solid)`` in the base frame (``solid``:
    :attr:`PointSets.solid`)."""
    file = entry.get("file")
    if not isinstance(file, str) or not file:
        raise LarcInputError(f"{source}: {where}.file must be a file name, got {short_repr(file)}")
    path = Path(file) if Path(file).is_absolute() else base / file
    if kind == "mesh":
        V, F, convex, sha = load_mesh_points(path, scale, source, where)
        world = _pose_points(V, p, R)
        pieces = [world] if convex else convex_pieces(world, F, MESH_PIECE_TRIANGLES)
    else:
        convex = False
        P, sha = load_cloud_points(path, source, where)
        pieces = convex_pieces(_pose_points(P, p, R), None, CLOUD_PIECE_POINTS)
    for piece in pieces:
        piece.setflags(write=False)
    return str(path), sha, pieces, convex
