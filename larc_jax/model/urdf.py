"""URDF loading: a URDF (and its collision meshes' locations) → :class:`~larc_jax.model.robot.Robot`.

Steps of :func:`load_robot`: parse the file with yourdfpy (:func:`load_urdf_model`, which also
checks that every collision mesh resolves to a file; the loaders read the parse as a
:class:`~larc_jax.model.urdf_tree.UrdfTree`), check the joints (:func:`_check_joints`),
order the links breadth-first, choose the active chain (:func:`_active_chain`), compute the held
values of the other movable joints and their mimics (:func:`_held_values`), then fill the arrays.

URDF coverage: fixed, revolute, prismatic and continuous joints; any tree (branches that carry no
movable joint, e.g. ``tool0`` or ``flange`` frames, are followed by the default trunk rule);
links with several or no collision elements. *Continuous* joints are revolute joints whose
limits are taken as ``±CONTINUOUS_LIMIT_RAD`` (4π, two turns each way): the motion constants of a
revolute joint never depend on its limits, and the bound keeps joint values small enough for
the documented floating-point rounding guard; a trajectory beyond it is refused as out of
limits. *Mimic* joints (``<mimic joint=... multiplier=... offset=...>``, e.g. linkage grippers)
are supported when they are not active and their leader is held: they are held at
``multiplier * leader + offset``. A mimic joint that follows an active joint, or another mimic
joint, is refused.

Mesh URIs: ``package://NAME/...`` (resolved through ``package_dirs``; a URDF at
``<pkg>/urdf/x.urdf`` belongs to the package named ``<pkg>``), ``file://...`` and paths
relative to the URDF (:func:`resolve_uri`).
"""

from __future__ import annotations

import functools
import hashlib
import os
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from ..errors import LarcInputError
from ..io import current_sha256, file_sha256  # re-exported: the model's file hashes
from .robot import CONTINUOUS_LIMIT_RAD, JointType, Robot
from .urdf_tree import UrdfTree

__all__ = [
    "load_robot",
    "load_urdf_model",
    "piper_description_dir",
    "piper_urdf_path",
    "package_dirs_for",
    "resolve_uri",
    "file_sha256",
    "current_sha256",
]



def piper_description_dir() -> Path:
    """The official PIPER description folder.

    Resolved from ``LARC_PIPER_DESCRIPTION`` (a ``piper_description`` folder), else from the
    ``robot_descriptions`` package (which clones it where there is internet).
    """
    env = os.environ.get("LARC_PIPER_DESCRIPTION")
    if env:
        folder = Path(env).expanduser().resolve()
        if not (folder / "urdf" / "piper_description.urdf").is_file():
            raise LarcInputError(
                f"LARC_PIPER_DESCRIPTION={env}: no urdf/piper_description.urdf in that folder"
            )
        return folder
    try:
        from robot_descriptions import piper_description  # type: ignore

        folder = Path(piper_description.PACKAGE_PATH)
        if (folder / "urdf" / "piper_description.urdf").is_file():
            return folder
    except Exception:  # noqa: BLE001 - any failure means "not available this way"
        pass
    raise LarcInputError(
        "PIPER description not found: set LARC_PIPER_DESCRIPTION to a piper_description folder "
        "(e.g. ../shared/robots/piper_description), or install the robot_descriptions package "
        "(pip install robot_descriptions; needs internet on first use)"
    )


def piper_urdf_path() -> Path:
    return piper_description_dir() / "urdf" / "piper_description.urdf"


def package_dirs_for(urdf_path: Path, package_dirs: Mapping[str, str] | None) -> dict[str, str]:
    dirs = {k: str(Path(v).expanduser().resolve()) for k, v in (package_dirs or {}).items()}
    # A URDF at <pkg>/urdf/x.urdf conventionally belongs to the package named <pkg>.
    guess = urdf_path.resolve().parent.parent
    dirs.setdefault(guess.name, str(guess))
    return dirs


def resolve_uri(uri: str, urdf_path: Path, package_dirs: Mapping[str, str]) -> Path:
    if uri.startswith("package://"):
        package, _, rest = uri[len("package://"):].partition("/")
        if package not in package_dirs:
            raise LarcInputError(
                f"{urdf_path}: mesh '{uri}' names package '{package}', which is unknown; "
                f"pass --package-dir {package}=PATH"
            )
        return Path(package_dirs[package]) / rest
    if uri.startswith("file://"):
        return Path(uri[len("file://"):])
    path = Path(uri)
    return path if path.is_absolute() else urdf_path.parent / path


