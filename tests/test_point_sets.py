"""Meshes and point clouds as obstacles (issue 22): convex pieces that contain them, the hull
bound's kernels against their NumPy twins and one-sided against python-fcl (a BVH of the mesh's
triangles) and brute-force point distances, the files and their errors, and end to end: the
camera cell certifies reach_left, an FCL audit agrees, the certificate verifies and a changed
cloud file is refused, and a bracket slid toward the arm until certification flips still clears
the margin there."""

from __future__ import annotations

import io
import math
import shutil
from pathlib import Path

import jax
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from larc_jax.errors import LarcInputError
from larc_jax.leaf.rounds import EARLY_ITERATIONS
from larc_jax.model.point_sets import PointSets, convex_pieces
from larc_jax.model.scene import Scene, read_scene, scene_from_dict
from larc_jax.obstacles import ConvexShapes, scene_obstacles, stack_scenes
from larc_jax.obstacles.polytope import GJK_ITERATIONS
from tests.capsule_audit import bracket_fcl, capsule_clearance, last_certified

EX = Path(__file__).resolve().parent.parent / "configs" / "examples"


def test_example_files_are_what_the_generator_writes(tmp_path):
    from experiments.example_cell import main

    assert main(["--out", str(tmp_path)]) == 0
    for name in ("bracket.stl", "table_cloud.npy"):
        assert (tmp_path / name).read_bytes() == (EX / name).read_bytes(), name


def test_pieces_hold_every_point_and_every_triangle():
    rng = np.random.default_rng(0)
    P = rng.normal(size=(1000, 3))
    pieces = convex_pieces(P, None, 32)
    assert all(len(p) <= 32 for p in pieces) and sum(len(p) for p in pieces) == len(P)
    assert {tuple(x) for p in pieces for x in p} == {tuple(x) for x in P}
    from experiments.example_cell import bracket_mesh

    m = bracket_mesh()
    V, F = np.asarray(m.vertices), np.asarray(m.faces)
    pieces = convex_pieces(V, F, 4)
    for tri in F:  # every triangle's three corners lie in one piece
        assert any(all((piece == V[c]).all(axis=1).any() for c in tri) for piece in pieces)


def _camera_scene() -> Scene:
    return read_scene(EX / "cell_camera.yaml", frame="base_link")


def test_camera_cell_reads_its_files():
    scene = _camera_scene()
    ps = scene.point_sets
    assert ps.kinds == ("mesh", "points") and ps.names == ("bracket", "table")
    assert scene.n_boxes == 0 and scene.shapes.count == 0 and scene.n_obstacles == ps.count
    cloud = np.load(EX / "table_cloud.npy")
    assert sum(len(p) for p, o in zip(ps.pieces, ps.owner) if o == 1) == len(cloud)
    assert ps.radius == (0.0, 0.002) and len(ps.file_sha256[0]) == 64
    assert scene.obstacle_names[0] == "bracket[0]" and scene.obstacle_names[-1].startswith("table[")
    assert isinstance(scene_obstacles(scene), ConvexShapes) and scene_obstacles(scene).any_polytope


@pytest.mark.parametrize("entry,needle", [
    ({"type": "mesh"}, r"obstacles\[0\]\.file must be a file name"),
    ({"type": "mesh", "file": "nowhere.stl"}, r"nowhere\.stl"),
    ({"type": "points", "file": "cloud.xyz"}, r"points are read from \.npy .*, \.ply or \.pcd files, not '\.xyz'"),
    ({"type": "points", "file": "cloud.pcd"}, r"cloud\.pcd: not a readable \.pcd file"),
    ({"type": "points", "file": "flat.npy"}, r"expected an \(N, 3\) array"),
    ({"type": "points", "file": "nan.npy"}, r"point 1 is not finite"),
    ({"type": "points", "file": "ok.npy", "radius": -1}, r"radius must not be negative"),
    ({"type": "mesh", "file": "junk.stl"}, r"junk\.stl: (not a readable mesh|the mesh has no triangles)"),
    ({"type": "mesh", "file": "ok.stl", "scale": [1, 0, 1]}, r"scale must be positive"),
    ({"type": "mesh", "file": "ok.stl", "size": [1, 1, 1]}, r"'size'"),
])
def test_point_set_entries_errors_name_the_entry(tmp_path, entry, needle):
    np.save(tmp_path / "flat.npy", np.zeros((4, 2)))
    np.save(tmp_path / "nan.npy", np.array([[0, 0, 0], [np.nan, 0, 0]]))
    np.save(tmp_path / "ok.npy", np.zeros((4, 3)))
    (tmp_path / "cloud.pcd").write_text("VERSION .7\n")
    (tmp_path / "cloud.xyz").write_text("0 0 0\n")
    (tmp_path / "junk.stl").write_bytes(b"\x00" * 7)
    shutil.copy(EX / "bracket.stl", tmp_path / "ok.stl")
    source = str(tmp_path / "scene.yaml")
    with pytest.raises(LarcInputError, match=needle) as err:
        scene_from_dict({"frame": "base_link", "obstacles": [entry]}, source=source)
    assert str(err.value).startswith(source) and "\n" not in str(err.value)


