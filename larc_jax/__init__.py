"""larc_jax: lazy adaptive reachability certification (LARC) of robot-arm trajectories in JAX.

Typical use::

    import larc_jax as lj
    robot = lj.load_robot()                                   # PIPER (LARC_PIPER_DESCRIPTION)
    capsules = lj.load_capsules(lj.default_capsule_path(), robot)
    trajs = [lj.read_trajectory(p, robot) for p in paths]
    result = lj.certify(trajs, lj.read_scene("scene.yaml"), robot, capsules)
    df = result.to_dataframe()
"""

from .capsules import (
    CapsuleModel,
    capsule_segments,
    default_capsule_path,
    fit_capsules,
    load_capsules,
    motion_constants,
    verify_containment,
)
from .certify import DatasetResult, Leaf, Method, TrajectoryResult, certify, interval_clearance
from .errors import LarcInputError
from .geometry import segment_box_distance, segment_box_distances
from .hermite import HermiteSpline, speed_max
from .robot import JointType, Robot, forward_kinematics, load_robot
from .scene import Scene, read_moveit_scene, read_scene
from .trajectory import Trajectory, finite_difference_velocities, read_trajectory, write_trajectory

__version__ = "0.1.0"

__all__ = [
    "CapsuleModel", "DatasetResult", "HermiteSpline", "JointType", "LarcInputError", "Leaf",
    "Method", "Robot", "Scene", "Trajectory", "TrajectoryResult", "capsule_segments", "certify",
    "default_capsule_path", "fit_capsules", "forward_kinematics", "interval_clearance",
    "load_capsules", "load_robot", "motion_constants", "read_scene", "read_trajectory",
    "segment_box_distance", "segment_box_distances", "speed_max", "verify_containment",
    "write_trajectory", "read_moveit_scene", "finite_difference_velocities",
]
