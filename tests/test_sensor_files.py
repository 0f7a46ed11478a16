"""``larc points`` (larc_jax.model.sensor_files): PCL .pcd clouds and OctoMap .bt / .ot maps turned
into the .npy clouds a scene reads. One-sided checks: every occupied OctoMap cube (the voxels
inserted, computed from their keys in float64, independently of the binding) lies inside a
written ball; every point a voxel reduction replaces lies inside its new ball; the .pcd points
come back exactly, converted or read by a scene itself; every bad input exits 2 naming the file
(a scene's, its file and entry)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import octomap  # larc_jax[dev] installs both readers: a missing one fails here, never skips
import pypcd4
import pytest
import yaml

from larc_jax.drivers import cli
from larc_jax.errors import LarcInputError
from larc_jax.model import sensor_files
from larc_jax.model.scene import read_scene
from larc_jax.model.sensor_files import convert_sensor_file, voxel_reduce, SensorCloud


EX = Path(__file__).resolve().parent.parent / "configs" / "examples"
KEY_ORIGIN = 32768  # OctoMap's key of the cell whose lower corner is the origin (tree_max_val)


def larc(capsys, *args):
    capsys.readouterr()
    rc = cli.main([str(a) for a in args])
    out, err = capsys.readouterr()
    return rc, out, err


def entries_of(out: str) -> list[dict]:
    """The ``obstacles:`` entries ``larc points`` printed (YAML, comments dropped)."""
    return yaml.safe_load(out)["obstacles"]


@pytest.mark.parametrize("encoding", ["ascii", "binary", "binary_compressed"])
def test_pcd_points_come_back_exactly_without_the_no_returns(capsys, tmp_path, encoding):
    rng = np.random.default_rng(1)
    P = rng.uniform(-2, 2, size=(500, 4)).astype(np.float32)  # x, y, z, intensity
    P[[3, 77, 400], 1] = np.nan  # pixels with no return
    P[9, 2] = np.inf
    src = tmp_path / "camera.pcd"
    pypcd4.PointCloud.from_xyzi_points(P).save(src, encoding=pypcd4.Encoding(encoding))
    rc, out, err = larc(capsys, "points", src, "-o", tmp_path / "camera.npy")
    assert rc == 0, err
    written = np.load(tmp_path / "camera.npy")
    finite = np.isfinite(P[:, :3]).all(axis=1)
    assert written.dtype == np.float64 and np.array_equal(written, P[finite, :3].astype(np.float64))
    (entry,) = entries_of(out)
    assert entry == {"name": "camera", "type": "points", "file": str(tmp_path / "camera.npy"), "radius": 0.0}
    assert "500 points read" in out and "4 without a finite x, y, z" in out


def test_converted_camera_cloud_is_the_scene_cloud(capsys, tmp_path):
    cloud = np.load(EX / "table_cloud.npy").astype(np.float32)
    pypcd4.PointCloud.from_xyz_points(cloud).save(tmp_path / "table.pcd")
    rc, out, err = larc(capsys, "points", tmp_path / "table.pcd", "-o", tmp_path / "table.npy", "--name", "table")
    assert rc == 0, err
    (entry,) = entries_of(out)
    entry["file"] = "table.npy"  # relative to the scene file, as the printed comment asks
    (tmp_path / "scene.yaml").write_text(yaml.safe_dump({"frame": "base_link", "obstacles": [entry]}))
    scene = read_scene(tmp_path / "scene.yaml", frame="base_link")
    assert scene.point_sets.names == ("table",) and scene.point_sets.radius == (0.0,)
    assert np.array_equal(np.concatenate(scene.point_sets.pieces[0]), np.concatenate(
        read_scene_pieces(cloud.astype(np.float64), tmp_path)))


@pytest.mark.parametrize("encoding", ["ascii", "binary", "binary_compressed"])
def test_a_scene_reads_a_pcd_as_its_finite_points(tmp_path, encoding):
    """A scene's ``type: points`` entry reads a .pcd itself: the pieces of its finite points (the
    no-returns dropped), posed and grown as an .npy of those points; the file's bytes hashed."""
    import hashlib

    P = np.random.default_rng(2).uniform(-1, 1, size=(300, 4)).astype(np.float32)
    P[[5, 200], 0] = np.nan
    P[17, 2] = -np.inf
    pypcd4.PointCloud.from_xyzi_points(P).save(tmp_path / "cam.pcd", encoding=pypcd4.Encoding(encoding))
    # What the file holds (pypcd4's ascii writer prints 10 decimals, so not always P itself).
    held = pypcd4.PointCloud.from_path(tmp_path / "cam.pcd").numpy(("x", "y", "z")).astype(np.float64)
    finite = held[np.isfinite(held).all(axis=1)]
    assert encoding == "ascii" or np.array_equal(finite, P[np.isfinite(P[:, :3]).all(axis=1), :3])
    np.save(tmp_path / "cam.npy", finite)
    pose = {"position": [0.1, -0.2, 0.3], "orientation": [0.0, 0.0, 0.6, 0.8]}
    scenes = {}
    for suffix in (".pcd", ".npy"):
        (tmp_path / f"s{suffix}.yaml").write_text(yaml.safe_dump({"frame": "base_link", "obstacles": [
            {"name": "cam", "type": "points", "file": f"cam{suffix}", "radius": 0.004, "pose": pose}]}))
        scenes[suffix] = read_scene(tmp_path / f"s{suffix}.yaml", frame="base_link").point_sets
    pcd, npy = scenes[".pcd"], scenes[".npy"]
    assert len(pcd.pieces) == len(npy.pieces) and all(np.array_equal(a, b) for a, b in zip(pcd.pieces, npy.pieces))
    assert sum(len(p) for p in pcd.pieces) == len(finite) == 297 and pcd.radius == (0.004,)
    assert pcd.file_sha256 == (hashlib.sha256((tmp_path / "cam.pcd").read_bytes()).hexdigest(),)
    assert "read from a .pcd file" in pcd.assumptions()[0] and ".pcd" not in npy.assumptions()[0]


