"""Certificate files: everything needed to re-check a certification result without JAX.

``larc certify --certificate OUT.json`` (or :func:`write_certificate`) writes one JSON document;
``larc verify`` (:mod:`larc_jax.products.verify`) re-checks it with the NumPy float64 references.

What it records (format ``larc-certificate``, :data:`CERTIFICATE_VERSION`):

* ``parameters``: the run's :class:`~larc_jax.run_spec.RunSpec` (``result.spec``) as
  :meth:`~larc_jax.run_spec.RunSpec.to_json` writes it (every field; floats as Python's shortest
  repr, exact): method, margin rho, maximum depth, enclosure (``capsules`` or the ``hull``
  cascade), the padding on every enclosure (``padding_m``), geometry dtype, velocity mode,
  tracking tolerance, self-collision test (margin, pairs the user skipped), stated joints (``hold``), active joints, links left out (``ignore_links``).
  ``larc verify`` reads it back with :meth:`~larc_jax.run_spec.RunSpec.from_json` (version 4;
  version 2 recorded its own parameters and version 3 no padding, which was then the robot
  file's: both are refused, re-certify).
* ``robot``: the robot file (path as given, ``null`` for PIPER's shipped capsule file) and the
  SHA-256 of its bytes, the URDF path and SHA-256, the collision geometry the capsules were
  proven on (every mesh's SHA-256, as :func:`~larc_jax.enclosure.meshes.collision_geometry`
  computes it from the files now), the active joints, the values of the held joints, which of
  them the user stated (``--hold``: the gripper opening), the capsule names, and
  ``enclosures_sha256`` (:func:`enclosures_sha256`): the hash of the enclosures the leaf test
  used, as placed (the run's padding and tracking growth included; with the cascade, its hull
  parts too), which ``larc verify`` rebuilds from the files and the parameters and compares.
* ``scenes``: per scene its file and the SHA-256 of its bytes (``null`` when certified through
  the Python API from a :class:`~larc_jax.model.scene.Scene`), and always ``arrays_sha256``, the
  SHA-256 of the canonical box arrays (:func:`scene_sha256`), and its box names.
* ``trajectories``: per trajectory its id (unique in the certificate: two trajectories with one
  id are refused, here and by ``larc verify``), file, file SHA-256 (``null`` through the API),
  ``arrays_sha256`` of the canonical waypoint arrays (:func:`trajectory_sha256`), the velocity
  mode it was read with, its scene, the claim ``certified``, the horizon, the rounding-bound
  inputs of :func:`~larc_jax.leaf.interval.trajectory_rounding` (offset, tau, speed slack, guard per
  capsule and hull part) and its leaf cover as columns (depth, index, t0, t1, clearance, guard,
  capsule and box index (-1: no pair), the second capsule of a self pair, the stage that passed
  it).

Every float outside ``parameters`` is written with :meth:`float.hex` (exact: ``float.fromhex`` gives the same double
back, ``inf`` and ``nan`` included), so interval ends and clearances are the computed values
bit for bit. The document is written atomically (temporary file, then ``os.replace``).

A certificate claims: for each trajectory marked ``certified``, at every real time of its
horizon, every link of the robot (placed by the Hermite curve through the recorded waypoints,
or by any execution within the tracking tolerance) is more than rho from every box of its
scene (each link proven by its capsules or, with the cascade, its hull parts), and, with the
self-collision test, no checked pair of links comes within its margin; it assumes the hashed
files, the held joint values (stated or enclosed over their stroke), and that links named in
``ignore_links`` are not checked at all.

Hull parts. ``larc verify`` proves, and tests with, the hull parts the robot file's split planes
build (:func:`~larc_jax.enclosure.proof.prove_enclosures`): a result certified with other parts
(``certify(hulls=...)``) is refused here when they are given (``hulls=``, as to ``certify``);
without ``hulls=`` the robot file's parts are assumed: ``larc verify`` re-checks every leaf with
them, and refutes a leaf that fails or whose stored clearance exceeds the recomputed one.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path
from typing import Sequence

import numpy as np

from ..enclosure.capsule import CapsuleModel
from ..enclosure.hull import HullModel, hull_model
from ..enclosure.meshes import collision_geometry
from ..errors import LarcInputError
from ..leaf.interval import trajectory_rounding
from ..leaf.reference import leaf_enclosures
from ..io import atomic_write_text
from ..engine.results import DatasetResult
from ..model.robot import JointType, Robot
from ..run_spec import RunSpec
from ..model.scene import Scene
from ..enclosure.tracking import check_tracking_tolerance
from ..model.urdf import file_sha256

__all__ = ["CERTIFICATE_FORMAT", "CERTIFICATE_VERSION", "certificate", "write_certificate", "hexf", "unhexf",
           "file_sha256", "trajectory_sha256", "scene_sha256", "enclosures_sha256", "robot_file_path"]

CERTIFICATE_FORMAT = "larc-certificate"
CERTIFICATE_VERSION = 4


def hexf(x) -> str:
    """A float as :meth:`float.hex` (exact)."""
    return float(x).hex()


def unhexf(s: str) -> float:
    """Inverse of :func:`hexf` (LarcInputError-free: the caller names the field)."""
    return float.fromhex(s)


def _arrays_sha256(header: dict, *arrays) -> str:
    h = hashlib.sha256(json.dumps(header, sort_keys=True).encode())
    for a in arrays:
        h.update(np.ascontiguousarray(a, dtype="<f8").tobytes())
    return h.hexdigest()


def trajectory_sha256(traj) -> str:
    """SHA-256 of a trajectory's canonical bytes: its joint names and shape (JSON), then ``t``,
    ``q`` and ``qd`` as little-endian float64."""
    q = np.asarray(traj.q)
    return _arrays_sha256({"joint_names": list(traj.joint_names), "shape": list(q.shape)}, traj.t, traj.q, traj.qd)


def scene_sha256(scene: Scene) -> str:
    """SHA-256 of a scene's canonical bytes: its box names and count (JSON), then the box
    corners ``lo`` and ``hi`` as little-endian float64; a scene with posed shapes, meshes or point
    clouds adds their kinds, names, files' SHA-256 and point radii to the JSON, and the shapes'
    dimensions, centres and rotation matrices and the pieces' vertices, sizes and owners to the arrays."""
    if not scene.posed:
        return _arrays_sha256({"boxes": list(scene.box_names), "n": int(scene.n_boxes)}, scene.lo, scene.hi)
    sh, ps = scene.shapes, scene.point_sets
    vertices, sizes, owner = ps.arrays()
    return _arrays_sha256({"boxes": list(scene.box_names), "n": int(scene.n_boxes), "shapes": list(sh.kinds),
                           "shape_names": list(sh.names), "point_sets": list(ps.kinds), "point_set_names": list(ps.names),
                           "point_set_files_sha256": list(ps.file_sha256), "point_radius": list(ps.radius)},
                          scene.lo, scene.hi, sh.dims, sh.p_world_shape, sh.R_world_shape, vertices,
                          sizes.astype(np.float64), owner.astype(np.float64))


