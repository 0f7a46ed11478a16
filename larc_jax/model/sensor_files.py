"""Point clouds and occupancy maps from sensor files, as the ``.npy`` clouds a scene reads.

A scene's ``type: points`` entry reads an (N, 3) ``.npy`` array, a ``.ply`` cloud or a PCL ``.pcd``
file, with one ``radius`` per cloud (:mod:`larc_jax.model.point_sets`). Mapping stacks write other
formats, and a cloud may be too large for a scene; :func:`convert_sensor_file` (``larc points``)
turns them into such clouds (optionally reduced on a voxel grid) and states what each converted
obstacle assumes.

* **PCL ``.pcd``** (ascii, binary and binary_compressed; read by pypcd4, a maintained reader:
  ``pip install 'larc_jax[clouds]'``): the ``x, y, z`` fields of every point, as float64. A point
  with a non-finite coordinate (in an organised cloud, a pixel with no return: PCL's NaN) is
  dropped and counted. The header's VIEWPOINT is the sensor's pose; PCL does not apply it to the
  points on reading and neither does this (place the cloud with the entry's ``pose``); one other
  than the identity is reported.
* **OctoMap ``.bt`` / ``.ot``** (read by octomap-python): the occupied leaves
  (``isNodeOccupied``, the map's own threshold). A leaf is a cube of edge ``s`` (the resolution,
  or a power of two times it where the map pruned eight equal children into one); the ball of
  radius ``s·√3/2`` about its centre contains it, so each leaf becomes a point of a cloud of that
  radius (plus the single-precision rounding of the centres the binding gives, ``√3·2^-22·max|c|``),
  one cloud per leaf size. Free and unknown space are not obstacles: a certificate against a
  map says nothing of space its sensor never saw (stated in the output), unless ``unknown_in``
  names a box (the workspace): then every finest voxel meeting it that the map holds neither
  occupied nor free is an obstacle too (:func:`unknown_voxels`).
* **Voxel reduction** (``voxel_m``, any input): the points in each cube of a grid of edge ``S``
  become the cube's centre, and the cloud's radius grows by the largest distance from a point to
  its centre (at most ``S·√3/2``). Every original ball then lies inside the new ball about its
  cube's centre (triangle inequality), so what the scene holds contains every original obstacle.
  A cloud of more than :data:`~larc_jax.model.point_sets.MAX_POINTS` points must be reduced.

Rounding: every radius written is rounded upwards (:func:`radius_up`: relative ``1e-12``, far
above float64's few ulps in ``s·√3/2``, a sum, or a norm), so a written radius is never below the
real one; the centres are the coordinates the reader or the grid gives, and the cube a radius
covers is the one about them.
"""

from __future__ import annotations

import dataclasses
import io
import math
from pathlib import Path

import numpy as np

from ..errors import LarcInputError
from ..io import read_input_bytes, short_repr
from .point_sets import MAX_POINTS, read_pcd_points

__all__ = ["SensorCloud", "read_pcd", "read_plain", "read_octomap", "unknown_voxels", "check_voxel", "voxel_reduce", "radius_up", "convert_sensor_file",
           "POINT_SUFFIXES", "OCTOMAP_SUFFIXES"]

POINT_SUFFIXES = (".pcd",)
"""Point-cloud files :func:`convert_sensor_file` reads besides ``.npy`` and ``.ply`` (a scene reads all three)."""
OCTOMAP_SUFFIXES = (".bt", ".ot")
"""OctoMap files :func:`convert_sensor_file` reads: binary (``.bt``) and full (``.ot``) trees."""

RADIUS_SLACK = 1e-12
"""Relative upward rounding of every radius written (module docstring)."""

HALF_DIAGONAL = math.sqrt(3.0) / 2.0
"""A cube of edge ``s`` lies in the ball of radius ``s·HALF_DIAGONAL`` about its centre."""


@dataclasses.dataclass(frozen=True)
class SensorCloud:
    """One cloud to write: points (N, 3) float64 in the file's frame, the radius of each point
    (m), and what it assumes (sentences for the output)."""

    points: np.ndarray
    radius_m: float
    notes: tuple[str, ...] = ()


def radius_up(r: float) -> float:
    """``r`` rounded upwards (:data:`RADIUS_SLACK`); 0 stays 0."""
    r = float(r)
    return 0.0 if r == 0.0 else float(np.nextafter(r * (1.0 + RADIUS_SLACK), np.inf))


