"""The robot, its capsules and the dataset as library objects, as the Stage B protocol names them
(used by the certification, timing and figure stages)."""

from __future__ import annotations

import dataclasses

from experiments.common import Layout, dataset_index, resolve, scene_paths

__all__ = ["robot_and_capsules", "load_dataset"]


def robot_and_capsules(config: dict):
    """PIPER (``LARC_PIPER_DESCRIPTION``) and the protocol's capsule file (``capsules``)."""
    from larc_jax.enclosure.robot_file import load_capsules
    from larc_jax.model.urdf import load_robot

    robot = load_robot()
    return robot, load_capsules(resolve(config["capsules"]), robot)


def load_dataset(layout: Layout, config: dict, robot):
    """``(index, trajectories, scenes)``: :func:`~experiments.common.dataset_index`, each file
    read for ``robot``, and each trajectory's scene (named after the protocol's scene)."""
    from larc_jax.model.scene import read_scene
    from larc_jax.model.trajectory_files import read_trajectory

    index = dataset_index(layout, config)
    scenes = {s: dataclasses.replace(read_scene(p, frame=robot.link_names[0]), name=s)
              for s, p in scene_paths(config).items()}
    trajs = [read_trajectory(r["path"], robot) for r in index]
    return index, trajs, [scenes[r["scene"]] for r in index]