@pytest.mark.parametrize("make,needle", [
    (lambda p: p.write_bytes(b"VERSION 0.7\nFIELDS x y\ngarbage"), "not a readable .pcd file"),
    (lambda p: _pcd_without_z(p), "the .pcd file has no field z (fields: x, y)"),
    (lambda p: pypcd4.PointCloud.from_xyz_points(np.full((3, 3), np.nan, np.float32)).save(p),
     "the .pcd file has no point with a finite x, y, z"),
])
def test_a_scene_names_its_bad_pcd(tmp_path, make, needle):
    make(tmp_path / "bad.pcd")
    (tmp_path / "s.yaml").write_text(yaml.safe_dump({"frame": "base_link", "obstacles": [
        {"name": "a", "type": "points", "file": "bad.pcd"}]}))
    with pytest.raises(LarcInputError) as err:
        read_scene(tmp_path / "s.yaml", frame="base_link")
    assert str(err.value).startswith(f"{tmp_path / 's.yaml'}: obstacles[0].file {tmp_path / 'bad.pcd'}: ")
    assert needle in str(err.value) and "\n" not in str(err.value)


def test_a_scene_without_pypcd4_says_what_to_install(tmp_path, monkeypatch):
    pypcd4.PointCloud.from_xyz_points(np.zeros((2, 3), np.float32)).save(tmp_path / "c.pcd")
    (tmp_path / "s.yaml").write_text(yaml.safe_dump({"frame": "base_link", "obstacles": [
        {"name": "a", "type": "points", "file": "c.pcd"}]}))
    monkeypatch.setitem(sys.modules, "pypcd4", None)  # import pypcd4 raises ImportError
    needle = r"c\.pcd: reading \.pcd files needs pypcd4 \(pip install 'larc_jax\[clouds\]'\)"
    with pytest.raises(LarcInputError, match=needle):
        read_scene(tmp_path / "s.yaml", frame="base_link")