@pytest.fixture(scope="module")
def values():
    """The camera cell (its bracket posed as in the file, the cloud thinned to keep FCL fast) and
    every JAX kernel on it in float64 and float32."""
    full = _camera_scene()
    ps = full.point_sets
    keep = [g for g, o in enumerate(ps.owner) if o == 0] + [g for g, o in enumerate(ps.owner) if o == 1][::8]
    scene = Scene(lo=np.zeros((0, 3)), hi=np.zeros((0, 3)), point_sets=PointSets(
        kinds=ps.kinds, names=ps.names, files=ps.files, file_sha256=ps.file_sha256, radius=ps.radius,
        pieces=tuple(ps.pieces[g] for g in keep), owner=tuple(ps.owner[g] for g in keep)))
    rng = np.random.default_rng(1)
    p_a = rng.uniform([-0.5, -0.5, -0.05], [0.8, 0.6, 0.4], (30, 3))
    p_b = p_a + rng.normal(0, 0.08, (30, 3))
    table = rng.normal(0, 0.03, (1, 10, 3))
    R = Rotation.random(12, random_state=rng).as_matrix()
    t = rng.uniform([-0.5, -0.5, 0.0], [0.8, 0.6, 0.3], (12, 3))

    def kernels(ob, p_a, p_b, table, R, t):
        seg = (ob.segment_distances(p_a, p_b), ob.segment_lower_bounds(p_a, p_b), ob.point_distances(p_a))
        one = jax.vmap(lambda item, r, tt: type(item).polytope_lower_bound(item, table, 0, table[0].mean(0), r, tt),
                       (None, 0, 0))
        points = jax.vmap(lambda item, r, tt: type(item).points_lower_bound(item, table, 0, table[0].mean(0), r, tt),
                          (None, 0, 0))
        bounds = jax.vmap(lambda item, r, tt: type(item).polytope_bounds(item, table, 0, table[0].mean(0), r, tt,
                                                                         EARLY_ITERATIONS), (None, 0, 0))
        return (*seg, jax.vmap(one, (0, None, None))(ob, R, t), jax.vmap(points, (0, None, None))(ob, R, t),
                *jax.vmap(bounds, (0, None, None))(ob, R, t))

    out = {}
    with jax.enable_x64(True):
        for dtype in (np.float64, np.float32):
            ob = stack_scenes([scene], dtype).take(0)
            cast = lambda x: np.asarray(x, dtype)  # noqa: E731
            out[np.dtype(dtype).name] = [np.asarray(x, np.float64) for x in
                                         jax.jit(kernels)(ob, cast(p_a), cast(p_b), cast(table), cast(R), cast(t))]
    return scene, p_a, p_b, table, R, t, out


def test_jax_kernels_equal_numpy_twins(values):
    scene, p_a, p_b, table, R, t, out = values
    dist, lb, point, poly, points = out["float64"][:5]
    ob = scene_obstacles(scene)
    for k in list(range(4)) + list(range(scene.n_obstacles - 3, scene.n_obstacles)):
        item = ob.take(k)
        for s in range(0, len(p_a), 3):
            assert dist[s, k] == pytest.approx(item.segment_distance_np(p_a[s], p_b[s]), abs=1e-12)
            assert lb[s, k] == pytest.approx(item.segment_lower_bound_np(p_a[s], p_b[s]), abs=1e-12)
            assert lb[s, k] <= dist[s, k] + 1e-15
        np.testing.assert_allclose(point[:, k], item.point_distance_np(p_a), atol=1e-12)
        for i in range(len(R)):
            assert poly[k, i] == pytest.approx(item.polytope_lower_bound_np(table[0], table[0].mean(0), R[i], t[i]),
                                               abs=1e-12)
            twin = item.points_lower_bound_np(table[0], table[0].mean(0), R[i], t[i])
            if twin > -np.inf:  # a cloud's piece
                assert points[k, i] == pytest.approx(twin, abs=1e-12), (k, i)
            else:
                assert points[k, i] == -np.inf, (k, i)


