"""What the loaders keep on disk with the compilation cache on (larc_jax.model.robot_cache): the
URDF's parse (larc_jax.model.urdf_tree) and the hull parts are what a fresh build gives, exactly;
an edited file is never served an old entry; and the command line refuses a bad option or file
before it imports JAX."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yourdfpy

from larc_jax import LarcInputError, compilation
from larc_jax.model import urdf as urdf_module
from larc_jax.model.urdf import load_robot, load_urdf_model
from larc_jax.model.urdf_tree import tree_from_json, tree_to_json, urdf_tree

EXAMPLES = Path(__file__).resolve().parents[1] / "configs" / "examples"

# Every kind of field the loaders read: primitives, a scaled mesh, a mimic joint with and without
# multiplier, a continuous joint without limits, a joint without origin or axis, a collision
# without origin, negative zero and values that need all 17 digits.
EDGE_URDF = """<robot name="edges">
  <link name="base"><collision><geometry><box size="0.3 0.1 -0.0"/></geometry></collision></link>
  <link name="a"><collision><origin xyz="0.1 0.30000000000000004 0" rpy="0 1.5707963267948966 0"/>
    <geometry><cylinder radius="0.04" length="0.3"/></geometry></collision>
    <collision><geometry><sphere radius="1e-300"/></geometry></collision></link>
  <link name="b"><collision><geometry><mesh filename="part.stl" scale="0.001 0.002 1"/></geometry></collision></link>
  <link name="f1"/><link name="f2"/><link name="c"/>
  <joint name="j1" type="continuous"><parent link="base"/><child link="a"/><axis xyz="0 0 1"/></joint>
  <joint name="j2" type="revolute"><parent link="a"/><child link="b"/><origin xyz="0 0 0.5"/>
    <limit lower="-2.5" upper="2.5" effort="1" velocity="1"/></joint>
  <joint name="g1" type="prismatic"><parent link="b"/><child link="f1"/><axis xyz="0 1 0"/>
    <limit lower="0" upper="0.04" effort="1" velocity="1"/></joint>
  <joint name="g2" type="prismatic"><parent link="b"/><child link="f2"/><axis xyz="0 -1 0"/>
    <limit lower="0" upper="0.04" effort="1" velocity="1"/><mimic joint="g1" multiplier="1" offset="0"/></joint>
  <joint name="g3" type="fixed"><parent link="b"/><child link="c"/></joint>
