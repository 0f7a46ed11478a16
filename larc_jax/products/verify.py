"""The independent checker of certificate files (``larc verify``), in NumPy float64, without JAX.

:func:`verify_certificate` re-reads the robot file, scenes and trajectories a certificate
(:mod:`larc_jax.products.certificate`) names (or the files given instead), and re-checks the claim with
the NumPy references only (:func:`~larc_jax.leaf.reference.leaf_test_np`: the capsule test, the
hull cascade, the self test, with the tracking tolerance, as the run was asked; and what they
call):

1. Hashes: the robot file's bytes, the URDF, every collision mesh (the robot loader also refuses
   a mesh that differs from the one the capsules were fitted to), the scene and trajectory files
   (when the certificate names files) and always their canonical arrays.
1b. Enclosures: every enclosure the leaf test will use (capsules, stated-finger capsules, the
   hull parts of the cascade) is proven to contain its link's collision geometry
   (:func:`~larc_jax.enclosure.proof.prove_enclosures`: the hashed meshes and primitives, finger
   strokes from the URDF); the robot file's numbers are not trusted. Motion constants, strokes
   and rounding guards are derived from the URDF, never read. The enclosures so built, with the
   certificate's padding and tracking tolerance, must hash to its ``robot.enclosures_sha256``
   (:func:`~larc_jax.products.certificate.enclosures_sha256`): the certificate names what it was
   made with, and a checker that would rebuild other enclosures refutes it rather than re-check
   another claim. A scene's planes must be the planes themselves wherever the capsules reach
   (:func:`~larc_jax.model.planes.check_plane_reach`).
2. Tiling: the leaves of every trajectory claimed certified are in time order, each the dyadic
   piece ``(depth, index)`` of the horizon (:func:`~larc_jax.leaf.interval.dyadic_ends`, exact), the
   first starts at ``t_0``, each ends where the next starts, the last ends at ``t_K``.
3. The test: for every such leaf, ``g`` and the guard are recomputed from the files with the
   float64 reference and its own rounding bounds (stored clearances are not trusted), with the
   enclosures, gripper state (stated joints), tracking tolerance and self-collision pairs the
   certificate records: the leaf must pass, ``g > guard``. The stored clearance may not exceed the
   recomputed one by more than ``CLEARANCE_TOL_M + 4 (stored guard + recomputed guard)`` (the JAX
   kernel and the reference round differently; both are within their guards of the exact value);
   a stored clearance below it claims less, which a culled leaf does where its ``g - guard``
   exceeds :data:`~larc_jax.leaf.record.CULL_SLACK_M` (:mod:`larc_jax.engine.cull`). Where the
   recomputed ``g - guard`` is at most half of that and the stored and recomputed leaf both
   passed the capsule stage, every engine records every pair's capsule clearance, so one below
   it by more than the same tolerance is refuted too. Not on other leaves: near the guard the
   engine and the reference may pass a leaf at different stages (the capsule test just passing
   in one, the tighter hull bound deciding in the other; the hull's first round or its full
   search), and their clearances then differ by more than rounding while both are sound. The
   stored rounding inputs must agree with the recomputed ones to a relative ``1e-9``.

Trajectories the certificate does not claim certified are not checked. The first failure
raises :class:`Refuted` naming the trajectory, the leaf and why (``larc verify`` exit 1); a
missing or malformed file or an unknown format version is :class:`LarcInputError` (exit 2).

Parameters. They are the run's :class:`~larc_jax.run_spec.RunSpec` (``parameters``, format
version 4), read with :meth:`~larc_jax.run_spec.RunSpec.from_dict` (:meth:`~larc_jax.run_spec.RunSpec.from_json`'s
rules: every field present, known and valid, else one line naming it); its model fields must be
the robot loaded (stated joints, active joints); the robot file's capsules take the spec's
``padding_m`` (:meth:`~larc_jax.enclosure.capsule.CapsuleModel.with_padding`) before anything is
proven or re-checked. A version-2 or -3 certificate (parameters of its own; no padding) is refused
with a message to re-certify: re-certifying costs one run, a second parser of parameters more.

What was checked is reported (:class:`~larc_jax.products.verify_report.VerifyReport`, also carried by a
:class:`Refuted` up to the refutation): every file read with the SHA-256 of its bytes and whether
the caller supplied it or the certificate named it, the parameters (always the certificate's),
held and stated joints, excluded links, the self-collision pairs not checked, each trajectory's
velocity mode. Labels are not trusted: a certificate naming two trajectories by one id is
refuted, and the report names the file behind each id (a file whose name is not its id, a scene
of zero boxes, are shown as such). :class:`~larc_jax.products.verify_report.VerifyPins` hold the
certificate to what the caller requires (margin, depth, enclosure, dtype, velocity mode, no
excluded links, tracking tolerance, self-collision, the robot file's hash, files with hashes);
a pin not met is a refutation naming it.

Velocities. A file that records velocities describes one motion: the Hermite curve through its
positions *and velocities*, what a controller following it executes. A certificate made with
``velocities: finite-difference`` covers the Hermite curve through velocities computed from the
positions instead, another motion, which can pass through an obstacle the file's motion hits
(three equal waypoints whose middle velocity swings the arm through a post: the
finite-difference curve stands still). Its hashes match the file, so a reader who sees that file
"verified" would believe its motion safe. The checker therefore refuses by default a trajectory
certified with finite-difference velocities whose file records velocities (at any waypoint);
``allow_finite_difference`` (``--allow-finite-difference``) accepts it, and the report says
how many recorded velocities were ignored. A file without velocities has only the
finite-difference reading: it is accepted, its mode printed (pin ``velocities="recorded"`` to
refuse it).

It defers JAX (:func:`larc_jax.lazy_jax.defer_jax`): ``larc verify`` never loads it (``tests/test_certificate.py``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
from pathlib import Path

from ..lazy_jax import defer_jax

defer_jax()

import numpy as np  # noqa: E402

from .certificate import (CERTIFICATE_FORMAT, CERTIFICATE_VERSION, enclosures_sha256, robot_file_path,  # noqa: E402
                          scene_sha256, trajectory_sha256, unhexf)
from .certificate_fields import check_certificate_fields  # noqa: E402
from ..defaults import VELOCITY_MODES  # noqa: E402
from ..enclosure.meshes import collision_geometry  # noqa: E402
from ..enclosure.proof import EnclosureNotProven, prove_enclosures  # noqa: E402
from ..enclosure.robot_file import load_robot_file  # noqa: E402
from ..errors import GeometryChanged, LarcInputError, OneLineError  # noqa: E402
from ..leaf.interval import dyadic_ends, trajectory_rounding  # noqa: E402
from ..leaf.record import CULL_SLACK_M, Stage  # noqa: E402
from ..io import parse_json, read_input_bytes, read_input_text, short_repr  # noqa: E402
from ..leaf.reference import LeafEnclosures, leaf_enclosures, leaf_test_np  # noqa: E402
from ..model.robot import JointType  # noqa: E402
from ..run_spec import RunSpec  # noqa: E402
from ..model.planes import check_plane_reach  # noqa: E402
from ..model.scene import read_scene  # noqa: E402
from ..leaf.self_collision import curve_ranges, load_separation, self_pairs  # noqa: E402
from ..enclosure.tracking import check_tracking_tolerance  # noqa: E402
from ..model.urdf import file_sha256  # noqa: E402
from ..model.trajectory_files import read_trajectory_file  # noqa: E402
from .verify_report import (InputFile, Parameters, Refuted, RobotFacts, SceneFacts, TrajectoryFacts,  # noqa: E402
                            VerifyPins, VerifyReport)

__all__ = ["Refuted", "VerifyReport", "VerifyPins", "verify_certificate", "CLEARANCE_TOL_M"]

CLEARANCE_TOL_M = 1e-9
"""Absolute part of the agreement asked of a stored clearance, m (module docstring, step 3)."""
_ROUNDING_RTOL = 1e-9


def _get(doc, key, where: str, kind=None):
    if not isinstance(doc, dict) or key not in doc:
        raise LarcInputError(f"{where}: missing field '{key}'")
    value = doc[key]
    if kind is not None and not isinstance(value, kind):
        raise LarcInputError(f"{where}.{key}: expected {getattr(kind, '__name__', kind)}, got {type(value).__name__}")
    return value


def _float(s, where: str) -> float:
    try:
        return unhexf(s)
    except (TypeError, ValueError, OverflowError):  # OverflowError: '0x1p+1024'
        raise LarcInputError(f"{where}: not a float.hex() number (or beyond the float64 range): "
                             f"{short_repr(s, 60)}") from None


def _floats(doc, key, where: str) -> np.ndarray:
    return np.array([_float(s, f"{where}.{key}[{i}]") for i, s in enumerate(_get(doc, key, where, list))],
                    np.float64)


def _ints(doc, key, where: str) -> np.ndarray:
    values = _get(doc, key, where, list)
    if not all(isinstance(v, int) and not isinstance(v, bool) for v in values):
        raise LarcInputError(f"{where}.{key}: expected a list of integers")
    big = next((i for i, v in enumerate(values) if not -2**63 <= v < 2**63), None)  # int64
    if big is not None:
        raise LarcInputError(f"{where}.{key}[{big}]: {short_repr(values[big], 40)} is out of range")
    return np.array(values, np.int64)


def _override(given, n: int, what: str) -> list:
    if not given:
        return [None] * n
    if len(given) != n:
        raise LarcInputError(f"{what}: {len(given)} files given, but the certificate has {n}")
    return list(given)


def _sha256(path, what: str) -> str:
    return hashlib.sha256(read_input_bytes(path, what)).hexdigest()  # regular files, at most the cap


def _check_hash(have: str, want, what: str) -> None:
    if want is not None and have != want:
        raise Refuted(f"{what} has sha256 {have}, the certificate records {want}")


def _load_robot(doc: dict, robot_path, excluded: list[str]):
    where = "robot"
    recorded = _get(doc, "file", where)
    path = robot_path if robot_path is not None else recorded
    file = robot_file_path(path)
    if not file.is_file():
        raise LarcInputError(f"{file}: robot file not found")
    _check_hash(_sha256(file, "robot file"), _get(doc, "sha256", where, str), f"robot file {file}")
    stated = {str(j): _float(v, f"{where}.stated_joints.{j}")
              for j, v in (_get(doc, "stated_joints", where, dict) or {}).items()}
    active = _get(doc, "active_joints", where, list)
    if not all(isinstance(j, str) for j in active):
        raise LarcInputError(f"{where}.active_joints: expected a list of joint names")
    try:
        robot, capsules = load_robot_file(path, hold=stated, active_joints=active)
    except GeometryChanged as exc:
        raise Refuted(f"robot: {exc}") from None
    _check_hash(robot.urdf_sha256, _get(doc, "urdf_sha256", where, str), f"URDF {robot.urdf_path}")
    if collision_geometry(robot) != _get(doc, "geometry", where, dict):
        raise Refuted(f"robot: the collision geometry of {robot.urdf_path} (mesh sha256, origins, sizes) differs "
                      "from the one the certificate records")
    if list(robot.active_joint_names) != _get(doc, "active_joints", where, list):
        raise Refuted(f"robot: active joints {list(robot.active_joint_names)} differ from the certificate's")
    more = [x for x in excluded if x not in capsules.excluded_links]
    if more:
        capsules = capsules.without_links(robot, more, what="certificate excluded_links:")
    if set(capsules.excluded_links) != set(excluded):  # the robot file's ignored_links must be declared
        raise Refuted(f"robot: links {sorted(capsules.excluded_links)} are left out, the certificate's excluded_links "
                      f"declares {sorted(excluded)}")
    held = {robot.joint_names[i]: float(robot.q_held[i]) for i in range(1, robot.n_links)
            if robot.q_index[i] < 0 and robot.joint_type[i] != JointType.FIXED}
    recorded_held = {str(j): _float(v, f"{where}.held_joints.{j}") for j, v in _get(doc, "held_joints", where, dict).items()}
    if recorded_held != held:
        raise Refuted(f"robot: the held joint values {held} (robot file, stated joints) differ from the certificate's")
    if list(capsules.names) != _get(doc, "capsules", where, list):
        raise Refuted("robot: the capsule names differ from the certificate's")
    return robot, capsules


def _input_file(path, given, recorded_sha256, what: str) -> InputFile:
    return InputFile(path=str(path), source="supplied" if given is not None else "certificate",
                     sha256=_sha256(path, what), recorded_sha256=recorded_sha256)


def _load_scenes(docs: list, files: list, robot, pins: VerifyPins, facts: list) -> list:
    scenes = []
    for k, (doc, given) in enumerate(zip(docs, files)):
        where = f"scenes[{k}]"
        path = given if given is not None else _get(doc, "file", where)
        if path is None:
            raise LarcInputError(f"{where}: certified from arrays through the Python API; give its file (larc verify --scene, verify_certificate(scenes=...))")
        file = _input_file(path, given, doc.get("sha256"), "scene file")
        pins.check_input(f"scene {k}", file)
        _check_hash(file.sha256, file.recorded_sha256, f"scene file {path}")
        scene = read_scene(path, frame=robot.link_names[0])
        arrays = _get(doc, "arrays_sha256", where, str)
        _check_hash(scene_sha256(scene), arrays, f"scene {path} (its obstacles)")
        assumes = scene.assumptions()
        if doc.get("assumes", []) != list(assumes):  # what it states of its meshes, clouds, planes: the files' truth
            raise Refuted(f"{where}.assumes {short_repr(doc.get('assumes'))} is not what scene {path} gives: "
                          f"{list(assumes)}")
        scenes.append(scene)
        facts.append(SceneFacts(index=k, file=file, arrays_sha256=arrays, boxes=tuple(scene.obstacle_names),
                                assumes=assumes))
    return scenes


def _check_tiling(tid: str, t_start: float, t_end: float, depth, index, t0, t1) -> None:
    for k in range(len(t0)):
        a, b = (float(x) for x in dyadic_ends(t_start, t_end, int(depth[k]), int(index[k])))
        if not (0 <= index[k] < 2 ** int(depth[k])) or a != t0[k] or b != t1[k]:
            raise Refuted(f"trajectory '{tid}' leaf {k}: [{t0[k]!r}, {t1[k]!r}] is not the dyadic piece "
                          f"(depth {depth[k]}, index {index[k]}) of its horizon")
        start = t_start if k == 0 else float(t1[k - 1])
        if t0[k] != start:
            raise Refuted(f"trajectory '{tid}' leaf {k}: starts at {t0[k]!r}, but the "
                          f"{'horizon starts' if k == 0 else 'previous leaf ends'} at {start!r} (the leaves do not "
                          "tile the horizon)")
    if not len(t1) or t1[-1] != t_end:
        raise Refuted(f"trajectory '{tid}': the leaves end at {t1[-1] if len(t1) else None!r}, the horizon at "
                      f"{t_end!r} (the leaves do not tile the horizon)")


def _check_rounding(tid: str, doc: dict, bnd, where: str) -> None:
    for key in ("offset_s", "tau_s", "omega_slack", "guard_m", "hull_guard_m"):
        stored = _floats(doc, key, where) if isinstance(doc.get(key), list) else np.array([_float(_get(doc, key, where),
                                                                                                 f"{where}.{key}")])
        have = np.atleast_1d(np.asarray(getattr(bnd, key), np.float64))
        if stored.shape != have.shape or not np.all(np.abs(stored - have) <= _ROUNDING_RTOL * np.abs(have)):
            raise Refuted(f"trajectory '{tid}': rounding input {key} {stored.tolist()} differs from the recomputed "
                          f"{have.tolist()}")


def _check_trajectory(doc: dict, k: int, traj, scene, robot, enc: LeafEnclosures, margin: float, dtype: str,
                      max_depth: int, pairs=None, delta=None):
    """Re-check one trajectory claimed certified; returns (leaves, max clearance diff, min excess)."""
    where = f"trajectories[{k}]"
    tid = str(_get(doc, "id", where))
    t_start, t_end = float(traj.t[0]), float(traj.t[-1])
    if _float(_get(doc, "t_start", where), f"{where}.t_start") != t_start or \
            _float(_get(doc, "t_end", where), f"{where}.t_end") != t_end:
        raise Refuted(f"trajectory '{tid}': the recorded horizon differs from the trajectory's [{t_start!r}, {t_end!r}]")
    capsules = enc.capsules
    _check_rounding(tid, _get(doc, "rounding", where, dict),
                    trajectory_rounding(traj, robot, capsules, dtype, enc.hulls), f"{where}.rounding")
    lv = _get(doc, "leaves", where, dict)
    lw = f"{where}.leaves"
    # Dyadic pieces of depth <= max_depth tile the horizon in at most 2**max_depth leaves: more
    # cannot be a cover, and refusing them first bounds the work below by the parameters.
    n_leaves = len(_get(lv, "depth", lw, list))
    if n_leaves > 2 ** max_depth:
        raise Refuted(f"trajectory '{tid}': {n_leaves} leaves, more than the 2**{max_depth} = {2 ** max_depth} "
                      f"dyadic pieces of depth <= max_depth {max_depth} that can tile a horizon")
    depth, index, capsule = _ints(lv, "depth", lw), _ints(lv, "index", lw), _ints(lv, "capsule", lw)
    t0, t1 = _floats(lv, "t0", lw).tolist(), _floats(lv, "t1", lw).tolist()
    g_stored, guard_stored = _floats(lv, "clearance_m", lw).tolist(), _floats(lv, "guard_m", lw).tolist()
    flags, stage_stored = _get(lv, "certified", lw, list), _ints(lv, "stage", lw)
    if len({len(x) for x in (depth, index, capsule, t0, t1, g_stored, guard_stored, flags, stage_stored)}) != 1:
        raise LarcInputError(f"{lw}: the leaf columns have different lengths")
    if np.any(depth < 0) or np.any(depth > max_depth):
        raise Refuted(f"trajectory '{tid}': a leaf depth is outside 0..{max_depth}")
    _check_tiling(tid, t_start, t_end, depth, index, t0, t1)
    bounds = trajectory_rounding(traj, robot, capsules, np.float64, enc.hulls)  # the float64 reference's own guard
    skip = pairs.skip_mask(*curve_ranges(traj, delta)) if pairs is not None else None
    diff, excess = 0.0, math.inf
    for j in range(len(t0)):
        leaf = f"trajectory '{tid}' leaf {j} (t=[{t0[j]!r}, {t1[j]!r}], depth {depth[j]})"
        if flags[j] is not True:
            raise Refuted(f"{leaf}: marked not certified in a trajectory claimed certified")
        g, guard, cap, box, other, stage = leaf_test_np(robot, enc, traj, scene, t0[j], t1[j], margin, bounds, pairs,
                                                        skip)
        g, guard = float(g), float(guard)
        if not (stage > 0 and g > guard):  # NaN fails
            pair = f"capsules {capsules.names[cap]} / {capsules.names[other]}" if other >= 0 else \
                f"capsule {capsules.names[cap]}, box {box}"
            raise Refuted(f"{leaf}: fails the reference test: clearance {g!r} m is not above the guard {guard!r} m "
                          f"({pair})")
        tol = CLEARANCE_TOL_M + 4 * (abs(guard_stored[j]) + abs(guard))
        # One-sided above CULL_SLACK_M / 2 and off the capsule stage: a stored clearance may claim
        # less than the recomputed one there (module docstring, 3).
        d = g_stored[j] - g if math.isfinite(g) else (0.0 if g_stored[j] <= g else math.inf)
        if not d <= tol:
            raise Refuted(f"{leaf}: stored clearance {g_stored[j]!r} m exceeds the recomputed {g!r} m by "
                          f"{d:.3g} m (> tolerance {tol:.3g} m)")
        capsule_stage = stage_stored[j] == stage == int(Stage.CAPSULE)
        if capsule_stage and g - guard <= CULL_SLACK_M / 2 and not d >= -tol:
            raise Refuted(f"{leaf}: stored clearance {g_stored[j]!r} m is below the recomputed {g!r} m by "
                          f"{-d:.3g} m (> tolerance {tol:.3g} m), within {CULL_SLACK_M / 2!r} m of the guard, "
                          "where every engine records the capsule clearance of every pair")
        diff, excess = max(diff, abs(d) if math.isfinite(d) else 0.0), min(excess, g - guard)
    return len(t0), diff, excess


def _spec(doc: dict, source: str) -> RunSpec:
    """The run spec the certificate records (``parameters``), read by :meth:`RunSpec.from_json`'s
    rules: every field known and valid, or a one-line :class:`LarcInputError`."""
    old = {2: "parameters of its own, before the run spec", 3: "no padding_m: the robot file's padding"}
    if doc.get("version") in old:
        raise LarcInputError(f"{source}: a version-{doc['version']} certificate ({old[doc['version']]}); "
                             f"this checker reads version {CERTIFICATE_VERSION}: re-certify (larc certify ... "
                             "--certificate)")
    if doc.get("version") != CERTIFICATE_VERSION:
        raise LarcInputError(f"{source}: unknown certificate version {short_repr(doc.get('version'), 40)} (this "
                             f"checker reads version {CERTIFICATE_VERSION})")
    check_certificate_fields(doc, source)
    params = _get(doc, "parameters", source, dict)
    for f in dataclasses.fields(RunSpec):  # a certificate states its whole spec: no field read as a default
        _get(params, f.name, "parameters")
    return RunSpec.from_dict(params, "parameters")


def _check_model(spec: RunSpec, rob) -> None:
    """The spec's model fields are the robot the checker loaded (from the ``robot`` section)."""
    stated = tuple(sorted((rob.joint_names[i], float(rob.q_held[i])) for i in range(rob.n_links)
                          if rob.joint_names[i] in rob.stated_joints))
    if spec.hold != stated:
        raise Refuted(f"parameters.hold {dict(spec.hold)} differs from the robot's stated joints {dict(stated)}")
    if spec.joints != tuple(rob.active_joint_names):
        raise Refuted(f"parameters.joints {list(spec.joints)} differ from the robot's active joints "
                      f"{list(rob.active_joint_names)}")


