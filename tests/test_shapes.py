"""Posed convex shapes (issue 22 item 1, first kinds): oriented boxes, spheres, cylinders and cones.

The JAX kernels equal their NumPy twins; every bound is one-sided against python-fcl (FCL's own
primitives with their rotations, distances sampled densely along each segment and over each
polytope); named edge cases; the float32 set contains the float64 one; the scene YAML
``obstacles:`` entries and their errors; and end to end: the example cell with a board turned
45 degrees certifies a move its axis-aligned bounding box blocks, the certificate verifies, an
FCL audit of the certified move finds every capsule more than the margin from every shape, and a
board slid toward the arm until certification flips still clears the margin there."""

from __future__ import annotations

import math
from pathlib import Path

import jax
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from larc_jax.errors import LarcInputError
from larc_jax.leaf.rounds import EARLY_ITERATIONS
from larc_jax.model.scene import Scene, read_scene, scene_from_dict
from larc_jax.model.shapes import Shapes, shape_project
from larc_jax.obstacles import AlignedBoxes, ConvexShapes, scene_obstacles, stack_scenes
from larc_jax.obstacles.polytope import GJK_ITERATIONS
from tests.capsule_audit import capsule_clearance, last_certified

EX = Path(__file__).resolve().parent.parent / "configs" / "examples"
QUAT_45Z = [0.0, 0.0, math.sin(math.pi / 8), math.cos(math.pi / 8)]


def _scene() -> Scene:
    """One of each kind, rotated, and an axis-aligned box."""
    rng = np.random.default_rng(3)
    quats = Rotation.random(4, random_state=rng).as_quat()
    return Scene(lo=[[0.3, -0.1, 0.0]], hi=[[0.4, 0.1, 0.2]], box_names=("crate",), shapes=Shapes(
        kinds=("box", "sphere", "cylinder", "cone"), names=("board", "ball", "post", "cone"),
        dims=[[0.5, 0.02, 0.3], [0.05, 0, 0], [0.04, 0.5, 0], [0.06, 0.2, 0]],
        p_world_shape=[[0.2, 0.3, 0.1], [-0.2, 0.1, 0.3], [0.0, -0.3, 0.25], [0.1, 0.1, 0.6]],
        R_world_shape=[Rotation.from_quat(q).as_matrix() for q in quats]))


def _fcl_objects(scene: Scene):
    from experiments.collision import SceneBoxes

    return SceneBoxes.from_scene(scene).objects


def _fcl_point_distance(obj, p) -> float:
    import fcl

    point = fcl.CollisionObject(fcl.Sphere(0.0), fcl.Transform(np.asarray(p, np.float64)))
    return max(fcl.distance(point, obj, fcl.DistanceRequest(), fcl.DistanceResult()), 0.0)


def _segments(rng, n):
    p_a = rng.uniform(-0.5, 0.7, (n, 3))
    p_b = p_a + rng.normal(0, 0.12, (n, 3))
    p_b[0] = p_a[0]  # a point
    return p_a, p_b


def _set_kernels(obstacles, p_a, p_b):
    return obstacles.segment_distances(p_a, p_b), obstacles.segment_lower_bounds(p_a, p_b), obstacles.point_distances(p_a)


def _random_polytope(rng, k=12):
    """A vertex table of one polytope (1, K, 3) in its link frame, and its centre."""
    V = rng.normal(0, 0.03, (1, k, 3)) * np.array([1.0, 1.5, 2.5])
    return V, V[0].mean(axis=0)


def _placements(rng, n):
    R = Rotation.random(n, random_state=rng).as_matrix()
    t = rng.uniform(-0.4, 0.6, (n, 3))
    return R, t


