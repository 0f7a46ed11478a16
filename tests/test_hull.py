"""Hull parts: containment proof, splits, motion constants against sampled point speeds."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from larc_jax import LarcInputError
from larc_jax.enclosure import link_elements
from larc_jax.enclosure.hull import build_parts, choose_split, hull_model, split_mask, support_set, verify_support
from larc_jax.model.robot import forward_kinematics


@pytest.fixture(scope="module")
def hulls(robot, capsules):
    return hull_model(robot, capsules.hull_parts, capsules.padding_m)


def test_every_element_is_in_its_part_and_the_parts_are_small(robot, capsules, hulls):
    """Each link's elements go whole into one part; every element vertex lies in its part's hull
    (support functions over 4096 directions, independently of the facet proof), and the hull
    keeps only a few hundred of the tens of thousands of mesh vertices."""
    planes = {p[0]: p[1:] for p in capsules.hull_parts}
    assert set(planes) == {"link2", "link3"}
    for link in dict.fromkeys(hulls.link_names):
        e = link_elements(robot, link)
        parts = [k for k, l in enumerate(hulls.link_names) if l == link]
        groups = [e] if len(parts) == 1 else [e[split_mask(e, *planes[link])], e[~split_mask(e, *planes[link])]]
        assert sum(len(g) for g in groups) == len(e)
        for k, g in zip(parts, groups):
            V = np.asarray(hulls.vertices[k])[: hulls.n_vertices[k]]
            slack = float(hulls.radius[k]) - hulls.padding_m
            assert 0 <= slack < 1e-8
            assert verify_support(g, V, slack) <= 1e-15, hulls.names[k]
            assert hulls.n_vertices[k] < 800 and len(np.unique(g.reshape(-1, 3), axis=0)) > 3 * hulls.n_vertices[k]


def test_support_set_handles_degenerate_sets():
    flat = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0.5, 0.5, 0]], float)
    V, slack = support_set(flat)  # no volume: every point kept
    assert len(V) == 5 and slack == 0.0
    rng = np.random.default_rng(0)
    cube = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
    pts = np.concatenate([cube, rng.uniform(0, 1, (200, 3)), np.c_[rng.uniform(0, 1, (50, 2)), np.zeros(50)]])
    V, slack = support_set(pts)  # interior and on-face points dropped, with their witnesses
    assert len(V) == 8 and slack < 1e-12
    assert verify_support(pts, V, slack) <= 1e-15


def test_split_planes_are_chosen_for_gain_only(robot):
    assert choose_split(link_elements(robot, "link2")) is not None  # an L-shaped link: two parts
    assert choose_split(link_elements(robot, "link4")) is None  # a compact one: one part


def test_stated_fingers_have_smaller_hulls(robot, capsules):
    import dataclasses

    stroke = {p.name: p for p in build_parts(robot, links=["link7"])}
    stated = {p.name: p for p in build_parts(dataclasses.replace(robot, stated_joints=("joint7", "joint8")),
                                             links=["link7"])}
    from scipy.spatial import ConvexHull

    v_stroke = ConvexHull(stroke["link7"].vertices).volume
    v_stated = ConvexHull(stated["link7"].vertices).volume
    assert v_stated < 0.35 * v_stroke  # the 38 mm stroke more than triples the finger's hull


def test_hull_model_is_cached_and_follows_the_robot(robot, capsules, hulls):
    import dataclasses

    assert hull_model(robot, capsules.hull_parts, capsules.padding_m) is hulls
    other = hull_model(dataclasses.replace(robot, stated_joints=("joint7",)), capsules.hull_parts, capsules.padding_m)
    assert other is not hulls and other.n_vertices[hulls.names.index("link7")] < hulls.n_vertices[
        hulls.names.index("link7")]


def test_unknown_link_in_planes_is_refused(robot):
    with pytest.raises(LarcInputError, match="elbow"):
        build_parts(robot, hull_parts=(("elbow", (1.0, 0.0, 0.0), 0.0),))


def test_part_motion_constants_bound_sampled_point_speeds(robot, hulls):
    """For 2000 random configurations (a quarter at joint limits) and joint velocities, the speed
    of every hull vertex, and of points at the padding distance from it, never exceeds
    sum_j a_pj |qd_j| (FK Jacobian by forward-mode differentiation)."""
    rng = np.random.default_rng(8)
    N = 2000
    Q = rng.uniform(robot.q_lower, robot.q_upper, size=(N, robot.n_joints))
    Q[: N // 4] = np.where(rng.random((N // 4, robot.n_joints)) < 0.5, robot.q_lower, robot.q_upper)
    QD = rng.normal(size=(N, robot.n_joints)) * rng.choice([0.1, 1.0, 5.0], size=(N, 1))
    link_index = np.asarray(hulls.link_index)
    V = jnp.asarray(hulls.vertices)  # (P, K, 3)
    u = rng.normal(size=(N, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)

    def points(q, u):
        T = forward_kinematics(robot, q)[link_index]
        return jnp.einsum("pij,pkj->pki", T[:, :3, :3], V + hulls.radius[:, None, None] * u) + T[:, None, :3, 3]

    def speeds(q, qd, u):
        _, pdot = jax.jvp(lambda qq: points(qq, u), (q,), (qd,))
        return jnp.linalg.norm(pdot, axis=-1).max(axis=-1)  # (P,)

    with jax.enable_x64(True):
        f = jax.jit(jax.vmap(speeds))
        v = np.concatenate([np.asarray(f(Q[k:k + 250], QD[k:k + 250], u[k:k + 250])) for k in range(0, N, 250)])
    bound = np.abs(QD) @ np.asarray(hulls.motion_a).T  # (N, P)
    assert (v <= bound * (1 + 1e-12) + 1e-15).all(), (v / np.maximum(bound, 1e-300)).max()
    assert (v / np.maximum(bound, 1e-300)).max() > 0.5  # and not vacuous
