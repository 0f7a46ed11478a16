"""The Python API speaks LarcInputError too: Trajectory, Scene and certify() refuse what the
command line refuses, naming the field, and never fail deep inside NumPy or JAX."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from larc_jax import LarcInputError, Scene, Trajectory, certify

NAMES = ("joint1", "joint2", "joint3", "joint4", "joint5", "joint6")
Q0 = [0.0, 1.0, -1.0, 0.0, 0.3, 0.0]
SETTINGS = settings(max_examples=300, deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


def still(n=2, **kw):
    args = dict(t=[float(k) for k in range(n)], q=[Q0] * n, qd=[[0.0] * 6] * n, joint_names=list(NAMES), id="still")
    args.update(kw)
    return Trajectory(**args)


# ----------------------------------------------------------------------------------------------
# The cases
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("make,msg", [
    (lambda: Scene(lo=np.zeros((1, 2)), hi=np.ones((1, 2))), r"Scene.lo must have shape \(N, 3\), got shape \(1, 2\)"),
    (lambda: Scene(lo=np.zeros(3), hi=np.ones(3)), r"Scene.lo must have shape \(N, 3\), got shape \(3,\)"),
    (lambda: Scene(lo=[[0, 0, 0]], hi=[[1, 1, 1], [2, 2, 2]]), "Scene.lo has 1 boxes but Scene.hi has 2"),
    (lambda: Scene(lo=[[0, 0, 2]], hi=[[1, 1, 1]]), r"box 0: Scene.lo\[0\]\[2\] = 2.0 exceeds Scene.hi\[0\]\[2\]"),
    (lambda: Scene(lo=[[0, 0, math.nan]], hi=[[1, 1, 1]]), r"Scene.lo\[0\]\[2\] is not finite"),
    (lambda: Scene(lo=[[0, 0, 0]], hi=[[1, 1, 1]], box_names=("a", "b")), "box_names has 2 names for 1 boxes"),
    (lambda: Scene(lo=[["a", 0, 0]], hi=[[1, 1, 1]]), "Scene.lo must be an array of real numbers"),
    (lambda: Scene(lo=[[0, 0, 0]], hi=[[1, 1, 1]], box_names="crate"), "Scene.box_names must be a list"),
    (lambda: still(0, t=[], q=np.zeros((0, 6)), qd=np.zeros((0, 6))), "Trajectory.t has 0 waypoints"),
    (lambda: still(1), "Trajectory.t has 1 waypoint; a trajectory needs at least 2"),
    (lambda: still(q=np.zeros((2, 5)), qd=np.zeros((2, 5))), "joint_names has 6 names, but q has 5 columns"),
    (lambda: still(q=np.zeros((3, 6))), "Trajectory.q has 3 rows, but t has 2 waypoints"),
    (lambda: still(qd=np.zeros((2, 5))), r"Trajectory.qd has shape \(2, 5\), but q has shape \(2, 6\)"),
    (lambda: still(t=[[0.0, 1.0]]), r"Trajectory.t \(waypoint times\) must have shape \(N\)"),
    (lambda: still(q=[[0.0] * 6, [0.0] * 5]), r"Trajectory.q \(positions\) must be an array of numbers"),
    (lambda: still(joint_names="joint1"), "Trajectory.joint_names must be a list of joint names"),
    (lambda: still(joint_names=[1, 2, 3, 4, 5, 6]), "Trajectory.joint_names must be a list of joint names"),
    (lambda: still(t=[0, True]), "Trajectory.t .* must be an array of real numbers"),
    (lambda: still(id=5), "Trajectory.id must be a string"),
])
def test_constructors_name_the_field(make, msg):
    with pytest.raises(LarcInputError, match=msg):
        make()


def test_plain_lists_are_accepted_and_read_only(robot, capsules):
    traj = still(3)
    assert traj.t.dtype == np.float64 and traj.q.shape == (3, 6) and traj.joint_names == NAMES
    with pytest.raises(ValueError):
        traj.q[0, 0] = 5.0  # a certified record cannot be edited behind the certificate's back
    scene = Scene(lo=[[0.3, -0.1, 0.0]], hi=[[0.5, 0.1, 0.2]])
    assert scene.box_names == ("box0",) and scene.lo.flags.writeable is False
    assert Scene(lo=[], hi=[]).n_boxes == 0
    res = certify(traj, scene, robot, capsules, max_depth=2)
    assert len(res) == 1 and res[0].leaves[0].box in ("box0", "")


@pytest.mark.parametrize("kwargs,msg", [
    (dict(trajectories=[]), "no trajectories given"),
    (dict(trajectories={"t": [0, 1]}), "trajectories must be a Trajectory or a list of them, got dict"),
    (dict(trajectories=[None]), r"trajectories\[0\] is a NoneType, not a Trajectory"),
    (dict(scenes=[Scene.empty(), Scene.empty()]), "1 trajectories but 2 scenes"),
    (dict(scenes=np.zeros((1, 3))), "scenes must be a Scene or a list of them"),
    (dict(scenes=Scene(lo=[[0, 0, 0]], hi=[[1, 1, 1]], frame="world")), "frame 'world' is not the robot base frame"),
    (dict(robot=None), "robot must be a Robot"),
    (dict(capsules="configs/piper_capsules.yaml"), "capsules must be a CapsuleModel"),
    (dict(method=None), "unknown method"),
    (dict(method=["larc"]), "unknown method"),
    (dict(margin="0.01"), "margin"),
    (dict(margin=np.float32(-1)), "margin"),
    (dict(max_depth=2.0), "max_depth"),
    (dict(coarse_depth=-1), "coarse_depth"),
    (dict(dtype=np.float16), "dtype float16 is not supported"),
    (dict(dtype="int"), "dtype"),
    (dict(dtype=object()), "dtype"),
    (dict(progress=5), "progress must be a function"),
    (dict(trajectories=still(t=[0.0, 0.0])), r"points\[1\].time_from_start .* strictly increasing"),
    (dict(trajectories=still(q=[Q0, [0, 9.0, 0, 0, 0, 0]])), r"points\[1\].positions\[1\] = 9.0 .* outside its limits"),
    (dict(trajectories=still(qd=[[0.0] * 6, [math.inf] + [0.0] * 5])), r"points\[1\].velocities\[0\] is not finite"),
    (dict(trajectories=still(joint_names=["a", "b", "c", "d", "e", "f"])), "do not match the robot's active joints"),
])
def test_certify_refuses_what_the_command_line_refuses(robot, capsules, kwargs, msg):
    args = dict(trajectories=still(), scenes=Scene.empty(), robot=robot, capsules=capsules)
    args.update(kwargs)
    with pytest.raises(LarcInputError, match=msg):
        certify(args.pop("trajectories"), args.pop("scenes"), args.pop("robot"), args.pop("capsules"), **args)


def test_numpy_scalars_are_accepted(robot, capsules):
    res = certify(still(), Scene.empty(), robot, capsules, margin=np.float32(0.01), max_depth=np.int64(2))
    assert res.max_depth == 2 and isinstance(res.max_depth, int) and res[0].certified


# ----------------------------------------------------------------------------------------------
# Hypothesis: anything given to the constructors and to certify() is a record or a LarcInputError
# ----------------------------------------------------------------------------------------------

_SCALARS = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-10**20, 10**20), st.booleans(),
                     st.none(), st.text(max_size=3), st.complex_numbers(max_magnitude=10))
_NESTED = st.recursive(_SCALARS, lambda c: st.lists(c, max_size=4), max_leaves=20)
_ARRAYS = hnp.arrays(st.sampled_from([np.float64, np.float32, np.int64, np.bool_, np.complex128, np.float16,
                                      np.uint8, np.dtype("U2")]),
                     hnp.array_shapes(min_dims=0, max_dims=3, max_side=4))


def _array_like(rows: int | None = None, cols: int | None = None):
    good = st.builds(lambda r, c, x: np.full((r, c), x).tolist(), st.just(rows or 2), st.just(cols or 6),
                     st.floats(-1, 1)) if cols else st.builds(lambda r: list(range(r)), st.just(rows or 2))
    return st.one_of(good, _NESTED, _ARRAYS)


def _check_trajectory(traj: Trajectory) -> None:
    assert traj.t.dtype == traj.q.dtype == traj.qd.dtype == np.float64
    assert traj.t.ndim == 1 and len(traj.t) >= 2 and traj.q.shape == traj.qd.shape == (len(traj.t), len(traj.joint_names))
    assert all(isinstance(n, str) for n in traj.joint_names)


@SETTINGS
@given(t=_array_like(), q=_array_like(2, 6), qd=_array_like(2, 6),
       names=st.one_of(st.just(list(NAMES)), st.lists(st.one_of(st.text(max_size=6), st.integers()), max_size=7),
                       st.text(max_size=6), st.none()))
def test_trajectory_constructor_fuzz(t, q, qd, names):
    try:
        traj = Trajectory(t=t, q=q, qd=qd, joint_names=names)
    except LarcInputError as exc:
        assert str(exc) and "\n" not in str(exc)
        return
    _check_trajectory(traj)


@SETTINGS
@given(lo=_array_like(1, 3), hi=_array_like(1, 3),
       names=st.one_of(st.just(()), st.lists(st.one_of(st.text(max_size=4), st.integers()), max_size=3), st.none()))
def test_scene_constructor_fuzz(lo, hi, names):
    try:
        scene = Scene(lo=lo, hi=hi, box_names=names)
    except LarcInputError as exc:
        assert str(exc) and "\n" not in str(exc)
        return
    assert scene.lo.shape == scene.hi.shape == (scene.n_boxes, 3) and len(scene.box_names) == scene.n_boxes
    assert np.isfinite(scene.lo).all() and (scene.lo <= scene.hi).all()


_GARBAGE = st.one_of(st.none(), st.integers(-3, 30), st.floats(), st.text(max_size=5), st.lists(st.integers(), max_size=2))


@settings(SETTINGS, max_examples=150)
@given(data=st.data())
def test_certify_arguments_fuzz(robot, capsules, data):
    """certify() with each argument either valid or garbage: a result or a LarcInputError."""
    def arg(valid, garbage=_GARBAGE):
        return data.draw(st.one_of(st.sampled_from(valid), garbage))

    traj = data.draw(st.one_of(st.just(still()), st.builds(lambda: [still(), still(3)]), _GARBAGE,
                               st.lists(st.sampled_from([still(), None, 1.0]), max_size=2)))
    scene = arg([Scene.empty(), Scene(lo=[[0.3, -0.1, 0.0]], hi=[[0.5, 0.1, 0.2]])])
    kwargs = dict(method=arg(["larc", "fine", "coarse", "reference"]), margin=arg([0.01, 0.02]),
                  max_depth=arg([0, 1, 2]), coarse_depth=arg([0, 1, 2]), dtype=arg([np.float64, np.float32, "float32"]),
                  progress=arg([None, lambda n: None]))
    try:
        res = certify(traj, scene, robot, capsules, **kwargs)
    except LarcInputError as exc:
        assert str(exc) and "\n" not in str(exc)
        return
    assert len(res) >= 1 and all(r.leaves for r in res)