</robot>
"""


@pytest.fixture
def kept_in(tmp_path, monkeypatch):
    """A fresh cache folder for this test, and no parse left from other tests."""
    monkeypatch.setattr(compilation, "_EXPORT_DIR", tmp_path / "cache" / "exported")
    urdf_module._parse_urdf.cache_clear()
    yield tmp_path / "cache"
    urdf_module._parse_urdf.cache_clear()


def _edge_urdf(folder: Path) -> Path:
    import trimesh

    folder.mkdir(parents=True, exist_ok=True)
    trimesh.creation.box(extents=[0.1, 0.2, 0.3]).export(folder / "part.stl")
    path = folder / "edges.urdf"
    path.write_text(EDGE_URDF)
    return path


def _same(tree_value, ref_value, where: str) -> None:
    """``tree_value`` (from the tree) equals ``ref_value`` (yourdfpy's) bit for bit, recursively."""
    if dataclasses.is_dataclass(tree_value):
        assert ref_value is not None, where
        for f in dataclasses.fields(tree_value):
            _same(getattr(tree_value, f.name), getattr(ref_value, f.name), f"{where}.{f.name}")
    elif isinstance(tree_value, tuple):
        assert len(tree_value) == len(ref_value), where
        for k, (x, y) in enumerate(zip(tree_value, ref_value)):
            _same(x, y, f"{where}[{k}]")
    elif isinstance(tree_value, np.ndarray):
        ref = np.asarray(ref_value, np.float64)
        assert tree_value.shape == ref.shape and tree_value.tobytes() == ref.tobytes(), where
    elif isinstance(tree_value, float):
        assert np.float64(tree_value).tobytes() == np.float64(ref_value).tobytes(), where
    else:
        assert tree_value == ref_value, where


@pytest.mark.parametrize("which", ["piper", "edges"])
def test_tree_is_yourdfpys_parse_and_round_trips(which, piper_dir, tmp_path):
    path = piper_dir / "urdf" / "piper_description.urdf" if which == "piper" else _edge_urdf(tmp_path)
    model = yourdfpy.URDF.load(str(path), build_scene_graph=False, build_collision_scene_graph=False,
                               load_meshes=False, load_collision_meshes=False)
    tree = urdf_tree(model)
    _same(tree, model.robot, "robot")
    text = tree_to_json(tree)
    again = tree_from_json(text)
    _same(again, tree, "round trip")
    assert tree_to_json(again) == text
    assert again.link_map.keys() == model.link_map.keys() and again.joint_map.keys() == model.joint_map.keys()


def test_kept_parse_builds_the_same_robot_without_yourdfpy(kept_in, tmp_path, monkeypatch):
    path = _edge_urdf(tmp_path / "desc")
    built = load_robot(path, held_joint_values={"g1": 0.01})
    assert len(list((kept_in / "urdf").glob("*.json"))) == 1
    urdf_module._parse_urdf.cache_clear()  # a later process: only the disk entry is left

    def no_parse(*a, **k):
        raise AssertionError("parsed again")

    monkeypatch.setattr(yourdfpy.URDF, "load", no_parse)
    again = load_robot(path, held_joint_values={"g1": 0.02})  # other arguments: built from the kept parse
    assert again.joint_names == built.joint_names and again.link_names == built.link_names
    np.testing.assert_array_equal(np.asarray(again.T_parent_joint), np.asarray(built.T_parent_joint))
    assert float(again.q_held[again.joint_names.index("g1")]) == 0.02
    # The kept parse's mistakes are refused as the file's, naming it.
    with pytest.raises(LarcInputError, match=r"edges.urdf: held_joint_values names unknown, fixed or active joints \['bogus'\]"):
        load_robot(path, held_joint_values={"bogus": 0.0})
    # An edited file has another SHA-256: it is parsed, never served the old entry.
    path.write_text(EDGE_URDF.replace('upper="2.5"', 'upper="2.25"'))
    with pytest.raises(LarcInputError, match="parsed again"):  # the parser ran (and was stopped)
        load_robot(path)


def test_a_non_finite_origin_is_refused_from_the_kept_parse_too(kept_in, tmp_path):
    path = _edge_urdf(tmp_path / "desc")
    path.write_text(EDGE_URDF.replace('<origin xyz="0 0 0.5"/>', '<origin xyz="0 nan 0.5"/>'))
    for _ in range(2):  # parsed, then from the disk entry
        with pytest.raises(LarcInputError, match="joint 'j2' has a non-finite origin"):
            load_robot(path)
        urdf_module._parse_urdf.cache_clear()
    assert len(list((kept_in / "urdf").glob("*.json"))) == 1


def test_kept_hull_parts_are_the_built_ones(kept_in, piper_dir, tmp_path, monkeypatch):
    import shutil

    from larc_jax.enclosure import hull

    desc = tmp_path / "piper_description"
    shutil.copytree(piper_dir, desc)
    urdf = desc / "urdf" / "piper_description.urdf"
    robot = load_robot(urdf)
    planes = (("link2", (1.0, 0.0, 0.0), 0.1),)
    monkeypatch.setattr(hull, "_CACHE", {})
    built = hull.hull_model(robot, planes, 0.001)
    assert len(list((kept_in / "hull_parts").glob("*.npz"))) == 1
    hull._CACHE.clear()
    calls = []
    real = hull.build_parts
    monkeypatch.setattr(hull, "build_parts", lambda *a, **k: calls.append(a) or real(*a, **k))
    kept = hull.hull_model(robot, planes, 0.001)
    assert kept is not built and not calls
    for f in dataclasses.fields(built):
        x, y = getattr(built, f.name), getattr(kept, f.name)
        if hasattr(x, "shape"):
            assert np.asarray(x).tobytes() == np.asarray(y).tobytes() and np.asarray(x).dtype == np.asarray(y).dtype, f.name
        else:
            assert x == y, f.name
    # Other planes, or an edited mesh (same triangles, other bytes): built again.
    hull._CACHE.clear()
    hull.hull_model(robot, (), 0.001)
    assert len(calls) == 1
    mesh = desc / "meshes" / "link2.STL"
    data = bytearray(mesh.read_bytes())
    data[:6] = b"edited"  # the binary STL's free-text header: same triangles, other bytes
    mesh.write_bytes(bytes(data))
    hull._CACHE.clear()
    hull.hull_model(load_robot(urdf), planes, 0.001)
    assert len(calls) == 2


def test_a_mesh_rewritten_during_the_hull_build_is_built_again(kept_in, piper_dir, tmp_path, monkeypatch):
    import shutil

    from larc_jax.enclosure import hull

    desc = tmp_path / "piper_description"
    shutil.copytree(piper_dir, desc)
    urdf = desc / "urdf" / "piper_description.urdf"
    robot = load_robot(urdf)
    mesh = desc / "meshes" / "link2.STL"
    original = mesh.read_bytes()
    edited = b"edited" + original[6:]  # the binary STL's free-text header: same triangles
    real = hull.build_parts
    calls = []

    def rewriting(*a, **k):  # the file changes after its bytes were hashed and read
        parts = real(*a, **k)
        calls.append(1)
        if len(calls) == 1:
            mesh.write_bytes(edited)
        return parts

    monkeypatch.setattr(hull, "_CACHE", {})
    monkeypatch.setattr(hull, "build_parts", rewriting)
    hull.hull_model(robot, (), 0.001)
    assert len(calls) == 2  # the first build belongs to no key: built again
    (entry,) = (kept_in / "hull_parts").glob("*.npz")  # only the second build was kept ...
    (key,) = hull._CACHE  # ... in memory under the hashes the second build read
    import hashlib

    (link2,) = [h for path, h in key[0][1:] if Path(path).name == "link2.STL"]
    assert link2 == hashlib.sha256(edited).hexdigest()

    def always(*a, **k):  # a file that never settles: refused, naming the robot
        mesh.write_bytes(original if mesh.read_bytes() == edited else edited)
        return real(*a, **k)

    hull._CACHE.clear()
    monkeypatch.setattr(hull, "build_parts", always)
    with pytest.raises(ValueError, match="kept changing while their hulls were built"):
        hull.hull_model(robot, (("link2", (1.0, 0.0, 0.0), 0.1),), 0.001)
    assert len(list((kept_in / "hull_parts").glob("*.npz"))) == 1 and not hull._CACHE


def test_the_hulls_freshness_check_refuses_a_changed_urdf_and_a_missing_mesh(piper_dir, tmp_path, monkeypatch):
    """hull_model keeps the meshes' paths per process (enclosure/hull.py, _geometry_hashes), yet
    every call still checks the files: a URDF edited after the robot was loaded, and a mesh
    removed, are refused with the full check's errors; the restored URDF is served again."""
    import shutil

    from larc_jax.enclosure import hull

    desc = tmp_path / "piper_description"
    shutil.copytree(piper_dir, desc)
    urdf = desc / "urdf" / "piper_description.urdf"
    robot = load_robot(urdf)
    monkeypatch.setattr(hull, "_CACHE", {})
    built = hull.hull_model(robot, (), 0.001)
    original = urdf.read_bytes()
    urdf.write_bytes(original + b"<!-- edited -->\n")
    with pytest.raises(LarcInputError, match="the URDF changed after the robot was loaded"):
        hull.hull_model(robot, (), 0.001)
    urdf.write_bytes(original)
    assert hull.hull_model(robot, (), 0.001) is built
    (desc / "meshes" / "link2.STL").unlink()
    with pytest.raises(LarcInputError, match="link 'link2' collision mesh .* does not exist"):
        hull.hull_model(robot, (), 0.001)


def _cli_imports(args: list[str], cache: Path) -> tuple[int, str]:
    code = ("import sys\nfrom larc_jax.drivers.cli import main\nrc = main(%r)\n"
            "print('RC', rc, 'jax' in sys.modules)\n") % (args,)
    env = {**__import__("os").environ, "LARC_COMPILE_CACHE": str(cache)}
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env)
    return p.stdout.strip().splitlines()[-1], p.stderr