@pytest.fixture(scope="module")
def jax_values():
    """Every JAX kernel on the test scene in float64 and float32, one jitted call each."""
    rng = np.random.default_rng(0)
    scene = _scene()
    p_a, p_b = _segments(rng, 40)
    V, centre = _random_polytope(rng)
    R, t = _placements(rng, 20)
    R2, t2 = R[:10, None].repeat(2, 1), np.stack([t[:10], t[:10] + rng.normal(0, 0.05, (10, 3))], 1)
    R2[:, 1] = _placements(rng, 10)[0]  # unions of two placements (the swept stage)

    def polytopes(obstacles, V, centre, R, t, R2, t2):
        one = jax.vmap(lambda item, r, tt: type(item).polytope_lower_bound(item, V, 0, centre, r, tt), (None, 0, 0))
        over_items = jax.vmap(one, (0, None, None))
        bounds = jax.vmap(jax.vmap(lambda item, r, tt: type(item).polytope_bounds(item, V, 0, centre, r, tt,
                                                                                  EARLY_ITERATIONS), (None, 0, 0)),
                          (0, None, None))(obstacles, R, t)
        return over_items(obstacles, R, t), over_items(obstacles, R2, t2), *bounds

    out = {}
    with jax.enable_x64(True):
        for dtype in (np.float64, np.float32):
            st = stack_scenes([scene], dtype).take(0)
            cast = lambda x: np.asarray(x, dtype)  # noqa: E731
            seg = jax.jit(_set_kernels)(st, cast(p_a), cast(p_b))
            poly = jax.jit(polytopes)(st, cast(V), cast(centre), cast(R), cast(t), cast(R2), cast(t2))
            out[np.dtype(dtype).name] = [np.asarray(x, np.float64) for x in (*seg, *poly)]
    return scene, p_a, p_b, V, centre, R, t, R2, t2, out


def test_stack_chooses_the_kind_and_keeps_box_only_scenes_aligned():
    boxes_only = Scene(lo=[[0, 0, 0]], hi=[[1, 1, 1]])
    assert isinstance(stack_scenes([boxes_only], np.float32), AlignedBoxes)
    assert isinstance(scene_obstacles(boxes_only), AlignedBoxes)
    mixed = stack_scenes([boxes_only, _scene()], np.float32)
    assert isinstance(mixed, ConvexShapes) and mixed.n_items == 5
    assert mixed.mask.tolist() == [[True] + [False] * 4, [True] * 5]
    assert isinstance(scene_obstacles(_scene()), ConvexShapes)


def test_jax_kernels_equal_numpy_twins(jax_values):
    scene, p_a, p_b, V, centre, R, t, R2, t2, out = jax_values
    dist, lb, point, poly, poly2 = out["float64"][:5]
    obstacles = scene_obstacles(scene)
    for k in range(scene.n_obstacles):
        item = obstacles.take(k)
        for s in range(len(p_a)):
            assert dist[s, k] == pytest.approx(item.segment_distance_np(p_a[s], p_b[s]), abs=1e-12)
            assert lb[s, k] == pytest.approx(item.segment_lower_bound_np(p_a[s], p_b[s]), abs=1e-12)
            assert lb[s, k] <= dist[s, k] + 1e-15
        np.testing.assert_allclose(point[:, k], item.point_distance_np(p_a), atol=1e-12)
        for i in range(len(R)):
            assert poly[k, i] == pytest.approx(item.polytope_lower_bound_np(V[0], centre, R[i], t[i]), abs=1e-12)
        for i in range(len(R2)):
            assert poly2[k, i] == pytest.approx(item.polytope_lower_bound_np(V[0], centre, R2[i], t2[i]), abs=1e-12)


