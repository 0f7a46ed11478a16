"""Robot model: URDF loading, forward kinematics against yourdfpy, and bad-input errors."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import jax
import numpy as np
import pytest
import yourdfpy

from larc_jax import LarcInputError
from larc_jax.model.robot import JointType, forward_kinematics, forward_kinematics_np
from larc_jax.model.urdf import load_robot


def test_piper_structure(robot):
    assert robot.active_joint_names == tuple(f"joint{i}" for i in range(1, 7))
    assert robot.link_names[0] == "base_link"
    assert set(robot.link_names) == {"base_link"} | {f"link{i}" for i in range(1, 9)}
    assert all(robot.parent[i] < i for i in range(1, robot.n_links))
    # The fingers branch off link6 and are held (not active).
    for finger in ("link7", "link8"):
        i = robot.link_names.index(finger)
        assert robot.q_index[i] == -1 and robot.joint_type[i] == JointType.PRISMATIC
        assert robot.link_names[robot.parent[i]] == "link6"
    np.testing.assert_allclose(robot.q_lower, [-2.618, 0, -2.967, -1.832, -1.22, -3.14])
    np.testing.assert_allclose(robot.q_upper, [2.618, 3.14, 0, 1.832, 1.22, 3.14])


def test_fk_matches_yourdfpy_1000_configs(robot):
    """JAX FK (float64) and the NumPy reference agree with yourdfpy to 1e-9 m for every link."""
    model = yourdfpy.URDF.load(robot.urdf_path, load_meshes=False, build_collision_scene_graph=False,
                               load_collision_meshes=False)
    rng = np.random.default_rng(1)
    Q = rng.uniform(robot.q_lower, robot.q_upper, size=(1000, robot.n_joints))
    with jax.enable_x64(True):
        T_jax = np.asarray(jax.jit(jax.vmap(forward_kinematics, in_axes=(None, 0)))(robot, Q))
    assert T_jax.dtype == np.float64
    worst = 0.0
    for k, q in enumerate(Q):
        model.update_cfg(np.concatenate([q, [0.0, 0.0]]))
        T_np = forward_kinematics_np(robot, q)
        for i, link in enumerate(robot.link_names):
            T_ref = model.get_transform(link)
            worst = max(worst, np.abs(T_ref - T_jax[k, i]).max(), np.abs(T_ref - T_np[i]).max())
    assert worst < 1e-9, worst


def test_fk_float32_is_close(robot):
    q = np.array([0.3, 1.0, -1.2, 0.4, -0.5, 2.0])
    T32 = np.asarray(forward_kinematics(robot, q.astype(np.float32)))  # x64 off: float32 path
    assert T32.dtype == np.float32
    np.testing.assert_allclose(T32, forward_kinematics_np(robot, q), atol=1e-5)


def _copy_description(piper_dir: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "piper_description"
    shutil.copytree(piper_dir, dst)
    return dst / "urdf" / "piper_description.urdf"


def test_missing_mesh_is_named(piper_dir, tmp_path):
    urdf = _copy_description(piper_dir, tmp_path)
    (urdf.parent.parent / "meshes" / "link3.STL").unlink()
    with pytest.raises(LarcInputError, match=r"link 'link3'.*link3\.STL.*does not exist"):
        load_robot(urdf)


def test_joint_without_limits_is_named(piper_dir, tmp_path):
    urdf = _copy_description(piper_dir, tmp_path)
    text = urdf.read_text()
    start = text.index('name="joint3"')
    lim = text.index("<limit", start)
    end = text.index("/>", lim) + 2
    urdf.write_text(text[:lim] + text[end:])
    with pytest.raises(LarcInputError, match=r"joint 'joint3'.*no <limit"):
        load_robot(urdf)


def test_active_fingers_branch_off_the_chain(robot):
    """Active joints may branch (an arm and both fingers): FK places the fingers by q."""
    from larc_jax.model.robot import forward_kinematics_np

    r = load_robot(robot.urdf_path, active_joints=["joint1", "joint7", "joint8"])
    assert r.n_joints == 3 and r.stroke_joints == ()
    T = forward_kinematics_np(r, np.array([0.3, -0.02, 0.01]))
    T0 = forward_kinematics_np(r, np.array([0.3, 0.0, 0.0]))
    i7, i8 = r.link_index("link7"), r.link_index("link8")
    assert np.linalg.norm(T[i7][:3, 3] - T0[i7][:3, 3]) == pytest.approx(0.02)
    assert np.linalg.norm(T[i8][:3, 3] - T0[i8][:3, 3]) == pytest.approx(0.01)


def test_stated_joints_must_be_held(robot):
    with pytest.raises(LarcInputError, match="stated joints"):
        load_robot(robot.urdf_path, stated_joints=["joint2"])
    r = load_robot(robot.urdf_path, held_joint_values={"joint7": -0.01}, stated_joints=["joint7"])
    assert r.stated_joints == ("joint7",) and r.stroke_joints == ("joint8",)


def test_unknown_joint_and_missing_file(robot, tmp_path):
    with pytest.raises(LarcInputError, match="no joint named 'elbow'"):
        load_robot(robot.urdf_path, active_joints=["joint1", "elbow"])
    with pytest.raises(LarcInputError, match="does not exist"):
        load_robot(tmp_path / "nothing.urdf")


def test_env_var_resolution(monkeypatch, tmp_path):
    from larc_jax.model.urdf import piper_description_dir

    monkeypatch.setenv("LARC_PIPER_DESCRIPTION", str(tmp_path))
    with pytest.raises(LarcInputError, match="LARC_PIPER_DESCRIPTION"):
        piper_description_dir()


def test_one_urdf_parse_per_robot_load(piper_dir, tmp_path, monkeypatch):
    """Loading a robot and reading every link's collision geometry (what fitting and the hull
    stage do) parses the URDF once; editing the file makes the next load parse it again. (With
    the compilation cache off: with it on, the parse is kept on disk, tests/test_robot_cache.py.)"""
    from larc_jax import compilation
    from larc_jax.enclosure.meshes import collision_geometry, link_elements, links_with_geometry

    monkeypatch.setattr(compilation, "_EXPORT_DIR", None)
    urdf = _copy_description(piper_dir, tmp_path)  # a new path: nothing cached for it yet
    parses = []
    real_load = yourdfpy.URDF.load
    monkeypatch.setattr(yourdfpy.URDF, "load", lambda *a, **k: parses.append(a) or real_load(*a, **k))
    rob = load_robot(urdf, held_joint_values={"joint7": 0.0}, stated_joints=["joint7"])
    for link in links_with_geometry(rob):
        assert link_elements(rob, link).size > 0
    collision_geometry(rob)
    load_robot(urdf)  # another robot from the same file: the parse is shared
    assert len(parses) == 1
    urdf.write_text(urdf.read_text().replace("</robot>", "<!-- edited --></robot>"))
    load_robot(urdf)
    assert len(parses) == 2


def _rewrite_keeping_stamp(path: Path, data: bytes) -> None:
    """Replace a file's bytes, keeping its size and modification time (a stat-keyed cache misses this)."""
    st = path.stat()
    assert len(data) == st.st_size
    path.chmod(0o644)
    path.write_bytes(data)
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert (path.stat().st_size, path.stat().st_mtime_ns) == (st.st_size, st.st_mtime_ns)