def enclosures_sha256(enc) -> str:
    """SHA-256 of the enclosures a run's leaf test used (a
    :class:`~larc_jax.leaf.reference.LeafEnclosures`): capsule names and links (JSON), then
    segment ends, radii and motion constants as little-endian float64; with the cascade also its
    hull parts' names, links and vertex counts, then their real vertices, radii and motion constants."""
    caps = enc.capsules
    head = {"capsules": list(caps.names), "capsule_links": list(caps.link_names)}
    arrays = [caps.p_link_a, caps.p_link_b, caps.radius, caps.motion_a]
    if enc.hulls is not None:
        h = enc.hulls
        head.update(parts=list(h.names), part_links=list(h.link_names), n_vertices=[int(n) for n in h.n_vertices])
        arrays += [np.concatenate([np.asarray(h.vertices)[p, :n] for p, n in enumerate(h.n_vertices)]),
                   h.radius, h.motion_a]
    return _arrays_sha256(head, *arrays)


def robot_file_path(robot_file) -> Path:
    """The robot file a run used: ``robot_file``, or PIPER's shipped capsule file for ``None``."""
    from ..enclosure.robot_file import default_capsule_path

    return Path(robot_file) if robot_file is not None else Path(default_capsule_path())


def _held_joints(robot: Robot) -> dict[str, str]:
    return {robot.joint_names[i]: hexf(robot.q_held[i]) for i in range(robot.n_links)
            if robot.joint_type[i] != JointType.FIXED and robot.q_index[i] < 0}


def _robot_section(robot: Robot, capsules: CapsuleModel, robot_file, enc) -> dict:
    path = robot_file_path(robot_file)
    return {
        "file": None if robot_file is None else str(robot_file), "sha256": file_sha256(path),
        "urdf": robot.urdf_path, "urdf_sha256": robot.urdf_sha256, "geometry": collision_geometry(robot),
        "active_joints": list(robot.active_joint_names), "held_joints": _held_joints(robot),
        # Held joints whose value the user stated (--hold): their links are enclosed at it alone.
        "stated_joints": {robot.joint_names[i]: hexf(robot.q_held[i]) for i in range(robot.n_links)
                          if robot.joint_names[i] in robot.stated_joints},
        "capsules": list(capsules.names), "enclosures_sha256": enclosures_sha256(enc),
    }