def test_upper_bound_twins_and_lower_bounds_below_it(jax_values):
    """``polytope_bounds`` (R8 of :mod:`larc_jax.obstacles.convex_shapes`): the kernel's (lower,
    upper) after the middle round's steps equal the NumPy twin's, the lower one is
    ``polytope_lower_bound``, and no lower bound after any number of steps (the full search's
    included) exceeds the upper bound after any number: a pair the hull stage stops because its
    upper bound is below the guard could not have passed with the full search. Over every kind
    (box, sphere, cylinder, cone, an axis-aligned box), placements that overlap included."""
    scene, _, _, V, centre, R, t, _, _, out = jax_values
    poly, lower, upper = (out["float64"][i] for i in (3, 5, 6))
    obstacles = scene_obstacles(scene)
    finite = 0
    for k in range(scene.n_obstacles):
        item = obstacles.take(k)
        for i in range(len(R)):
            lb, ub = item.polytope_bounds_np(V[0], centre, R[i], t[i], EARLY_ITERATIONS)
            assert (lower[k, i], upper[k, i]) == pytest.approx((lb, ub), abs=1e-12), (k, i)
            assert lb == item.polytope_lower_bound_np(V[0], centre, R[i], t[i], EARLY_ITERATIONS)
            assert poly[k, i] <= upper[k, i] + 1e-12  # the kernel's full search
            runs = [item.polytope_bounds_np(V[0], centre, R[i], t[i], n) for n in (0, 2, EARLY_ITERATIONS, 8,
                                                                                  GJK_ITERATIONS)]
            assert max(r[0] for r in runs) <= min(r[1] for r in runs) + 1e-12, (k, i, runs)
            finite += math.isfinite(ub)  # not the protocol's default (+inf: never stops)
    assert finite == scene.n_obstacles * len(R)


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_segment_bounds_never_exceed_fcl_and_are_tight(jax_values, dtype):
    """One-sided: every segment bound <= the densely sampled FCL distance (an upper bound of the
    true one). Tight: boxes and spheres within 0.1 mm of it (201 samples on a segment of <= ~0.4 m
    miss the minimum by ~1 um), a cylinder within a factor 1/sqrt 2 (its rim), a cone as its cylinder."""
    scene, p_a, p_b, *_, out = jax_values
    dist, lb, point = out[dtype][:3]
    objects = _fcl_objects(scene)
    s_grid = np.linspace(0.0, 1.0, 201)
    kinds = ("box",) * scene.n_boxes + scene.shapes.kinds
    for k, obj in enumerate(objects):
        for s in range(len(p_a)):
            sampled = min(_fcl_point_distance(obj, p_a[s] + x * (p_b[s] - p_a[s])) for x in s_grid)
            assert dist[s, k] <= sampled + 1e-12 and lb[s, k] <= dist[s, k] + 1e-12, (k, s)
            if kinds[k] in ("box", "sphere"):
                assert dist[s, k] >= sampled - 1e-4, (k, s, dist[s, k], sampled)
            elif kinds[k] == "cylinder":
                assert dist[s, k] >= sampled / math.sqrt(2) - 1e-4, (k, s, dist[s, k], sampled)
        # point_distance is only an upper-bound skip: it never exceeds the distance to the tested set
        np.testing.assert_array_less(lb[:, k] - 1e-9, point[:, k] + 1e-6)


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_polytope_bounds_never_exceed_fcl(jax_values, dtype):
    """The hull-stage bound on one placement and on a union of two (the swept stage) never exceeds
    FCL's distance from any point of the placed polytopes (vertices and random convex combinations)."""
    scene, p_a, p_b, V, centre, R, t, R2, t2, out = jax_values
    poly, poly2 = out[dtype][3:5]
    objects = _fcl_objects(scene)
    rng = np.random.default_rng(5)
    W = np.vstack([np.eye(V.shape[1]), rng.dirichlet(np.ones(V.shape[1]), 30)])  # points of the polytope
    for k, obj in enumerate(objects):
        for i in range(len(R)):
            pts = W @ (V[0] @ R[i].T + t[i])
            assert poly[k, i] <= min(_fcl_point_distance(obj, p) for p in pts) + 1e-12, (k, i)
        for i in range(len(R2)):
            pts = np.vstack([W @ (V[0] @ R2[i, m].T + t2[i, m]) for m in range(2)])
            assert poly2[k, i] <= min(_fcl_point_distance(obj, p) for p in pts) + 1e-12, (k, i)
    assert np.isfinite(poly).all() and (poly > 0).any()  # finite, and not vacuous


def test_float32_items_contain_the_float64_ones():
    """Outward rounding (R5): the float32 item's box and radius contain the float64 ones after
    the centre moved; the rotation's error bound covers the rounded matrix."""
    scene = _scene()
    s64, s32 = (stack_scenes([scene], dt).take(0) for dt in (np.float64, np.float32))
    shift = np.linalg.norm(s32.centre.astype(np.float64) - s64.centre, axis=-1)
    assert (s32.lo.astype(np.float64) <= s64.lo - shift[:, None]).all()
    assert (s32.hi.astype(np.float64) >= s64.hi + shift[:, None]).all()
    assert (s32.radius.astype(np.float64) >= s64.radius + shift).all()
    moved = np.linalg.norm((s32.rotation.astype(np.float64) - s64.rotation).reshape(-1, 9), axis=-1)
    assert (s32.rot_err.astype(np.float64) >= s64.rot_err + moved).all()
    assert (s64.rot_err[1:] > 0).all() and s64.rot_err[0] == 0  # the axis-aligned box: R = I exactly