def _check_ids(docs: list) -> None:
    """A certificate names each trajectory once: two claims under one id would let a reader take
    the one re-checked for the other."""
    seen: dict[str, int] = {}
    for k, tdoc in enumerate(docs):
        tid = str(_get(tdoc, "id", f"trajectories[{k}]"))
        if tid in seen:
            raise Refuted(f"trajectories[{seen[tid]}] and trajectories[{k}] have the same id '{tid}' (a certificate "
                          "names each trajectory once)")
        seen[tid] = k


def _robot_facts(doc: dict, given, rob, capsules, cert_excluded) -> RobotFacts:
    recorded = doc.get("file")
    path = robot_file_path(given if given is not None else recorded)
    source = "supplied" if given is not None else ("certificate" if recorded is not None else "shipped")
    geometry = tuple((link, ", ".join(f"{k} {v}" for k, v in e.items() if k not in ("origin", "sha256")),
                      e.get("sha256")) for link, elements in _get(doc, "geometry", "robot", dict).items()
                     for e in elements)  # equal to the files' (checked by _load_robot)
    held = tuple((rob.joint_names[i], float(rob.q_held[i]), rob.joint_names[i] in rob.stated_joints)
                 for i in range(rob.n_links) if rob.joint_type[i] != JointType.FIXED and rob.q_index[i] < 0)
    return RobotFacts(
        file=InputFile(str(path), source, _sha256(path, "robot file"), doc.get("sha256")), urdf=str(rob.urdf_path),
        urdf_sha256=rob.urdf_sha256, geometry=geometry, active_joints=tuple(rob.active_joint_names), held_joints=held,
        capsules=int(capsules.n_capsules),
        fixed_joints=tuple(j for j, _, stated in held if not stated and j not in rob.stroke_joints),
        excluded_links=tuple((x, "certificate" if x in cert_excluded else "robot file")
                             for x in capsules.excluded_links))