def read_scene_pieces(points: np.ndarray, folder: Path):
    np.save(folder / "direct.npy", points)
    (folder / "direct.yaml").write_text(yaml.safe_dump(
        {"frame": "base_link", "obstacles": [{"name": "table", "type": "points", "file": "direct.npy"}]}))
    return read_scene(folder / "direct.yaml", frame="base_link").point_sets.pieces[0]


def _octomap(tmp_path, resolution: float, voxels: np.ndarray, block: np.ndarray, free: np.ndarray):
    """A map with the finest voxels ``voxels`` (integer indices: the cube [i, i + 1] * resolution)
    occupied, the 2x2x2 block at even corner ``block`` occupied (pruned into one leaf) and
    ``free`` observed free; written as .bt and .ot."""
    tree = octomap.OcTree(resolution)
    centre = lambda i: (np.asarray(i, np.float64) + 0.5) * resolution  # noqa: E731
    for i in voxels:
        tree.updateNode(centre(i), True)
    for d in np.ndindex(2, 2, 2):
        tree.updateNode(centre(block + np.array(d)), True)
    tree.updateNode(centre(free), False)
    tree.updateInnerOccupancy()
    assert tree.writeBinary(str(tmp_path / "map.bt").encode()) and tree.write(str(tmp_path / "map.ot").encode())


@pytest.mark.parametrize("suffix", [".bt", ".ot"])
def test_octomap_balls_hold_every_occupied_cube(capsys, tmp_path, suffix):
    rng = np.random.default_rng(2)
    resolution = 0.05
    voxels = np.unique(rng.integers(-120, 120, size=(300, 3)), axis=0)  # up to 6 m from the origin
    block = np.array([60, 80, -100])
    free = np.array([61, -90, 11])
    voxels = voxels[~np.all((voxels >= block) & (voxels <= block + 1), axis=1) & ~np.all(voxels == free, axis=1)]
    _octomap(tmp_path, resolution, voxels, block, free)
    rc, out, err = larc(capsys, "points", tmp_path / f"map{suffix}", "-o", tmp_path / "map.npy")
    assert rc == 0, err
    entries = entries_of(out)
    assert [e["file"] for e in entries] == [str(tmp_path / "map_0.npy"), str(tmp_path / "map_1.npy")]
    assert "free space is not an obstacle, nor unknown space (nothing is proven" in out
    centres = [np.load(e["file"]) for e in entries]
    radius = [e["radius"] for e in entries]
    assert [len(c) for c in centres] == [len(voxels), 1]
    assert radius[0] > resolution * np.sqrt(3) / 2 and radius[1] > 2 * resolution * np.sqrt(3) / 2
    # Every corner of every occupied finest voxel (float64, from its index) lies in some ball.
    occupied = np.concatenate([voxels, block + np.array(list(np.ndindex(2, 2, 2)))])
    corners = ((occupied[:, None, :] + np.array(list(np.ndindex(2, 2, 2)))[None]) * resolution).reshape(-1, 3)
    inside = np.zeros(len(corners), bool)
    for C, r in zip(centres, radius):
        for chunk in range(0, len(corners), 512):
            d = np.linalg.norm(corners[chunk:chunk + 512, None, :] - C[None], axis=2).min(axis=1)
            inside[chunk:chunk + 512] |= d <= r
    assert inside.all()
    # Without the single-precision term the farthest corners fall outside: the term is needed.
    bare = resolution * np.sqrt(3) / 2
    d = np.linalg.norm(corners[:, None, :] - centres[0][None], axis=2).min(axis=1)[: 8 * len(voxels)]
    assert d.max() > bare
    # The free voxel is no obstacle.
    assert np.linalg.norm(centres[0] - (free + 0.5) * resolution, axis=1).min() > resolution / 2