def _need(module: str, package: str, path: Path):
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        raise LarcInputError(f"{path}: reading {path.suffix} files needs {package} "
                             f"(pip install 'larc_jax[clouds]')") from None


def read_pcd(path: str | Path) -> SensorCloud:
    """The finite ``x, y, z`` points of a PCL ``.pcd`` file (radius 0), read as a scene reads one
    (:func:`~larc_jax.model.point_sets.read_pcd_points`); :class:`LarcInputError` naming the file
    for an unreadable one, one without x, y, z, or one with no finite point."""
    path = Path(path)
    if not path.is_file():
        raise LarcInputError(f"{path}: no such file")
    P, vp = read_pcd_points(read_input_bytes(path, "point cloud"), str(path))  # as scenes read it: size capped
    notes = ()
    if vp.shape == (7,) and not np.array_equal(vp, [0, 0, 0, 1, 0, 0, 0]):
        notes = (f"its VIEWPOINT (sensor pose tx ty tz qw qx qy qz = {' '.join(f'{v:g}' for v in vp)}) is not "
                 f"applied: place the cloud with the entry's pose",)
    finite = np.isfinite(P).all(axis=1)
    notes += (f"{len(P)} points read",)
    if not finite.all():
        notes += (f"{int((~finite).sum())} without a finite x, y, z (no return) dropped",)
    if not finite.any():
        raise LarcInputError(f"{path}: the file has no point with a finite x, y, z")
    return SensorCloud(P[finite], 0.0, notes)


def read_plain(path: str | Path) -> SensorCloud:
    """The points of an ``.npy`` (N, 3) array or a ``.ply`` cloud of any size (radius 0), checked as
    the scene reader checks them (numbers, finite) except for its limit of points: this is what
    reduces a larger cloud."""
    path = Path(path)
    if not path.is_file():
        raise LarcInputError(f"{path}: no such file")
    try:
        if path.suffix.lower() == ".npy":
            P = np.load(path, allow_pickle=False)
        else:
            import trimesh

            P = np.asarray(trimesh.load(path, file_type="ply").vertices)
    except Exception as exc:  # noqa: BLE001 - NumPy and trimesh raise many kinds for a bad file
        raise LarcInputError(f"{path}: not a readable {path.suffix} point file ({type(exc).__name__})") from None
    if P.dtype.kind not in "iuf" or P.ndim != 2 or P.shape[1] != 3 or len(P) == 0:
        raise LarcInputError(f"{path}: expected an (N, 3) array of numbers with N >= 1, got shape {P.shape} "
                             f"of dtype {P.dtype}")
    P = P.astype(np.float64)
    if not np.isfinite(P).all():  # as the scene reader: here a non-finite point is bad data, not a no-return
        raise LarcInputError(f"{path}: point {int(np.argwhere(~np.isfinite(P))[0][0])} is not finite")
    return SensorCloud(P, 0.0, (f"{len(P)} points read",))