def load_urdf_model(
    urdf_path: str | os.PathLike,
    package_dirs: Mapping[str, str] | None = None,
    *,
    sha256: str | None = None,
) -> UrdfTree:
    """Parse a URDF with yourdfpy, resolving ``package://`` URIs; checks every mesh file exists.

    The file is hashed (:func:`current_sha256`: again whenever its status changed) and the bytes
    with that hash are parsed: the parse is cached per process, keyed by the SHA-256 of the
    bytes, the resolved path and package folders, so that loading a robot and then reading its collision geometry
    (:mod:`larc_jax.enclosure.meshes`) parses the file once, and a changed file (even one of the
    same size and modification time) is parsed again; with the compilation cache on, the parse
    is also kept on disk by that SHA-256 (:func:`_parse_urdf`). With ``sha256`` (a robot's
    ``urdf_sha256``) the bytes must have that hash: the geometry read for a robot is the file
    its certificate names, never a later edit. Returns what the loaders read of the parse
    (:class:`~larc_jax.model.urdf_tree.UrdfTree`, shared and frozen). Raises :class:`LarcInputError` naming the file and the link for an unreadable or
    changed URDF or a missing mesh.
    """
    urdf_path = Path(urdf_path)
    if not urdf_path.is_file():
        raise LarcInputError(f"{urdf_path}: URDF file does not exist")
    digest = current_sha256(urdf_path, "URDF file")
    if sha256 is not None and digest != sha256:
        raise LarcInputError(
            f"{urdf_path}: the URDF changed after the robot was loaded from it (SHA-256 now "
            f"{digest[:16]}..., the robot's {sha256[:16]}...); load the robot again"
        )
    dirs = package_dirs_for(urdf_path, package_dirs)
    model = _parse_urdf(str(urdf_path.resolve()), digest, tuple(sorted(dirs.items())))
    for link in model.links:  # checked on every call: a mesh may vanish after the parse
        for col in link.collisions:
            mesh = col.geometry.mesh if col.geometry is not None else None
            if mesh is not None:
                path = resolve_uri(mesh.filename, urdf_path, dirs)
                if not path.is_file():
                    raise LarcInputError(
                        f"{urdf_path}: link '{link.name}' collision mesh '{mesh.filename}' "
                        f"resolves to {path}, which does not exist"
                    )
    return model


@functools.lru_cache(maxsize=8)
def _parse_urdf(urdf_path: str, sha256: str, package_dirs: tuple) -> UrdfTree:
    """What the loaders read of the yourdfpy parse of the bytes of ``urdf_path`` that hash to
    ``sha256`` (behind :func:`load_urdf_model`): :mod:`larc_jax.model.urdf_tree`, kept on disk
    by that SHA-256 while the compilation cache is on (:mod:`larc_jax.model.robot_cache`)."""
    import io

    from ..io import read_input_bytes
    from .robot_cache import keep_text, kept_text
    from .urdf_tree import tree_from_json, tree_to_json, urdf_tree

    key = {"urdf_sha256": sha256}
    text = kept_text("urdf", key)
    if text is not None:
        try:
            return tree_from_json(text)
        except (ValueError, KeyError, TypeError):  # unreadable: parse again
            pass
    data = read_input_bytes(urdf_path, "URDF file")
    if hashlib.sha256(data).hexdigest() != sha256:
        raise LarcInputError(f"{urdf_path}: the URDF changed while it was being read; load the robot again")
    import yourdfpy

    dirs = dict(package_dirs)

    def handler(fname: str) -> str:
        return str(resolve_uri(fname, Path(urdf_path), dirs))

    try:
        model = yourdfpy.URDF.load(
            io.BytesIO(data),
            filename_handler=handler,
            mesh_dir=str(Path(urdf_path).parent),
            build_scene_graph=False,
            build_collision_scene_graph=False,
            load_meshes=False,
            load_collision_meshes=False,
        )
    except Exception as exc:  # noqa: BLE001 - report any parse failure as bad input
        raise LarcInputError(f"{urdf_path}: cannot parse URDF ({exc})") from None
    tree = urdf_tree(model)
    keep_text("urdf", key, tree_to_json(tree))
    return tree


_TYPE_OF = {
    "fixed": JointType.FIXED,
    "revolute": JointType.REVOLUTE,
    "continuous": JointType.REVOLUTE,
    "prismatic": JointType.PRISMATIC,
}