def test_piece_upper_bound_twins_and_lower_bounds_below_it(values):
    """``polytope_bounds`` of the pieces (R8 of :mod:`larc_jax.obstacles.convex_shapes`: the better
    of the bounding box's and the hull's searches, less ``inflate``): the kernel's (lower, upper)
    after the middle round's steps equal the NumPy twin's, and no lower bound after any number of
    steps exceeds the upper bound after any number (a pair stopped early could not have passed)."""
    scene, _, _, table, R, t, out = values
    poly, lower, upper = (out["float64"][i] for i in (3, 5, 6))
    ob = scene_obstacles(scene)
    for k in list(range(4)) + list(range(scene.n_obstacles - 3, scene.n_obstacles)):
        item = ob.take(k)
        for i in range(len(R)):
            lb, ub = item.polytope_bounds_np(table[0], table[0].mean(0), R[i], t[i], EARLY_ITERATIONS)
            assert (lower[k, i], upper[k, i]) == pytest.approx((lb, ub), abs=1e-12), (k, i)
            assert math.isfinite(ub) and poly[k, i] <= ub + 1e-12
            runs = [item.polytope_bounds_np(table[0], table[0].mean(0), R[i], t[i], n)
                    for n in (0, EARLY_ITERATIONS, GJK_ITERATIONS)]
            assert max(r[0] for r in runs) <= min(r[1] for r in runs) + 1e-12, (k, i, runs)


def _truth(scene):
    """FCL's bracket (a BVH of its triangles, posed) and the cloud's points with their radius."""
    import fcl
    import trimesh

    from larc_jax.model.shapes import rotation_from_quaternion

    mesh = trimesh.load(EX / "bracket.stl")
    R = rotation_from_quaternion([0.0, 0.0, 0.9238795325112867, -0.3826834323650898])
    V = np.asarray(mesh.vertices) @ R.T + [-0.275, 0.325, 0.0]
    bvh = fcl.BVHModel()
    bvh.beginModel(len(V), len(mesh.faces))
    bvh.addSubModel(V, np.asarray(mesh.faces))
    bvh.endModel()
    cloud = np.concatenate([p for p, o in zip(scene.point_sets.pieces, scene.point_sets.owner) if o == 1])
    return fcl.CollisionObject(bvh, fcl.Transform()), cloud, scene.point_sets.radius[1]


def _point_to_mesh(obj, p) -> float:
    import fcl

    ball = fcl.CollisionObject(fcl.Sphere(0.0), fcl.Transform(np.asarray(p, np.float64)))
    return max(fcl.distance(ball, obj, fcl.DistanceRequest(), fcl.DistanceResult()), 0.0)


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_bounds_never_exceed_fcl_or_the_points(values, dtype):
    """One-sided: the smallest bound over the bracket's pieces <= FCL's distance from densely
    sampled segment points to the bracket's triangles; over the cloud's pieces <= the smallest
    point distance less the radius (the segment kernels use a piece's bounding box). The hull
    bound of the hull stage is also tight: within 1 mm of FCL's polytope-mesh distance at the
    median, and never above it."""
    scene, p_a, p_b, table, R, t, out = values
    dist, lb, point, poly, _ = out[dtype][:5]
    mesh, cloud, radius = _truth(scene)
    bracket = np.array(scene.point_sets.owner) == 0
    grid = np.linspace(0.0, 1.0, 101)
    gaps = []
    for s in range(len(p_a)):
        pts = p_a[s] + grid[:, None] * (p_b[s] - p_a[s])
        to_mesh = min(_point_to_mesh(mesh, x) for x in pts)
        to_cloud = float(np.sqrt(((pts[:, None] - cloud[None]) ** 2).sum(-1)).min()) - radius
        assert dist[s, bracket].min() <= to_mesh + 1e-12 and dist[s, ~bracket].min() <= to_cloud + 1e-12, s
    # the hull-stage bound against the placed polytope's points, and against FCL's convex-mesh distance
    import fcl
    import trimesh

    W = np.vstack([np.eye(table.shape[1]), np.random.default_rng(2).dirichlet(np.ones(table.shape[1]), 20)])
    for i in range(len(R)):
        placed = table[0] @ R[i].T + t[i]
        pts = W @ placed
        assert poly[bracket, i].min() <= min(_point_to_mesh(mesh, x) for x in pts) + 1e-12, i
        to_cloud = float(np.sqrt(((pts[:, None] - cloud[None]) ** 2).sum(-1)).min()) - radius
        assert poly[~bracket, i].min() <= to_cloud + 1e-12, i
        hull = trimesh.convex.convex_hull(placed)
        faces = np.hstack([np.full((len(hull.faces), 1), 3), hull.faces]).ravel()
        convex = fcl.CollisionObject(fcl.Convex(np.asarray(hull.vertices), len(hull.faces), faces), fcl.Transform())
        exact = max(fcl.distance(convex, mesh, fcl.DistanceRequest(), fcl.DistanceResult()), 0.0)
        assert poly[bracket, i].min() <= exact + 1e-9, i
        gaps.append(exact - poly[bracket, i].min())
    assert np.median(gaps) < 1e-3, gaps


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_point_bounds_never_exceed_fcl_and_beat_the_hull(values, dtype):
    """The hull stage's third round (R7 of convex_shapes): per cloud piece, the per-point bound
    is one-sided against python-fcl's distance from the placed polytope to each of the piece's
    points (less the radius), within 0.1 mm of it at the worst, and at least the piece hull's
    bound less 0.1 mm (it searches a smaller set); on this cloud it beats the hull bound by more than 0.5 mm
    somewhere (the hull spans the 1 cm gaps between points)."""
    import fcl
    import trimesh

    scene, p_a, p_b, table, R, t, out = values
    _, _, _, poly, points = out[dtype][:5]
    ps = scene.point_sets
    n_fixed = scene.n_obstacles - ps.count
    gains = []
    for i in range(len(R)):
        placed = table[0] @ R[i].T + t[i]
        hull = trimesh.convex.convex_hull(placed)
        faces = np.hstack([np.full((len(hull.faces), 1), 3), hull.faces]).ravel()
        convex = fcl.CollisionObject(fcl.Convex(np.asarray(hull.vertices), len(hull.faces), faces), fcl.Transform())
        for g, (piece, owner) in enumerate(zip(ps.pieces, ps.owner)):
            k = n_fixed + g
            if ps.kinds[owner] != "points":
                assert points[k, i] == -np.inf
                continue
            if poly[k, i] > 0.1:  # far pieces: FCL is slow and adds nothing
                continue
            exact = min(max(fcl.distance(convex, fcl.CollisionObject(fcl.Sphere(0.0), fcl.Transform(y)),
                                         fcl.DistanceRequest(), fcl.DistanceResult()), 0.0) for y in piece)
            exact -= ps.radius[owner]
            assert points[k, i] <= exact + 1e-9, (i, g)
            assert points[k, i] >= exact - 1e-4, (i, g)
            assert points[k, i] >= poly[k, i] - 1e-4, (i, g)
            gains.append(points[k, i] - poly[k, i])
    assert len(gains) >= 8 and max(gains) > 5e-4, gains