def test_named_edge_cases_and_nan():
    scene = Scene(lo=np.zeros((0, 3)), hi=np.zeros((0, 3)), shapes=Shapes(
        kinds=("sphere", "cylinder", "box", "sphere"), names=("s", "c", "flat", "point"),
        dims=[[0.1, 0, 0], [0.1, 0.4, 0], [0.2, 0.2, 0.0], [0.0, 0, 0]],
        p_world_shape=np.zeros((4, 3)), R_world_shape=np.broadcast_to(np.eye(3), (4, 3, 3))))
    ob = scene_obstacles(scene)
    sphere, cyl, flat, point = (ob.take(k) for k in range(4))
    assert sphere.segment_distance_np([0.3, 0, 0], [0.3, 0, 0]) == pytest.approx(0.2, abs=1e-12)
    assert sphere.segment_distance_np([-1, 0.05, 0], [1, 0.05, 0]) <= 0  # through the ball
    assert cyl.segment_distance_np([0, 0, 0.5], [0, 0, 0.7]) == pytest.approx(0.3, abs=1e-12)  # above the top face
    assert cyl.segment_distance_np([0.3, 0, 0], [0.3, 0.1, 0.1]) == pytest.approx(0.2, abs=1e-12)  # beside it
    # beyond the rim (0.1 out radially and axially): true 0.1414, the bound at least 1/sqrt 2 of it
    rim = cyl.segment_distance_np([0.2, 0, 0.3], [0.2, 0, 0.3])
    assert 0.1 - 1e-12 <= rim <= math.hypot(0.1, 0.1)
    assert flat.segment_distance_np([0, 0, 0.5], [0, 0, 0.5]) == pytest.approx(0.5, abs=1e-12)  # zero thickness
    assert point.segment_distance_np([0, 0, 0.5], [0, 0, -0.5]) <= 0 < point.segment_distance_np([0, 0.1, 1], [0, 0.1, 2])
    nan = [math.nan, 0.0, 0.0]
    assert math.isnan(sphere.segment_distance_np(nan, [0, 0, 0]))
    assert math.isnan(cyl.polytope_lower_bound_np(np.eye(3), np.zeros(3), np.eye(3), np.array(nan)))
    assert np.allclose(shape_project(scene.shapes, 1, np.array([0.2, 0, 0.3])), [0.1, 0, 0.2])


# ---------------------------------------------------------------------------------------------- files

def _doc(entries, **extra):
    return {"frame": "base_link", "obstacles": entries, **extra}


def test_obstacles_yaml_reads_every_kind():
    scene = scene_from_dict(_doc([
        {"name": "board", "type": "box", "size": [0.6, 0.02, 0.5],
         "pose": {"position": [0.1, 0.2, 0.3], "orientation": QUAT_45Z}},
        {"name": "ball", "type": "sphere", "radius": 0.06},
        {"type": "cylinder", "radius": 0.04, "length": 0.45, "pose": {"position": [0.3, 0, 0.2]}},
        {"type": "cone", "radius": 0.05, "length": 0.1, "pose": {"orientation": [1, 0, 0, 0]}},
    ]))
    assert scene.n_boxes == 0 and scene.shapes.kinds == ("box", "sphere", "cylinder", "cone")
    assert scene.obstacle_names == ("board", "ball", "cylinder2", "cone3")
    np.testing.assert_allclose(scene.shapes.R_world_shape[0], Rotation.from_quat(QUAT_45Z).as_matrix(), atol=1e-15)
    np.testing.assert_array_equal(scene.shapes.R_world_shape[1], np.eye(3))  # no pose: identity at the origin
    np.testing.assert_array_equal(scene.shapes.dims[2], [0.04, 0.45, 0])
    np.testing.assert_allclose(scene.shapes.R_world_shape[3], np.diag([1.0, -1.0, -1.0]), atol=1e-15)