def _leaf_columns(result: DatasetResult, i: int, box_offset: int) -> dict:
    lv, sl = result.leaves, result.leaf_slice(i)
    box = lv.box[sl].astype(np.int64)
    return {
        "depth": [int(x) for x in lv.depth[sl]], "index": [int(x) for x in lv.index[sl]],
        "t0": [hexf(x) for x in lv.t0[sl]], "t1": [hexf(x) for x in lv.t1[sl]],
        "clearance_m": [hexf(x) for x in lv.clearance_m[sl]], "guard_m": [hexf(x) for x in lv.guard_m[sl]],
        "certified": [bool(x) for x in lv.certified[sl]], "capsule": [int(x) for x in lv.capsule[sl]],
        "box": [int(b - box_offset) if b >= 0 else -1 for b in box],
        "other_capsule": [int(x) for x in lv.other_capsule[sl]], "stage": [int(x) for x in lv.stage[sl]],
    }


def _certified_spec(result: DatasetResult, velocities: str | None) -> RunSpec:
    """The run spec the certificate records: the result's (with the velocity mode the files were
    read with), refused if the result's own fields say another run."""
    spec = result.spec
    if spec is None:
        raise LarcInputError("certificate: the result carries no run spec (result.spec is None: not made by "
                             "larc_jax.engine.certify); certify the trajectories to write a certificate")
    if velocities is not None:
        spec = dataclasses.replace(spec, velocities=velocities)  # validated again
    have = {"method": result.method, "margin_m": float(result.margin_m), "max_depth": int(result.max_depth),
            "enclosure": result.enclosure, "dtype": result.dtype, "ignore_links": tuple(result.excluded_links)}
    differ = [k for k, v in have.items() if getattr(spec, k) != (v if k != "ignore_links" else tuple(v))]
    if differ:
        raise LarcInputError(f"certificate: the result's {differ[0]} {have[differ[0]]!r} is not its spec's "
                             f"{getattr(spec, differ[0])!r} (a result edited after certify)")
    return spec


def _same_hulls(a: HullModel, b: HullModel) -> bool:
    arrays = ("vertices", "centre", "probes", "radius", "motion_a")
    return (a.names, a.link_names, a.n_vertices, a.padding_m) == (b.names, b.link_names, b.n_vertices, b.padding_m) \
        and all(np.array_equal(np.asarray(getattr(a, k)), np.asarray(getattr(b, k))) for k in arrays)


def _certified_hulls(robot: Robot, capsules: CapsuleModel, enclosure: str, hulls: HullModel | None):
    """The hull parts the certificate relies on (module docstring, "Hull parts"): those the robot
    file's split planes build, which ``larc verify`` proves; ``hulls`` (what certify was given)
    must be exactly those."""
    if enclosure != "hull" or hulls is None:
        return None
    own = hull_model(robot, capsules.hull_parts, capsules.padding_m).on_links(capsules.link_names)
    if not isinstance(hulls, HullModel) or not _same_hulls(own, hulls.on_links(capsules.link_names)):
        raise LarcInputError("certificate: the result was certified with hull parts (hulls=) other than the ones the "
                             "robot file's hull_parts build, and larc verify proves only those: write the split "
                             "planes into the robot file (hull_parts) and certify without hulls=")
    return own


