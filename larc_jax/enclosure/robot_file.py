"""The robot file (capsule file): the one reader and writer of its format.

Written by ``larc fit-capsules`` (:func:`save_capsules`), read by :func:`load_capsules` (the
capsules for a given robot) and :func:`load_robot_file` (the robot *and* its capsules, from the
file's ``urdf``, ``package_dirs``, ``active_joints`` and ``held_joints`` fields: what
``larc certify --robot FILE`` uses). Relative paths in the file are relative to its folder.

A capsule file is trusted only while the geometry its containment was proven on is unchanged.
It records the SHA-256 of the URDF text (``urdf_sha256``: joint origins, limits, collision
origins, scales and primitive sizes) and, in ``geometry``, every collision element of every
link as the fit used it (:func:`~larc_jax.enclosure.meshes.collision_geometry`: the SHA-256 of
each collision mesh file, its scale, the primitive parameters, the placement). Loading checks
all of it and refuses a mismatch ("refit with larc fit-capsules"), a file without ``geometry``
(written before revision ``larc-capsules-2``), and a file that leaves a link with collision
geometry without a capsule. Containment itself is re-proven on demand by ``larc
verify-capsules`` (:func:`~larc_jax.enclosure.fit.verify_containment`), and by ``fit-capsules``
after writing.

Gripper. ``capsules`` enclose every link of the robot as fitted: links below a held prismatic
joint (a finger) over its whole stroke, placed at the recorded ``held_joints`` value
(``held_prismatic_stroke_enclosed``). ``stated_capsules`` enclose those links alone, in their
own link frames: they are used instead when the joints above the link are *stated*
(``load_robot_file(path, hold={...})``, ``larc certify --hold joint7=0``), wherever FK puts
them. (A stroke capsule also contains its link placed anywhere by FK, since it holds the
unshifted copy of every element; the stated capsule is just tighter.) ``hull_parts`` records how
the hull stage splits links into parts (:mod:`larc_jax.enclosure.hull`).

Fields. Any field the readers do not know, at the top or in a capsule or hull part, is an error
naming it. Written for people and not read (documented as ignored): ``revision``,
``gripper_opening_m``, ``held_prismatic_stroke_enclosed``, and a capsule's ``volume_m3`` and
``hull_volume_m3``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import yaml

from ..errors import GeometryChanged, LarcInputError
from ..io import atomic_write_text, check_keys, parse_number, parse_vector, parse_yaml, read_input_text, short_repr
from ..model.robot import JointType, Robot
from .capsule import CapsuleModel
from .fit import FittedCapsule
from .meshes import collision_geometry, links_with_geometry, stroke_shifts
from .motion import motion_constants

__all__ = ["save_capsules", "load_capsules", "load_robot_file", "default_capsule_path", "MODEL_REVISION"]

MODEL_REVISION = "larc-capsules-2"
"""Revision 2 added ``geometry`` (collision-geometry hashes); files without it are refused."""


def default_capsule_path() -> Path:
    """PIPER's capsule file, shipped with the package (``larc_jax/data/piper_capsules.yaml``)."""
    from ..data import PIPER_CAPSULES, data_path

    return data_path(PIPER_CAPSULES)


def _capsule_entries(fitted: Sequence[FittedCapsule]) -> list[dict]:
    return [
        {
            "name": f.name,
            "link": f.link,
            "a": [round(float(x), 6) for x in f.a],
            "b": [round(float(x), 6) for x in f.b],
            "radius": round(f.radius, 6),
            "volume_m3": float(f"{f.volume_m3:.6g}"),
            "hull_volume_m3": float(f"{f.hull_volume_m3:.6g}"),
        }
        for f in fitted
    ]