@pytest.mark.parametrize("entries,needle", [
    ([{"name": "p", "radius": 1}], r"obstacles\[0\]\.type must be one of box, sphere, cylinder, cone"),
    ([{"type": "sphere"}], r"obstacles\[0\]\.radius is missing"),
    ([{"type": "cylinder", "radius": 0.1}], r"obstacles\[0\]\.length is missing"),
    ([{"type": "sphere", "radius": -0.1}], r"obstacles\[0\]: radius must not be negative"),
    ([{"type": "box", "size": [1, 1]}], r"obstacles\[0\]\.size has 2 entries"),
    ([{"type": "box", "size": [1, 1, "x"]}], r"obstacles\[0\]\.size\[2\] is not a number"),
    ([{"type": "sphere", "radius": 0.1, "pose": {"orientation": [0, 0, 0, 2]}}], r"obstacles\[0\]\.pose\.orientation quaternion .* norm 2"),
    ([{"type": "sphere", "radius": 0.1, "pose": [0, 0, 0]}], r"obstacles\[0\]\.pose must be a mapping"),
    ([{"type": "sphere", "radius": math.inf}], r"obstacles\[0\]\.radius must be finite"),
    ([{"type": "capsule", "radius": 0.1}], r"obstacles\[0\]\.type must be one of box, sphere, cylinder, cone, mesh, points"),
    ({"type": "sphere"}, r"obstacles must be a list"),
])
def test_obstacles_yaml_errors_name_the_entry(entries, needle):
    with pytest.raises(LarcInputError, match=needle) as err:
        scene_from_dict(_doc(entries), source="cell.yaml")
    assert str(err.value).startswith("cell.yaml: ")


def test_scene_needs_boxes_or_obstacles():
    with pytest.raises(LarcInputError, match="missing field 'boxes' or 'obstacles'"):
        scene_from_dict({"frame": "base_link"})
    assert scene_from_dict({"frame": "base_link", "obstacles": []}).n_obstacles == 0


# ---------------------------------------------------------------------------------------------- end to end

@pytest.fixture(scope="module")
def cell():
    from larc_jax.model.trajectory_files import read_trajectory

    return read_trajectory(EX / "reach_left.yaml"), read_scene(EX / "cell_shapes.yaml", frame="base_link")


def _board_aabb(scene: Scene) -> Scene:
    """The cell with its board replaced by the board's axis-aligned bounding box (rounded out)."""
    k = scene.shapes.names.index("board")
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * scene.shapes.dims[k] / 2
    world = corners @ scene.shapes.R_world_shape[k].T + scene.shapes.p_world_shape[k]
    keep = [i for i in range(scene.shapes.count) if i != k]
    sh = scene.shapes
    return Scene(lo=np.vstack([scene.lo, world.min(0) - 1e-9]), hi=np.vstack([scene.hi, world.max(0) + 1e-9]),
                 box_names=scene.box_names + ("board_aabb",), shapes=Shapes(
                     kinds=tuple(sh.kinds[i] for i in keep), names=tuple(sh.names[i] for i in keep),
                     dims=sh.dims[keep], p_world_shape=sh.p_world_shape[keep], R_world_shape=sh.R_world_shape[keep]))


def test_example_cell_certifies_what_the_boards_aabb_blocks(cell, robot, capsules):
    from larc_jax import certify

    traj, scene = cell
    aabb = _board_aabb(scene)
    for enclosure in ("capsules", "hull"):
        res = certify([traj, traj], [scene, aabb], robot, capsules, method="larc", enclosure=enclosure)
        assert [r.certified for r in res] == [True, False], enclosure
    ref = certify([traj, traj], [scene, aabb], robot, capsules, method="reference", enclosure="capsules")
    assert [r.certified for r in ref] == [True, False]


def _audit_clearance(robot, capsules, traj, scene, n=400) -> float:
    """FCL's smallest capsule-obstacle distance over ``n`` states (tests/capsule_audit.py)."""
    return capsule_clearance(robot, capsules, traj, _fcl_objects(scene), n)