def _move_first_stl_vertex(stl: Path, dx: float) -> float:
    """Move the first vertex of a binary STL (80-byte header, count, 50-byte triangles) by ``dx``
    along x, in place, keeping the file's size and modification time; returns its old x."""
    data = bytearray(stl.read_bytes())
    assert not data[:5].lower().startswith(b"solid")
    x = np.frombuffer(bytes(data[96:100]), "<f4")[0]
    data[96:100] = np.float32(x + dx).tobytes()
    _rewrite_keeping_stamp(stl, bytes(data))
    return x


def test_a_changed_urdf_is_parsed_again_and_hashed_as_parsed(piper_dir, tmp_path):
    """The parse cache is keyed by the bytes' SHA-256: an edit that keeps the size and the
    modification time is still seen, and the robot's urdf_sha256 is the hash of what was parsed."""
    from larc_jax.enclosure.meshes import links_with_geometry
    from larc_jax.model.urdf import file_sha256

    urdf = _copy_description(piper_dir, tmp_path)
    before = load_robot(urdf)
    assert before.q_lower[0] == -2.618 and before.urdf_sha256 == file_sha256(urdf)
    _rewrite_keeping_stamp(urdf, urdf.read_bytes().replace(b'lower="-2.618"', b'lower="-2.617"', 1))
    after = load_robot(urdf)
    assert after.q_lower[0] == -2.617 and after.urdf_sha256 == file_sha256(urdf) != before.urdf_sha256
    # Geometry read for the old robot would come from a file it does not describe: refused.
    with pytest.raises(LarcInputError, match=r"changed after the robot was loaded"):
        links_with_geometry(before)
    assert links_with_geometry(after)