def save_capsules(path: str | Path, robot: Robot, fitted: Sequence[FittedCapsule], *,
                  padding_m: float, urdf: str | None = None,
                  package_dirs: Mapping[str, str] | None = None,
                  stated: Sequence[FittedCapsule] = (), hull_parts: Sequence[tuple] = ()) -> None:
    """Write the capsule file atomically.

    ``urdf`` and ``package_dirs`` (written only when ``urdf`` is given) let ``larc certify
    --robot FILE`` rebuild the robot; relative paths there are relative to the file's folder.
    ``stated``: capsules of the stroke-enclosed links fitted in their own frames (module
    docstring); ``hull_parts``: ``(link, normal, offset)`` split planes of the hull stage.
    """
    held = {
        robot.joint_names[i]: float(robot.q_held[i])
        for i in range(1, robot.n_links)
        if robot.q_index[i] < 0 and robot.joint_type[i] != JointType.FIXED
    }
    finger_joints = [j for j in held if robot.joint_type[robot.joint_names.index(j)] == JointType.PRISMATIC]
    doc = {
        "urdf_sha256": robot.urdf_sha256,
        "padding_m": padding_m,
        "revision": MODEL_REVISION,
        "gripper_opening_m": float(sum(abs(held[j]) for j in finger_joints)) if finger_joints else None,
        "active_joints": list(robot.active_joint_names),
        "held_joints": held,
        "held_prismatic_stroke_enclosed": True,
        "geometry": collision_geometry(robot),
        "capsules": _capsule_entries(fitted),
    }
    if stated:
        doc["stated_capsules"] = _capsule_entries(stated)
    if hull_parts:
        doc["hull_parts"] = {link: {"normal": [float(x) for x in n], "offset": float(o)} for link, n, o in hull_parts}
    if urdf is not None:
        extra = {"package_dirs": dict(package_dirs)} if package_dirs else {}
        doc = {"urdf": urdf, **extra, **doc}
    header = (
        "# Capsules fitted by `larc fit-capsules`; containment of every collision-mesh vertex is\n"
        "# proven by `larc verify-capsules`. Link frames, metres; radius includes padding_m.\n"
        "# `geometry` records what the fit used; a changed mesh or URDF is refused at load.\n"
    )
    atomic_write_text(path, header + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=120))


_FILE_KEYS = ("urdf", "package_dirs", "urdf_sha256", "padding_m", "active_joints", "held_joints", "geometry",
              "capsules", "stated_capsules", "hull_parts", "ignored_links")
_FILE_IGNORED = ("revision", "gripper_opening_m", "held_prismatic_stroke_enclosed")
_CAPSULE_KEYS = ("name", "link", "a", "b", "radius")
_CAPSULE_IGNORED = ("volume_m3", "hull_volume_m3")


def _field(doc: Mapping, key: str, source: str, where: str = ""):
    if key not in doc:
        raise LarcInputError(f"{source}: missing field '{where}{key}'")
    return doc[key]


_MAX_CAPSULE_M = 1e6
"""Capsule coordinates and radii beyond this (m) are refused as implausible (squares overflow)."""


def _vec3(value, source: str, where: str) -> np.ndarray:
    v = parse_vector(value, 3, source, where, finite=True)
    if np.abs(v).max() > _MAX_CAPSULE_M:
        raise LarcInputError(f"{source}: {where} = {short_repr(value)} is beyond {_MAX_CAPSULE_M:g} m of its link frame")
    return v


def _refit(robot: Robot, source: str) -> str:
    return f"refit with `larc fit-capsules {robot.urdf_path} -o {source}`"


def _check_geometry(doc: Mapping, robot: Robot, source: str) -> None:
    """The recorded collision geometry must be what the robot's URDF and files give now."""
    if "geometry" not in doc:
        raise LarcInputError(
            f"{source}: no 'geometry' field (collision-geometry hashes; the file is revision "
            f"{short_repr(doc.get('revision'))}, older than {MODEL_REVISION}), so the meshes its capsules "
            f"were proven on cannot be checked; {_refit(robot, source)}")
    recorded = doc["geometry"]
    if not isinstance(recorded, dict):
        raise LarcInputError(f"{source}: geometry must be a mapping LINK: [collision elements]")
    current = collision_geometry(robot)
    for link in sorted(set(recorded) | set(current), key=str):
        have, want = current.get(link), recorded.get(link)
        if want is None:
            raise LarcInputError(f"{source}: link '{link}' has collision geometry in {robot.urdf_path} that the "
                                 f"capsules were not fitted to; {_refit(robot, source)}")
        if have is None:
            raise LarcInputError(f"{source}: geometry records link '{link}', which has no collision geometry in "
                                 f"{robot.urdf_path}; {_refit(robot, source)}")
        if not isinstance(want, list) or len(want) != len(have):
            raise LarcInputError(
                f"{source}: geometry.{link} records {len(want) if isinstance(want, list) else short_repr(want)} "
                f"collision elements, {robot.urdf_path} has {len(have)}; {_refit(robot, source)}")
        for k, (w, h) in enumerate(zip(want, have)):
            if w == h:
                continue
            if isinstance(w, dict) and "sha256" in w and "mesh" in h and w.get("sha256") != h["sha256"]:
                raise GeometryChanged(
                    f"{source}: link '{link}' collision mesh {h['mesh']} has changed since the capsules were "
                    f"fitted (sha256 {h['sha256']}, fitted to {short_repr(w.get('sha256'))}); {_refit(robot, source)}")
            raise LarcInputError(
                f"{source}: geometry.{link}[{k}] = {short_repr(w)} differs from what {robot.urdf_path} gives "
                f"now ({short_repr(h)}); {_refit(robot, source)}")


