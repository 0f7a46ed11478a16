"""Input readers: MoveIt .scene text, ros2 topic echo / RobotTrajectory / DisplayTrajectory YAML,
CSV, missing velocities and finite differences, and the CLI on the example files."""

from __future__ import annotations

import itertools
import logging
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from larc_jax.errors import LarcInputError
from larc_jax.model.scene import read_moveit_scene, read_scene
from larc_jax.model.trajectory import finite_difference_velocities
from larc_jax.model.trajectory_files import read_trajectory, trajectory_from_msg, write_trajectory

EXAMPLES = Path(__file__).resolve().parent.parent / "configs" / "examples"
NAMES = [f"joint{i}" for i in range(1, 7)]

# --------------------------------------------------------------------------------------------
# MoveIt .scene

OLD_LAYOUT = """(noname)+
* table_top
1
box
0.4 0.6 0.02
0.5 0 -0.05
0 0 0 1
0 0 0 0
.
"""

NEW_LAYOUT = """bench
* table_top
0.5 0 -0.05
0 0 0 1
1
box
0.4 0.6 0.02
0 0 0
0 0 0 1
0.8 0.8 0.8 1
0
.
"""


def _write(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


@pytest.mark.parametrize("text", [OLD_LAYOUT, NEW_LAYOUT], ids=["old", "new"])
def test_scene_identity_box_is_exact(tmp_path, caplog, text):
    path = _write(tmp_path, "cell.scene", text)
    with caplog.at_level(logging.WARNING):
        scene = read_scene(path, frame="base_link")
    assert not caplog.records
    assert scene.box_names == ("table_top",) and scene.frame == "base_link" and scene.name == "cell"
    center, half = np.array([0.5, 0.0, -0.05]), np.array([0.4, 0.6, 0.02]) / 2
    np.testing.assert_array_equal(scene.lo[0], center - half)
    np.testing.assert_array_equal(scene.hi[0], center + half)


def _corners(center, rot, size):
    half = np.asarray(size) / 2
    return np.array([center + rot @ (half * s) for s in itertools.product([-1, 1], repeat=3)])


def test_rotated_box_is_kept_as_a_posed_box(tmp_path, caplog):
    """A rotated box is no longer replaced by its enclosing AABB: it is a posed shape with the
    file's rotation (quaternion normalised), and nothing is warned."""
    text = NEW_LAYOUT.replace("0.5 0 -0.05\n0 0 0 1\n1", "0.5 0 0.01\n0 0 0.7071068 0.7071068\n1")
    with caplog.at_level(logging.WARNING):
        scene = read_moveit_scene(_write(tmp_path, "rot.scene", text))
    assert not caplog.records and scene.n_boxes == 0 and scene.shapes.kinds == ("box",)
    assert scene.obstacle_names == ("table_top",)
    q = np.array([0, 0, 0.7071068, 0.7071068])
    np.testing.assert_allclose(scene.shapes.R_world_shape[0], Rotation.from_quat(q / np.linalg.norm(q)).as_matrix(),
                               atol=1e-15)
    np.testing.assert_array_equal(scene.shapes.p_world_shape[0], [0.5, 0, 0.01])
    np.testing.assert_array_equal(scene.shapes.dims[0], [0.4, 0.6, 0.02])


def test_example_scene_rotated_post_is_posed():
    scene = read_scene(EXAMPLES / "pick.scene")
    assert scene.box_names == ("crate",) and scene.shapes.names == ("post",)
    assert scene.obstacle_names == ("crate", "post")
    np.testing.assert_allclose(scene.lo[0], [-0.8, -0.8, 0.0], atol=1e-15)
    np.testing.assert_allclose(scene.hi[0], [-0.6, -0.6, 0.2], atol=1e-15)
    rot = Rotation.from_quat([0, 0, 0.258819, 0.965926]).as_matrix()   # (x, y, z, w)
    np.testing.assert_allclose(scene.shapes.R_world_shape[0], rot, atol=1e-6)
    np.testing.assert_array_equal(scene.shapes.p_world_shape[0], [0.0, -0.6, 0.25])


def test_scene_nearly_identity_box_is_posed_not_rounded_away(tmp_path, caplog):
    # A rotation of 1e-10 rad is not the identity: the box keeps it (a posed box), never the
    # unrotated box.
    angle = 1e-10
    q = Rotation.from_euler("z", angle).as_quat()
    size, center = [2.0, 1.0, 0.5], np.array([0.3, -0.2, 0.1])
    fmt = lambda v: " ".join(repr(float(x)) for x in v)  # noqa: E731
    text = (f"s\n* wall\n{fmt(center)}\n{fmt(q)}\n1\nbox\n{fmt(size)}\n0 0 0\n0 0 0 1\n"
            "0 0 0 0\n0\n.\n")
    with caplog.at_level(logging.WARNING):
        scene = read_scene(_write(tmp_path, "near.scene", text))
    assert not caplog.records and scene.n_boxes == 0 and scene.shapes.count == 1
    assert scene.shapes.R_world_shape[0][1, 0] > 0  # the 1e-10 rad rotation is kept


def test_scene_object_pose_composed_with_shape_pose(tmp_path):
    r_obj = Rotation.from_euler("xyz", [0.3, -0.7, 1.1])
    r_shape = Rotation.from_euler("xyz", [-0.4, 0.2, 0.9])
    p_obj, p_shape, size = np.array([0.3, -0.2, 0.4]), np.array([0.05, 0.1, -0.02]), [0.12, 0.3, 0.07]
    fmt = lambda v: " ".join(repr(float(x)) for x in v)  # noqa: E731
    text = (f"s\n* tilted\n{fmt(p_obj)}\n{fmt(r_obj.as_quat())}\n1\nbox\n{fmt(size)}\n"
            f"{fmt(p_shape)}\n{fmt(r_shape.as_quat())}\n0 0 0 0\n0\n.\n")
    scene = read_scene(_write(tmp_path, "tilted.scene", text))
    np.testing.assert_allclose(scene.shapes.R_world_shape[0], (r_obj * r_shape).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(scene.shapes.p_world_shape[0], p_obj + r_obj.as_matrix() @ p_shape, atol=1e-12)
    np.testing.assert_array_equal(scene.shapes.dims[0], size)


def test_scene_multi_shape_object_and_empty_scene(tmp_path):
    text = ("s\n* shelf\n0 0 0\n0 0 0 1\n2\nbox\n1 1 1\n0 0 0\n0 0 0 1\n0 0 0 0\n"
            "box\n2 2 2\n5 0 0\n0 0 0 1\n0 0 0 0\n1\ngrasp 0 0 1 0 0 0 1\n.\n")
    scene = read_moveit_scene(_write(tmp_path, "shelf.scene", text))
    assert scene.box_names == ("shelf[0]", "shelf[1]")
    np.testing.assert_array_equal(scene.lo, [[-0.5] * 3, [4, -1, -1]])
    empty = read_moveit_scene(_write(tmp_path, "empty.scene", "(noname)\n.\n"))
    assert empty.n_boxes == 0


@pytest.mark.parametrize("shape,dims", [("octree", "1"), ("torus", "1 1")])
def test_scene_unsupported_shape_refused(tmp_path, shape, dims):
    text = f"s\n* ball\n0 0 0\n0 0 0 1\n1\n{shape}\n{dims}\n0 0 0\n0 0 0 1\n0 0 0 0\n0\n.\n"
    path = _write(tmp_path, "ball.scene", text)
    with pytest.raises(LarcInputError) as exc:
        read_scene(path)
    msg = str(exc.value)
    assert msg.startswith(f"{path}:6: ") and "'ball'" in msg and shape in msg and "\n" not in msg


def _mesh_scene(V, F, p_obj, q_obj, p_shape, q_shape) -> str:
    """One object holding one mesh, as ``PlanningScene::saveGeometryToStream`` and
    ``shapes::saveAsText`` write it (newer layout)."""
    nums = lambda a: " ".join(repr(float(x)) for x in a)  # noqa: E731
    return ("cell\n* fixture\n" + nums(p_obj) + "\n" + nums(q_obj) + "\n1\nmesh\n" + f"{len(V)} {len(F)}\n"
            + "".join(nums(v) + "\n" for v in V) + "".join(" ".join(map(str, f)) + "\n" for f in F)
            + nums(p_shape) + "\n" + nums(q_shape) + "\n0.5 0.5 0.5 1\n0\n.\n")


@pytest.mark.parametrize("stl", ["bracket.stl", "box"])
def test_scene_mesh_reads_as_the_yaml_mesh_of_its_triangles(tmp_path, stl):
    """A .scene mesh (the example bracket, non-convex; a box, convex and watertight) is the mesh
    obstacle a YAML ``type: mesh`` entry of the same triangles and the composed pose gives: the
    same pieces to 1e-15 m (the YAML pose is a quaternion, the .scene's the product of two
    rotation matrices) and the same solid or surface statement."""
    import trimesh
    import yaml

    mesh = (trimesh.load(EXAMPLES / stl, force="mesh") if stl.endswith(".stl")
            else trimesh.creation.box(extents=[0.3, 0.2, 0.1]))
    mesh.export(tmp_path / "m.stl")
    mesh = trimesh.load(tmp_path / "m.stl", force="mesh", process=True)  # as a scene's mesh file is read
    r_obj, r_shape = Rotation.from_euler("xyz", [0.3, -0.2, 0.9]), Rotation.from_euler("z", 0.4)
    p_obj, p_shape = np.array([0.4, -0.1, 0.2]), np.array([0.0, 0.05, 0.01])
    path = _write(tmp_path, "cell.scene", _mesh_scene(mesh.vertices, mesh.faces, p_obj, r_obj.as_quat(), p_shape,
                                                      r_shape.as_quat()))
    scene = read_scene(path)
    R = (r_obj * r_shape).as_matrix()
    pose = {"position": (p_obj + r_obj.as_matrix() @ p_shape).tolist(),
            "orientation": (r_obj * r_shape).as_quat().tolist()}
    (tmp_path / "cell.yaml").write_text(yaml.safe_dump({"frame": "base_link", "obstacles": [
        {"name": "fixture", "type": "mesh", "file": "m.stl", "pose": pose}]}))
    want = read_scene(tmp_path / "cell.yaml").point_sets
    got = scene.point_sets
    assert got.kinds == ("mesh",) and got.names == ("fixture",) and scene.n_boxes == 0 and scene.shapes.count == 0
    assert got.files == (str(path),) and got.assumptions() == want.assumptions()
    assert got.solid == want.solid == ((stl == "box"),)
    # The YAML pose goes through a quaternion; the .scene's composed rotation is the matrix product.
    assert len(got.pieces) == len(want.pieces)
    for a, b in zip(got.pieces, want.pieces):
        np.testing.assert_allclose(a, b, atol=1e-15)
    world = mesh.vertices @ R.T + p_obj + r_obj.as_matrix() @ p_shape
    assert {tuple(np.round(v, 12)) for piece in got.pieces for v in piece} == {tuple(np.round(v, 12)) for v in world}


@pytest.mark.parametrize("body,line,needle", [
    ("3 1\n0 0 0\n1 0 0\n0 1 0\n0 1 3\n", 11, "triangle 0 names vertex 3, but the mesh has 3 vertices"),
    ("3 0\n0 0 0\n1 0 0\n0 1 0\n", 7, "has no triangles"),
    ("3 1\n0 0 0\n1 0 x\n0 1 0\n0 1 2\n", 9, "'x' is not a number"),
    ("3 1\n0 0 0\n1 0 0\n0 1 0\n0 1 -2\n", 11, "'-2' is not a non-negative integer"),
])
def test_scene_mesh_errors_name_file_and_line(tmp_path, body, line, needle):
    text = "s\n* m\n0 0 0\n0 0 0 1\n1\nmesh\n" + body + "0 0 0\n0 0 0 1\n0 0 0 0\n0\n.\n"
    path = _write(tmp_path, "bad.scene", text)
    with pytest.raises(LarcInputError) as exc:
        read_scene(path)
    assert str(exc.value).startswith(f"{path}:{line}: ") and needle in str(exc.value), str(exc.value)


@pytest.mark.parametrize("shape,dims,want", [("sphere", "0.1", [0.1, 0, 0]), ("cylinder", "0.1 0.4", [0.1, 0.4, 0]),
                                             ("cone", "0.1 0.2", [0.1, 0.2, 0])])
def test_scene_round_shapes_read_with_pose(tmp_path, shape, dims, want):
    q = Rotation.from_euler("xyz", [0.2, 0.4, -0.3]).as_quat()
    text = (f"s\n* thing\n0.1 0.2 0.3\n{' '.join(map(repr, q.tolist()))}\n1\n{shape}\n{dims}\n0 0 0.05\n0 0 0 1\n"
            "0 0 0 0\n0\n.\n")
    scene = read_scene(_write(tmp_path, "round.scene", text))
    R = Rotation.from_quat(q).as_matrix()
    assert scene.shapes.kinds == (shape,) and scene.n_boxes == 0
    np.testing.assert_array_equal(scene.shapes.dims[0], want)
    np.testing.assert_allclose(scene.shapes.p_world_shape[0], [0.1, 0.2, 0.3] + R @ [0, 0, 0.05], atol=1e-15)
    np.testing.assert_allclose(scene.shapes.R_world_shape[0], R, atol=1e-15)


@pytest.mark.parametrize("text,line,needle", [
    ("s\n* a\n1\nbox\n1 x 1\n0 0 0\n0 0 0 1\n0 0 0 0\n.\n", 5, "'x' is not a number"),
    ("s\n* a\n1\nbox\n1 1 1\n0 0 0\n0 0 0 1\n0 0 0 0\n", 8, "no '.' end line"),
    ("s\n* a\n1\nbox\n1 1 1\n0 0 0\n0 0 0 1\n0 0 0 0\n.\n* b\n", 10, "after the end line"),
    ("s\n* a\n1\nbox\n1 1 -1\n0 0 0\n0 0 0 1\n0 0 0 0\n.\n", 5, "negative"),
    ("s\n* a\n1\nbox\n1 1 1\n0 0 0\n0 0 0 0\n0 0 0 0\n.\n", 7, "norm"),
    ("s\n* a\n1\nbox\n1 1 nan\n0 0 0\n0 0 0 1\n0 0 0 0\n.\n", 5, "not finite"),
    ("s\nbox\n.\n", 2, "expected '* object name'"),
    ("s\n* a\n1\nbox\n1 1 1\n0 0 0\n0 0 0 1\n0 0 0 0\n* a\n1\nbox\n1 1 1\n0 0 0\n0 0 0 1\n0 0 0 0\n.\n",
     9, "appears twice"),
])
def test_scene_parse_errors_name_file_and_line(tmp_path, text, line, needle):
    path = _write(tmp_path, "bad.scene", text)
    with pytest.raises(LarcInputError) as exc:
        read_scene(path)
    assert str(exc.value).startswith(f"{path}:{line}: ") and needle in str(exc.value)


# --------------------------------------------------------------------------------------------
# Trajectories

def _block(values, indent):
    return "".join(f"\n{indent}- {v!r}" for v in values)


def _echo(points, *, vel=True, extra=""):
    """A JointTrajectory as `ros2 topic echo` prints it (block lists, header, ---)."""
    out = ("header:\n  stamp:\n    sec: 0\n    nanosec: 0\n  frame_id: ''\njoint_names:"
           + _block(NAMES, "") + "\npoints:")
    for t, q, qd in points:
        out += "\n- positions:" + _block(q, "  ")
        out += ("\n  velocities:" + _block(qd, "  ")) if vel else "\n  velocities: []"
        out += (f"\n  accelerations: []\n  effort: []\n  time_from_start:\n    sec: {int(t)}"
                f"\n    nanosec: {int(round((t - int(t)) * 1e9))}")
    return out + "\n---\n" + extra


POINTS = [
    (0.0, [0.0, 0.5, -0.8, 0.0, 0.3, 0.0], [0.0] * 6),
    (1.5, [0.6, 0.9, -1.1, 0.2, 0.4, 0.5], [0.1, 0, 0, 0, 0, 0]),
    (3.0, [1.2, 0.9, -1.1, 0.2, 0.4, 0.5], [0.0] * 6),
]


def _same(a, b):
    np.testing.assert_array_equal(a.t, b.t)
    np.testing.assert_array_equal(a.q, b.q)
    np.testing.assert_array_equal(a.qd, b.qd)
    assert a.joint_names == b.joint_names


def test_example_echo_and_csv_agree(robot):
    echo = read_trajectory(EXAMPLES / "echo_joint_trajectory.yaml", robot)
    table = read_trajectory(EXAMPLES / "traj.csv", robot)
    _same(echo, table)
    assert echo.n_waypoints == 5 and echo.duration == 2.0 and echo.id == "echo_joint_trajectory"


def test_echo_flow_lists_and_old_array_repr(tmp_path, robot):
    block = read_trajectory(_write(tmp_path, "block.yaml", _echo(POINTS)), robot)
    flow = "joint_names: [" + ", ".join(NAMES) + "]\npoints:\n" + "".join(
        f"- positions: array('d', {q!r})\n  velocities: [{', '.join(map(repr, qd))}]\n"
        f"  accelerations: []\n  time_from_start: {{sec: {int(t)}, nanosec: {int(round((t % 1) * 1e9))}}}\n"
        for t, q, qd in POINTS) + "---\n"
    _same(block, read_trajectory(_write(tmp_path, "flow.yaml", flow), robot))
    ros1 = _echo(POINTS).replace("sec:", "secs:").replace("nanosecs:", "nsecs:")
    _same(block, read_trajectory(_write(tmp_path, "ros1.yaml", "---\n" + ros1), robot))


def _indent(text, n):
    return "\n".join((" " * n + line) if line else line for line in text.split("\n"))


def _robot_trajectory(jt_yaml, multi="  header:\n    frame_id: ''\n  joint_names: []\n  points: []"):
    return "joint_trajectory:\n" + _indent(jt_yaml.replace("---\n", ""), 2) + "\nmulti_dof_joint_trajectory:\n" + multi + "\n"


def test_robot_and_display_trajectory(tmp_path, robot):
    plain = read_trajectory(_write(tmp_path, "plain.yaml", _echo(POINTS)), robot)
    rt = _robot_trajectory(_echo(POINTS))
    _same(plain, read_trajectory(_write(tmp_path, "rt.yaml", rt + "---\n"), robot))
    display = "model_id: piper\ntrajectory:\n- " + _indent(rt, 2).lstrip() + "\ntrajectory_start: {}\n"
    _same(plain, read_trajectory(_write(tmp_path, "display.yaml", display), robot))
    # field paths carry the prefix
    bad = rt.replace("- 1.2\n", "- 9.0\n")
    with pytest.raises(LarcInputError, match=r"joint_trajectory\.points\[2\]\.positions\[0\]"):
        read_trajectory(_write(tmp_path, "rt_bad.yaml", bad), robot)
    two = "trajectory:\n- " + _indent(rt, 2).lstrip() + "\n- " + _indent(rt, 2).lstrip() + "\n"
    with pytest.raises(LarcInputError, match="holds 2 RobotTrajectory"):
        read_trajectory(_write(tmp_path, "two.yaml", two), robot)


def test_multi_dof_refused(tmp_path, robot):
    multi = ("  joint_names: [virtual_joint]\n  points:\n  - transforms: []\n    velocities: []\n"
             "    time_from_start: {sec: 0, nanosec: 0}")
    path = _write(tmp_path, "mdof.yaml", _robot_trajectory(_echo(POINTS), multi))
    with pytest.raises(LarcInputError, match=r"mdof\.yaml: multi_dof_joint_trajectory has 1 points"):
        read_trajectory(path, robot)


def test_multiple_messages_refused(tmp_path, robot):
    path = _write(tmp_path, "many.yaml", _echo(POINTS) * 3)
    with pytest.raises(LarcInputError) as exc:
        read_trajectory(path, robot)
    assert "holds 3 messages" in str(exc.value) and "--once" in str(exc.value)


def test_missing_velocities_refused_with_hint(tmp_path, robot):
    for name, text in [("empty_vel.yaml", _echo(POINTS, vel=False)),
                       ("no_vel.yaml", _echo(POINTS, vel=False).replace("  velocities: []\n", ""))]:
        with pytest.raises(LarcInputError) as exc:
            read_trajectory(_write(tmp_path, name, text), robot)
        msg = str(exc.value)
        assert name in msg and "points[0].velocities" in msg and "--velocities finite-difference" in msg
    csv = "t," + ",".join(NAMES) + "\n" + "".join(f"{t}," + ",".join(map(repr, q)) + "\n" for t, q, _ in POINTS)
    with pytest.raises(LarcInputError, match="--velocities finite-difference"):
        read_trajectory(_write(tmp_path, "pos.csv", csv), robot)
    fd = read_trajectory(tmp_path / "pos.csv", robot, velocities="finite-difference")
    fd_yaml = read_trajectory(tmp_path / "empty_vel.yaml", robot, velocities="finite-difference")
    _same(fd, fd_yaml)


def test_finite_differences_exact_for_quadratics():
    a, b, c = np.array([0.1, -0.3]), np.array([0.5, 0.2]), np.array([-0.25, 0.4])
    for t in (np.linspace(0.0, 2.0, 9), np.array([0.0, 0.1, 0.35, 0.4, 1.0, 1.7])):
        q = a + b * t[:, None] + c * t[:, None] ** 2
        np.testing.assert_allclose(finite_difference_velocities(t, q), b + 2 * c * t[:, None],
                                   rtol=0, atol=1e-12)
    # uniform grid: interior knots are the plain central difference
    t = np.linspace(0.0, 1.0, 5)
    q = np.sin(3 * t)[:, None]
    qd = finite_difference_velocities(t, q)
    np.testing.assert_allclose(qd[1:-1, 0], (q[2:, 0] - q[:-2, 0]) / (t[2:] - t[:-2]), atol=1e-14)
    np.testing.assert_array_equal(finite_difference_velocities([0.0, 2.0], [[0.0], [1.0]]), [[0.5], [0.5]])
    with pytest.raises(LarcInputError, match=r"points\[2\]\.time_from_start .* strictly increasing"):
        finite_difference_velocities([0.0, 1.0, 1.0], np.zeros((3, 1)))


def test_finite_difference_ignores_recorded_with_warning(tmp_path, robot, caplog):
    path = _write(tmp_path, "rec.yaml", _echo(POINTS))
    with caplog.at_level(logging.WARNING):
        traj = read_trajectory(path, robot, velocities="finite-difference")
    assert "ignoring the recorded velocities" in caplog.text
    q = np.array([p[1] for p in POINTS])
    np.testing.assert_allclose(traj.qd, np.gradient(q, [0.0, 1.5, 3.0], axis=0, edge_order=2))
    with pytest.raises(LarcInputError, match="velocities must be one of"):
        read_trajectory(path, robot, velocities="spline")


def test_yaml_csv_round_trips(tmp_path, robot):
    yaml_traj = read_trajectory(_write(tmp_path, "a.yaml", _echo(POINTS)), robot)
    write_trajectory(tmp_path / "a.csv", yaml_traj)
    assert (tmp_path / "a.csv").read_text().startswith("t,joint1,")
    _same(yaml_traj, read_trajectory(tmp_path / "a.csv", robot))
    csv_traj = read_trajectory(EXAMPLES / "traj.csv", robot)
    write_trajectory(tmp_path / "b.yaml", csv_traj)
    write_trajectory(tmp_path / "b.json", csv_traj)
    _same(csv_traj, read_trajectory(tmp_path / "b.yaml", robot))
    _same(csv_traj, read_trajectory(tmp_path / "b.json", robot))


def test_csv_qd_prefix_any_column_order(tmp_path, robot):
    ref = read_trajectory(EXAMPLES / "traj.csv", robot)
    order = [5, 2, 0, 1, 4, 3]
    header = ["time"] + [f"qd_{NAMES[j]}" for j in order] + [NAMES[j] for j in order[::-1]]
    rows = [",".join(header)]
    for k in range(ref.n_waypoints):
        rows.append(", ".join(repr(float(v)) for v in
                              [ref.t[k], *ref.qd[k, order], *ref.q[k, order[::-1]]]))
    text = "# exported\n\n" + "\n".join(rows) + "\n\n"
    _same(ref, read_trajectory(_write(tmp_path, "perm.csv", text), robot))


CSV_HEAD = "t," + ",".join(NAMES) + "," + ",".join(f"{n}_vel" for n in NAMES)
CSV_ROWS = ["0.0,0,0.5,-0.8,0,0.3,0,0,0,0,0,0,0", "1.0,0.6,0.9,-1.1,0.2,0.4,0.5,0,0,0,0,0,0",
            "2.0,1.2,0.9,-1.1,0.2,0.4,0.5,0,0,0,0,0,0"]


@pytest.mark.parametrize("head,rows,needle", [
    (CSV_HEAD, [CSV_ROWS[0], CSV_ROWS[1].replace("-1.1", "nan"), CSV_ROWS[2]], ":3: column 'joint3': 'nan' is not finite"),
    (CSV_HEAD, [CSV_ROWS[0], CSV_ROWS[1], CSV_ROWS[2].replace("0.2,0.4", "0.2,abc")], ":4: column 'joint5': 'abc' is not a number"),
    (CSV_HEAD, [CSV_ROWS[0], CSV_ROWS[1] + ",7", CSV_ROWS[2]], ":3: row has 14 cells, the header has 13"),
    (CSV_HEAD.replace("t,", "stamp,", 1), CSV_ROWS, ":1: header needs exactly one time column"),
    (CSV_HEAD.replace("joint6_vel", "joint7_vel"), CSV_ROWS, "velocity column 'joint7_vel' names joint 'joint7'"),
    (CSV_HEAD.replace(",joint6_vel", "") , [r.rsplit(",", 1)[0] for r in CSV_ROWS], "no velocity column for ['joint6']"),
    (CSV_HEAD.replace("joint2,", "joint1,", 1), CSV_ROWS, "header names column 'joint1' twice"),
    (CSV_HEAD.replace("joint6,", "joint7,", 1).replace("joint6_vel", "joint7_vel"), CSV_ROWS, "joint_names"),
    (CSV_HEAD, [CSV_ROWS[0], CSV_ROWS[2], CSV_ROWS[1]], "line 4 column 't' (1.0 s) is not after line 3"),
    (CSV_HEAD, [CSV_ROWS[0], CSV_ROWS[1].replace("0.6,", "9.0,", 1), CSV_ROWS[2]], "line 3 column 'joint1' = 9.0"),
    (CSV_HEAD, [CSV_ROWS[0]], "at least 2 waypoint rows"),
])
def test_csv_errors_name_file_line_column(tmp_path, robot, head, rows, needle):
    path = _write(tmp_path, "bad.csv", "\n".join([head, *rows]) + "\n")
    with pytest.raises(LarcInputError) as exc:
        read_trajectory(path, robot)
    assert str(exc.value).startswith(str(path)) and needle in str(exc.value), str(exc.value)


def test_waypoint_limit_applies_to_csv_and_yaml(tmp_path, robot, monkeypatch):
    import larc_jax.model.trajectory_files as tr

    monkeypatch.setattr(tr, "MAX_WAYPOINTS", 2)
    with pytest.raises(LarcInputError, match="more than 2 waypoints"):
        read_trajectory(_write(tmp_path, "big.csv", "\n".join([CSV_HEAD, *CSV_ROWS]) + "\n"), robot)
    with pytest.raises(LarcInputError, match="3 waypoints"):
        read_trajectory(_write(tmp_path, "big.yaml", _echo(POINTS)), robot)


def test_trajectory_from_msg_unwraps_robot_trajectory():
    msg = {"joint_trajectory": {"joint_names": ["a"], "points": [
        {"positions": [0.0], "time_from_start": {"sec": 0, "nanosec": 0}},
        {"positions": [1.0], "time_from_start": {"sec": 2, "nanosec": 0}}]},
        "multi_dof_joint_trajectory": {"joint_names": [], "points": []}}
    traj = trajectory_from_msg(msg, velocities="finite-difference")
    np.testing.assert_array_equal(traj.qd, [[0.5], [0.5]])
    with pytest.raises(LarcInputError, match=r"joint_trajectory\.points\[0\]\.velocities is missing"):
        trajectory_from_msg(msg)


# --------------------------------------------------------------------------------------------
# Command line (in-process)

@pytest.mark.slow
def test_cli_formats_and_exit_codes(tmp_path, capsys):
    from larc_jax.drivers.cli import main

    ex = {name: str(EXAMPLES / name) for name in
          ("echo_joint_trajectory.yaml", "traj.csv", "positions_only.csv", "pick.scene")}
    assert main(["-q", "certify", ex["echo_joint_trajectory.yaml"], ex["traj.csv"],
                 "--scene", ex["pick.scene"]]) == 0
    capsys.readouterr()
    assert main(["-q", "certify", ex["positions_only.csv"], "--scene", ex["pick.scene"]]) == 2
    err = capsys.readouterr().err
    assert "positions_only.csv" in err and "--velocities finite-difference" in err
    assert main(["-q", "certify", ex["positions_only.csv"], "--scene", ex["pick.scene"],
                 "--velocities", "finite-difference"]) == 0
    # a box on the path: uncertified; the same pillar as a cylinder too, and a plane through it;
    # a plane without a normal: bad input naming file and line
    blocked = "s\n* pillar\n0.3 0 0.25\n0 0 0 1\n1\nbox\n0.1 0.1 0.5\n0 0 0\n0 0 0 1\n0 0 0 0\n0\n.\n"
    assert main(["-q", "certify", ex["traj.csv"], "--scene", str(_write(tmp_path, "p.scene", blocked))]) == 1
    cylinder = blocked.replace("box\n0.1 0.1 0.5", "cylinder\n0.05 0.5")
    assert main(["-q", "certify", ex["traj.csv"], "--scene", str(_write(tmp_path, "c.scene", cylinder))]) == 1
    capsys.readouterr()
    plane = blocked.replace("box\n0.1 0.1 0.5", "plane\n0 0 1 0")  # z = 0.25: through the arm
    assert main(["-q", "certify", ex["traj.csv"], "--scene", str(_write(tmp_path, "a.scene", plane))]) == 1
    plane = blocked.replace("box\n0.1 0.1 0.5", "plane\n0 0 0 1")
    assert main(["-q", "certify", ex["traj.csv"], "--scene", str(_write(tmp_path, "b.scene", plane))]) == 2
    assert "b.scene:7:" in (err := capsys.readouterr().err) and "no normal" in err


def test_readme_scene_example_parses(tmp_path):
    import re

    readme = (Path(__file__).resolve().parent.parent / "README.md").read_text()
    section = readme.split("### Input formats", 1)[1]
    (block,) = re.findall(r"```text\n(.*?)```", section.split("\n## ", 1)[0], re.S)
    scene = read_scene(_write(tmp_path, "readme.scene", block))
    ref = read_scene(EXAMPLES / "pick.scene")
    assert scene.box_names == ("crate", "floor") and [p.name for p in scene.planes] == ["floor"]
    np.testing.assert_allclose(scene.lo[1], [-5, -5, -0.05], rtol=0, atol=1e-12)  # the floor 5 cm down: its square
    np.testing.assert_array_equal(scene.lo[0], ref.lo[0])
    np.testing.assert_array_equal(scene.hi[0], ref.hi[0])