def test_certified_move_clears_every_shape_in_an_fcl_audit_and_verifies(cell, robot, capsules, tmp_path):
    from larc_jax import certify, verify_certificate, write_certificate
    from larc_jax.defaults import DEFAULT_MARGIN_M

    traj, scene = cell
    res = certify(traj, scene, robot, capsules, method="larc", enclosure="capsules")
    assert res[0].certified
    assert _audit_clearance(robot, capsules, traj, scene) > DEFAULT_MARGIN_M
    path = tmp_path / "cert.json"
    write_certificate(path, res, [traj], [scene], robot, capsules, trajectory_files=[EX / "reach_left.yaml"],
                      scene_files=[EX / "cell_shapes.yaml"])
    report = verify_certificate(path)
    assert report.scene_files[0].boxes == ("tray", "board", "post", "ball")


def test_board_slid_to_the_flip_still_clears_the_margin(cell, robot, capsules):
    """Slide the board toward the arm (along its normal) until the capsule test stops certifying
    (bisection on the reference scheduler): the last certified position's true clearance (FCL
    capsules vs the posed box) exceeds the margin, and is within the motion bound's slack."""
    from larc_jax import certify
    from larc_jax.defaults import DEFAULT_MARGIN_M

    traj, scene = cell
    k = scene.shapes.names.index("board")
    normal = scene.shapes.R_world_shape[k][:, 1]  # the board's thin axis, toward the arm
    normal = normal if normal @ -scene.shapes.p_world_shape[k] > 0 else -normal

    def moved(s):
        p = scene.shapes.p_world_shape.copy()
        p[k] = p[k] + s * normal
        sh = scene.shapes
        return Scene(lo=scene.lo, hi=scene.hi, box_names=scene.box_names,
                     shapes=Shapes(kinds=sh.kinds, names=sh.names, dims=sh.dims, p_world_shape=p, R_world_shape=sh.R_world_shape))

    def ok(s):
        return certify(traj, moved(s), robot, capsules, method="reference", enclosure="capsules")[0].certified

    lo = last_certified(ok, 0.0, 0.08, 12)
    clearance = _audit_clearance(robot, capsules, traj, moved(lo))
    assert clearance > DEFAULT_MARGIN_M
    assert clearance - DEFAULT_MARGIN_M < 0.03  # the depth-9 motion bound's slack, not a vacuous pass


def test_readme_obstacle_kinds_example_is_the_example_file():
    import re

    import yaml

    readme = (Path(__file__).resolve().parent.parent / "README.md").read_text()
    section = readme.split("### Obstacle kinds", 1)[1].split("\n### ", 1)[0]
    (block,) = re.findall(r"```yaml\n(.*?)```", section, re.S)
    example = read_scene(EX / "cell_shapes.yaml", frame="base_link")
    scene = scene_from_dict(yaml.safe_load(block))
    assert scene.obstacle_names == example.obstacle_names and scene.shapes.kinds == example.shapes.kinds
    for field in ("dims", "p_world_shape", "R_world_shape"):
        np.testing.assert_array_equal(getattr(scene.shapes, field), getattr(example.shapes, field))
    np.testing.assert_array_equal(scene.lo, example.lo)


def test_boxes_only_shape_sets_skip_the_capsule_test_with_the_same_bounds():
    """A set without a round item is built with any_rounded False (static: the kernels skip the
    capsule test); its bounds equal those of the same set with the flag forced on."""
    import dataclasses

    rng = np.random.default_rng(9)
    scene = Scene(lo=[[0.3, -0.1, 0.0]], hi=[[0.4, 0.1, 0.2]], shapes=Shapes(
        kinds=("box",), names=("board",), dims=[[0.5, 0.02, 0.3]], p_world_shape=[[0.2, 0.3, 0.1]],
        R_world_shape=[Rotation.from_quat(QUAT_45Z).as_matrix()]))
    plain = stack_scenes([scene], np.float64).take(0)
    assert plain.any_rounded is False and _scene_set_any_rounded()
    forced = dataclasses.replace(plain, any_rounded=True)
    p_a, p_b = _segments(rng, 12)
    with jax.enable_x64(True):
        a, b = (np.asarray(jax.jit(_set_kernels)(s, p_a, p_b)[0]) for s in (plain, forced))
    np.testing.assert_array_equal(a, b)


def _scene_set_any_rounded() -> bool:
    return stack_scenes([_scene()], np.float64).any_rounded is True
