"""Robot model: URDF → frozen, jit-friendly kinematic tree, and forward kinematics.

The model is a :class:`Robot` pytree. Static structure (link order, parent indices, joint types,
which configuration entry drives which joint) lives in Python tuples (pytree metadata, hashable,
so it is baked into compiled code); numeric data (joint origins, axes, limits, the values at
which non-trajectory joints are held) are arrays.

A *configuration* ``q`` holds the values of the robot's **active joints**: the serial chain of
revolute/prismatic joints that a trajectory carries (for PIPER: joint1..joint6). Every other
movable joint (e.g. the gripper fingers, which branch off link6) is held at a fixed value
recorded in the model.

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

Frames: the URDF root link is the world/base frame. ``T_world_link[i]`` maps link ``i``
coordinates to base coordinates (4×4 homogeneous, metres).
"""

from __future__ import annotations

import dataclasses
import enum
import hashlib
import os
from pathlib import Path
from typing import Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from .errors import LarcInputError

__all__ = [
    "JointType",
    "Robot",
    "load_robot",
    "load_urdf_model",
    "forward_kinematics",
    "forward_kinematics_np",
    "piper_description_dir",
    "piper_urdf_path",
    "file_sha256",
    "CONTINUOUS_LIMIT_RAD",
]

CONTINUOUS_LIMIT_RAD = 4.0 * np.pi
"""Limits (±) given to the values of continuous joints, rad (see the module docstring)."""


class JointType(enum.IntEnum):
    """Kinds of joint the model supports (continuous joints are revolute, limits ±CONTINUOUS_LIMIT_RAD)."""

    FIXED = 0
    REVOLUTE = 1
    PRISMATIC = 2


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Robot:
    """A kinematic tree whose active joints form one serial chain from the root.

    Links are stored in topological order: ``parent[i] < i`` and link 0 is the root.
    Entry ``i`` of the per-link arrays describes the joint that connects ``parent[i]`` to
    link ``i`` (entry 0, the root, is an unused identity).
    """

    T_parent_joint: jax.Array
    """(L, 4, 4) joint origin: pose of joint ``i``'s frame in its parent link's frame, m."""
    axis: jax.Array
    """(L, 3) unit joint axis in the joint frame (zeros for fixed joints)."""
    q_held: jax.Array
    """(L,) value at which a movable joint that is *not* active is held (rad or m); 0 otherwise."""
    q_lower: jax.Array
    """(n,) lower limits of the active joints (rad or m; -CONTINUOUS_LIMIT_RAD for continuous joints)."""
    q_upper: jax.Array
    """(n,) upper limits of the active joints (rad or m; +CONTINUOUS_LIMIT_RAD for continuous joints)."""

    name: str = dataclasses.field(metadata=dict(static=True))
    link_names: tuple[str, ...] = dataclasses.field(metadata=dict(static=True))
    parent: tuple[int, ...] = dataclasses.field(metadata=dict(static=True))
    """Parent link index per link; -1 for the root."""
    joint_names: tuple[str, ...] = dataclasses.field(metadata=dict(static=True))
    """Name of the joint whose child is link ``i`` ('' for the root)."""
    joint_type: tuple[JointType, ...] = dataclasses.field(metadata=dict(static=True))
    q_index: tuple[int, ...] = dataclasses.field(metadata=dict(static=True))
    """Index into the configuration vector of the joint driving link ``i``; -1 if not active."""
    active_joint_names: tuple[str, ...] = dataclasses.field(metadata=dict(static=True))
    urdf_path: str = dataclasses.field(metadata=dict(static=True))
    urdf_sha256: str = dataclasses.field(metadata=dict(static=True))
    package_dirs: tuple[tuple[str, str], ...] = dataclasses.field(metadata=dict(static=True))
    """(package name, folder) pairs used to resolve ``package://`` mesh URIs."""

    @property
    def n_links(self) -> int:
        return len(self.link_names)

    @property
    def n_joints(self) -> int:
        """Number of active joints (the configuration dimension n)."""
        return len(self.active_joint_names)

    def link_index(self, link: str) -> int:
        try:
            return self.link_names.index(link)
        except ValueError:
            raise LarcInputError(
                f"{self.urdf_path}: robot has no link '{link}' (links: {', '.join(self.link_names)})"
            ) from None

    def ancestors(self, link: int) -> list[int]:
        """Link indices from the root down to ``link`` (inclusive)."""
        chain = []
        while link >= 0:
            chain.append(link)
            link = self.parent[link]
        return chain[::-1]


