"""larc_jax: lazy adaptive reachability certification of robot-arm trajectories in JAX."""

from .errors import LarcInputError
from .robot import JointType, Robot, forward_kinematics, forward_kinematics_np, load_robot

__version__ = "0.1.0"
