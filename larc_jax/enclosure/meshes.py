"""Collision geometry of the links: mesh and primitive loading, cached, as vertex sets.

Meshes are read with trimesh without processing (the vertices are exactly the file's), in any
format it reads (STL, OBJ, PLY, GLB; DAE through pycollada); a COLLADA ``<unit meter="s"/>``
scales the vertices by ``s`` (as ROS tools do), then the URDF ``scale`` applies. Boxes are
their 8 corners; spheres and cylinders are replaced by *circumscribed* polyhedra (every face
plane at least the radius from the centre), so enclosing the polyhedron's vertices encloses the
primitive. The parsed URDF and the meshes are cached per process, keyed on the SHA-256 of the
bytes read (each call reads the file again; a changed file is parsed again, whatever its size
and modification time), and the URDF parse must be of the bytes the robot hashed
(``Robot.urdf_sha256``), so the geometry is always that of the files a certificate names.

The collision geometry of a link is split into *elements* (one mesh triangle, or one whole
primitive): :func:`link_elements`. A convex enclosure holds an element iff it holds each of
its vertices, which is what the containment proof (:mod:`larc_jax.enclosure.fit`) checks.

Finger stroke. For a link below a held prismatic joint whose value is not stated
(:attr:`~larc_jax.model.robot.Robot.stroke_joints`, e.g. PIPER's fingers without ``--hold``), every
element also carries its copies shifted to both ends of the joint's stroke (relative to the
held reference value at which FK places the link). A prismatic stroke sweeps the element along
a segment, and the convex hull of the two end copies contains that sweep, so a convex enclosure
of the widened element holds the link at *any* opening; it also holds the unshifted copy, i.e.
the link at the reference value itself. With several such joints above a link the copies take
every combination of stroke ends (the sweep is then the element plus a zonotope, whose vertices
are those combinations). The shift is a constant vector in the link frame as long as no active
joint lies between the prismatic joint and the link; otherwise the link's position along the
stroke is not a rigid offset and its value must be stated (an error says so).

Why not "mid-stroke plus half the stroke". Another sound way to cover an unknown opening
places the finger at mid-stroke and inflates its enclosure by half the stroke s/2 (a prismatic
joint moves every point by |dq| <= s/2). For the hull stage the widened elements are never
worse: conv(E + [-s/2, s/2] u) = conv(E) + [-s/2, s/2] u is contained in conv(E) + B(0, s/2)
(a segment of half-length s/2 lies in the ball of that radius). For capsules either construction
is a feasible capsule around the swept finger; :func:`~larc_jax.enclosure.fit.fit_capsules`
fits the widened elements directly, which on PIPER's fingers gives a smaller capsule than
(fit at mid-stroke) + 19 mm (tests/test_gripper.py compares them).

Held revolute joints (linkage grippers, mimic joints) are enclosed at their held value only (a
rotation's sweep is not the hull of its ends): the capsule file records the values."""

from __future__ import annotations

import functools
import hashlib
import io
import math
from pathlib import Path

import numpy as np

from ..errors import LarcInputError
from ..io import read_input_bytes
from ..model.robot import JointType, Robot
from ..model.urdf import file_sha256, load_urdf_model, resolve_uri

__all__ = ["link_elements", "link_collisions", "stroke_shifts", "held_joint_states", "robot_urdf_model",
           "joint_limits", "collision_geometry", "links_with_geometry"]


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


def robot_urdf_model(robot: Robot):
    """The parsed URDF of ``robot``: the parse :func:`~larc_jax.model.urdf.load_robot` made
    (:func:`~larc_jax.model.urdf.load_urdf_model` caches it); :class:`LarcInputError` if the
    file no longer has the robot's ``urdf_sha256``."""
    return load_urdf_model(robot.urdf_path, dict(robot.package_dirs), sha256=robot.urdf_sha256)


_MESH_CACHE: dict[tuple[str, str, str], tuple[np.ndarray, np.ndarray]] = {}
_MESH_CACHE_SIZE = 256


def _mesh(path: Path, link: str) -> tuple[np.ndarray, np.ndarray]:
    """The vertices and faces of the mesh file ``path`` as read now (cached by its bytes' SHA-256)."""
    data = read_input_bytes(path, f"collision mesh of link '{link}'")
    key = (str(path), hashlib.sha256(data).hexdigest(), link)
    hit = _MESH_CACHE.get(key)
    if hit is None:
        if len(_MESH_CACHE) >= _MESH_CACHE_SIZE:
            _MESH_CACHE.pop(next(iter(_MESH_CACHE)))  # the oldest entry
        hit = _MESH_CACHE[key] = _parse_mesh(path, data, link)
    return hit