# ----------------------------------------------------------------------------------------------
# Forward kinematics (JAX kernel for one configuration, NumPy float64 reference)
# ----------------------------------------------------------------------------------------------


def _joint_motion(jtype: JointType, axis: jax.Array, value: jax.Array) -> jax.Array:
    """4×4 motion of a joint about/along its unit ``axis`` by ``value`` (Rodrigues' formula)."""
    dtype = axis.dtype
    if jtype == JointType.FIXED:
        return jnp.eye(4, dtype=dtype)
    if jtype == JointType.PRISMATIC:
        return jnp.eye(4, dtype=dtype).at[:3, 3].set(axis * value)
    x, y, z = axis[0], axis[1], axis[2]
    zero = jnp.zeros((), dtype)
    K = jnp.array([[zero, -z, y], [z, zero, -x], [-y, x, zero]])
    R = jnp.eye(3, dtype=dtype) + jnp.sin(value) * K + (1.0 - jnp.cos(value)) * (K @ K)
    return jnp.eye(4, dtype=dtype).at[:3, :3].set(R)


def forward_kinematics(robot: Robot, q: jax.Array) -> jax.Array:
    """Poses of every link for one configuration.

    Args:
      robot: the model.
      q: (n,) active joint values (rad / m).

    Returns:
      T_world_link: (L, 4, 4) link poses in the base frame.

    Pure and jit-able; the loop over links is unrolled at trace time (static structure).
    Batch with ``jax.vmap(forward_kinematics, in_axes=(None, 0))``.
    """
    q = jnp.asarray(q)
    # Compute in the configuration's precision (float64 under `jax.enable_x64`).
    dtype = q.dtype if jnp.issubdtype(q.dtype, jnp.floating) else jnp.result_type(float)
    T_world = [jnp.eye(4, dtype=dtype)]
    for i in range(1, robot.n_links):
        k = robot.q_index[i]
        value = q[k] if k >= 0 else robot.q_held[i]
        M = _joint_motion(robot.joint_type[i], robot.axis[i].astype(dtype), value.astype(dtype))
        T_world.append(T_world[robot.parent[i]] @ robot.T_parent_joint[i].astype(dtype) @ M)
    return jnp.stack(T_world)


def forward_kinematics_np(robot: Robot, q: np.ndarray) -> np.ndarray:
    """NumPy float64 reference of :func:`forward_kinematics` (rotations via SciPy's rotvec)."""
    from scipy.spatial.transform import Rotation

    q = np.asarray(q, dtype=np.float64)
    T_pj = np.asarray(robot.T_parent_joint, dtype=np.float64)
    axis = np.asarray(robot.axis, dtype=np.float64)
    held = np.asarray(robot.q_held, dtype=np.float64)
    out = np.zeros((robot.n_links, 4, 4))
    out[0] = np.eye(4)
    for i in range(1, robot.n_links):
        k = robot.q_index[i]
        value = q[k] if k >= 0 else held[i]
        M = np.eye(4)
        if robot.joint_type[i] == JointType.REVOLUTE:
            M[:3, :3] = Rotation.from_rotvec(axis[i] * value).as_matrix()
        elif robot.joint_type[i] == JointType.PRISMATIC:
            M[:3, 3] = axis[i] * value
        out[i] = out[robot.parent[i]] @ T_pj[i] @ M
    return out


# ----------------------------------------------------------------------------------------------
# URDF loading
# ----------------------------------------------------------------------------------------------


def file_sha256(path: str | os.PathLike) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


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


