"""FCL mesh collision model, scenes and the allowed self-collision pairs (experiments/)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

pytest.importorskip("fcl")

ROOT = Path(__file__).resolve().parent.parent
SCENES = ("open", "easy_window", "medium_window", "easy_shelf")
ALLOWED = ROOT / "larc_jax" / "data" / "piper_allowed_collisions.yaml"


@pytest.fixture(scope="module")
def model(robot):
    from experiments.collision import CollisionModel

    return CollisionModel(robot)


def _world_vertices(model, q):
    """link name -> (V, 3) world vertices of its collision meshes (no FCL involved)."""
    from larc_jax.model.robot import forward_kinematics_np

    T = forward_kinematics_np(model.robot, np.asarray(q, float))
    out = {}
    for link, meshes in model.meshes.items():
        V = np.concatenate([m.vertices for m in meshes])
        Tl = T[model.robot.link_index(link)]
        out[link] = V @ Tl[:3, :3].T + Tl[:3, 3]
    return out


def _world_triangles(model, q):
    """(F, 3, 3) world triangles of every link's collision mesh (no FCL involved)."""
    from larc_jax.model.robot import forward_kinematics_np

    T = forward_kinematics_np(model.robot, np.asarray(q, float))
    tris = []
    for link, meshes in model.meshes.items():
        Tl = T[model.robot.link_index(link)]
        for m in meshes:
            tris.append(np.asarray(m.triangles) @ Tl[:3, :3].T + Tl[:3, 3])
    return np.concatenate(tris)


def test_box_around_link_collides_far_box_does_not(model):
    q = np.array([0.3, 1.2, -1.0, 0.2, 0.4, 0.1])
    V = _world_vertices(model, q)["link6"]
    lo, hi = V.min(0) - 0.005, V.max(0) + 0.005
    assert model.scene_collision(q, (lo[None], hi[None]))
    assert ("link6", "box0") in model.scene_contacts(q, (lo[None], hi[None]))
    # A far box is clear.
    far = (np.array([[1.5, 1.5, 1.5]]), np.array([[1.7, 1.7, 1.7]]))
    assert not model.scene_collision(q, far)
    assert model.min_distance(q, far) > 1.0
    # Empty scene never collides.
    assert not model.scene_collision(q, (np.zeros((0, 3)), np.zeros((0, 3))))