def _limits(j) -> tuple[float, float]:
    if j.type == "continuous":
        return -CONTINUOUS_LIMIT_RAD, CONTINUOUS_LIMIT_RAD
    if j.type == "fixed":
        return 0.0, 0.0
    return float(j.limit.lower), float(j.limit.upper)


def _movable(j) -> bool:
    return j is not None and _TYPE_OF[j.type] != JointType.FIXED


def _check_joints(model, urdf_path: Path) -> dict:
    """Supported joint types, finite ordered limits, mimic leaders that exist and are movable."""
    joints = {j.name: j for j in model.joints}
    for j in model.joints:
        if j.type not in _TYPE_OF:
            raise LarcInputError(f"{urdf_path}: joint '{j.name}' has unsupported type '{j.type}'")
        if j.type in ("revolute", "prismatic") and (
            j.limit is None or j.limit.lower is None or j.limit.upper is None
        ):
            raise LarcInputError(
                f"{urdf_path}: joint '{j.name}' ({j.type}) has no <limit lower=... upper=...>"
            )
        if (j.type in ("revolute", "prismatic")
                and not (np.isfinite(j.limit.lower) and np.isfinite(j.limit.upper))):
            raise LarcInputError(f"{urdf_path}: joint '{j.name}' has a non-finite limit")
        if j.type in ("revolute", "prismatic") and j.limit.lower > j.limit.upper:
            raise LarcInputError(f"{urdf_path}: joint '{j.name}' has limit lower > upper")
        if j.mimic is not None:
            leader = joints.get(j.mimic.joint)
            if leader is None or leader.type not in _TYPE_OF or leader.type == "fixed":
                raise LarcInputError(
                    f"{urdf_path}: mimic joint '{j.name}' follows '{j.mimic.joint}', which is not "
                    f"a movable joint"
                )
            if leader.mimic is not None:
                raise LarcInputError(
                    f"{urdf_path}: mimic joint '{j.name}' follows '{leader.name}', itself a mimic "
                    f"joint (unsupported)"
                )
    return joints


def _tree(model, urdf_path: Path):
    """Links in breadth-first order from the single root, each with its parent index and the
    joint that connects it (None for the root); and the child joints of every link."""
    children: dict[str, list] = {}
    for j in model.joints:
        children.setdefault(j.parent, []).append(j)
    child_links = {j.child for j in model.joints}
    roots = [l.name for l in model.links if l.name not in child_links]
    if len(roots) != 1:
        raise LarcInputError(f"{urdf_path}: expected one root link, found {roots}")
    link_names, parent, joint_of = [roots[0]], [-1], [None]
    k = 0
    while k < len(link_names):
        for j in children.get(link_names[k], []):
            link_names.append(j.child)
            parent.append(k)
            joint_of.append(j)
        k += 1
    if len(link_names) != len(model.links):
        raise LarcInputError(f"{urdf_path}: links and joints do not form one tree")
    return link_names, parent, joint_of, children


def _active_chain(urdf_path: Path, joints: dict, link_names, parent, joint_of, children,
                  active_joints: Sequence[str] | None) -> list[str]:
    """The active joints: given (any movable, non-mimic joints) or the trunk (see load_robot)."""

    def has_movable(j) -> bool:
        """Whether joint ``j`` or any joint below it is movable."""
        return _movable(j) or any(has_movable(c) for c in children.get(j.child, []))

    branches: list = []
    link = link_names[0]
    if active_joints is None:
        active = []
        while True:
            branches = [j for j in children.get(link, []) if has_movable(j)]
            if len(branches) != 1:
                break
            j = branches[0]
            if _movable(j):
                active.append(j.name)
            link = j.child
    else:
        active = list(active_joints)
        if len(set(active)) != len(active):
            raise LarcInputError(f"{urdf_path}: active joints have duplicates: {active}")
        for name in active:
            if name not in joints:
                raise LarcInputError(f"{urdf_path}: no joint named '{name}'")
            if not _movable(joints[name]):
                raise LarcInputError(f"{urdf_path}: joint '{name}' is fixed and cannot be active")
        # The active joints need not be one serial chain: every link's motion constants are
        # derived along its own path to the root (larc_jax.enclosure.motion), so an arm with
        # its finger joints (siblings below the wrist) is fine.
    if not active:
        where = f" (the trunk branches at link '{link}': choose them with --joints)" if (
            active_joints is None and branches) else ""
        raise LarcInputError(f"{urdf_path}: no movable joints to form a serial chain{where}")
    for name in active:
        if joints[name].mimic is not None:
            raise LarcInputError(
                f"{urdf_path}: joint '{name}' is a mimic joint (follows '{joints[name].mimic.joint}') "
                f"and cannot be active"
            )
    for j in joints.values():
        if j.mimic is not None and j.mimic.joint in active:
            raise LarcInputError(
                f"{urdf_path}: mimic joint '{j.name}' follows the active joint '{j.mimic.joint}' "
                f"(unsupported: the motion constants assume independent joints)"
            )
    return active