def _read_claimed(tdoc: dict, k: int, given, rob, pins: VerifyPins, default_mode: str):
    """Read the file of a trajectory claimed certified; returns it and its facts."""
    where = f"trajectories[{k}]"
    tid = str(_get(tdoc, "id", where))
    mode = tdoc.get("velocities")
    mode = default_mode if mode is None else mode  # null: the run spec's; "" or false is no mode
    if mode not in VELOCITY_MODES:
        raise LarcInputError(f"{where}.velocities: {str(mode)[:40]!r} is not one of {', '.join(VELOCITY_MODES)}")
    pins.check_velocities(tid, mode)
    tpath = given if given is not None else _get(tdoc, "file", where)
    if tpath is None:
        raise LarcInputError(f"{where} ('{tid}'): certified from arrays through the Python API; give its file "
                             "(larc verify --trajectory, verify_certificate(trajectories=...))")
    file = _input_file(tpath, given, tdoc.get("sha256"), "trajectory file")
    pins.check_input(f"trajectory '{tid}'", file)
    _check_hash(file.sha256, file.recorded_sha256, f"trajectory file {tpath}")
    traj, ignored = read_trajectory_file(tpath, rob, velocities=mode)
    if ignored and not pins.allow_finite_difference:
        raise Refuted(f"trajectory '{tid}': certified with finite-difference velocities, but its file {tpath} records "
                      f"velocities at {ignored} waypoints: the certificate covers another motion than the one the file "
                      "describes (--allow-finite-difference accepts it)")
    arrays = _get(tdoc, "arrays_sha256", where, str)
    _check_hash(trajectory_sha256(traj), arrays, f"trajectory '{tid}' ({tpath})")
    scene = _get(tdoc, "scene", where, int)
    if isinstance(scene, bool):  # JSON true/false would index scene 1/0 and be reported as "scene True"
        raise LarcInputError(f"{where}.scene: expected a scene index, got {scene!r}")
    return traj, TrajectoryFacts(id=tid, claimed=True, scene=scene, velocities=mode,
                                 file=file, arrays_sha256=arrays, ignored_velocities=ignored)