def read_octomap(path: str | Path, unknown_in=None) -> list[SensorCloud]:
    """The occupied leaves of an OctoMap ``.bt`` / ``.ot`` file, as one cloud per leaf size (the
    leaves' centres, radius ``size·√3/2`` rounded up), smallest size first; with ``unknown_in``
    (``xmin, ymin, zmin, xmax, ymax, zmax``, m, the map's frame) also the finest voxels meeting
    that box which the map holds neither occupied nor free (:func:`unknown_voxels`)."""
    path = Path(path)
    octomap = _need("octomap", "octomap-python", path)
    if not path.is_file():
        raise LarcInputError(f"{path}: no such file")
    try:
        if path.suffix.lower() == ".bt":
            tree = octomap.OcTree(0.1)
            ok = tree.readBinary(str(path).encode())
        else:
            tree = octomap.OcTree.read(str(path).encode())
            ok = tree is not None
    except Exception as exc:  # noqa: BLE001 - the binding raises many kinds for a bad file
        raise LarcInputError(f"{path}: not a readable OctoMap file ({type(exc).__name__})") from None
    if not ok:
        raise LarcInputError(f"{path}: not a readable OctoMap file")
    centres, sizes = [], []
    for leaf in tree.begin_leafs():
        if tree.isNodeOccupied(leaf):
            centres.append(np.asarray(leaf.getCoordinate(), np.float64))
            sizes.append(float(leaf.getSize()))
    C, S = np.asarray(centres, np.float64).reshape(-1, 3), np.asarray(sizes, np.float64)
    if not (np.isfinite(C).all() and np.isfinite(S).all() and (S > 0).all()):
        raise LarcInputError(f"{path}: a leaf's centre or size is not finite")
    unknown = "free space is not an obstacle, nor unknown space " + (
        "outside the --unknown-in box" if unknown_in is not None else
        "(nothing is proven about space the map does not hold as occupied; --unknown-in makes a box's unknown "
        "voxels obstacles)")
    out = []
    for s in np.unique(S):
        notes = (f"{int((S == s).sum())} occupied leaves of edge {s:g} m (resolution {tree.getResolution():g} m), "
                 f"each inside a ball of radius {s:g}·√3/2 about its centre", unknown)
        # The binding gives centres in single precision (OctoMap's point3d, a double rounded to
        # float): each coordinate is within 2^-24 |c| of the leaf's own, so the ball grows by
        # sqrt(3) 2^-22 max|c| (four times that) to hold the leaf about its real centre.
        error = math.sqrt(3.0) * 2.0**-22 * float(np.abs(C[S == s]).max())
        out.append(SensorCloud(C[S == s], radius_up(s * HALF_DIAGONAL + error), notes))
    if unknown_in is not None:
        out += unknown_voxels(tree, unknown_in, path)
    if not out:
        raise LarcInputError(f"{path}: the map has no occupied leaf" + (" and no unknown voxel in the --unknown-in box"
                                                                          if unknown_in is not None else ""))
    return out


MAX_PROBED = 10_000_000
"""Voxels of an ``--unknown-in`` box looked up at most (the binding looks up about a million a second)."""


def unknown_voxels(tree, box, path: Path) -> list[SensorCloud]:
    """The finest voxels of ``tree`` meeting ``box`` (``xmin, ymin, zmin, xmax, ymax, zmax``, m)
    that it holds neither occupied nor free (``getLabels`` -1), as a cloud of their centres with
    radius ``resolution·√3/2`` rounded up ([] when there is none). Voxel ``i`` of an axis is the
    cell ``[i, i + 1]·resolution`` (OctoMap's keys); the range is widened by one voxel on each
    side, so the box is covered whatever the rounding of ``box / resolution``; the centres
    ``(i + 1/2)·resolution`` are float64, within ``4 eps |c|`` of the cell's real centre."""
    box = np.asarray(box, np.float64).reshape(-1)
    lo, hi = box[:3], box[3:]
    if box.shape != (6,) or not np.isfinite(box).all() or not (lo <= hi).all():
        raise LarcInputError(f"--unknown-in: expected XMIN YMIN ZMIN XMAX YMAX ZMAX (m, finite, each min <= max), "
                             f"got {short_repr(box.tolist())}")
    res = float(tree.getResolution())
    first, last = np.floor(lo / res) - 1, np.floor(hi / res) + 1
    shape = (last - first + 1).astype(np.int64)
    if int(np.prod(shape)) > MAX_PROBED:
        raise LarcInputError(f"{path}: the --unknown-in box meets {int(np.prod(shape))} voxels of "
                             f"{res:g} m, more than {MAX_PROBED}: give a smaller box")
    yz = np.stack(np.meshgrid(np.arange(shape[1]), np.arange(shape[2]), indexing="ij"), -1).reshape(-1, 2)
    found = []
    for ix in range(shape[0]):  # one slab of the box at a time: memory of one slab
        idx = np.column_stack([np.full(len(yz), ix), yz]) + first
        centres = (idx + 0.5) * res
        found.append(centres[np.asarray(tree.getLabels(centres)) < 0])
    U = np.concatenate(found)
    if not len(U):
        return []
    error = math.sqrt(3.0) * 4 * float(np.finfo(np.float64).eps) * float(np.abs(U).max())
    note = (f"{len(U)} voxels of edge {res:g} m meeting the box [{', '.join(f'{v:g}' for v in lo)}] - "
            f"[{', '.join(f'{v:g}' for v in hi)}] that the map holds neither occupied nor free: obstacles, each "
            f"inside a ball of radius {res:g}·√3/2 about its centre")
    return [SensorCloud(U, radius_up(res * HALF_DIAGONAL + error), (note,))]


