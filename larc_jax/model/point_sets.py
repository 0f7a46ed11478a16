"""Obstacles given by their points: triangle meshes and point clouds, split into convex pieces.

A scene's ``obstacles:`` entry of ``type: mesh`` (a triangle mesh file: STL, OBJ, PLY, or DAE,
read by trimesh, scaled per axis, then posed) or ``type: points`` (an ``.npy`` file holding an
(N, 3) array, a ``.ply`` point cloud, or a PCL ``.pcd`` file; posed; optionally a ``radius`` per
cloud: every point is then a ball) becomes one or more *pieces*, each given by its vertices in
the base frame and tested as their convex hull (:mod:`larc_jax.obstacles.convex_shapes`).

A ``.pcd`` file (:func:`read_pcd_points`, read by pypcd4: ascii, binary and binary_compressed) gives
its ``x, y, z`` fields as float64. A point without a finite coordinate is an organised cloud's
pixel with no return (PCL's NaN): it has no place, so it is no obstacle and is dropped (PCL's
``removeNaNFromPointCloud``); a certificate states that, and that the header's VIEWPOINT (the
sensor's pose) is not applied to the points, as PCL does not apply it on reading
(:meth:`PointSets.assumptions`): the entry's ``pose`` places the cloud.

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

__all__ = ["PointSets", "convex_pieces", "load_mesh_points", "load_cloud_points", "read_pcd_points", "mesh_from_arrays",
           "posed_mesh_pieces", "MESH_PIECE_TRIANGLES", "CLOUD_PIECE_POINTS", "POINT_SET_KINDS", "PCD_SUFFIX"]

POINT_SET_KINDS = ("mesh", "points")
MESH_PIECE_TRIANGLES = 16
"""Triangles per mesh piece at most (a non-convex mesh)."""
CLOUD_PIECE_POINTS = 64
"""Points per cloud piece at most."""
PCD_SUFFIX = ".pcd"
"""A PCL point-cloud file (:func:`read_pcd_points`)."""
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
                pcd = (", read from a .pcd file: its points with a finite x, y, z (a point without one, a pixel with "
                       "no return, is no obstacle), its header's VIEWPOINT not applied"
                       if Path(self.files[k]).suffix.lower() == PCD_SUFFIX else "")
                out.append(f"{name}: points, each a ball of radius {r!r} m{pcd}")
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
    V, F, convex = _checked_mesh(mesh, f"{source}: {where}.file {path}")
    return V * scale, F, convex, hashlib.sha256(data).hexdigest()


def mesh_from_arrays(vertices: np.ndarray, triangles: np.ndarray, where: str):
    """A mesh given by its arrays (a MoveIt ``.scene`` file's inline mesh), processed as a mesh
    file is (trimesh merges equal vertices): vertices (V, 3), triangles (T, 3), whether convex;
    :class:`LarcInputError` starting with ``where``."""
    import trimesh

    return _checked_mesh(trimesh.Trimesh(vertices=np.asarray(vertices, np.float64),
                                         faces=np.asarray(triangles, np.int64), process=True), where)


def _checked_mesh(mesh, where: str):
    V = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), np.float64)
    F = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), np.int64)
    if len(F) == 0 or len(V) == 0:
        raise LarcInputError(f"{where}: the mesh has no triangles")
    if len(V) > MAX_POINTS:
        raise LarcInputError(f"{where}: {len(V)} vertices, more than {MAX_POINTS}")
    if not np.isfinite(V).all():
        raise LarcInputError(f"{where}: a vertex is not finite")
    return V, F, bool(mesh.is_watertight and mesh.is_convex)


def posed_mesh_pieces(V: np.ndarray, F: np.ndarray, convex: bool, p, R) -> list[np.ndarray]:
    """A mesh's pieces in the base frame (read-only): the whole mesh if convex, else groups of at
    most :data:`MESH_PIECE_TRIANGLES` whole triangles (module docstring)."""
    world = _pose_points(V, p, R)
    pieces = [world] if convex else convex_pieces(world, F, MESH_PIECE_TRIANGLES)
    for piece in pieces:
        piece.setflags(write=False)
    return pieces


def read_pcd_points(data: bytes, where: str):
    """``(points (N, 3) float64, viewpoint (7,))`` of a PCL ``.pcd`` file's bytes: its ``x, y, z``
    fields, non-finite coordinates kept (the caller drops or reports them), and the header's
    VIEWPOINT (tx ty tz qw qx qy qz); :class:`LarcInputError` starting with ``where`` (the file, or
    the scene entry and file) for a file pypcd4 cannot read, one without x, y or z, or pypcd4
    missing."""
    import io

    try:
        import pypcd4
    except ImportError:
        raise LarcInputError(f"{where}: reading .pcd files needs pypcd4 (pip install 'larc_jax[clouds]')") from None
    try:
        cloud = pypcd4.PointCloud.from_fileobj(io.BytesIO(data))
        fields = tuple(cloud.fields)
    except Exception as exc:  # noqa: BLE001 - pypcd4 raises many kinds for a bad file
        raise LarcInputError(f"{where}: not a readable .pcd file ({type(exc).__name__}: "
                             f"{' '.join(str(exc).split())[:200]})") from None
    missing = [f for f in ("x", "y", "z") if f not in fields]
    if missing:
        raise LarcInputError(f"{where}: the .pcd file has no field {', '.join(missing)} (fields: {', '.join(fields)})")
    try:
        P = np.asarray(cloud.numpy(("x", "y", "z")), np.float64).reshape(-1, 3)
    except Exception as exc:  # noqa: BLE001 - a header that does not match its data
        raise LarcInputError(f"{where}: the .pcd file's x, y, z cannot be read ({type(exc).__name__})") from None
    return P, np.asarray(cloud.metadata.viewpoint, np.float64)


def load_cloud_points(path: Path, source: str, where: str):
    """Points (N, 3) of an ``.npy``, ``.ply`` or ``.pcd`` file (a ``.pcd``'s points without a finite
    x, y, z dropped: module docstring), and the file's SHA-256."""
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
    elif suffix == PCD_SUFFIX:
        P, _ = read_pcd_points(data, f"{source}: {where}.file {path}")
        P = P[np.isfinite(P).all(axis=1)]  # no return: no obstacle (module docstring)
        if len(P) == 0:
            raise LarcInputError(f"{source}: {where}.file {path}: the .pcd file has no point with a finite x, y, z")
    else:
        raise LarcInputError(f"{source}: {where}.file {path}: points are read from .npy (an (N, 3) array), .ply or "
                             f".pcd files, not {short_repr(suffix or path.name)} (larc points converts OctoMap "
                             "files)")
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
        return str(path), sha, posed_mesh_pieces(V, F, convex, p, R), convex
    P, sha = load_cloud_points(path, source, where)
    pieces = convex_pieces(_pose_points(P, p, R), None, CLOUD_PIECE_POINTS)
    for piece in pieces:
        piece.setflags(write=False)
    return str(path), sha, pieces, False