@pytest.mark.parametrize("bad, message", [
    (["--hold", "bogus=1"], "held_joint_values names unknown, fixed or active joints ['bogus']"),
    (["--hold", "joint7=0.5"], "held value 0.5 of joint 'joint7' is outside"),
    (["--scene", "configs/examples/missing.yaml"], "missing.yaml: scene file does not exist"),
])
def test_certify_refuses_bad_input_before_importing_jax(bad, message, tmp_path):
    """Checked with the parse kept (the run before wrote it) and without (an empty cache)."""
    root = Path(__file__).resolve().parents[1]
    args = ["certify", str(root / "configs/examples/reach_left.yaml"), "--scene", str(root / "configs/examples/cell.yaml")]
    args = args + [str(root / b) if b.startswith("configs/") else b for b in bad]
    for _ in range(2):
        last, err = _cli_imports(args, tmp_path / "cache")
        assert last == "RC 2 False" and message in err, err


def test_current_sha256_hashes_again_whenever_the_status_changed(tmp_path, monkeypatch):
    import os
    import time

    path = tmp_path / "part.stl"
    path.write_bytes(b"a" * 100)
    from larc_jax import io as io_module

    hashes = []
    real = io_module.file_sha256
    monkeypatch.setattr(io_module, "file_sha256", lambda p, what="file": hashes.append(p) or real(p, what))
    monkeypatch.setattr(io_module, "_CURRENT", {})
    # Just written: not settled, so not remembered; every call hashes.
    first = io_module.current_sha256(path)
    assert io_module.current_sha256(path) == first and len(hashes) == 2 and not io_module._CURRENT
    # Settled (the rule switched off here): remembered, and a second call reads nothing.
    monkeypatch.setattr(io_module, "UNSETTLED_NS", -1)
    io_module.current_sha256(path)
    assert io_module.current_sha256(path) == first and len(hashes) == 3
    # Same size, modification time put back: the change time still moved, so it is hashed again.
    st = path.stat()
    time.sleep(0.05)  # past the kernel clock's tick (the settled rule covers a write within it)
    path.write_bytes(b"b" * 100)
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert (path.stat().st_size, path.stat().st_mtime_ns) == (st.st_size, st.st_mtime_ns)
    assert io_module.current_sha256(path) != first and len(hashes) == 4
    # Replaced by another file (new inode), and removed: never the remembered hash.
    time.sleep(0.05)
    other = tmp_path / "other.stl"
    other.write_bytes(b"c" * 100)
    os.replace(other, path)
    assert io_module.current_sha256(path) == real(path) and len(hashes) == 5
    path.unlink()
    with pytest.raises(LarcInputError, match="does not exist|No such file"):
        io_module.current_sha256(path)