def _parse_mesh(path: Path, data: bytes, link: str) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    try:
        mesh = trimesh.load(io.BytesIO(data), file_type=path.suffix.lstrip(".").lower(), force="mesh",
                            process=False, resolver=trimesh.resolvers.FilePathResolver(str(path)))
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
    ``T_link_geometry`` the (4, 4) collision origin, ``geometry`` the URDF geometry (:class:`~larc_jax.model.urdf_tree.Geometry`:
    ``.box``, ``.sphere``, ``.cylinder``, ``.mesh``) and ``mesh`` the ``(vertices (V, 3), faces
    (F, 3))`` of a mesh in the geometry frame, COLLADA units and the URDF ``scale`` applied
    (``None`` for a primitive). The one mesh loader of the project: the capsule fit and the FCL
    audit of the experiments see the same geometry."""
    out = []
    for origin, geom, path in _collisions(robot, link):
        mesh = None
        if path is not None:
            v, faces = _mesh(path, link)
            scale = np.asarray(geom.mesh.scale if geom.mesh.scale is not None else 1.0, float)
            mesh = (v * scale, faces)
        out.append((origin, geom, mesh))
    return out


def link_elements(robot: Robot, link: str) -> np.ndarray:
    """Collision elements of ``link`` in its own frame: (E, P, 3) vertex sets, float64.

    An element is one mesh triangle (P = 3) or one whole primitive. If the link hangs below a
    held prismatic joint whose value is not stated, every element also carries its copies
    shifted to the stroke ends (:func:`stroke_shifts`, module docstring): P is tripled per joint.
    """
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
    shifts = stroke_shifts(robot, link)
    if len(shifts) > 1:
        elems = np.concatenate([elems + d for d in shifts], axis=1)
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


def stroke_shifts(robot: Robot, link: str, model=None) -> np.ndarray:
    """Link-frame offsets (S, 3) at which :func:`link_elements` copies ``link``'s elements: the
    zero offset, then every combination of stroke ends of the unstated held prismatic joints
    above it (module docstring); just the zero offset when there are none."""
    model = model if model is not None else robot_urdf_model(robot)
    shifts = [np.zeros(3)]
    R_link_child = np.eye(3)  # rotation: frame of the current link -> frame of `link`
    i = robot.link_index(link)
    while i > 0:
        if robot.q_index[i] >= 0:  # an active joint: a stroke above it is no rigid offset
            above = [robot.joint_names[k] for k in robot.ancestors(i)[1:-1]]
            stroke = [j for j in above if j in robot.stroke_joints]
            if stroke:
                raise LarcInputError(
                    f"{robot.urdf_path}: link '{link}' hangs below the active joint '{robot.joint_names[i]}' "
                    f"and the held prismatic joint '{stroke[0]}' above it, whose value is not stated; "
                    f"state it (--hold {stroke[0]}=VALUE)")
            break
        jname = robot.joint_names[i]
        if jname in robot.stroke_joints:
            lo, hi = joint_limits(model, jname)
            held = float(robot.q_held[i])
            u = R_link_child @ np.asarray(robot.axis[i], float)
            shifts = [d + e * u for e in (0.0, lo - held, hi - held) for d in shifts]
        R_motion = np.eye(3)
        if robot.joint_type[i] == JointType.REVOLUTE:
            from scipy.spatial.transform import Rotation  # here: SciPy's import (0.3 s) only where needed

            R_motion = Rotation.from_rotvec(np.asarray(robot.axis[i], float) * float(robot.q_held[i])).as_matrix()
        R_link_child = R_link_child @ (np.asarray(robot.T_parent_joint[i], float)[:3, :3] @ R_motion).T
        i = robot.parent[i]
    return np.array(shifts)


def held_joint_states(robot: Robot) -> tuple[tuple[str, str, float, float], ...]:
    """What the enclosures assume about each held joint: ``(joint, state, lo, hi)`` with state
    ``stated`` (the user stated its value lo == hi), ``stroke`` (a prismatic joint anywhere in
    [lo, hi]: its links are enclosed over the stroke) or ``held`` (a revolute joint at lo == hi)."""
    out = []
    for i in range(1, robot.n_links):
        if robot.q_index[i] >= 0 or robot.joint_type[i] == JointType.FIXED:
            continue
        name, value = robot.joint_names[i], float(robot.q_held[i])
        if name in robot.stated_joints:
            out.append((name, "stated", value, value))
        elif robot.joint_type[i] == JointType.PRISMATIC:
            out.append((name, "stroke") + _urdf_joint_limits(robot.urdf_path, robot.urdf_sha256,
                                                             robot.package_dirs)[name])
        else:
            out.append((name, "held", value, value))
    return tuple(out)


@functools.lru_cache(maxsize=16)
def _urdf_joint_limits(urdf_path: str, urdf_sha256: str, package_dirs: tuple) -> dict:
    """Prismatic joint name -> ``(lower, upper)`` of the URDF with that SHA-256 (its parse must be of those
    bytes: :func:`robot_urdf_model`), once per process and file content: a certify call states
    its held joints without reading the URDF again (0.9 ms a call, measured on PIPER)."""
    model = load_urdf_model(urdf_path, dict(package_dirs), sha256=urdf_sha256)
    return {j.name: joint_limits(model, j.name) for j in model.joints if j.type == "prismatic"}


def joint_limits(model, joint: str) -> tuple[float, float]:
    j = model.joint_map[joint]
    return float(j.limit.lower), float(j.limit.upper)