def verify_certificate(path, *, trajectories=None, scenes=None, robot=None, pins: VerifyPins | None = None,
                       **pin_values) -> VerifyReport:
    """Re-check the certificate at ``path`` (module docstring). ``trajectories`` / ``scenes``:
    files to use instead of the ones it names (one per trajectory / scene, in its order);
    ``robot``: the robot file instead of its. ``pins`` (or its fields as keyword arguments, e.g.
    ``margin_at_least_m=0.01``): what the certificate must also meet (:class:`VerifyPins`).
    Returns the :class:`VerifyReport`; raises :class:`Refuted` (carrying the report up to the
    refutation) or :class:`LarcInputError`."""
    if pins is None:
        pins = VerifyPins(**pin_values)
    elif pin_values:
        raise LarcInputError("verify_certificate: give pins= or pin keyword arguments, not both")
    est = {"certificate": str(path), "pins": pins.asked(), "allow_finite_difference": pins.allow_finite_difference,
           "scene_files": [], "trajectory_files": []}
    try:
        return _verify(path, trajectories, scenes, robot, pins, est)
    except Refuted as exc:
        exc.report = _report(est, refuted=str(exc))
        raise


def _report(est: dict, **more) -> VerifyReport:
    return VerifyReport(**{k: tuple(v) if isinstance(v, list) else v for k, v in {**est, **more}.items()})