def _stated(urdf_path: Path, joints: dict, active: list[str], stated_joints) -> tuple[str, ...]:
    """The held joints whose value is stated, with the mimic joints that follow a stated leader."""
    stated = list(dict.fromkeys(stated_joints or ()))
    bad = sorted(n for n in stated if n not in joints or n in active or not _movable(joints[n]))
    if bad:
        raise LarcInputError(f"{urdf_path}: stated joints {bad} are unknown, fixed or active (state held joints only)")
    stated += [j.name for j in joints.values() if j.mimic is not None and j.mimic.joint in stated and j.name not in stated]
    return tuple(stated)


def _held_values(urdf_path: Path, joints: dict, active: list[str],
                 held_joint_values: Mapping[str, float] | None) -> dict[str, float]:
    """Values of the movable joints that are not active: explicit, or 0 clipped into the limits;
    then every mimic joint from its leader."""
    held = dict(held_joint_values or {})
    unknown = sorted(n for n in held if n not in joints or n in active or not _movable(joints[n]))
    if unknown:
        raise LarcInputError(
            f"{urdf_path}: held_joint_values names unknown, fixed or active joints {unknown}"
        )
    held_value: dict[str, float] = {}
    for j in joints.values():
        if not _movable(j) or j.name in active or j.mimic is not None:
            continue
        lo, hi = _limits(j)
        if j.name in held:
            v = float(held[j.name])
            if not lo <= v <= hi:
                raise LarcInputError(
                    f"{urdf_path}: held value {v} of joint '{j.name}' is outside [{lo}, {hi}]"
                )
        else:
            v = float(np.clip(0.0, lo, hi))
        held_value[j.name] = v
    for j in joints.values():
        if j.mimic is None:
            continue
        v = float(j.mimic.multiplier if j.mimic.multiplier is not None else 1.0) * held_value[
            j.mimic.joint] + float(j.mimic.offset if j.mimic.offset is not None else 0.0)
        if j.name in held and abs(float(held[j.name]) - v) > 1e-9:
            raise LarcInputError(
                f"{urdf_path}: held value {held[j.name]} of mimic joint '{j.name}' differs from "
                f"{v} implied by '{j.mimic.joint}'; hold '{j.mimic.joint}' instead"
            )
        lo, hi = _limits(j)
        tol = 1e-9 * max(1.0, abs(lo), abs(hi))
        if not lo - tol <= v <= hi + tol:
            raise LarcInputError(
                f"{urdf_path}: mimic joint '{j.name}' would be held at {v} (from "
                f"'{j.mimic.joint}' = {held_value[j.mimic.joint]}), outside its limits [{lo}, {hi}]"
            )
        held_value[j.name] = v
    return held_value