def test_a_changed_mesh_is_read_again(piper_dir, tmp_path):
    """Mesh vertices are cached by the file's bytes, not by its size and modification time."""
    from larc_jax.enclosure.meshes import link_collisions

    urdf = _copy_description(piper_dir, tmp_path)
    rob = load_robot(urdf)
    (_, _, (v0, _)), = link_collisions(rob, "link6")
    x = _move_first_stl_vertex(urdf.parent.parent / "meshes" / "link6.STL", 0.5)
    (_, _, (v1, _)), = link_collisions(rob, "link6")
    assert v0[0, 0] == x and v1[0, 0] == np.float32(x + 0.5)  # read unprocessed: vertex 0 is that vertex
    np.testing.assert_array_equal(v1[1:], v0[1:])


def test_a_changed_mesh_rebuilds_the_hulls(piper_dir, tmp_path):
    """The hull cache is keyed by the files' contents: a mesh edited in place (same size and
    modification time) gives new hull parts, never the old mesh's."""
    from larc_jax.enclosure.hull import hull_model

    urdf = _copy_description(piper_dir, tmp_path)
    rob = load_robot(urdf)
    before = hull_model(rob)
    assert hull_model(rob) is before
    _move_first_stl_vertex(urdf.parent.parent / "meshes" / "link6.STL", 0.5)  # 0.5 m out: the link6 hull must grow
    after = hull_model(rob)
    p = before.names.index("link6")
    assert after is not before
    assert np.asarray(after.vertices[p])[:, 0].max() > np.asarray(before.vertices[p])[:, 0].max() + 0.4


def test_a_changed_robot_file_is_loaded_again_by_a_manifest_run(tmp_path):
    """The manifest's per-process robot-file cache is keyed by the file's content."""
    from larc_jax.drivers.manifest import ManifestJob, _load_model
    from larc_jax.enclosure.robot_file import default_capsule_path
    from larc_jax.model.urdf import piper_urdf_path

    path = tmp_path / "capsules.yaml"  # PIPER's shipped file, made a robot file by naming its URDF
    path.write_bytes(f"urdf: {piper_urdf_path()}\n".encode() + Path(default_capsule_path()).read_bytes())
    job = ManifestJob(out=str(tmp_path / "out"), leaves=None, robot_file=str(path))
    _, capsules = _load_model(job)
    text = path.read_bytes()
    assert text.count(b"radius: 0.06218\n") == 1
    _rewrite_keeping_stamp(path, text.replace(b"radius: 0.06218\n", b"radius: 0.07218\n"))  # a larger capsule stays sound
    _, again = _load_model(job)
    r0, r1 = np.asarray(capsules.radius, float), np.asarray(again.radius, float)
    changed = np.flatnonzero(r0 != r1)
    assert again is not capsules and len(changed) == 1
    assert np.isclose(r0[changed[0]], 0.06218) and np.isclose(r1[changed[0]], 0.07218)
