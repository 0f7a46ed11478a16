"""Capsules: the committed file, proven containment, motion constants, bad input."""

from __future__ import annotations

import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import yaml

from larc_jax import LarcInputError
from larc_jax.enclosure.fit import point_segment_distance
from larc_jax.enclosure import capsule_segments, capsule_segments_np, default_capsule_path, link_elements, load_capsules, verify_containment
from larc_jax.model.urdf import file_sha256


def test_committed_file_matches_urdf(robot):
    doc = yaml.safe_load(default_capsule_path().read_text())
    assert doc["urdf_sha256"] == file_sha256(robot.urdf_path) == robot.urdf_sha256
    assert doc["padding_m"] == 0.001
    assert doc["revision"] and "gripper_opening_m" in doc
    assert len(doc["capsules"]) == 11
    links = [c["link"] for c in doc["capsules"]]
    assert set(links) == {"base_link"} | {f"link{i}" for i in range(1, 9)}


def test_containment_reproven_from_meshes(robot, capsules):
    """Every vertex of every mesh triangle lies within radius - padding of one capsule of its
    link, with the whole triangle in that one capsule (re-derived here, independently of
    verify_containment)."""
    checked = verify_containment(robot, capsules)
    assert sum(checked.values()) > 100_000
    for link in set(capsules.link_names):
        elems = link_elements(robot, link)
        ok = np.zeros(len(elems), bool)
        for c, l in enumerate(capsules.link_names):
            if l == link:
                core = capsules.radius[c] - capsules.padding_m
                d = point_segment_distance(elems, np.asarray(capsules.p_link_a[c]), np.asarray(capsules.p_link_b[c]))
                ok |= (d <= core).all(axis=1)
        assert ok.all(), link


def test_finger_capsule_holds_whole_stroke(robot, capsules):
    """The finger elements include copies at both stroke ends, and those are contained."""
    import trimesh

    plain = trimesh.load(str(robot.urdf_path).replace("urdf/piper_description.urdf", "meshes/link7.STL"))
    elems = link_elements(robot, "link7")
    assert elems.shape == (len(plain.faces), 9, 3)
    c = capsules.names.index("link7")
    stroke_end = plain.vertices + np.array([0.0, 0.0, -1.0]) * -0.038  # axis (0,0,-1), q = -0.038
    d = point_segment_distance(stroke_end, np.asarray(capsules.p_link_a[c]), np.asarray(capsules.p_link_b[c]))
    assert d.max() <= capsules.radius[c]


def test_tampered_capsule_is_rejected(robot, tmp_path):
    doc = yaml.safe_load(default_capsule_path().read_text())
    doc["capsules"][3]["radius"] = round(doc["capsules"][3]["radius"] - 0.005, 6)
    path = tmp_path / "caps.yaml"
    path.write_text(yaml.safe_dump(doc))
    caps = load_capsules(path, robot)
    with pytest.raises(LarcInputError, match=r"caps.yaml: link 'link2' element \d+ .*not inside"):
        verify_containment(robot, caps, source=str(path))


def test_hash_mismatch_says_how_to_refit(robot, tmp_path):
    doc = yaml.safe_load(default_capsule_path().read_text())
    doc["urdf_sha256"] = "0" * 64
    path = tmp_path / "other.yaml"
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(LarcInputError, match="larc fit-capsules"):
        load_capsules(path, robot)


@pytest.mark.parametrize("field,value,msg", [
    ("link", "link99", "capsules\\[0\\].link 'link99'"),
    ("radius", -1.0, "capsules\\[0\\].radius"),
    ("a", [0, 1], "capsules\\[0\\].a"),
    ("b", [0, float("nan"), 0], "capsules\\[0\\].b"),
])
def test_malformed_capsule_fields(robot, tmp_path, field, value, msg):
    doc = yaml.safe_load(default_capsule_path().read_text())
    doc["capsules"][0][field] = value
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(LarcInputError, match=msg):
        load_capsules(path, robot)


def test_capsule_segments_kernel_matches_reference(robot, capsules):
    rng = np.random.default_rng(3)
    Q = rng.uniform(robot.q_lower, robot.q_upper, size=(50, 6))
    with jax.enable_x64(True):
        f = jax.jit(jax.vmap(capsule_segments, in_axes=(None, None, 0)))
        A, B = map(np.asarray, f(robot, capsules, Q))
    for k in range(len(Q)):
        a, b = capsule_segments_np(robot, capsules, Q[k])
        np.testing.assert_allclose(A[k], a, atol=1e-12)
        np.testing.assert_allclose(B[k], b, atol=1e-12)


def test_motion_constants_bound_surface_speeds(robot, capsules):
    """For 10^4 random configurations and joint velocities, the speed of points on every capsule
    surface (from the FK Jacobian) never exceeds sum_j a_lj |qd_j|."""
    rng = np.random.default_rng(7)
    N, M = 10_000, 8
    Q = rng.uniform(robot.q_lower, robot.q_upper, size=(N, 6))
    # Mix of generic and extreme (at-limit) configurations.
    Q[: N // 4] = np.where(rng.random((N // 4, 6)) < 0.5, robot.q_lower, robot.q_upper)
    QD = rng.normal(size=(N, 6)) * rng.choice([0.1, 1.0, 5.0], size=(N, 1))
    s = rng.random((N, M))  # position along the segment
    u = rng.normal(size=(N, M, 3))
    u /= np.linalg.norm(u, axis=-1, keepdims=True)  # direction to the surface

    def surface_points(q, s, u):
        a, b = capsule_segments(robot, capsules, q)
        core = a[:, None] + s[None, :, None] * (b - a)[:, None]  # (C, M, 3)
        return core + capsules.radius[:, None, None] * u[None]

    def speeds(q, qd, s, u):
        _, pdot = jax.jvp(lambda qq: surface_points(qq, s, u), (q,), (qd,))
        return jnp.linalg.norm(pdot, axis=-1)  # (C, M)

    with jax.enable_x64(True):
        v = np.asarray(jax.jit(jax.vmap(speeds))(Q, QD, s, u))
    bound = np.abs(QD) @ np.asarray(capsules.motion_a).T  # (N, C)
    ratio = v.max(axis=2) / np.maximum(bound, 1e-300)
    assert (v.max(axis=2) <= bound * (1 + 1e-12) + 1e-15).all(), ratio.max()
    # Not vacuous: the bound is reasonably tight somewhere.
    assert ratio.max() > 0.5


def test_a_is_zero_for_non_ancestor_joints(capsules):
    a = np.asarray(capsules.motion_a)
    base = capsules.names.index("base_link")
    assert (a[base] == 0).all()
    link1 = capsules.names.index("link1")
    assert a[link1, 0] > 0 and (a[link1, 1:] == 0).all()