def _triangles_hit_box(tri: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> bool:
    """Exact triangle/solid-box overlap by the separating-axis theorem (13 axes), NumPy only."""
    tlo, thi = tri.min(axis=1), tri.max(axis=1)
    cand = tri[np.all((thi >= lo) & (tlo <= hi), axis=1)]  # box-normal axes (AABB overlap)
    if len(cand) == 0:
        return False
    c, h = (lo + hi) / 2, (hi - lo) / 2
    v = cand - c  # (F, 3, 3)
    e = np.roll(v, -1, axis=1) - v  # edges (F, 3, 3)
    axes = [np.cross(e[:, 0], e[:, 1])]  # triangle normal
    for i in range(3):
        unit = np.zeros(3)
        unit[i] = 1.0
        for j in range(3):
            axes.append(np.cross(unit, e[:, j]))
    sep = np.zeros(len(cand), dtype=bool)
    for a in axes:  # (F, 3)
        p = np.einsum("fvk,fk->fv", v, a)
        r = np.abs(a) @ h
        sep |= (p.min(axis=1) > r) | (p.max(axis=1) < -r)
    return bool((~sep).any())


@pytest.mark.slow
def test_fcl_agrees_with_independent_check(model, robot):
    """FCL mesh-vs-box agrees with an exact NumPy triangle/box separating-axis test on random
    boxes near random poses; and a mesh vertex inside a box always means a hit."""
    rng = np.random.default_rng(7)
    lo_q, hi_q = np.asarray(robot.q_lower), np.asarray(robot.q_upper)
    n_hit = n_clear = n_vertex = 0
    for _ in range(10):
        q = rng.uniform(lo_q, hi_q)
        tri = _world_triangles(model, q)
        V = tri.reshape(-1, 3)
        for _ in range(20):
            d = rng.normal(size=3)
            centre = V[rng.integers(len(V))] + d / np.linalg.norm(d) * rng.uniform(0.0, 0.08)
            half = rng.uniform(0.003, 0.04, 3)
            lo, hi = centre - half, centre + half
            hit = model.scene_collision(q, (lo[None], hi[None]))
            want = _triangles_hit_box(tri, lo, hi)
            assert hit == want, f"FCL {hit} vs SAT {want} at q={q}, box {lo}..{hi}"
            if np.all((V > lo) & (V < hi), axis=1).any():
                n_vertex += 1
                assert hit
            n_hit += hit
            n_clear += not hit
    assert n_hit >= 20 and n_clear >= 20 and n_vertex >= 10  # every branch exercised


def test_states_in_collision_matches_single_queries(model, robot):
    rng = np.random.default_rng(3)
    Q = rng.uniform(np.asarray(robot.q_lower), np.asarray(robot.q_upper), size=(20, 6))
    boxes = (np.array([[0.15, -0.4, 0.0]]), np.array([[0.3, 0.4, 0.4]]))
    got = model.states_in_collision(Q, boxes)
    want = np.array([model.scene_collision(q, boxes) for q in Q])
    assert (got == want).all() and got.any() and not got.all()


def test_self_collision_and_allowed_pairs(model, robot):
    from experiments.self_collision import adjacent_pairs, load_allowed_pairs

    allowed = load_allowed_pairs(ALLOWED, robot)
    q0 = np.zeros(6)
    assert not model.self_collision(q0, allowed)
    # With nothing allowed, touching neighbours (and the closed fingers) collide.
    assert model.self_collision(q0, ())
    assert ("link7", "link8") in {tuple(sorted(p)) for p in model.self_contacts(q0, ())}
    # The gripper folded onto the base: a genuine self-collision the allowed pairs do not hide.
    rng = np.random.default_rng(0)
    found = False
    for _ in range(2000):
        q = rng.uniform(np.asarray(robot.q_lower), np.asarray(robot.q_upper))
        if model.self_collision(q, allowed):
            found = True
            pairs = model.self_contacts(q, allowed)
            assert all(tuple(sorted(p)) not in allowed for p in pairs)
            break
    assert found
    adj = adjacent_pairs(robot, model.links_with_geometry)
    assert ("link6", "link7") in adj and ("link6", "link8") in adj and ("base_link", "link1") in adj
    assert ("link7", "link8") not in adj


def test_allowed_file_has_adjacent_pairs_and_matches_urdf(robot, model, tmp_path):
    from experiments.self_collision import adjacent_pairs, load_allowed_file, load_allowed_pairs

    path = ALLOWED
    doc = load_allowed_file(path, robot)
    assert doc["urdf_sha256"] == robot.urdf_sha256
    assert doc["n_samples"] >= 10_000 and isinstance(doc["seed"], int)
    allowed = load_allowed_pairs(path, robot)
    adj = adjacent_pairs(robot, model.links_with_geometry)
    assert len(adj) == 8
    assert adj <= allowed
    reasons = {(tuple(sorted((p["a"], p["b"])))): p["reason"] for p in doc["pairs"]}
    assert set(reasons.values()) <= {"adjacent", "never", "always", "default"}
    assert all(reasons[p] == "adjacent" for p in adj)
    # "never" pairs were never seen in contact; checked pairs were.
    for key, n in doc["contact_counts"].items():
        a, b = key.split(":")
        if reasons.get((a, b)) == "never":
            assert n == 0
    # A file made for another URDF is refused.
    bad = dict(doc, urdf_sha256="0" * 64)
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(bad))
    with pytest.raises(ValueError, match="sha256"):
        load_allowed_pairs(p, robot)


@pytest.mark.parametrize("scene", SCENES)
def test_scene_files(scene, model, robot):
    from experiments.collision import SceneBoxes

    boxes = SceneBoxes.from_file(ROOT / "configs" / "scenes" / f"{scene}.yaml")
    names, lo, hi = boxes.names, boxes.lo, boxes.hi
    assert lo.shape == hi.shape == (len(names), 3)
    assert (hi >= lo).all()
    if scene == "open":
        assert len(names) == 0 or (hi[:, 2] <= -0.01).all()
    else:
        assert len(names) >= 4
    # The base and link1 (which only turns about the base axis) are never in contact.
    rng = np.random.default_rng(1)
    for _ in range(30):
        q = rng.uniform(np.asarray(robot.q_lower), np.asarray(robot.q_upper))
        for link, _box in model.scene_contacts(q, (names, lo, hi)):
            assert link not in ("base_link", "link1")


def test_audit_scene_reader_is_the_librarys(tmp_path):
    """The audit reads scenes with the library's reader: same errors, same boxes (also .scene)."""
    from experiments.collision import SceneBoxes
    from larc_jax.errors import LarcInputError
    from larc_jax.model.scene import read_scene

    p = tmp_path / "s.yaml"
    p.write_text("frame: base_link\nboxes:\n  - {name: a, min: [0, 0, 1], max: [1, 1, 0]}\n")
    with pytest.raises(LarcInputError, match=r"boxes\[0\]"):
        SceneBoxes.from_file(p)
    p.write_text("frame: world\nboxes: []\n")
    with pytest.raises(LarcInputError, match="frame"):
        SceneBoxes.from_file(p)
    pick = ROOT / "configs" / "examples" / "pick.scene"
    boxes, scene = SceneBoxes.from_file(pick), read_scene(pick)
    np.testing.assert_array_equal(boxes.lo, scene.lo)
    np.testing.assert_array_equal(boxes.hi, scene.hi)
    assert boxes.names == scene.obstacle_names and len(boxes) == scene.n_obstacles == 2  # the posed post too
