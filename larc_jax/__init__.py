"""larc_jax: lazy adaptive reachability certification (LARC) of robot-arm trajectories in JAX.

Typical use::

    import larc_jax as lj
    robot = lj.load_robot()                                   # PIPER (LARC_PIPER_DESCRIPTION)
    capsules = lj.load_capsules(lj.default_capsule_path(), robot)
    trajs = [lj.read_trajectory(p, robot) for p in paths]
    result = lj.certify(trajs, lj.read_scene("scene.yaml"), robot, capsules)
    df = result.to_dataframe()
"""

from .certify import Method, certify
from .compilation import enable_compile_cache
from .defaults import DEFAULT_COARSE_DEPTH, DEFAULT_MARGIN_M, DEFAULT_MAX_DEPTH
from .enclosure import (
    CapsuleModel,
    capsule_segments,
    default_capsule_path,
    fit_capsules,
    load_capsules,
    load_robot_file,
    motion_constants,
    verify_containment,
)
from .errors import LarcInputError
from .geometry import segment_box_distance, segment_box_distances
from .hermite import HermiteSpline, speed_max
from .interval import IntervalEval, evaluate_interval, interval_clearance
from .results import DatasetResult, Leaf, LeafTable, TrajectoryResult
from .robot import JointType, Robot, forward_kinematics
from .scene import Scene, read_moveit_scene, read_scene
from .stream import certify_stream
from .trajectory import Trajectory, finite_difference_velocities
from .trajectory_files import read_trajectory, write_trajectory
from .urdf import load_robot

__version__ = "0.1.0"

__all__ = [
    "CapsuleModel", "DatasetResult", "HermiteSpline", "IntervalEval", "JointType", "LarcInputError", "Leaf",
    "Method", "Robot", "Scene", "Trajectory", "TrajectoryResult", "capsule_segments", "certify",
    "default_capsule_path", "evaluate_interval", "fit_capsules", "forward_kinematics", "interval_clearance",
    "load_capsules", "load_robot", "load_robot_file", "motion_constants", "read_scene", "read_trajectory",
    "segment_box_distance", "segment_box_distances", "speed_max", "verify_containment",
    "write_trajectory", "read_moveit_scene", "finite_difference_velocities", "enable_compile_cache",
    "DEFAULT_MARGIN_M", "DEFAULT_MAX_DEPTH", "DEFAULT_COARSE_DEPTH", "certify_stream", "LeafTable",
]