def test_octomap_without_occupied_leaves_is_refused(capsys, tmp_path):
    tree = octomap.OcTree(0.1)
    tree.updateNode(np.array([0.05, 0.05, 0.05]), False)
    tree.updateInnerOccupancy()
    assert tree.writeBinary(str(tmp_path / "empty.bt").encode())
    rc, _, err = larc(capsys, "points", tmp_path / "empty.bt", "-o", tmp_path / "x.npy")
    assert rc == 2 and "empty.bt: the map has no occupied leaf" in err


@pytest.mark.parametrize("radius", [0.0, 0.004])
def test_voxel_reduction_holds_every_ball(radius):
    rng = np.random.default_rng(3)
    corners = lambda lo, n: np.round(rng.uniform(lo, lo + 1, size=(n, 3)) / 0.02) * 0.02  # noqa: E731 - on grid corners
    P = np.concatenate([rng.uniform(-1.5, 1.5, size=(4000, 3)), rng.uniform(999.0, 1001.0, size=(500, 3)),
                        corners(-0.5, 200), corners(1e5, 2000)])  # 100 km out the centres' rounding shows
    out = voxel_reduce(SensorCloud(P, radius), 0.02)
    assert len(out.points) < len(P)
    cell = np.floor(P / 0.02)
    keys, inverse = np.unique(cell, axis=0, return_inverse=True)
    assert np.array_equal(out.points, (keys + 0.5) * 0.02)
    reach = np.linalg.norm(P - out.points[inverse.reshape(-1)], axis=1) + radius
    assert reach.max() <= out.radius_m and out.radius_m >= radius + 0.02 * np.sqrt(3) / 2
    assert out.radius_m < radius + 0.02 * np.sqrt(3) / 2 + 1e-9


def test_voxel_option_reduces_an_npy_cloud(capsys, tmp_path):
    P = np.random.default_rng(4).uniform(-1, 1, size=(3000, 3))
    np.save(tmp_path / "dense.npy", P)
    rc, out, err = larc(capsys, "points", tmp_path / "dense.npy", "-o", tmp_path / "coarse.npy", "--voxel", "0.1")
    assert rc == 0, err
    (entry,) = entries_of(out)
    C = np.load(tmp_path / "coarse.npy")
    assert len(C) <= 8000 and entry["radius"] >= 0.1 * np.sqrt(3) / 2
    assert np.linalg.norm(P[:, None] - C[None], axis=2).min(axis=1).max() <= entry["radius"]


def test_too_many_points_ask_for_a_voxel_grid(capsys, tmp_path, monkeypatch):
    monkeypatch.setattr(sensor_files, "MAX_POINTS", 100)
    pypcd4.PointCloud.from_xyz_points(np.random.default_rng(5).normal(size=(101, 3)).astype(np.float32)).save(
        tmp_path / "big.pcd")
    rc, _, err = larc(capsys, "points", tmp_path / "big.pcd", "-o", tmp_path / "big.npy")
    assert rc == 2 and "big.pcd: 101 points, more than a scene's 100 per cloud" in err and "--voxel" in err
    rc, _, err = larc(capsys, "points", tmp_path / "big.pcd", "-o", tmp_path / "big.npy", "--voxel", "5")
    assert rc == 0, err


def _pcd_without_z(path: Path):
    pypcd4.PointCloud.from_points(np.ones((4, 2), np.float32), ("x", "y"), (np.float32, np.float32)).save(path)


