"""A capsule file is trusted only while the geometry it was proven on is unchanged: collision
mesh hashes, primitive parameters, coverage of every link, and `larc verify-capsules`."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from larc_jax import LarcInputError, Scene, Trajectory, certify
from larc_jax.drivers.cli import main as larc_main
from larc_jax.enclosure import capsule_segments_np, default_capsule_path, load_capsules, load_robot_file, verify_containment
from larc_jax.enclosure.fit import point_segment_distance
from larc_jax.enclosure.meshes import collision_geometry, link_elements

ROOT = Path(__file__).resolve().parent.parent


def larc(capsys, *argv):
    rc = larc_main(list(argv))
    out, err = capsys.readouterr()
    return rc, out, err


@pytest.fixture
def piper_copy(tmp_path, piper_dir):
    """A copy of the PIPER description and a robot file (the shipped capsules) pointing at it."""
    desc = tmp_path / "piper_description"
    shutil.copytree(piper_dir / "urdf", desc / "urdf")
    shutil.copytree(piper_dir / "meshes", desc / "meshes")
    doc = yaml.safe_load(default_capsule_path().read_text())
    doc = {"urdf": "piper_description/urdf/piper_description.urdf",
           "package_dirs": {"piper_description": "piper_description"}, **doc}
    robot_file = tmp_path / "piper.yaml"
    robot_file.write_text(yaml.safe_dump(doc, sort_keys=False))
    return desc, robot_file


def test_committed_file_records_every_collision_mesh(robot):
    doc = yaml.safe_load(default_capsule_path().read_text())
    assert doc["revision"] == "larc-capsules-2"
    assert doc["geometry"] == collision_geometry(robot)
    for link, entries in doc["geometry"].items():
        for e in entries:
            assert len(e["sha256"]) == 64 and e["scale"] == [1.0, 1.0, 1.0] and len(e["origin"]) == 3
    assert set(doc["geometry"]) == {c["link"] for c in doc["capsules"]}


def test_mesh_scaled_after_fitting_is_refused(piper_copy, robot, capsules, capsys):
    """The issue's example: the gripper mesh scaled by 1.4 after fitting, URDF untouched. Main
    kept the old capsules and certified a trajectory whose real gripper comes within rho of a
    box; the file must now be refused, naming the mesh and how to refit."""
    import trimesh

    desc, robot_file = piper_copy
    robot_c, caps_c = load_robot_file(robot_file)  # unchanged copy: trusted
    q = np.array([0.0, 1.2, -1.0, 0.0, 0.8, 0.0])
    traj = Trajectory(t=np.array([0.0, 1.0]), q=np.stack([q, q]), qd=np.zeros((2, 6)),
                      joint_names=robot.active_joint_names, id="still")
    mesh_path = desc / "meshes" / "link6.STL"
    mesh = trimesh.load(mesh_path, force="mesh", process=False)
    mesh.vertices = mesh.vertices * 1.4
    mesh.export(mesh_path)
    # The old capsules no longer hold the scaled link: a box the certificate keeps rho + 2 mm
    # from the link6 capsule is within rho of the real, scaled mesh.
    c = caps_c.names.index("link6")
    pa, pb = capsule_segments_np(robot, capsules, q)
    far = int(np.argmax(np.linalg.norm(link_elements(robot_c, "link6").reshape(-1, 3), axis=1)))
    from larc_jax.model.robot import forward_kinematics_np

    T = forward_kinematics_np(robot, q)[robot.link_index("link6")]
    p_far = T[:3, :3] @ link_elements(robot_c, "link6").reshape(-1, 3)[far] + T[:3, 3]
    u = (p_far - (pa[c] + pb[c]) / 2)
    u /= np.linalg.norm(u)
    centre = p_far + u * 0.001
    axis = int(np.argmax(np.abs(u)))
    e = np.zeros(3)
    e[axis] = np.sign(u[axis])
    lo, hi = centre - 0.02, centre + 0.02
    lo[axis], hi[axis] = (centre[axis], centre[axis] + 0.04) if e[axis] > 0 else (centre[axis] - 0.04, centre[axis])
    d_cap = min(float(np.linalg.norm(np.clip(p, lo, hi) - p)) for p in
                (pa[c] + s * (pb[c] - pa[c]) for s in np.linspace(0, 1, 2001))) - float(capsules.radius[c])
    shift = e * (d_cap - 0.012)  # capsule 12 mm from the box: certified with rho = 10 mm
    scene = Scene(lo=(lo - shift)[None], hi=(hi - shift)[None], box_names=("box",))
    scaled = link_elements(robot_c, "link6").reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]
    real_gap = float(np.linalg.norm(np.clip(scaled, scene.lo[0], scene.hi[0]) - scaled, axis=1).min())
    assert real_gap < 0.01  # the real (scaled) link is within rho of the box ...
    assert certify(traj, scene, robot_c, caps_c, margin=0.01)[0].certified  # ... yet the old model certifies
    with pytest.raises(LarcInputError, match=r"link 'link6' collision mesh package://piper_description/meshes/"
                                             r"link6.STL has changed .*refit with `larc fit-capsules"):
        load_robot_file(robot_file)
    with pytest.raises(LarcInputError, match="not inside"):
        verify_containment(robot_c, caps_c)  # the old capsules really do not contain it
    scene_file = robot_file.parent / "scene.yaml"
    scene_file.write_text(yaml.safe_dump({"frame": "base_link", "boxes": [
        {"name": "box", "min": scene.lo[0].tolist(), "max": scene.hi[0].tolist()}]}))
    from larc_jax.model.trajectory_files import write_trajectory

    traj_file = robot_file.parent / "still.yaml"
    write_trajectory(traj_file, traj)
    rc, out, err = larc(capsys, "certify", str(traj_file), "--scene", str(scene_file), "--robot", str(robot_file))
    assert rc == 2 and "has changed" in err and "refit with `larc fit-capsules" in err and out == ""
    rc, out, err = larc(capsys, "verify-capsules", str(robot_file))
    assert rc == 2 and "link6.STL has changed" in err


def test_link_without_capsule_is_refused(robot, tmp_path):
    doc = yaml.safe_load(default_capsule_path().read_text())
    doc["capsules"] = [c for c in doc["capsules"] if c["link"] != "link7"]
    path = tmp_path / "caps.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    with pytest.raises(LarcInputError, match="link 'link7' has collision geometry but no capsule"):
        load_capsules(path, robot)


@pytest.mark.parametrize("edit,msg", [
    (lambda d: d.pop("geometry"), r"no 'geometry' field .* refit with `larc fit-capsules"),
    (lambda d: d["geometry"]["link3"][0].update(sha256="0" * 64), r"link 'link3' collision mesh .*link3.STL has changed"),
    (lambda d: d["geometry"]["link3"][0].update(scale=[1.0, 1.0, 1.4]), r"geometry.link3\[0\] = .* differs"),
    (lambda d: d["geometry"].pop("link5"), r"link 'link5' has collision geometry .* not fitted to"),
    (lambda d: d["geometry"].update(link9={"box": [1, 1, 1]}), r"records link 'link9', which has no collision"),
    (lambda d: d["geometry"]["link2"].append(d["geometry"]["link2"][0]), r"geometry.link2 records 2 collision elements"),
    (lambda d: d.update(geometry=[1, 2]), r"geometry must be a mapping"),
])
def test_recorded_geometry_must_match(robot, tmp_path, edit, msg):
    doc = yaml.safe_load(default_capsule_path().read_text())
    edit(doc)
    path = tmp_path / "caps.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    with pytest.raises(LarcInputError, match=msg):
        load_capsules(path, robot)


def test_primitive_parameters_are_recorded(tmp_path):
    from .test_fit_primitives import write_primitive_urdf
    from larc_jax.model.urdf import load_robot

    urdf = write_primitive_urdf(tmp_path)
    geom = collision_geometry(load_robot(urdf))
    assert geom["post"] == [{"cylinder": [0.04, 0.3], "origin": [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0],
                                                              [0.0, 0.0, 1.0, 0.15]]}]
    assert geom["block"][0]["box"] == [0.1, 0.06, 0.2] and "sphere" in geom["tip"][0]


def test_verify_capsules_command(capsys, tmp_path, robot):
    rc, out, err = larc(capsys, "verify-capsules")
    assert rc == 0 and "containment proven for" in out and "9 links in 11 capsules" in out
    # Not contained: exit 2, naming the link and the element.
    doc = yaml.safe_load(default_capsule_path().read_text())
    from larc_jax.model.urdf import piper_urdf_path

    doc = {"urdf": str(piper_urdf_path()), **doc}
    doc["capsules"][3]["radius"] = round(doc["capsules"][3]["radius"] - 0.005, 6)
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(doc, sort_keys=False))
    rc, out, err = larc(capsys, "verify-capsules", str(bad))
    assert rc == 2 and "link 'link2' element" in err and "not inside" in err
    rc, out, err = larc(capsys, "verify-capsules", str(tmp_path / "missing.yaml"))
    assert rc == 2 and "missing.yaml" in err
    rc, out, err = larc(capsys, "-q", "verify-capsules")
    assert rc == 0 and out == ""


def test_containment_counts_distance_rounding():
    """A vertex exactly on the shrunk capsule surface, up to rounding, is not claimed inside."""
    from larc_jax.enclosure.fit import inside_capsule

    a, b = np.array([0.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0])
    p = np.array([[0.5, 0.3, 0.0]])
    assert not inside_capsule(p, a, b, float(point_segment_distance(p, a, b)[0])).any()
    assert inside_capsule(p, a, b, 0.3 + 1e-12).all()