def test_point_round_decides_as_the_reference_and_refines_less(tmp_path, monkeypatch):
    """The hull stage's third round on a depth camera's wall of points (tightness_kinds' points
    window; its path of least clearance cut to 4 waypoints around where it passes nearest, depth
    <= 5, gripper stated): batched LARC and the NumPy reference take the same decisions (frontier,
    stages, clearances within 1e-9 m), both run the round, and without it LARC bisects more
    (the piece hulls alone cannot pass some intervals the points pass). ``larc verify`` re-checks
    the certificate, the third round's leaves with the NumPy twins."""
    import dataclasses

    import larc_jax as lj
    import larc_jax.engine.batch as batch_module
    import larc_jax.leaf.cascade as cascade_module
    from experiments import tightness_kinds as tk
    from experiments.mesh_truth import HOLD
    from larc_jax.enclosure.robot_file import load_robot_file
    from larc_jax.model.trajectory_files import read_trajectory, write_trajectory

    robot, capsules = load_robot_file(None, hold=HOLD)
    scene = lj.read_scene(tk.write_scenes(tmp_path, ("points",))["points"])
    assert (tmp_path / "points.yaml").is_file()
    root = Path(__file__).resolve().parent.parent / "results" / "tightness_kinds" / "dataset"
    traj = read_trajectory(root / "pad10mm" / "points" / "points_p05.yaml", robot)
    j = int(np.searchsorted(traj.t, 9.156))  # truth.csv: the least clearance, 12.8 mm, at 9.156 s
    cut = slice(j - 2, j + 2)
    traj = dataclasses.replace(traj, t=traj.t[cut] - traj.t[cut][0], q=traj.q[cut], qd=traj.qd[cut], id="cut")
    write_trajectory(tmp_path / "cut.yaml", traj)
    traj = read_trajectory(tmp_path / "cut.yaml", robot)
    spec = dict(margin_m=0.01, max_depth=5, enclosure="hull")
    asked = {"larc": 0, "reference": 0}

    def spy(module, key):
        real = module.point_round

        def counting(g, guard, separate, points):
            asked[key] += int((~(g > guard) & np.asarray(separate, bool)).sum())
            return real(g, guard, separate, points)

        monkeypatch.setattr(module, "point_round", counting)

    spy(batch_module, "larc")
    spy(cascade_module, "reference")
    larc = lj.certify(traj, scene, robot, capsules, spec=lj.RunSpec(method="larc", **spec))
    ref = lj.certify(traj, scene, robot, capsules, spec=lj.RunSpec(method="reference", **spec))
    assert asked["larc"] > 0 and asked["reference"] > 0, asked
    assert larc.certified.tolist() == ref.certified.tolist() == [True]
    np.testing.assert_array_equal(larc.frontier, ref.frontier)
    np.testing.assert_array_equal(larc.leaves.stage, ref.leaves.stage)
    np.testing.assert_allclose(larc.leaves.clearance_m, ref.leaves.clearance_m, rtol=0, atol=1e-9)
    cert = lj.write_certificate(tmp_path / "cert.json", larc, [traj], [scene], robot, capsules,
                                trajectory_files=[tmp_path / "cut.yaml"], scene_files=[tmp_path / "points.yaml"])
    lj.verify_certificate(cert)
    monkeypatch.setattr(batch_module, "point_round", lambda g, guard, separate, points: g)
    hulls_only = lj.certify(traj, scene, robot, capsules, spec=lj.RunSpec(method="larc", **spec))
    assert hulls_only.frontier.sum() > larc.frontier.sum(), (hulls_only.frontier, larc.frontier)