@pytest.mark.parametrize("make, args, needle", [
    (lambda p: p.with_suffix(".pcd").write_bytes(b"VERSION 0.7\nFIELDS x y\ngarbage"), (), "not a readable .pcd file"),
    (lambda p: _pcd_without_z(p.with_suffix(".pcd")), (), "the .pcd file has no field z (fields: x, y)"),
    (lambda p: pypcd4.PointCloud.from_xyz_points(np.full((3, 3), np.nan, np.float32)).save(p.with_suffix(".pcd")),
     (), "the file has no point with a finite x, y, z"),
    (lambda p: None, (), "no such file"),
    (lambda p: p.with_suffix(".xyz").write_text("1 2 3\n"), (), "cannot convert '.xyz' files"),
    (lambda p: np.save(p.with_suffix(".npy"), np.zeros((2, 3))), (), "scenes read it directly"),
    (lambda p: p.with_suffix(".bt").write_bytes(b"# Octomap OcTree binary file\nnonsense"), (),
     "not a readable OctoMap file"),
    (lambda p: pypcd4.PointCloud.from_xyz_points(np.zeros((2, 3), np.float32)).save(p.with_suffix(".pcd")),
     ("--voxel", "0"), "--voxel must be a finite length > 0 m"),
    (lambda p: np.save(p.with_suffix(".npy"), np.array([[0, 0, 0], [1, np.nan, 0]])), ("--voxel", "0.1"),
     "point 1 is not finite"),
])
def test_bad_input_exits_2_naming_the_file(capsys, tmp_path, make, args, needle):
    base = tmp_path / "in"
    make(base)
    src = next(iter(sorted(tmp_path.glob("in.*"))), base.with_suffix(".pcd"))
    rc, out, err = larc(capsys, "points", src, "-o", tmp_path / "out.npy", *args)
    assert rc == 2 and needle in err and out == "", err
    assert str(src) in err or needle.startswith("--voxel")  # an option's error names the option
    assert not (tmp_path / "out.npy").exists()


def test_output_must_be_npy(tmp_path):
    pypcd4.PointCloud.from_xyz_points(np.zeros((2, 3), np.float32)).save(tmp_path / "a.pcd")
    with pytest.raises(LarcInputError, match="the output must be an .npy file"):
        convert_sensor_file(tmp_path / "a.pcd", tmp_path / "a.ply")


def test_a_pcd_viewpoint_is_reported_not_applied(capsys, tmp_path):
    pc = pypcd4.PointCloud.from_xyz_points(np.array([[1, 2, 3], [4, 5, 6]], np.float32))
    metadata = pc.metadata.model_copy(update={"viewpoint": (0.5, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)})
    pypcd4.PointCloud(metadata, pc.pc_data).save(tmp_path / "posed.pcd")
    rc, out, err = larc(capsys, "points", tmp_path / "posed.pcd", "-o", tmp_path / "posed.npy")
    assert rc == 0, err
    assert "VIEWPOINT (sensor pose tx ty tz qw qx qy qz = 0.5 0 1 0 0 0 1) is not applied" in out
    assert np.array_equal(np.load(tmp_path / "posed.npy"), [[1, 2, 3], [4, 5, 6]])