def load_robot(
    urdf_path: str | os.PathLike | None = None,
    package_dirs: Mapping[str, str] | None = None,
    *,
    active_joints: Sequence[str] | None = None,
    held_joint_values: Mapping[str, float] | None = None,
    stated_joints: Sequence[str] | None = None,
) -> Robot:
    """Build a :class:`Robot` from a URDF (default: the official PIPER description).

    Args:
      urdf_path: URDF file; ``None`` resolves PIPER via :func:`piper_urdf_path`.
      package_dirs: ``{package name: folder}`` for ``package://`` URIs.
      active_joints: joints a trajectory carries, in configuration order. Default: the movable
        joints of the trunk: from the root, follow the one child joint whose subtree holds a
        movable joint, and stop where none or several do (PIPER: joint1..joint6, the two finger
        joints branch off link6; a UR arm's fixed ``base``/``tool0`` frames are passed over).
      held_joint_values: values for movable joints that are not active (default 0 clipped into
        the joint's limits). Mimic joints follow their leader; a value given for one must equal
        ``multiplier * leader + offset``.
      stated_joints: held joints whose value the user *states* (e.g. the gripper opening,
        ``larc certify --hold joint7=0``): their links are enclosed at that value alone. A held
        prismatic joint not stated may be anywhere in its stroke, which the enclosures of its
        links then cover (:attr:`Robot.stroke_joints`). Mimic joints of a stated leader are stated.
    """
    from .robot_cache import cached_robot, keep_robot

    urdf_path = Path(urdf_path) if urdf_path is not None else piper_urdf_path()
    if not urdf_path.is_file():
        raise LarcInputError(f"{urdf_path}: URDF file does not exist")
    sha256 = file_sha256(urdf_path)  # what the robot (and a certificate) names; the parse is of these bytes
    key = dict(urdf=str(urdf_path.resolve()), sha256=sha256,
               package_dirs=sorted(package_dirs_for(urdf_path, package_dirs).items()),
               active_joints=list(active_joints) if active_joints is not None else None,
               held=sorted((str(k), float(v)) for k, v in (held_joint_values or {}).items()),
               stated=sorted(str(j) for j in (stated_joints or ())))
    robot = cached_robot(key)  # None unless the compilation cache is on (the command line)
    if robot is not None:
        return robot
    model = load_urdf_model(urdf_path, package_dirs, sha256=sha256)
    robot = _build_robot(model, urdf_path, sha256, package_dirs, active_joints, held_joint_values, stated_joints)
    keep_robot(key, robot, _mesh_files(model, urdf_path, robot.package_dirs))
    return robot


def _mesh_files(model, urdf_path: Path, package_dirs) -> list[Path]:
    dirs = dict(package_dirs)
    return [resolve_uri(c.geometry.mesh.filename, urdf_path, dirs) for link in model.link_map.values()
            for c in link.collisions if c.geometry is not None and c.geometry.mesh is not None]


def _build_robot(model, urdf_path: Path, urdf_sha256: str, package_dirs, active_joints, held_joint_values,
                 stated_joints) -> Robot:
    """The steps of :func:`load_robot` after parsing."""
    joints = _check_joints(model, urdf_path)
    link_names, parent, joint_of, children = _tree(model, urdf_path)
    active = _active_chain(urdf_path, joints, link_names, parent, joint_of, children, active_joints)
    held_value = _held_values(urdf_path, joints, active, held_joint_values)
    stated = _stated(urdf_path, joints, active, stated_joints)

    n_links = len(link_names)
    T = np.tile(np.eye(4), (n_links, 1, 1))
    axis = np.zeros((n_links, 3))
    q_held = np.zeros(n_links)
    jtype, jname, q_index = [JointType.FIXED], [""], [-1]
    lower = np.zeros(len(active))
    upper = np.zeros(len(active))
    for i in range(1, n_links):
        j = joint_of[i]
        t = _TYPE_OF[j.type]
        T[i] = np.asarray(j.origin if j.origin is not None else np.eye(4), dtype=np.float64)
        if not np.isfinite(T[i]).all():
            raise LarcInputError(f"{urdf_path}: joint '{j.name}' has a non-finite origin")
        if t != JointType.FIXED:
            ax = np.asarray(j.axis if j.axis is not None else [1.0, 0.0, 0.0], dtype=np.float64)
            norm = np.linalg.norm(ax)
            if not np.isfinite(norm) or norm == 0:
                raise LarcInputError(f"{urdf_path}: joint '{j.name}' has a zero or invalid axis")
            axis[i] = ax / norm
        jtype.append(t)
        jname.append(j.name)
        if j.name in active:
            q_index.append(active.index(j.name))
            lower[active.index(j.name)], upper[active.index(j.name)] = _limits(j)
        else:
            q_index.append(-1)
            if t != JointType.FIXED:
                q_held[i] = held_value[j.name]

    dirs = package_dirs_for(urdf_path, package_dirs)
    return Robot(
        T_parent_joint=T,
        axis=axis,
        q_held=q_held,
        q_lower=lower,
        q_upper=upper,
        name=model.name,
        link_names=tuple(link_names),
        parent=tuple(parent),
        joint_names=tuple(jname),
        joint_type=tuple(jtype),
        q_index=tuple(q_index),
        active_joint_names=tuple(active),
        urdf_path=str(urdf_path.resolve()),
        urdf_sha256=urdf_sha256,
        package_dirs=tuple(sorted(dirs.items())),
        stated_joints=stated,
    )