# ---------------------------------------------------------------------------------------------- end to end

def test_camera_cell_certifies_verifies_and_refuses_a_changed_cloud(robot, capsules, tmp_path):
    import json

    from larc_jax import certify, verify_certificate, write_certificate
    from larc_jax.products.verify import Refuted
    from larc_jax.products.verify_report import report_lines
    from larc_jax.model.trajectory_files import read_trajectory

    for name in ("cell_camera.yaml", "bracket.stl", "table_cloud.npy", "reach_left.yaml"):
        shutil.copy(EX / name, tmp_path / name)
    traj, scene = read_trajectory(tmp_path / "reach_left.yaml"), read_scene(tmp_path / "cell_camera.yaml")
    res = certify(traj, scene, robot, capsules, method="larc")
    assert res[0].certified
    path = tmp_path / "cert.json"
    write_certificate(path, res, [traj], [scene], robot, capsules, trajectory_files=[tmp_path / "reach_left.yaml"],
                      scene_files=[tmp_path / "cell_camera.yaml"])
    report = verify_certificate(path)
    # What the claim assumes of the mesh and the cloud is stated, and checked against the files.
    doc = json.loads(path.read_text())
    assumes = ["bracket: mesh, its surface only (not a convex watertight mesh: a link wholly inside it is not seen)",
               "table: points, each a ball of radius 0.002 m"]
    assert doc["scenes"][0]["assumes"] == assumes and report.scene_files[0].assumes == tuple(assumes)
    assert all(a in "\n".join(report_lines(report)) for a in assumes)
    doc["scenes"][0]["assumes"][0] = "bracket: mesh, a solid (convex and watertight: its hull)"
    forged = tmp_path / "forged.json"
    forged.write_text(json.dumps(doc))
    with pytest.raises(Refuted, match=r"scenes\[0\]\.assumes"):
        verify_certificate(forged)
    cloud = np.load(tmp_path / "table_cloud.npy")
    cloud[0, 2] += 1e-3
    buf = io.BytesIO()
    np.save(buf, cloud)
    (tmp_path / "table_cloud.npy").write_bytes(buf.getvalue())
    with pytest.raises(Exception, match="obstacles"):
        verify_certificate(path)


def test_camera_cell_from_a_pcd_certifies_and_verifies_as_from_its_npy(robot, capsules, tmp_path):
    """The camera cell with its cloud given as a PCL .pcd file (float64 fields, binary_compressed,
    one pixel with no return): the scene holds the .npy's pieces exactly, reach_left's result is
    the same, the certificate states what the .pcd reading assumes and verifies, and a changed
    .pcd is refused."""
    import json

    import pypcd4
    import yaml

    from larc_jax import certify, verify_certificate, write_certificate
    from larc_jax.model.trajectory_files import read_trajectory

    cloud = np.load(EX / "table_cloud.npy")
    with_gap = np.insert(cloud, 7, np.nan, axis=0)  # a pixel with no return
    pypcd4.PointCloud.from_points(with_gap, ("x", "y", "z"), (np.float64,) * 3).save(
        tmp_path / "table.pcd", encoding=pypcd4.Encoding.BINARY_COMPRESSED)
    shutil.copy(EX / "bracket.stl", tmp_path / "bracket.stl")
    doc = yaml.safe_load((EX / "cell_camera.yaml").read_text())
    doc["obstacles"][1]["file"] = "table.pcd"
    (tmp_path / "cell.yaml").write_text(yaml.safe_dump(doc))
    scene, npy = read_scene(tmp_path / "cell.yaml"), _camera_scene()
    assert len(scene.point_sets.pieces) == len(npy.point_sets.pieces)
    assert all(np.array_equal(a, b) for a, b in zip(scene.point_sets.pieces, npy.point_sets.pieces))
    traj = read_trajectory(EX / "reach_left.yaml")
    res = certify(traj, scene, robot, capsules, method="larc")
    ref = certify(traj, npy, robot, capsules, method="larc")
    assert res[0].certified
    assert (res[0].min_clearance_m, res[0].evaluations) == (ref[0].min_clearance_m, ref[0].evaluations)
    path = tmp_path / "cert.json"
    write_certificate(path, res, [traj], [scene], robot, capsules, trajectory_files=[EX / "reach_left.yaml"],
                      scene_files=[tmp_path / "cell.yaml"])
    assumes = json.loads(path.read_text())["scenes"][0]["assumes"][1]
    assert assumes == ("table: points, each a ball of radius 0.002 m, read from a .pcd file: its points with a "
                       "finite x, y, z (a point without one, a pixel with no return, is no obstacle), its header's "
                       "VIEWPOINT not applied")
    assert verify_certificate(path).scene_files[0].assumes[1] == assumes
    with_gap[0, 2] += 1e-3
    pypcd4.PointCloud.from_points(with_gap, ("x", "y", "z"), (np.float64,) * 3).save(
        tmp_path / "table.pcd", encoding=pypcd4.Encoding.BINARY_COMPRESSED)
    with pytest.raises(Exception, match="obstacles"):
        verify_certificate(path)