def check_voxel(voxel_m: float) -> None:
    """:class:`LarcInputError` unless ``voxel_m`` is a finite length > 0."""
    if not (math.isfinite(voxel_m) and voxel_m > 0):
        raise LarcInputError(f"--voxel must be a finite length > 0 m, got {short_repr(voxel_m)}")


def voxel_reduce(cloud: SensorCloud, voxel_m: float) -> SensorCloud:
    """``cloud`` with the points of each grid cube of edge ``voxel_m`` replaced by the cube's
    centre and the radius grown by the largest point-to-centre distance (module docstring)."""
    check_voxel(voxel_m)
    cell = np.floor(cloud.points / voxel_m)
    keys, inverse = np.unique(cell, axis=0, return_inverse=True)
    centres = (keys + 0.5) * voxel_m
    reach = float(np.linalg.norm(cloud.points - centres[inverse.reshape(-1)], axis=1).max())
    grow = max(reach, voxel_m * HALF_DIAGONAL)  # the bound for any point of a cube, whichever the grid rounding
    note = (f"{len(cloud.points)} points reduced to {len(centres)} cube centres (grid {voxel_m:g} m): "
            f"radius {cloud.radius_m:g} + {grow:g} m")
    return SensorCloud(centres, radius_up(cloud.radius_m + grow), cloud.notes + (note,))


def convert_sensor_file(src: str | Path, out: str | Path, voxel_m: float | None = None,
                        name: str | None = None, unknown_in=None) -> list[dict]:
    """Convert ``src`` (:data:`POINT_SUFFIXES` or :data:`OCTOMAP_SUFFIXES`) into ``.npy`` clouds
    (float64, (N, 3), written atomically): ``out`` itself, or, for a map with several leaf sizes,
    ``<out stem>_<k>.npy`` per size. Returns one scene ``obstacles:`` entry per file written
    (``name, type: points, file, radius``; ``file`` as written, to be made relative to the scene
    file) with its notes under ``"notes"``."""
    from ..io import atomic_write_bytes

    src, out = Path(src), Path(out)
    suffix = src.suffix.lower()
    if unknown_in is not None and suffix not in OCTOMAP_SUFFIXES:
        raise LarcInputError(f"{src}: --unknown-in applies to OctoMap files ({', '.join(OCTOMAP_SUFFIXES)}) only")
    if out.suffix.lower() != ".npy":
        raise LarcInputError(f"{out}: the output must be an .npy file (what a scene's points entry reads)")
    if voxel_m is not None:
        check_voxel(voxel_m)  # before reading the file
    if suffix in POINT_SUFFIXES:
        clouds = [read_pcd(src)]
    elif suffix in OCTOMAP_SUFFIXES:
        clouds = read_octomap(src, unknown_in)
    elif suffix in (".npy", ".ply") and voxel_m is not None:
        clouds = [read_plain(src)]
    else:
        readable = " (scenes read it directly; convert it only to reduce it with --voxel)" \
            if suffix in (".npy", ".ply") else ""
        raise LarcInputError(f"{src}: cannot convert {short_repr(suffix or src.name)} files{readable}; "
                             f"larc points reads {', '.join(POINT_SUFFIXES + OCTOMAP_SUFFIXES)}")
    if voxel_m is not None:
        clouds = [voxel_reduce(c, voxel_m) for c in clouds]
    for c in clouds:
        if len(c.points) > MAX_POINTS:
            raise LarcInputError(f"{src}: {len(c.points)} points, more than a scene's {MAX_POINTS} per cloud: "
                                 f"reduce them with --voxel (a grid edge, m)")
    name = name or src.stem
    entries = []
    for k, c in enumerate(clouds):
        path = out if len(clouds) == 1 else out.with_name(f"{out.stem}_{k}.npy")
        buf = io.BytesIO()
        np.save(buf, np.ascontiguousarray(c.points, np.float64), allow_pickle=False)
        atomic_write_bytes(path, buf.getvalue())
        entries.append({"name": name if len(clouds) == 1 else f"{name}_{k}", "type": "points", "file": str(path),
                        "radius": c.radius_m, "notes": list(c.notes)})
    return entries
