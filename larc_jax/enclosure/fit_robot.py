"""A complete robot (capsule) file from a URDF: what ``larc fit-capsules`` writes.

:func:`fit_robot_file` loads the robot, fits its capsules (:func:`~.fit.fit_capsules`), the
stated-finger capsules (:func:`~.fit.fit_stated_capsules`) and the hull stage's split planes
(:func:`~.hull.choose_hull_parts`), writes the file (:func:`~.robot_file.save_capsules`), loads
it back and proves that its capsules contain every collision element
(:func:`~.fit.verify_containment`). A file whose proof fails is removed, never left for a later
run to trust. ``larc verify-capsules`` (:func:`~.proof.prove_robot_file`) re-proves every
enclosure the file gives, the hull parts and the stated capsules too.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Callable, Mapping, Sequence

from ..defaults import DEFAULT_PADDING_M, check_padding
from ..errors import LarcInputError
from ..model.robot import Robot
from .capsule import CapsuleModel
from .fit import FittedCapsule, fit_capsules, fit_stated_capsules, verify_containment
from .hull import choose_hull_parts
from .robot_file import load_capsules, save_capsules

__all__ = ["FittedRobotFile", "fit_robot_file"]


@dataclasses.dataclass(frozen=True)
class FittedRobotFile:
    """A robot file written by :func:`fit_robot_file`, and what its fit and proof found."""

    path: Path
    """The file written; its URDF and package paths are relative to its folder."""
    fitted: tuple[FittedCapsule, ...]
    """Its capsules, with their volumes (:meth:`table_lines`); the stated-finger capsules and
    hull parts are in the file."""
    elements_proven: int
    """Collision elements proven inside the file's capsules."""
    robot: Robot
    """As loaded from the URDF, with the active and held joints asked for."""
    capsules: CapsuleModel
    """As loaded back from the file (what ``load_robot_file(path)`` gives)."""

    def table_lines(self) -> list[str]:
        """One row per capsule (radius, volume, volume of its elements' hull, their ratio), then
        what was written and proven."""
        wc = max([12] + [len(f.name) for f in self.fitted])  # long link names keep the columns
        wl = max([10] + [len(f.link) for f in self.fitted])
        lines = [f"{'capsule':<{wc}} {'link':<{wl}} {'radius_m':>9} {'vol_cm3':>8} {'hull_cm3':>8} {'ratio':>6}"]
        lines += [f"{f.name:<{wc}} {f.link:<{wl}} {f.radius:>9.6f} {f.volume_m3 * 1e6:>8.1f} "
                  f"{f.hull_volume_m3 * 1e6:>8.1f} {f.volume_m3 / max(f.hull_volume_m3, 1e-30):>6.2f}"
                  for f in self.fitted]
        lines.append(f"wrote {self.path}: {len(self.fitted)} capsules; containment proven for "
                     f"{self.elements_proven} mesh elements")
        return lines


def fit_robot_file(
    urdf: str | os.PathLike,
    output: str | os.PathLike,
    *,
    package_dirs: Mapping[str, str] | None = None,
    active_joints: Sequence[str] | None = None,
    held_joint_values: Mapping[str, float] | None = None,
    n_capsules: int | None = None,
    capsules_per_link: Mapping[str, int] | None = None,
    padding_m: float = DEFAULT_PADDING_M,
    record_urdf: bool = True,
    progress: Callable[[str], None] | None = None,
) -> FittedRobotFile:
    """Fit, write and prove the robot file ``output`` for the URDF ``urdf`` (module docstring).

    Args:
      package_dirs: ``{package name: folder}`` for ``package://`` URIs.
      active_joints: the joints trajectories carry (default: the trunk chain, as
        :func:`~larc_jax.model.urdf.load_robot` chooses).
      held_joint_values: value at which a non-active joint is held; a held prismatic joint's
        links are fitted over its whole stroke (and alone, for a stated opening).
      n_capsules, capsules_per_link: how many capsules (:func:`~.fit.fit_capsules`).
      padding_m: added to every radius on top of the proven containment.
      record_urdf: write the URDF path (and the package folders) into the file, relative to
        its folder, so that ``load_robot_file(output)`` rebuilds the robot; ``False`` for a
        robot found otherwise (PIPER via ``LARC_PIPER_DESCRIPTION``).
      progress: called with a message (``"fitting link6"``) before each link of each step.

    Raises :class:`LarcInputError` for bad input (named) or a failed proof.
    """
    from ..model.urdf import load_robot

    padding_m = check_padding(padding_m)
    output = Path(output)
    if output.is_dir():  # before the work
        raise LarcInputError(f"{output}: is a directory, expected a robot file name to write")
    robot = load_robot(urdf, package_dirs, active_joints=active_joints, held_joint_values=held_joint_values)
    step = progress or (lambda msg: None)
    fitted = fit_capsules(robot, n_capsules=n_capsules, capsules_per_link=capsules_per_link, padding_m=padding_m,
                          progress=step)
    stated = fit_stated_capsules(robot, padding_m=padding_m, progress=step)
    hull_parts = choose_hull_parts(robot, progress=step)
    out_dir = output.resolve().parent  # the file's paths are relative to its folder
    rel = lambda p: os.path.relpath(Path(p).expanduser().resolve(), out_dir)  # noqa: E731
    try:
        save_capsules(output, robot, fitted, padding_m=padding_m, urdf=rel(urdf) if record_urdf else None,
                      package_dirs={k: rel(v) for k, v in (package_dirs or {}).items()},
                      stated=stated, hull_parts=hull_parts)
    except OSError as exc:
        raise LarcInputError(f"{output}: cannot write the robot file ({exc.strerror or exc})") from None
    try:
        capsules = load_capsules(output, robot)
        checked = verify_containment(robot, capsules, source=str(output), progress=lambda l: step(f"proving {l}"))
    except BaseException:
        output.unlink(missing_ok=True)  # a file whose containment is not proven must not stay to be used
        raise
    return FittedRobotFile(path=output, fitted=tuple(fitted), elements_proven=sum(checked.values()), robot=robot,
                           capsules=capsules)