def test_bracket_in_a_moveit_scene_certifies_and_verifies_as_in_yaml(robot, capsules, tmp_path):
    """The camera cell's bracket written into a MoveIt .scene file as MoveIt writes a mesh (its
    vertices and triangles inline, the object's pose): reach_left's result equals the YAML
    mesh entry's, the certificate verifies against the .scene, and a moved vertex is refused."""
    import trimesh
    import yaml

    from larc_jax import certify, verify_certificate, write_certificate
    from larc_jax.model.trajectory_files import read_trajectory
    from larc_jax.products.verify import Refuted

    mesh = trimesh.load(EX / "bracket.stl", force="mesh", process=True)
    entry = yaml.safe_load((EX / "cell_camera.yaml").read_text())["obstacles"][0]
    pose = entry["pose"]

    def write(V):
        rows = [" ".join(repr(float(x)) for x in v) for v in V] + [" ".join(map(str, f)) for f in mesh.faces]
        (tmp_path / "cell.scene").write_text("\n".join(
            ["cell", "* bracket", " ".join(map(repr, pose["position"])), " ".join(map(repr, pose["orientation"])),
             "1", "mesh", f"{len(V)} {len(mesh.faces)}", *rows, "0 0 0", "0 0 0 1", "0.5 0.5 0.5 1", "0", "."]) + "\n")

    write(mesh.vertices)
    shutil.copy(EX / "bracket.stl", tmp_path / "bracket.stl")
    (tmp_path / "cell.yaml").write_text(yaml.safe_dump({"frame": "base_link", "obstacles": [entry]}))
    traj = read_trajectory(EX / "reach_left.yaml")
    scene, ref = read_scene(tmp_path / "cell.scene"), read_scene(tmp_path / "cell.yaml")
    res = certify(traj, scene, robot, capsules, method="larc")
    want = certify(traj, ref, robot, capsules, method="larc")
    assert res[0].certified and (res[0].evaluations, res[0].min_clearance_m) == (want[0].evaluations,
                                                                                 want[0].min_clearance_m)
    path = tmp_path / "cert.json"
    write_certificate(path, res, [traj], [scene], robot, capsules, trajectory_files=[EX / "reach_left.yaml"],
                      scene_files=[tmp_path / "cell.scene"])
    assert verify_certificate(path).scene_files[0].assumes == ref.point_sets.assumptions()
    V = mesh.vertices.copy()
    V[0, 2] += 1e-3
    write(V)
    with pytest.raises(Refuted, match=r"cell\.scene has sha256 [0-9a-f]{64}, the certificate records"):
        verify_certificate(path)


def test_bracket_slid_to_the_flip_still_clears_the_margin(robot, capsules):
    from larc_jax import certify
    from larc_jax.defaults import DEFAULT_MARGIN_M
    from larc_jax.model.trajectory_files import read_trajectory

    traj = read_trajectory(EX / "reach_left.yaml")
    full = _camera_scene()
    ps = full.point_sets
    mine = [g for g, o in enumerate(ps.owner) if o == 0]
    toward = -np.array([-0.275, 0.325, 0.0]) / np.linalg.norm([-0.275, 0.325])  # toward the arm's base

    def moved(s):
        return Scene(lo=np.zeros((0, 3)), hi=np.zeros((0, 3)), point_sets=PointSets(
            kinds=ps.kinds[:1], names=ps.names[:1], files=ps.files[:1], file_sha256=ps.file_sha256[:1],
            radius=ps.radius[:1], pieces=tuple(ps.pieces[g] + s * toward for g in mine), owner=tuple(0 for _ in mine)))

    def ok(s):
        return certify(traj, moved(s), robot, capsules, method="larc", enclosure="capsules")[0].certified

    lo = last_certified(ok, 0.0, 0.1, 10)
    scene = moved(lo)
    # the truth: FCL on the bracket's triangles moved by the same amount
    clearance = capsule_clearance(robot, capsules, traj, [bracket_fcl(EX, lo * toward)])
    assert clearance > DEFAULT_MARGIN_M
    assert clearance - DEFAULT_MARGIN_M < 0.03, clearance  # the motion bound's slack, not a vacuous pass
    assert scene.point_sets.count == len(mine)