def test_unknown_voxels_in_a_box_become_obstacles_and_known_ones_do_not(capsys, tmp_path):
    resolution = 0.05
    rng = np.random.default_rng(6)
    box_lo, box_hi = np.array([-0.23, 0.1, -0.4]), np.array([0.31, 0.52, 0.0])  # not on voxel faces
    first = np.floor(box_lo / resolution).astype(int) - 1
    last = np.floor(box_hi / resolution).astype(int) + 1
    grid = np.stack(np.meshgrid(*[np.arange(f, l + 1) for f, l in zip(first, last)], indexing="ij"), -1).reshape(-1, 3)
    pick = rng.permutation(len(grid))
    occupied, free = grid[pick[:60]], grid[pick[60:400]]
    tree = octomap.OcTree(resolution)
    for i in occupied:
        tree.updateNode((i + 0.5) * resolution, True)
    for i in free:
        tree.updateNode((i + 0.5) * resolution, False)
    tree.updateInnerOccupancy()
    assert tree.writeBinary(str(tmp_path / "ws.bt").encode())
    rc, out, err = larc(capsys, "points", tmp_path / "ws.bt", "-o", tmp_path / "ws.npy",
                        "--unknown-in", *box_lo, *box_hi)
    assert rc == 0, err
    entries = entries_of(out)
    assert len(entries) == 2 and "neither occupied nor free: obstacles" in out and "outside the --unknown-in box" in out
    clouds = [(np.load(e["file"]), e["radius"]) for e in entries]
    unknown = grid[pick[400:]]
    assert len(clouds[1][0]) == len(unknown)  # every other voxel of the widened box
    # Every corner of every voxel not known free lies in a written ball: the box is covered.
    solid = np.concatenate([occupied, unknown])
    corners = ((solid[:, None, :] + np.array(list(np.ndindex(2, 2, 2)))[None]) * resolution).reshape(-1, 3)
    inside = np.zeros(len(corners), bool)
    for C, r in clouds:
        inside |= np.linalg.norm(corners[:, None] - C[None], axis=2).min(axis=1) <= r
    assert inside.all()
    # No known-free voxel's centre is written.
    written = np.concatenate([C for C, _ in clouds])
    assert np.linalg.norm(((free + 0.5) * resolution)[:, None] - written[None], axis=2).min() > resolution / 2


@pytest.mark.parametrize("args, needle", [
    (("--unknown-in", "0", "0", "0", "-1", "1", "1"), "--unknown-in: expected XMIN YMIN ZMIN XMAX YMAX ZMAX"),
    (("--unknown-in", "-50", "-50", "-50", "50", "50", "50"), "more than 10000000: give a smaller box"),
])
def test_unknown_in_errors(capsys, tmp_path, args, needle):
    tree = octomap.OcTree(0.05)
    tree.updateNode(np.array([0.01, 0.01, 0.01]), True)
    tree.updateInnerOccupancy()
    assert tree.writeBinary(str(tmp_path / "m.bt").encode())
    rc, _, err = larc(capsys, "points", tmp_path / "m.bt", "-o", tmp_path / "m.npy", *args)
    assert rc == 2 and needle in err, err
    pypcd4.PointCloud.from_xyz_points(np.zeros((2, 3), np.float32)).save(tmp_path / "c.pcd")
    rc, _, err = larc(capsys, "points", tmp_path / "c.pcd", "-o", tmp_path / "c.npy", "--unknown-in", 0, 0, 0, 1, 1, 1)
    assert rc == 2 and "c.pcd: --unknown-in applies to OctoMap files (.bt, .ot) only" in err


def test_a_colour_octree_reads_as_its_occupancy(capsys, tmp_path):
    tree = octomap.ColorOcTree(0.05)
    for c in ([0.01, 0.01, 0.01], [0.31, 0.01, 0.01]):
        tree.updateNode(np.array(c), True)
    tree.updateNode(np.array([0.61, 0.01, 0.01]), False)
    tree.updateInnerOccupancy()
    assert tree.write(str(tmp_path / "colour.ot").encode())
    rc, out, err = larc(capsys, "points", tmp_path / "colour.ot", "-o", tmp_path / "colour.npy")
    assert rc == 0, err
    assert np.allclose(np.load(tmp_path / "colour.npy"), [[0.025, 0.025, 0.025], [0.325, 0.025, 0.025]], atol=1e-7)


@pytest.mark.parametrize("module, suffix, package", [("pypcd4", ".pcd", "pypcd4"), ("octomap", ".bt", "octomap-python")])
def test_a_missing_reader_is_named(capsys, tmp_path, monkeypatch, module, suffix, package):
    monkeypatch.setitem(__import__("sys").modules, module, None)  # import fails as when not installed
    (tmp_path / f"f{suffix}").write_bytes(b"x")
    rc, _, err = larc(capsys, "points", tmp_path / f"f{suffix}", "-o", tmp_path / "f.npy")
    assert rc == 2 and f"needs {package} (pip install 'larc_jax[clouds]')" in err, err
