"""Link poses as 3×4 affine blocks: the forward-kinematics kernel the leaf test places links with.

:func:`link_poses` returns, for one configuration, the top three rows ``[R | p]`` of every link's
pose ``T_world_link`` (the bottom row of a rigid pose is always ``[0, 0, 0, 1]``). It chains the
joints as :func:`larc_jax.model.robot.forward_kinematics` does (the same Rodrigues rotation, the
same parent-then-origin-then-motion order), but on 3×3 rotations and 3-vectors instead of 4×4
products: per joint one 3×3-by-3×4 product (the parent's rotation times the joint origin's
rotation and offset together) and, for a revolute joint, one 3×3 product, no arithmetic on the
constant row. On fine's 4,096-interval capsule call of Stage B (this 2-core CPU, measured while
developing; ``experiments/bench.py`` has the stage's time), the midpoint configuration, forward
kinematics and capsule segments took 3.9-4.1 ms with the 4×4 form and 1.7-2.1 ms with this one,
the whole call 8.3-8.5 ms before and 5.0 ms after. Tried and not kept: the origin as two products
(rotation and offset apart; 2.0 ms, but one more dot operation per joint, and every compiled
program held 15-20 % more memory mappings, so a process that compiles many shapes reaches
``vm.max_map_count`` sooner); elementwise multiply-and-sum instead of products (3.2-3.3 ms);
entry by entry on scalars (6.8 ms).

Rounding (budget G1 of :mod:`larc_jax.leaf.interval`). The entries computed are the same sums of
the same products as the 4×4 form's: a 4×4 product with rows ``[0, 0, 0, 1]`` adds terms that
are exact zeros or products by one, so a rotation entry is an inner product of 3 rounded terms
and a translation entry ``(R_parent p_origin)_i + p_parent,i`` one of 3 products and a fourth
exact term, in either form. Inner products of n terms are within ``gamma_n = n u / (1 - n u)``
of their exact value relative to the sum of the terms' magnitudes, *whatever the order of the
additions* (and a fused multiply-add only removes roundings), so G1's bound per product
(``gamma_4 |A| |B|`` entrywise, the constant column counted), and with it ``K_FK``, covers this
form as it covers the 4×4 one. The two forms' results differ in the last bits (XLA orders the
sums of a 3×3 product differently from a 4×4 one's): ``tests/test_kinematics.py`` compares this
kernel with the NumPy reference (1e-12) and the 4×4 form (1e-14, relative to the configuration's
largest coordinate); ``tests/test_rounding.py`` checks the placement against G1 itself.

:func:`larc_jax.model.robot.forward_kinematics` (4×4, the public function) stays as it is: its
module is part of the OMPL dataset generator's code fingerprint (``experiments.generate``), which
any change to it would invalidate. Its NumPy float64 reference,
:func:`~larc_jax.model.robot.forward_kinematics_np`, is this kernel's reference too.
"""

from __future__ import annotations

from ..lazy_jax import jax, jnp
from .robot import JointType, Robot

__all__ = ["link_poses"]


def _mm(a, b):
    """Full-precision product (float32 products on GPUs default to TF32, outside G1's bound)."""
    return jnp.matmul(a, b, precision=jax.lax.Precision.HIGHEST)


def _rotation(axis, value):
    """Rotation about the unit ``axis`` by ``value`` (Rodrigues' formula, as the 4×4 form's)."""
    dtype = axis.dtype
    x, y, z = axis[0], axis[1], axis[2]
    zero = jnp.zeros((), dtype)
    K = jnp.array([[zero, -z, y], [z, zero, -x], [-y, x, zero]])
    return jnp.eye(3, dtype=dtype) + jnp.sin(value) * K + (1.0 - jnp.cos(value)) * _mm(K, K)


def link_poses(robot: Robot, q: jax.Array) -> jax.Array:
    """Poses of every link for one configuration, without their constant bottom row.

    Args:
      robot: the model.
      q: (n,) active joint values (rad / m).

    Returns:
      T_world_link: (L, 3, 4) ``[R_world_link | p_world_link]`` in the base frame, metres, in
      ``q``'s dtype (float64 under ``jax.enable_x64``).

    Pure and jit-able; the loop over links is unrolled at trace time (static structure). Batch
    with ``jax.vmap(link_poses, in_axes=(None, 0))``.
    """
    q = jnp.asarray(q)
    dtype = q.dtype if jnp.issubdtype(q.dtype, jnp.floating) else jnp.result_type(float)
    R_world = [jnp.eye(3, dtype=dtype)]
    p_world = [jnp.zeros(3, dtype)]
    for i in range(1, robot.n_links):
        parent = robot.parent[i]
        T_origin = robot.T_parent_joint[i].astype(dtype)
        # The joint frame: the parent's pose times the joint's fixed origin, one 3x3-by-3x4
        # product (rotation and offset together: one dot operation, not two).
        T_joint = _mm(R_world[parent], T_origin[:3, :])
        R_joint, p_joint = T_joint[:, :3], T_joint[:, 3] + p_world[parent]
        jtype = robot.joint_type[i]
        k = robot.q_index[i]
        value = (q[k] if k >= 0 else robot.q_held[i]).astype(dtype)
        axis = robot.axis[i].astype(dtype)
        if jtype == JointType.REVOLUTE:
            R_world.append(_mm(R_joint, _rotation(axis, value)))
            p_world.append(p_joint)
        elif jtype == JointType.PRISMATIC:
            R_world.append(R_joint)
            p_world.append(p_joint + _mm(R_joint, axis * value))
        else:
            R_world.append(R_joint)
            p_world.append(p_joint)
    return jnp.concatenate([jnp.stack(R_world), jnp.stack(p_world)[:, :, None]], axis=2)