def test_fcl_audit_of_the_certified_move_in_the_camera_cell(robot, capsules):
    """Every capsule stays more than the margin from the bracket's triangles (FCL) and from every
    cloud point less its radius, over 300 states of the certified move."""
    from larc_jax.defaults import DEFAULT_MARGIN_M
    from larc_jax.enclosure.capsule import capsule_segments_np
    from larc_jax.model.hermite_reference import evaluate_np
    from larc_jax.model.trajectory_files import read_trajectory
    from larc_jax.obstacles.geometry import segment_box_distance_np

    traj, scene = read_trajectory(EX / "reach_left.yaml"), _camera_scene()
    mesh, cloud, radius = _truth(scene)
    assert capsule_clearance(robot, capsules, traj, [mesh]) > DEFAULT_MARGIN_M
    worst = math.inf
    for time in np.linspace(traj.t[0], traj.t[-1], 300):
        q, _ = evaluate_np(traj.t, traj.q, traj.qd, time)
        p_a, p_b = capsule_segments_np(robot, capsules, q)[:2]
        for a, b, r in zip(p_a, p_b, np.asarray(capsules.radius)):
            near = cloud[np.linalg.norm(cloud - (a + b) / 2, axis=1) < np.linalg.norm(b - a) / 2 + r + 0.05]
            for x in near:
                worst = min(worst, segment_box_distance_np(a, b, x, x) - r - radius)
    assert worst > DEFAULT_MARGIN_M


@pytest.mark.parametrize("kwargs,needle", [
    (dict(kinds=("mesh",), names=("a",), files=("f",), file_sha256=("",), radius=(0.0,), pieces=(np.zeros((2, 2)),),
          owner=(0,)), r"PointSets\.pieces\[0\] must have shape \(N, 3\)"),
    (dict(kinds=("mesh",), names=("a",), files=("f",), file_sha256=("",), radius=(0.0,), pieces=(np.zeros((2, 3)),),
          owner=(1,)), r"PointSets\.owner\[0\] = 1 is not an obstacle index"),
    (dict(kinds=("cloud",), names=("a",), files=("f",), file_sha256=("",), radius=(0.0,)), r"PointSets\.kinds\[0\]"),
    (dict(kinds=("points",), names=("a",), files=("f",), file_sha256=("",), radius=(-1.0,)), r"PointSets\.radius\[0\]"),
    (dict(kinds=("points",), names=("a",), files=("f",), file_sha256=("",), radius=(0.0,),
          pieces=(np.array([[0, 0, np.nan]]),), owner=(0,)), r"all finite"),
    (dict(kinds=("points", "points"), names=("a", "b"), files=("f",), file_sha256=("",), radius=(0.0,)),
     r"files has 1 entries"),
    (dict(kinds=("points",), names=("a",), files=("f",), file_sha256=("",), radius=(0.0,), solid=(True,),
          pieces=(np.zeros((1, 3)),), owner=(0,)), r"PointSets\.solid\[0\] must be True or False \(True only for a mesh\)"),
    (dict(kinds=("mesh",), names=("a",), files=("f",), file_sha256=("",), radius=(0.0,), solid=(True,),
          pieces=(np.zeros((1, 3)), np.ones((1, 3))), owner=(0, 0)), r"a solid mesh is one piece"),
    (dict(kinds=("mesh",), names=("a",), files=("f",), file_sha256=("",), radius=(0.0,), solid=(True, False)),
     r"PointSets\.solid has 2 entries for 1 obstacles"),
])
def test_point_sets_api_errors(kwargs, needle):
    with pytest.raises(LarcInputError, match=needle):
        PointSets(**kwargs)


def test_a_convex_watertight_mesh_is_a_solid(tmp_path):
    """A mesh trimesh finds convex and watertight is one piece, stated as a solid; a box with a
    dent is its surface, in pieces."""
    import trimesh

    trimesh.creation.box([0.1, 0.2, 0.3]).export(tmp_path / "box.stl")
    dented = trimesh.creation.box([0.1, 0.2, 0.3])
    dented.vertices[0] *= 0.5  # a corner pushed inwards: not convex
    dented.export(tmp_path / "dented.stl")
    (tmp_path / "s.yaml").write_text("obstacles:\n  - {name: b, type: mesh, file: box.stl}\n"
                                     "  - {name: d, type: mesh, file: dented.stl}\n")
    ps = read_scene(tmp_path / "s.yaml").point_sets
    assert ps.solid == (True, False) and ps.owner.count(0) == 1
    assert ps.assumptions()[0] == "b: mesh, a solid (convex and watertight: its hull)"
    assert ps.assumptions()[1].startswith("d: mesh, its surface only")