def certificate(result: DatasetResult, trajectories, scenes, robot: Robot, capsules: CapsuleModel, *,
                robot_file=None, trajectory_files: Sequence | None = None, scene_files: Sequence | None = None,
                velocities: str | None = None, hulls: HullModel | None = None) -> dict:
    """The certificate document of ``result`` (a dict; :func:`write_certificate` writes it).

    ``trajectories``, ``scenes``, ``robot`` and ``capsules`` are what :func:`~larc_jax.engine.certify`
    was given (one scene or one per trajectory), ``hulls`` the hull parts if it was given them
    (module docstring, "Hull parts"). ``robot_file``: the robot file they came from
    (``None``: PIPER's shipped one). ``trajectory_files`` / ``scene_files`` (optional, one per
    trajectory / scene): the files read, whose bytes are then hashed too; ``velocities``: the
    mode they were read with (:func:`~larc_jax.read_trajectory`; default: the spec's).
    """
    spec = _certified_spec(result, velocities)
    capsules = capsules.with_padding(spec.padding_m)  # as certify placed them (RunSpec.padding_m)
    trajectories = [trajectories] if not isinstance(trajectories, (list, tuple)) else list(trajectories)
    per_traj = [scenes] * len(trajectories) if isinstance(scenes, Scene) else list(scenes)
    if len(trajectories) != len(result.ids) or len(per_traj) != len(trajectories):
        raise LarcInputError(f"certificate: the result has {len(result.ids)} trajectories, but "
                             f"{len(trajectories)} trajectories and {len(per_traj)} scenes were given")
    ids = [t.id for t in trajectories]
    twice = next((i for k, i in enumerate(ids) if i in ids[:k]), None)
    if twice is not None:  # larc verify refuses a certificate naming two trajectories by one id
        raise LarcInputError(f"certificate: two trajectories have the id '{twice}' (e.g. files of the same name in "
                             "two folders): give each trajectory its own id")
    if tuple(ids) != tuple(result.ids):
        raise LarcInputError("certificate: the trajectories are not the ones the result was computed for (ids differ)")
    # Scenes in order of first appearance: the result's box codes are offset in the same order.
    unique = list(dict.fromkeys(id(s) for s in per_traj))
    first = {u: next(s for s in per_traj if id(s) == u) for u in unique}
    offsets = np.cumsum([0] + [first[u].n_obstacles for u in unique])
    files = list(scene_files) if scene_files is not None else [None] * len(unique)
    if len(files) != len(unique):
        raise LarcInputError(f"certificate: {len(unique)} scenes but {len(files)} scene files")
    scene_docs = [{"file": None if f is None else str(f), "sha256": None if f is None else file_sha256(f),
                   "arrays_sha256": scene_sha256(first[u]), "name": first[u].name,
                   "boxes": list(first[u].obstacle_names),
                   "assumes": list(first[u].assumptions())} for u, f in zip(unique, files)]
    tfiles = list(trajectory_files) if trajectory_files is not None else [None] * len(trajectories)
    if len(tfiles) != len(trajectories):
        raise LarcInputError(f"certificate: {len(trajectories)} trajectories but {len(tfiles)} trajectory files")
    delta = check_tracking_tolerance(spec.tolerance_arg(), robot)
    enc = leaf_enclosures(robot, capsules, spec.enclosure, delta,
                          _certified_hulls(robot, capsules, spec.enclosure, hulls))
    traj_docs = []
    for i, (traj, scene, f) in enumerate(zip(trajectories, per_traj, tfiles)):
        s = unique.index(id(scene))
        bnd = trajectory_rounding(traj, robot, enc.capsules, spec.dtype, enc.hulls)
        traj_docs.append({
            "id": traj.id, "file": None if f is None else str(f), "sha256": None if f is None else file_sha256(f),
            "arrays_sha256": trajectory_sha256(traj), "velocities": spec.velocities, "scene": s,
            "certified": bool(result.certified[i]),
            "t_start": hexf(traj.t[0]), "t_end": hexf(traj.t[-1]),
            "rounding": {"offset_s": hexf(bnd.offset_s), "tau_s": hexf(bnd.tau_s),
                         "omega_slack": [hexf(x) for x in np.asarray(bnd.omega_slack)],
                         "guard_m": [hexf(x) for x in np.asarray(bnd.guard_m)],
                         "hull_guard_m": [hexf(x) for x in np.asarray(bnd.hull_guard_m)]},
            "leaves": _leaf_columns(result, i, int(offsets[s])),
        })
    return {
        "format": CERTIFICATE_FORMAT, "version": CERTIFICATE_VERSION, "float_encoding": "float.hex",
        "parameters": json.loads(spec.to_json()),
        "robot": _robot_section(robot, capsules, robot_file, enc),
        "scenes": scene_docs,
        "trajectories": traj_docs,
    }


def write_certificate(path, result: DatasetResult, trajectories, scenes, robot: Robot, capsules: CapsuleModel,
                      **kwargs) -> Path:
    """Write :func:`certificate` to ``path`` atomically (JSON); returns the path."""
    doc = certificate(result, trajectories, scenes, robot, capsules, **kwargs)
    try:
        atomic_write_text(path, json.dumps(doc, indent=1) + "\n")
    except OSError as exc:
        raise LarcInputError(f"{path}: cannot write the certificate ({exc.strerror or exc})") from None
    return Path(path)
