"""Link enclosures: what encloses each link's collision geometry, proven, and how fast it moves.

* :mod:`~larc_jax.enclosure.capsule` — the capsule model pytree and its placement kernel;
* :mod:`~larc_jax.enclosure.meshes` — collision geometry (meshes, primitives) as vertex sets;
* :mod:`~larc_jax.enclosure.fit` — capsule fitting and the containment proof;
* :mod:`~larc_jax.enclosure.motion` — motion constants a_lj (paper eq. 6);
* :mod:`~larc_jax.enclosure.robot_file` — the robot (capsule) file: read, write;
* :mod:`~larc_jax.enclosure.fit_robot` — a complete robot file from a URDF: fit, write, prove.
"""

from .capsule import CapsuleModel, capsule_segments, capsule_segments_np
from .fit import FittedCapsule, fit_capsules, verify_containment
from .fit_robot import FittedRobotFile, fit_robot_file
from .meshes import link_elements
from .motion import motion_constants
from .robot_file import default_capsule_path, load_capsules, load_robot_file, save_capsules

__all__ = [
    "CapsuleModel", "FittedCapsule", "FittedRobotFile", "capsule_segments", "capsule_segments_np", "default_capsule_path",
    "fit_capsules", "fit_robot_file", "link_elements", "load_capsules", "load_robot_file", "motion_constants",
    "save_capsules", "verify_containment",
]