def _check_coverage(links: list[str], robot: Robot, source: str) -> None:
    """Every link with collision geometry has a capsule (cheap: no mesh is read)."""
    missing = [link for link in links_with_geometry(robot) if link not in links]
    if missing:
        raise LarcInputError(
            f"{source}: link{'s' if len(missing) > 1 else ''} {', '.join(repr(m) for m in missing)} "
            f"{'have' if len(missing) > 1 else 'has'} collision geometry but no capsule; {_refit(robot, source)}")


def load_capsules(path: str | Path, robot: Robot) -> CapsuleModel:
    """Read a capsule file for ``robot`` and compute its motion constants.

    Fails with :class:`LarcInputError` if the file was fitted to another URDF or to other
    collision geometry (hash mismatch), leaves a link with collision geometry uncovered, names
    unknown links, or holds malformed numbers. The optional field ``ignored_links: [LINK,
    ...]`` leaves those links out of the certificate (:meth:`CapsuleModel.without_links`: only
    links that never move, e.g. a base standing on its table).
    """
    path = Path(path)
    source = str(path)
    doc = parse_yaml(read_input_text(path, "capsule file"), source)
    if not isinstance(doc, dict):
        raise LarcInputError(f"{source}: expected a mapping with 'capsules'")
    check_keys(doc, _FILE_KEYS, source, ignored=_FILE_IGNORED)
    if _field(doc, "urdf_sha256", source) != robot.urdf_sha256:
        raise GeometryChanged(
            f"{source}: fitted to a URDF with sha256 {short_repr(doc['urdf_sha256'])}, but {robot.urdf_path} "
            f"has sha256 {robot.urdf_sha256}; {_refit(robot, source)}"
        )
    _check_geometry(doc, robot, source)
    padding = parse_number(_field(doc, "padding_m", source), source, "padding_m")
    if not (np.isfinite(padding) and padding >= 0):
        raise LarcInputError(f"{source}: padding_m must be a finite number >= 0")
    active = doc.get("active_joints")
    held = doc.get("held_joints") or {}
    if not isinstance(held, dict):
        raise LarcInputError(f"{source}: held_joints must be a mapping JOINT: VALUE")
    # The robot may make active some joints the file holds (fingers a trajectory carries): every
    # capsule holds its link wherever FK puts it (module docstring).
    if active is not None and (
            not isinstance(active, list)
            or [j for j in robot.active_joint_names if j in active] != active
            or any(j not in active and j not in held for j in robot.active_joint_names)):
        raise LarcInputError(
            f"{source}: active_joints {short_repr(active)} differ from the robot's {list(robot.active_joint_names)} "
            f"(a robot may add only joints the file holds)"
        )
    # A stated joint's links are placed by FK at the stated value, and every capsule holds its
    # link wherever FK puts it (module docstring): only unstated held values must match.
    held = {j: v for j, v in held.items() if j not in robot.stated_joints and j not in robot.active_joint_names}
    if "held_joints" in doc:
        # The capsules of links on held joints are valid at the recorded values only: every
        # joint the robot holds must be recorded (and equal, below).
        for i in range(1, robot.n_links):
            jname = robot.joint_names[i]
            if (robot.q_index[i] < 0 and robot.joint_type[i] != JointType.FIXED and jname not in held
                    and jname not in robot.stated_joints):
                raise LarcInputError(
                    f"{source}: held_joints does not record joint '{jname}', which the robot holds "
                    f"at {float(robot.q_held[i])}"
                )
    for jname, value in held.items():
        if jname not in robot.joint_names:
            raise LarcInputError(f"{source}: held_joints names unknown joint '{jname}'")
        i = robot.joint_names.index(jname)
        value = parse_number(value, source, f"held_joints.{jname}")
        if not abs(float(robot.q_held[i]) - value) <= 1e-12:
            raise LarcInputError(
                f"{source}: held_joints.{jname} = {value} but the robot holds it at {float(robot.q_held[i])}"
            )
    entries = _field(doc, "capsules", source)
    if not isinstance(entries, list) or not entries:
        raise LarcInputError(f"{source}: 'capsules' must be a non-empty list")
    stated_entries = doc.get("stated_capsules") or []
    if not isinstance(stated_entries, list):
        raise LarcInputError(f"{source}: 'stated_capsules' must be a list")
    parsed = _parse_capsules(entries, "capsules", source, robot, padding)
    stated = _parse_capsules(stated_entries, "stated_capsules", source, robot, padding)
    # Links whose stroke joints are all stated take their stated capsules (module docstring).
    free = {l for l in robot.link_names if len(stroke_shifts(robot, l)) == 1}
    use_stated = {e[1] for e in stated if e[1] in free}
    chosen = [e for e in parsed if e[1] not in use_stated] + [e for e in stated if e[1] in use_stated]
    chosen.sort(key=lambda e: robot.link_names.index(e[1]))  # link order, as fitted
    names, links, idx, A, B, R = (list(x) for x in zip(*chosen))
    _check_coverage(links, robot, source)
    ignored = doc.get("ignored_links") or []
    if not isinstance(ignored, list) or not all(isinstance(x, str) for x in ignored):
        raise LarcInputError(f"{source}: ignored_links must be a list of link names, got {short_repr(ignored)}")
    A, B, R = np.array(A), np.array(B), np.array(R)
    model = CapsuleModel(
        p_link_a=A,
        p_link_b=B,
        radius=R,
        motion_a=motion_constants(robot, idx, A, B, R),
        names=tuple(names),
        link_names=tuple(links),
        link_index=tuple(idx),
        padding_m=padding,
        hull_parts=_parse_hull_parts(doc.get("hull_parts"), source, robot),
    )
    return model.without_links(robot, ignored, what=f"{source}: ignored_links:")