def test_fcl_audit_refuses_point_sets():
    from experiments.collision import SceneBoxes

    with pytest.raises(ValueError, match="does not read meshes or point clouds"):
        SceneBoxes.from_scene(_camera_scene())


def test_explain_measures_a_piece_as_the_capsule_test_does(tmp_path, capsys):
    """`larc explain` on the camera cell: the worst leaf is decided by a bracket piece, and the
    distance it prints (to the piece's bounding box, what the capsule test measures) less the
    shell is the printed clearance; the figure is written."""
    import re

    from larc_jax.drivers.cli import main

    png = tmp_path / "why.png"
    assert main(["explain", str(EX / "reach_left.yaml"), "--scene", str(EX / "cell_camera.yaml"), "--leaf", "worst",
                 "-o", str(png)]) == 0
    out = capsys.readouterr().out
    assert "bracket[" in out and png.stat().st_size > 10_000
    g = float(re.search(r"clearance ([+-][\d.]+) mm", out).group(1))
    d, r, rho, b = (float(x) for x in re.search(
        r"distance ([\d.]+) mm vs shell r \+ margin \+ motion = ([\d.]+) \+ ([\d.]+) \+ ([\d.]+) mm", out).groups())
    assert d - (r + rho + b) == pytest.approx(g, abs=0.02)


def test_view_draws_shapes_and_pieces(tmp_path):
    """`larc view` on a certificate whose scene holds a box, a posed cylinder, the bracket and the
    cloud: one handle per box and shape, one point cloud for the pieces; a leaf recorded on a
    piece is drawn with that piece."""
    pytest.importorskip("viser")
    from larc_jax.drivers.cli import main
    from larc_jax.products.view import view
    from tests.browser import free_port

    for name in ("bracket.stl", "table_cloud.npy", "reach_left.yaml"):
        shutil.copy(EX / name, tmp_path / name)
    text = (EX / "cell_camera.yaml").read_text() + (
        "  - {name: post, type: cylinder, radius: 0.04, length: 0.45, pose: {position: [0.34, 0.0, 0.225]}}\n"
        "boxes:\n  - {name: tray, min: [0.10, -0.45, 0.0], max: [0.30, -0.30, 0.08]}\n")
    (tmp_path / "cell.yaml").write_text(text)
    cert = tmp_path / "cert.json"
    assert main(["certify", str(tmp_path / "reach_left.yaml"), "--scene", str(tmp_path / "cell.yaml"),
                 "--certificate", str(cert), "-q"]) == 0
    v = view(cert, port=free_port(), block=False)
    try:
        scene = v.data.items[0].scene
        assert scene.n_boxes == 1 and scene.shapes.count == 1 and scene.point_sets.count > 2
        assert len(v.box_handles) == 1 + 1 + 1  # the tray, the post, the pieces' points
        leaves = v.data.items[0].leaves
        on_piece = np.flatnonzero(leaves.box >= scene.n_boxes + scene.shapes.count)
        assert len(on_piece)
        v.select_leaf(int(on_piece[0]))
        assert v._leaf_nodes
    finally:
        v.stop()


def test_piece_tables_are_the_pieces():
    """:func:`piece_bounds` and :func:`padded_pieces` of convex_shapes (vectorised, what the
    obstacle sets and the cull are built from) against a loop over the pieces, on pieces of 1 to 64
    vertices; a piece wider than the table is refused."""
    rng = np.random.default_rng(5)
    pieces = tuple(rng.normal(0, 1, (n, 3)) for n in (1, 64, 3, 17, 2, 64, 5))
    ps = PointSets(kinds=("points",), names=("c",), files=("c.npy",), file_sha256=("0" * 64,), radius=(0.0,),
                   pieces=pieces, owner=(0,) * len(pieces))
    from larc_jax.obstacles.convex_shapes import padded_pieces, piece_bounds

    lo, hi = piece_bounds(ps)
    np.testing.assert_array_equal(lo, [p.min(axis=0) for p in pieces])
    np.testing.assert_array_equal(hi, [p.max(axis=0) for p in pieces])
    table = padded_pieces(ps, 64)
    for p, row in zip(pieces, table):
        np.testing.assert_array_equal(row, np.concatenate([p, np.repeat(p[:1], 64 - len(p), axis=0)]))
    with pytest.raises(ValueError, match="more than 32"):
        padded_pieces(ps, 32)
    empty = PointSets()
    assert piece_bounds(empty)[0].shape == (0, 3) and padded_pieces(empty, 4).shape == (0, 4, 3)
