"""Collision geometry of the links: mesh and primitive loading, cached, as vertex sets.

Meshes are read with trimesh without processing (the vertices are exactly the file's), in any
format it reads (STL, OBJ, PLY, GLB; DAE through pycollada); a COLLADA ``<unit meter="s"/>``
scales the vertices by ``s`` (as ROS tools do), then the URDF ``scale`` applies. Boxes are
their 8 corners; spheres and cylinders are replaced by *circumscribed* polyhedra (every face
plane at least the radius from the centre), so enclosing the polyhedron's vertices encloses the
primitive. The parsed URDF and the meshes are cached (keyed on the file, its size and
modification time).

The collision geometry of a link is split into *elements* (one mesh triangle, or one whole
primitive): :func:`link_elements`. A convex enclosure holds an element iff it holds each of
its vertices, which is what the containment proof (:mod:`larc_jax.enclosure.fit`) checks.

Finger stroke. For a link on a held (non-active) prismatic joint (e.g. PIPER's fingers), every
element also carries its copies shifted to both ends of the joint's stroke. A prismatic stroke
sweeps the element along a segment, and the convex hull of the two end copies contains that
sweep, so an enclosure of the tripled element holds the finger at *any* opening. Held revolute
joints (linkage grippers, mimic joints) are enclosed at their held value only (a rotation's
sweep is not the hull of its ends): the capsule file records the values.
"""

from __future__ import annotations

import functools
import math
import os
from pathlib import Path

import numpy as np

from ..errors import LarcInputError
from ..robot import JointType, Robot
from ..urdf import file_sha256, load_urdf_model, resolve_uri

__all__ = ["link_elements", "link_collisions", "robot_urdf_model", "joint_limits", "collision_geometry",
           "links_with_geometry"]


def _circumscribed_sphere_vertices(radius: float) -> np.ndarray:
    import trimesh

    ico = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    # Scale so that every face plane is at least `radius` from the centre: the polyhedron then
    # contains the sphere, so enclosing its vertices encloses the sphere.
    inradius = np.min(np.abs(np.einsum("fi,fi->f", ico.face_normals, ico.triangles_center)))
    return ico.vertices * (radius / inradius)


def _primitive_vertices(geometry) -> np.ndarray | None:
    if geometry.box is not None:
        sx, sy, sz = np.asarray(geometry.box.size, float) / 2
        return np.array([[x, y, z] for x in (-sx, sx) for y in (-sy, sy) for z in (-sz, sz)])
    if geometry.sphere is not None:
        return _circumscribed_sphere_vertices(float(geometry.sphere.radius))
    if geometry.cylinder is not None:
        m = 32
        r = float(geometry.cylinder.radius) / math.cos(math.pi / m)  # circumscribed m-gon
        h = float(geometry.cylinder.length) / 2
        ang = 2 * np.pi * np.arange(m) / m
        ring = np.stack([r * np.cos(ang), r * np.sin(ang)], axis=1)
        return np.concatenate([np.c_[ring, np.full(m, -h)], np.c_[ring, np.full(m, h)]])
    return None


@functools.lru_cache(maxsize=8)
def _model_cached(urdf_path: str, stamp: tuple, package_dirs: tuple):
    return load_urdf_model(urdf_path, dict(package_dirs))


def _file_stamp(path: str | Path) -> tuple:
    st = os.stat(path)
    return (str(path), st.st_size, st.st_mtime_ns)


def robot_urdf_model(robot: Robot):
    """The parsed URDF of ``robot`` (cached; re-parsed if the file changed)."""
    return _model_cached(robot.urdf_path, _file_stamp(robot.urdf_path), tuple(robot.package_dirs))