def _parse_capsules(entries: list, key: str, source: str, robot: Robot, padding: float) -> list[tuple]:
    """``(name, link, link index, a, b, radius)`` of each entry of a capsule list."""
    out = []
    for k, e in enumerate(entries):
        where = f"{key}[{k}]"
        if not isinstance(e, dict):
            raise LarcInputError(f"{source}: {where} must be a mapping")
        check_keys(e, _CAPSULE_KEYS, source, where, ignored=_CAPSULE_IGNORED)
        link = _field(e, "link", source, where + ".")
        if not isinstance(link, str):
            raise LarcInputError(f"{source}: {where}.link must be a link name, got {short_repr(link)}")
        if link not in robot.link_names:
            raise LarcInputError(f"{source}: {where}.link '{link}' is not a link of {robot.urdf_path}")
        r = parse_number(e.get("radius"), source, f"{where}.radius")
        if not np.isfinite(r) or r <= padding or r > _MAX_CAPSULE_M:
            raise LarcInputError(
                f"{source}: {where}.radius must be a finite number > padding_m and <= {_MAX_CAPSULE_M:g} m, got {r!r}")
        name = e.get("name", f"{link}_{k}")
        if not isinstance(name, (str, int)) or isinstance(name, bool):
            raise LarcInputError(f"{source}: {where}.name must be a string, got {short_repr(name)}")
        out.append((str(name), link, robot.link_names.index(link),
                    _vec3(_field(e, "a", source, where + "."), source, where + ".a"),
                    _vec3(_field(e, "b", source, where + "."), source, where + ".b"), float(r)))
    return out


def _parse_hull_parts(value, source: str, robot: Robot) -> tuple:
    """``hull_parts: {link: {normal: [x, y, z], offset: d}}`` -> ``((link, normal, offset), ...)``."""
    if value is None:
        return ()
    if not isinstance(value, dict):
        raise LarcInputError(f"{source}: hull_parts must be a mapping LINK: {{normal: [x, y, z], offset: d}}")
    out = []
    for link, plane in value.items():
        where = f"hull_parts.{link}"
        if link not in robot.link_names:
            raise LarcInputError(f"{source}: {where}: '{link}' is not a link of {robot.urdf_path}")
        if not isinstance(plane, dict):
            raise LarcInputError(f"{source}: {where} must be a mapping {{normal: [x, y, z], offset: d}}")
        check_keys(plane, ("normal", "offset"), source, where)
        normal = _vec3(_field(plane, "normal", source, where + "."), source, where + ".normal")
        offset = parse_number(_field(plane, "offset", source, where + "."), source, where + ".offset")
        if not np.isfinite(offset) or not np.linalg.norm(normal) > 0:
            raise LarcInputError(f"{source}: {where}: needs a non-zero normal and a finite offset")
        out.append((str(link), tuple(float(x) for x in normal), float(offset)))
    return tuple(out)


