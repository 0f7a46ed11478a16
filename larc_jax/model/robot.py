"""Robot model: a frozen, jit-friendly kinematic tree, and forward kinematics.

The model is a :class:`Robot` pytree. Static structure (link order, parent indices, joint types,
which configuration entry drives which joint) lives in Python tuples (pytree metadata, hashable,
so it is baked into compiled code); numeric data (joint origins, axes, limits, the values at
which non-trajectory joints are held) are arrays. :mod:`larc_jax.model.urdf` builds it from a URDF.

A *configuration* ``q`` holds the values of the robot's **active joints**: the revolute/prismatic
joints that a trajectory carries (for PIPER: joint1..joint6 by default; the fingers joint7 and
joint8 too when a trajectory carries them). Every other movable joint is *held* at a value
recorded in the model. A held joint is **stated** (``stated_joints``) when the user says it
stays at that value (e.g. ``larc certify --hold joint7=0``): FK places its links there and their
enclosures are those of the links alone. A held prismatic joint that is *not* stated may be
anywhere in its stroke: the enclosures of the links below it cover the whole stroke
(:mod:`larc_jax.enclosure.meshes`), and FK places them at the recorded reference value.

Frames: the URDF root link is the world/base frame. ``T_world_link[i]`` maps link ``i``
coordinates to base coordinates (4×4 homogeneous, metres).
"""

from __future__ import annotations

import dataclasses
import enum

import numpy as np

from ..errors import LarcInputError
from ..lazy_jax import jax, jnp, pytree_dataclass

__all__ = [
    "JointType",
    "Robot",
    "forward_kinematics",
    "forward_kinematics_np",
    "CONTINUOUS_LIMIT_RAD",
    "chain_terms",
]

CONTINUOUS_LIMIT_RAD = 4.0 * np.pi
"""Limits (±) given to the values of continuous joints, rad (see the module docstring)."""


class JointType(enum.IntEnum):
    """Kinds of joint the model supports (continuous joints are revolute, limits ±CONTINUOUS_LIMIT_RAD)."""

    FIXED = 0
    REVOLUTE = 1
    PRISMATIC = 2


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class Robot:
    """A kinematic tree; its active joints are usually one serial chain from the root (an arm),
    possibly with branches (an arm and its finger joints).

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
    stated_joints: tuple[str, ...] = dataclasses.field(default=(), metadata=dict(static=True))
    """Held joints whose value the user stated (module docstring); the others' strokes are enclosed."""

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

    @property
    def stroke_joints(self) -> tuple[str, ...]:
        """Held prismatic joints without a stated value: enclosures cover their whole stroke."""
        return tuple(self.joint_names[i] for i in range(1, self.n_links)
                     if self.q_index[i] < 0 and self.joint_type[i] == JointType.PRISMATIC
                     and self.joint_names[i] not in self.stated_joints)

    def ancestors(self, link: int) -> list[int]:
        """Link indices from the root down to ``link`` (inclusive)."""
        chain = []
        while link >= 0:
            chain.append(link)
            link = self.parent[link]
        return chain[::-1]


def chain_terms(robot: Robot, link_index, end_norms):
    """Per enclosure (on link ``link_index[e]``, farthest point ``end_norms[e]`` from its link origin):
    the chain length (joints from the root), the fixed part of its reach (m) and the active
    prismatic joints (indices into ``q``) whose travel adds to it.

    A point of the enclosure is ``T_1 M_1(q_1) ... T_k M_k(q_k) x`` with ``|x| <= end_norms[e]``:
    rotations keep norms, so its distance from the root origin is at most ``|x|`` plus each joint
    origin's offset ``|t_i|``, each held prismatic joint's ``|q_i|`` and each active prismatic
    joint's ``|q_j|`` (the last left to the caller: the rounding guard's G1 of
    :mod:`larc_jax.leaf.interval` takes a trajectory's curve bound, a plane's reach check the limits)."""
    T_pj = np.asarray(robot.T_parent_joint, np.float64)
    held = np.asarray(robot.q_held, np.float64)
    offset = [float(np.linalg.norm(T[:3, 3])) for T in T_pj]  # each joint's once: the same bits as per chain
    lengths, fixed, prismatic = [], [], []
    for e, li in enumerate(link_index):
        chain = robot.ancestors(li)[1:]
        r = float(end_norms[e]) + sum(offset[i] for i in chain)
        active = []
        for i in chain:
            if robot.joint_type[i] == JointType.PRISMATIC:
                if robot.q_index[i] >= 0:
                    active.append(robot.q_index[i])
                else:
                    r += abs(float(held[i]))
        lengths.append(len(chain))
        fixed.append(r)
        prismatic.append(active)
    return np.array(lengths, np.float64), np.array(fixed), prismatic


# ----------------------------------------------------------------------------------------------
# Forward kinematics (JAX kernel for one configuration, NumPy float64 reference)
# ----------------------------------------------------------------------------------------------


def _matmul(a, b):
    """Full-precision product (float32 products on GPUs default to TF32, which the rounding
    guard of :mod:`larc_jax.leaf.interval` does not cover)."""
    return jnp.matmul(a, b, precision=jax.lax.Precision.HIGHEST)


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
    R = jnp.eye(3, dtype=dtype) + jnp.sin(value) * K + (1.0 - jnp.cos(value)) * _matmul(K, K)
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
        T_world.append(_matmul(_matmul(T_world[robot.parent[i]], robot.T_parent_joint[i].astype(dtype)), M))
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