@functools.lru_cache(maxsize=256)
def _mesh_cached(stamp: tuple, link: str) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    path = stamp[0]
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # noqa: BLE001
        raise LarcInputError(f"{path}: cannot read mesh of link '{link}' ({exc})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise LarcInputError(f"{path}: mesh of link '{link}' has no triangles")
    v = np.array(mesh.vertices, dtype=np.float64)
    if getattr(mesh, "units", None):
        try:
            v *= float(trimesh.units.unit_conversion(mesh.units, "meters"))
        except Exception:  # noqa: BLE001
            raise LarcInputError(f"{path}: mesh of link '{link}' has unknown units {mesh.units!r}") from None
    if not np.isfinite(v).all():
        raise LarcInputError(f"{path}: mesh of link '{link}' has non-finite vertices")
    f = np.array(mesh.faces, dtype=np.int64)
    v.flags.writeable = False
    f.flags.writeable = False
    return v, f


def _collisions(robot: Robot, link: str):
    """``(origin 4x4, geometry, mesh path or None)`` of each ``<collision>`` of ``link``; mesh
    paths are resolved and must exist, other geometry must be a box, sphere or cylinder."""
    model = robot_urdf_model(robot)
    dirs = dict(robot.package_dirs)
    out = []
    for col in model.link_map[link].collisions:
        origin = np.asarray(col.origin if col.origin is not None else np.eye(4), float)
        geom = col.geometry
        if geom is None:
            raise LarcInputError(f"{robot.urdf_path}: link '{link}' has a <collision> without geometry")
        path = None
        if geom.mesh is not None:
            path = resolve_uri(geom.mesh.filename, Path(robot.urdf_path), dirs)
            if not path.is_file():
                raise LarcInputError(
                    f"{robot.urdf_path}: link '{link}' collision mesh '{geom.mesh.filename}' "
                    f"resolves to {path}, which does not exist"
                )
        elif geom.box is None and geom.sphere is None and geom.cylinder is None:
            raise LarcInputError(f"{robot.urdf_path}: link '{link}' has an unsupported collision geometry")
        out.append((origin, geom, path))
    return out


def link_collisions(robot: Robot, link: str) -> list[tuple[np.ndarray, object, tuple | None]]:
    """The ``<collision>`` elements of ``link``: ``(T_link_geometry, geometry, mesh)`` each, with
    ``T_link_geometry`` the (4, 4) collision origin, ``geometry`` the URDF geometry (yourdfpy:
    ``.box``, ``.sphere``, ``.cylinder``, ``.mesh``) and ``mesh`` the ``(vertices (V, 3), faces
    (F, 3))`` of a mesh in the geometry frame, COLLADA units and the URDF ``scale`` applied
    (``None`` for a primitive). The one mesh loader of the project: the capsule fit and the FCL
    audit of the experiments see the same geometry."""
    out = []
    for origin, geom, path in _collisions(robot, link):
        mesh = None
        if path is not None:
            v, faces = _mesh_cached(_file_stamp(path), link)
            scale = np.asarray(geom.mesh.scale if geom.mesh.scale is not None else 1.0, float)
            mesh = (v * scale, faces)
        out.append((origin, geom, mesh))
    return out


def link_elements(robot: Robot, link: str) -> np.ndarray:
    """Collision elements of ``link`` in its own frame: (E, P, 3) vertex sets, float64.

    An element is one mesh triangle (P = 3) or one whole primitive. If the link hangs on a held
    (non-active) prismatic joint, every element also carries its copies shifted to both stroke
    ends (see module docstring), so P is tripled.
    """
    i = robot.link_index(link)
    groups: list[np.ndarray] = []
    for origin, geom, mesh in link_collisions(robot, link):
        elems = mesh[0][mesh[1]] if mesh is not None else _primitive_vertices(geom)[None]  # (E, P, 3)
        elems = elems @ origin[:3, :3].T + origin[:3, 3]
        if groups and groups[0].shape[1] != elems.shape[1]:
            # Mixed element sizes: pad by repeating the first vertex (same hull, same test).
            p = max(groups[0].shape[1], elems.shape[1])
            groups = [np.concatenate([g, np.repeat(g[:, :1], p - g.shape[1], 1)], 1) for g in groups]
            elems = np.concatenate([elems, np.repeat(elems[:, :1], p - elems.shape[1], 1)], 1)
        groups.append(elems)
    if not groups:
        return np.zeros((0, 3, 3))
    elems = np.concatenate(groups)
    if robot.q_index[i] < 0 and robot.joint_type[i] == JointType.PRISMATIC:
        lo, hi = joint_limits(robot_urdf_model(robot), robot.joint_names[i])
        ax = np.asarray(robot.axis[i], float)
        held = float(robot.q_held[i])
        elems = np.concatenate(
            [elems, elems + (lo - held) * ax, elems + (hi - held) * ax], axis=1
        )
    return elems


def links_with_geometry(robot: Robot) -> list[str]:
    """Links that have at least one ``<collision>`` element (from the parsed URDF; no mesh is read)."""
    model = robot_urdf_model(robot)
    return [link for link in robot.link_names if model.link_map[link].collisions]


def collision_geometry(robot: Robot) -> dict[str, list[dict]]:
    """What the capsules of each link are fitted to, as the robot file records it: per link with
    collision geometry, one entry per ``<collision>`` element with its placement in the link
    frame (``origin``: the top three rows of the 4x4 transform) and either the mesh URI, the
    SHA-256 of the file it resolves to and the URDF ``scale``, or the primitive's parameters
    (``box: [sx, sy, sz]``, ``sphere: r``, ``cylinder: [r, length]``). Mesh files are hashed
    afresh on every call (never cached: a replaced file must be seen)."""
    out: dict[str, list[dict]] = {}
    for link in links_with_geometry(robot):
        entries = []
        for origin, geom, path in _collisions(robot, link):
            if path is not None:
                scale = np.broadcast_to(np.asarray(geom.mesh.scale if geom.mesh.scale is not None else 1.0, float), 3)
                entry = {"mesh": geom.mesh.filename, "sha256": file_sha256(path), "scale": [float(x) for x in scale]}
            elif geom.box is not None:
                entry = {"box": [float(x) for x in geom.box.size]}
            elif geom.sphere is not None:
                entry = {"sphere": float(geom.sphere.radius)}
            else:
                entry = {"cylinder": [float(geom.cylinder.radius), float(geom.cylinder.length)]}
            entry["origin"] = [[float(x) for x in row] for row in origin[:3]]
            entries.append(entry)
        out[link] = entries
    return out


def joint_limits(model, joint: str) -> tuple[float, float]:
    j = model.joint_map[joint]
    return float(j.limit.lower), float(j.limit.upper)