def load_robot_file(path: str | Path | None = None, hold: Mapping[str, float] | None = None,
                    active_joints: Sequence[str] | None = None) -> tuple[Robot, CapsuleModel]:
    """The robot and its capsules from a robot file written by ``larc fit-capsules`` (its
    ``urdf``, ``package_dirs``, ``active_joints`` and ``held_joints`` fields rebuild the robot);
    ``None``: PIPER (``LARC_PIPER_DESCRIPTION``) with the shipped capsule file.

    ``hold``: held joints whose value the user *states* (``{"joint7": 0.0, "joint8": 0.0}``,
    ``larc certify --hold``): FK places their links at those values and the links are enclosed
    alone (module docstring). Without it, every held prismatic joint's stroke is enclosed.
    ``active_joints``: the joints a trajectory carries, if not the file's (``larc certify
    --joints``): the file's active joints plus some it holds, e.g. the fingers.
    """
    from ..model.urdf import load_robot

    hold = _check_hold(hold)
    if path is None:
        robot = load_robot(active_joints=active_joints, held_joint_values=hold, stated_joints=list(hold))
        return robot, load_capsules(default_capsule_path(), robot)
    path = Path(path)
    doc = parse_yaml(read_input_text(path, "robot file"), str(path))
    if doc is None:
        raise LarcInputError(f"{path}: robot file is empty")
    if isinstance(doc, dict):
        check_keys(doc, _FILE_KEYS, str(path), ignored=_FILE_IGNORED)
    if not isinstance(doc, dict) or "urdf" not in doc:
        raise LarcInputError(f"{path}: missing field 'urdf' (write it with `larc fit-capsules URDF -o FILE`; "
                             f"PIPER's shipped capsule file is used when no robot file is given)")
    if not isinstance(doc["urdf"], str) or not doc["urdf"]:
        raise LarcInputError(f"{path}: urdf must be a file path, got {short_repr(doc['urdf'])}")
    urdf = Path(doc["urdf"])
    if not urdf.is_absolute():
        urdf = path.parent / urdf
    dirs = doc.get("package_dirs") or {}
    if not isinstance(dirs, dict) or not all(isinstance(v, str) for v in dirs.values()):
        raise LarcInputError(f"{path}: package_dirs must be a mapping NAME: FOLDER, got {short_repr(dirs)}")
    dirs = {str(k): str(path.parent / str(v)) for k, v in dirs.items()}  # relative to the file
    active = doc.get("active_joints")
    if active is not None and not (isinstance(active, list) and all(isinstance(n, str) for n in active)):
        raise LarcInputError(f"{path}: active_joints must be a list of joint names, got {short_repr(active)}")
    held = doc.get("held_joints") or {}
    if not isinstance(held, dict):
        raise LarcInputError(f"{path}: held_joints must be a mapping JOINT: VALUE, got {short_repr(held)}")
    for name, value in held.items():
        parse_number(value, str(path), f"held_joints.{name}", finite=True)
    held = {j: v for j, v in held.items() if active_joints is None or j not in active_joints}
    robot = load_robot(urdf, dirs, active_joints=active_joints if active_joints is not None else active,
                       held_joint_values={**held, **hold}, stated_joints=list(hold))
    return robot, load_capsules(path, robot)


def _check_hold(hold) -> dict[str, float]:
    if hold is None:
        return {}
    if not isinstance(hold, Mapping):
        raise LarcInputError(f"hold must be a mapping JOINT: VALUE, got {short_repr(hold)}")
    out = {}
    for name, value in hold.items():
        if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)) or not np.isfinite(value):
            raise LarcInputError(f"hold: {name} must be a finite number (the joint's stated value), got {short_repr(value)}")
        out[str(name)] = float(value)
    return out
