"""The leaf test's forward kinematics (``larc_jax.model.kinematics.link_poses``, 3×4 affine blocks)
against the NumPy float64 reference, the 4×4 JAX form and yourdfpy, on random configurations and
on every joint kind (active and held revolute and prismatic, fixed), in float64 and float32. Its
rounding against budget G1 is ``tests/test_rounding.py::test_placement_error_is_within_budget``
(the capsule segments are placed with it)."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest
import yourdfpy

from larc_jax.model.kinematics import link_poses
from larc_jax.model.robot import JointType, forward_kinematics, forward_kinematics_np

_poses = jax.jit(jax.vmap(link_poses, in_axes=(None, 0)))
_poses_4x4 = jax.jit(jax.vmap(forward_kinematics, in_axes=(None, 0)))


def _variants(robot):
    """PIPER as loaded, and changed so that every joint kind occurs: the fingers held open (held
    prismatic, non-zero), joint6 held at 1.1 rad (held revolute), finger joint7 active (active
    prismatic), joint4 made fixed."""
    i6, i7, i8, i4 = (robot.link_index(f"link{k}") for k in (6, 7, 8, 4))
    held = np.asarray(robot.q_held, np.float64).copy()
    held[i7], held[i8] = 0.021, -0.017
    opened = dataclasses.replace(robot, q_held=held)
    held6 = held.copy()
    held6[i6] = 1.1
    q_index = list(robot.q_index)
    q_index[i6] = -1
    wrist_held = dataclasses.replace(robot, q_held=held6, q_index=tuple(q_index))
    q_index = list(robot.q_index)
    q_index[i7] = robot.n_joints
    finger_active = dataclasses.replace(robot, q_index=tuple(q_index))
    types, q_index, axis = list(robot.joint_type), list(robot.q_index), np.asarray(robot.axis).copy()
    types[i4], axis[i4] = JointType.FIXED, 0.0
    q_index = [k - (k > robot.q_index[i4]) if k >= 0 else k for k in q_index]
    q_index[i4] = -1
    fixed4 = dataclasses.replace(robot, joint_type=tuple(types), q_index=tuple(q_index), axis=axis)
    return {"as loaded": (robot, robot.n_joints), "fingers held open": (opened, robot.n_joints),
            "joint6 held": (wrist_held, robot.n_joints), "joint7 active": (finger_active, robot.n_joints + 1),
            "joint4 fixed": (fixed4, robot.n_joints - 1)}


@pytest.mark.parametrize("variant", ["as loaded", "fingers held open", "joint6 held", "joint7 active", "joint4 fixed"])
def test_link_poses_match_the_reference_for_every_joint_kind(robot, variant):
    model, n = _variants(robot)[variant]
    rng = np.random.default_rng(3)
    # Angles up to 1000 rad: sin/cos of large arguments, and q = 0 exactly.
    Q = rng.uniform(-1, 1, (64, n)) * 10.0 ** rng.uniform(0, 3, (64, 1))
    Q[0] = 0.0
    with jax.enable_x64(True):
        T = np.asarray(_poses(model, Q))
        T4 = np.asarray(_poses_4x4(model, Q))
    assert T.shape == (len(Q), model.n_links, 3, 4) and T.dtype == np.float64
    T_ref = np.stack([forward_kinematics_np(model, q)[:, :3, :] for q in Q])
    # Relative to each configuration's largest coordinate (an active prismatic joint travels to 1 km).
    scale = 1.0 + np.abs(T_ref).max(axis=(1, 2, 3))[:, None, None, None]
    assert (np.abs(T - T_ref) < 1e-12 * scale).all()
    # Against the 4x4 form: the same sums in another order, a few units of the last place.
    assert (np.abs(T - T4[:, :, :3, :]) < 1e-14 * scale).all()
    np.testing.assert_array_equal(T[0, 0], np.eye(4)[:3])  # the root is the identity


def test_link_poses_match_yourdfpy(robot):
    """Configurations within the limits, every link: 200 against yourdfpy to 1e-9 m (as the 4×4 form's
    test), all 1,000 against the NumPy reference to 1e-12 m."""
    model = yourdfpy.URDF.load(robot.urdf_path, load_meshes=False, build_collision_scene_graph=False,
                               load_collision_meshes=False)
    Q = np.random.default_rng(1).uniform(robot.q_lower, robot.q_upper, size=(1000, robot.n_joints))
    with jax.enable_x64(True):
        T = np.asarray(_poses(robot, Q))
    worst = 0.0
    for k, q in enumerate(Q[:200]):
        model.update_cfg(np.concatenate([q, [0.0, 0.0]]))
        for i, link in enumerate(robot.link_names):
            worst = max(worst, np.abs(model.get_transform(link)[:3] - T[k, i]).max())
    assert worst < 1e-9, worst
    T_ref = np.stack([forward_kinematics_np(robot, q)[:, :3, :] for q in Q])
    assert np.abs(T - T_ref).max() < 1e-12


def test_link_poses_float32_and_non_finite(robot):
    q = np.array([0.3, 1.0, -1.2, 0.4, -0.5, 2.0])
    T32 = np.asarray(jax.jit(link_poses)(robot, q.astype(np.float32)))  # x64 off: the float32 path
    assert T32.dtype == np.float32 and T32.shape == (robot.n_links, 3, 4)
    np.testing.assert_allclose(T32, forward_kinematics_np(robot, q)[:, :3, :], atol=1e-5)
    with jax.enable_x64(True):
        bad = np.asarray(link_poses(robot, np.where(np.arange(6) == 2, np.nan, q)))
    i3 = robot.link_index("link3")
    assert np.isnan(bad[i3]).any() and np.isfinite(bad[: i3]).all()  # NaN reaches the links it moves
