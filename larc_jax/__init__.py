"""larc_jax: lazy adaptive reachability certification (LARC) of robot-arm trajectories in JAX.

Typical use::

    import larc_jax as lj
    robot = lj.load_robot()                                   # PIPER (LARC_PIPER_DESCRIPTION)
    capsules = lj.load_capsules(lj.default_capsule_path(), robot)
    trajs = [lj.read_trajectory(p, robot) for p in paths]
    scene = lj.read_scene("scene.yaml")
    result = lj.certify(trajs, scene, robot, capsules)
    df = result.to_dataframe()
    lj.write_certificate("cert.json", result, trajs, scene, robot, capsules)  # re-check: lj.verify_certificate
    lj.view("cert.json")                                      # see it in 3-D in the browser (viser)
"""

import sys
import types

__version__ = "0.1.0"

__all__ = [
    "CapsuleModel", "DatasetResult", "HermiteSpline", "IntervalEval", "JointType", "LarcInputError", "Leaf",
    "Method", "Robot", "Scene", "Trajectory", "TrajectoryResult", "capsule_segments", "certify",
    "default_capsule_path", "evaluate_interval", "fit_capsules", "forward_kinematics", "interval_clearance",
    "load_capsules", "load_robot", "load_robot_file", "motion_constants", "read_scene", "read_trajectory",
    "segment_box_distance", "segment_box_distances", "speed_max", "verify_containment",
    "write_trajectory", "read_moveit_scene", "finite_difference_velocities", "enable_compile_cache",
    "DEFAULT_MARGIN_M", "DEFAULT_MAX_DEPTH", "DEFAULT_COARSE_DEPTH", "certify_stream", "LeafTable",
    "write_certificate", "verify_certificate", "Refuted", "VerifyPins", "VerifyReport", "view",
    "RunSpec", "fit_robot_file", "parse_hold", "parse_joints", "parse_package_dirs",
    "ObstacleSet", "AlignedBoxes", "ConvexShapes", "Shapes", "scene_obstacles", "warm_up_tree",
]

_loaded = False


def _load() -> None:
    """Import the public API into this namespace (on first use: see :func:`__getattr__`)."""
    global _loaded
    from .engine.certify import Method, certify
    from .engine.warm_up import warm_up_tree
    from .compilation import enable_compile_cache
    from .defaults import DEFAULT_COARSE_DEPTH, DEFAULT_MARGIN_M, DEFAULT_MAX_DEPTH
    from .enclosure import (
        CapsuleModel,
        capsule_segments,
        default_capsule_path,
        fit_capsules,
        fit_robot_file,
        load_capsules,
        load_robot_file,
        motion_constants,
        verify_containment,
    )
    from .errors import LarcInputError
    from .obstacles import AlignedBoxes, ConvexShapes, ObstacleSet, scene_obstacles
    from .model.shapes import Shapes
    from .obstacles.geometry import segment_box_distance, segment_box_distances
    from .model.hermite import HermiteSpline, speed_max
    from .leaf.interval import IntervalEval, evaluate_interval, interval_clearance
    from .option_values import parse_hold, parse_joints, parse_package_dirs
    from .engine.results import DatasetResult, Leaf, LeafTable, TrajectoryResult
    from .model.robot import JointType, Robot, forward_kinematics
    from .run_spec import RunSpec
    from .model.scene import Scene, read_moveit_scene, read_scene
    from .drivers.stream import certify_stream
    from .model.trajectory import Trajectory, finite_difference_velocities
    from .model.trajectory_files import read_trajectory, write_trajectory
    from .model.urdf import load_robot
    from .products.certificate import write_certificate
    from .products.verify import Refuted, VerifyPins, VerifyReport, verify_certificate  # last: it defers JAX, which is loaded by now
    from .products.view import view  # NumPy; viser is imported when a view opens
    globals().update({k: v for k, v in locals().items() if k in __all__})
    _loaded = True


def __getattr__(name: str):
    # PEP 562: ``import larc_jax`` loads no JAX until an attribute is used, so that the
    # NumPy-only checker (larc_jax.products.verify, `larc verify`) runs in a process without JAX
    # (larc_jax.lazy_jax). Any attribute loads the whole public API at once.
    if not _loaded and not name.startswith("__"):
        _load()
        if name in globals():
            return globals()[name]
    raise AttributeError(f"module 'larc_jax' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(__all__))


class _Package(types.ModuleType):
    """Keeps the API names: importing a submodule of the same name (``larc_jax.engine.certify``) before
    the API is loaded must not bind the module where :func:`certify` belongs."""

    def __setattr__(self, name, value):
        if name in __all__ and isinstance(value, types.ModuleType):
            return
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package