def _package_dirs_for(urdf_path: Path, package_dirs: Mapping[str, str] | None) -> dict[str, str]:
    dirs = {k: str(Path(v).expanduser().resolve()) for k, v in (package_dirs or {}).items()}
    # A URDF at <pkg>/urdf/x.urdf conventionally belongs to the package named <pkg>.
    guess = urdf_path.resolve().parent.parent
    dirs.setdefault(guess.name, str(guess))
    return dirs


def _resolve_uri(uri: str, urdf_path: Path, package_dirs: Mapping[str, str]) -> Path:
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
):
    """Parse a URDF with yourdfpy, resolving ``package://`` URIs; checks every mesh file exists.

    Returns the ``yourdfpy.URDF`` object. Raises :class:`LarcInputError` naming the file and the
    link for any unreadable URDF or missing mesh.
    """
    import yourdfpy

    urdf_path = Path(urdf_path)
    if not urdf_path.is_file():
        raise LarcInputError(f"{urdf_path}: URDF file does not exist")
    dirs = _package_dirs_for(urdf_path, package_dirs)

    def handler(fname: str) -> str:
        return str(_resolve_uri(fname, urdf_path, dirs))

    try:
        model = yourdfpy.URDF.load(
            str(urdf_path),
            filename_handler=handler,
            build_scene_graph=False,
            build_collision_scene_graph=False,
            load_meshes=False,
            load_collision_meshes=False,
        )
    except Exception as exc:  # noqa: BLE001 - report any parse failure as bad input
        raise LarcInputError(f"{urdf_path}: cannot parse URDF ({exc})") from None
    for link in model.robot.links:
        for col in link.collisions:
            mesh = col.geometry.mesh if col.geometry is not None else None
            if mesh is not None:
                path = _resolve_uri(mesh.filename, urdf_path, dirs)
                if not path.is_file():
                    raise LarcInputError(
                        f"{urdf_path}: link '{link.name}' collision mesh '{mesh.filename}' "
                        f"resolves to {path}, which does not exist"
                    )
    return model


_TYPE_OF = {
    "fixed": JointType.FIXED,
    "revolute": JointType.REVOLUTE,
    "continuous": JointType.REVOLUTE,
    "prismatic": JointType.PRISMATIC,
}