def _verify(path, trajectories, scenes, robot, pins: VerifyPins, est: dict) -> VerifyReport:
    source = str(path)
    doc = parse_json(read_input_text(Path(path), "certificate"), source)  # hostile JSON: one line, exit 2
    if not isinstance(doc, dict) or doc.get("format") != CERTIFICATE_FORMAT:
        raise LarcInputError(f"{source}: not a larc certificate (format {CERTIFICATE_FORMAT!r} expected)")
    spec = _spec(doc, source)
    est["parameters"] = params = Parameters.of(spec)
    traj_docs = _get(doc, "trajectories", source, list)
    est["trajectories"] = len(traj_docs)
    pins.check_parameters(spec)
    _check_ids(traj_docs)
    robot_doc = _get(doc, "robot", source, dict)
    rob, capsules = _load_robot(robot_doc, robot, list(spec.ignore_links))
    capsules = capsules.with_padding(spec.padding_m)  # the certified run's padding; the proof checks the cores
    est["robot"] = _robot_facts(robot_doc, robot, rob, capsules, spec.ignore_links)
    _check_model(spec, rob)
    delta = check_tracking_tolerance(spec.tolerance_arg(), rob, "parameters.tracking_tolerance")
    if delta is not None:
        est["parameters"] = params = dataclasses.replace(params, tracking_tolerance=tuple(
            (j, float(x)) for j, x in zip(rob.active_joint_names, delta)))
    pins.check_robot(est["robot"], rob, delta)
    robot_file = robot_file_path(robot if robot is not None else robot_doc["file"])
    try:  # module docstring, step 1b: the hull parts proven are the ones the leaf test gets
        hulls = prove_enclosures(rob, capsules, spec.enclosure == "hull", source=str(robot_file))
    except EnclosureNotProven as exc:
        raise Refuted(str(exc)) from None
    enc = leaf_enclosures(rob, capsules, spec.enclosure, delta, hulls, spec.swept)
    if enclosures_sha256(enc) != _get(robot_doc, "enclosures_sha256", "robot", str):
        raise Refuted("robot.enclosures_sha256: the enclosures rebuilt from the robot file, the URDF and its meshes "
                      "with the certificate's parameters (padding, tracking tolerance, held joints, enclosure) are "
                      "not the ones the certificate was made with")
    pairs = None
    if spec.self_collision:
        pairs = self_pairs(rob, capsules, spec.self_margin_m, list(spec.self_skip), proven=load_separation(rob))
        est["parameters"] = dataclasses.replace(params, self_not_checked=tuple(pairs.skipped))
        pairs = pairs if pairs.n_pairs else None
    scene_docs = _get(doc, "scenes", source, list)
    loaded_scenes = _load_scenes(scene_docs, _override(scenes, len(scene_docs), "--scene"), rob, pins,
                                 est["scene_files"])
    check_plane_reach(loaded_scenes, rob, enc.capsules, Refuted)  # certify refuses a plane the robot reaches past
    files = _override(trajectories, len(traj_docs), "--trajectory")
    checked = n_leaves = 0
    diff, excess = 0.0, math.inf
    for k, (tdoc, given) in enumerate(zip(traj_docs, files)):
        where = f"trajectories[{k}]"
        if _get(tdoc, "certified", where, bool) is not True:  # no claim, nothing to check
            pins.check_claimed(str(_get(tdoc, "id", where)))
            est["trajectory_files"].append(TrajectoryFacts(id=str(_get(tdoc, "id", where)), claimed=False,
                                                           scene=tdoc.get("scene"),
                                                           velocities=tdoc.get("velocities") or spec.velocities))
            continue
        traj, facts = _read_claimed(tdoc, k, given, rob, pins, spec.velocities)
        s = facts.scene
        if not 0 <= s < len(loaded_scenes):
            raise LarcInputError(f"{where}.scene: {s} is not a scene index (0..{len(loaded_scenes) - 1})")
        est["trajectory_files"].append(facts)
        nl, d, e = _check_trajectory(tdoc, k, traj, loaded_scenes[s], rob, enc, spec.margin_m, spec.dtype,
                                     spec.max_depth, pairs, delta)
        est["trajectory_files"][-1] = dataclasses.replace(facts, leaves=nl)
        checked, n_leaves, diff, excess = checked + 1, n_leaves + nl, max(diff, d), min(excess, e)
    return _report(est, checked=checked, leaves=n_leaves, max_clearance_diff_m=diff, min_excess_m=excess)