def load_robot(
    urdf_path: str | os.PathLike | None = None,
    package_dirs: Mapping[str, str] | None = None,
    *,
    active_joints: Sequence[str] | None = None,
    held_joint_values: Mapping[str, float] | None = None,
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
    """
    urdf_path = Path(urdf_path) if urdf_path is not None else piper_urdf_path()
    model = load_urdf_model(urdf_path, package_dirs)
    joints = {j.name: j for j in model.robot.joints}
    children: dict[str, list] = {}
    for j in model.robot.joints:
        children.setdefault(j.parent, []).append(j)
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
    child_links = {j.child for j in model.robot.joints}
    roots = [l.name for l in model.robot.links if l.name not in child_links]
    if len(roots) != 1:
        raise LarcInputError(f"{urdf_path}: expected one root link, found {roots}")

    # Topological (breadth-first) link order.
    link_names, parent, joint_of = [roots[0]], [-1], [None]
    k = 0
    while k < len(link_names):
        for j in children.get(link_names[k], []):
            link_names.append(j.child)
            parent.append(k)
            joint_of.append(j)
        k += 1
    if len(link_names) != len(model.robot.links):
        raise LarcInputError(f"{urdf_path}: links and joints do not form one tree")

    movable = lambda j: j is not None and _TYPE_OF[j.type] != JointType.FIXED  # noqa: E731

    def has_movable(j) -> bool:
        """Whether joint ``j`` or any joint below it is movable."""
        return movable(j) or any(has_movable(c) for c in children.get(j.child, []))

    if active_joints is None:
        active, link = [], roots[0]
        while True:
            branches = [j for j in children.get(link, []) if has_movable(j)]
            if len(branches) != 1:
                break
            j = branches[0]
            if movable(j):
                active.append(j.name)
            link = j.child
    else:
        active = list(active_joints)
        if len(set(active)) != len(active):
            raise LarcInputError(f"{urdf_path}: active joints have duplicates: {active}")
        for name in active:
            if name not in joints:
                raise LarcInputError(f"{urdf_path}: no joint named '{name}'")
            if not movable(joints[name]):
                raise LarcInputError(f"{urdf_path}: joint '{name}' is fixed and cannot be active")
        # Serial chain: each active joint must be an ancestor of the next one.
        for a, b in zip(active, active[1:]):
            i = link_names.index(joints[b].child)
            chain = set()
            while i >= 0:
                if joint_of[i] is not None:
                    chain.add(joint_of[i].name)
                i = parent[i]
            if a not in chain:
                raise LarcInputError(
                    f"{urdf_path}: active joints are not a serial chain: '{a}' is not an "
                    f"ancestor of '{b}'"
                )
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
    for j in model.robot.joints:
        if j.mimic is not None and j.mimic.joint in active:
            raise LarcInputError(
                f"{urdf_path}: mimic joint '{j.name}' follows the active joint '{j.mimic.joint}' "
                f"(unsupported: the motion constants assume independent joints)"
            )

    def limits(j) -> tuple[float, float]:
        if j.type == "continuous":
            return -CONTINUOUS_LIMIT_RAD, CONTINUOUS_LIMIT_RAD
        if j.type == "fixed":
            return 0.0, 0.0
        return float(j.limit.lower), float(j.limit.upper)

    # Held values: explicit or 0 clipped into the limits for leaders, then the mimic joints.
    held = dict(held_joint_values or {})
    unknown = sorted(n for n in held if n not in joints or n in active or not movable(joints[n]))
    if unknown:
        raise LarcInputError(
            f"{urdf_path}: held_joint_values names unknown, fixed or active joints {unknown}"
        )
    held_value: dict[str, float] = {}
    for j in model.robot.joints:
        if not movable(j) or j.name in active or j.mimic is not None:
            continue
        lo, hi = limits(j)
        if j.name in held:
            v = float(held[j.name])
            if not lo <= v <= hi:
                raise LarcInputError(
                    f"{urdf_path}: held value {v} of joint '{j.name}' is outside [{lo}, {hi}]"
                )
        else:
            v = float(np.clip(0.0, lo, hi))
        held_value[j.name] = v
    for j in model.robot.joints:
        if j.mimic is None:
            continue
        v = float(j.mimic.multiplier if j.mimic.multiplier is not None else 1.0) * held_value[
            j.mimic.joint] + float(j.mimic.offset if j.mimic.offset is not None else 0.0)
        if j.name in held and abs(float(held[j.name]) - v) > 1e-9:
            raise LarcInputError(
                f"{urdf_path}: held value {held[j.name]} of mimic joint '{j.name}' differs from "
                f"{v} implied by '{j.mimic.joint}'; hold '{j.mimic.joint}' instead"
            )
        lo, hi = limits(j)
        tol = 1e-9 * max(1.0, abs(lo), abs(hi))
        if not lo - tol <= v <= hi + tol:
            raise LarcInputError(
                f"{urdf_path}: mimic joint '{j.name}' would be held at {v} (from "
                f"'{j.mimic.joint}' = {held_value[j.mimic.joint]}), outside its limits [{lo}, {hi}]"
            )
        held_value[j.name] = v

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
            lower[active.index(j.name)], upper[active.index(j.name)] = limits(j)
        else:
            q_index.append(-1)
            if t != JointType.FIXED:
                q_held[i] = held_value[j.name]

    dirs = _package_dirs_for(urdf_path, package_dirs)
    return Robot(
        T_parent_joint=T,
        axis=axis,
        q_held=q_held,
        q_lower=lower,
        q_upper=upper,
        name=model.robot.name,
        link_names=tuple(link_names),
        parent=tuple(parent),
        joint_names=tuple(jname),
        joint_type=tuple(jtype),
        q_index=tuple(q_index),
        active_joint_names=tuple(active),
        urdf_path=str(urdf_path.resolve()),
        urdf_sha256=file_sha256(urdf_path),
        package_dirs=tuple(sorted(dirs.items())),
    )
