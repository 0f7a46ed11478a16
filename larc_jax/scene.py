"""Static obstacle scenes: axis-aligned boxes in the robot base frame.

Scene YAML::

    frame: base_link            # must be the robot's root link
    units: m                    # optional; only metres are accepted
    boxes:
      - {name: wall_left, min: [x, y, z], max: [x, y, z]}
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Sequence

import numpy as np
import yaml

from .errors import LarcInputError

__all__ = ["Scene", "read_scene", "scene_from_dict", "pad_scenes"]


@dataclasses.dataclass(frozen=True)
class Scene:
    """Obstacle boxes of one scene."""

    lo: np.ndarray
    """(B, 3) box minimum corners in the base frame, m."""
    hi: np.ndarray
    """(B, 3) box maximum corners in the base frame, m (hi >= lo componentwise)."""
    box_names: tuple[str, ...] = ()
    name: str = ""
    frame: str = "base_link"
    source: str = ""

    @property
    def n_boxes(self) -> int:
        return len(self.lo)

    @staticmethod
    def empty(name: str = "empty") -> "Scene":
        return Scene(lo=np.zeros((0, 3)), hi=np.zeros((0, 3)), name=name)


def _vec3(value, source: str, where: str) -> np.ndarray:
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        raise LarcInputError(f"{source}: {where} must be a list of 3 numbers, got {value!r}")
    for i, v in enumerate(value):
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise LarcInputError(f"{source}: {where}[{i}] is not a number ({v!r})")
    out = np.asarray(value, dtype=np.float64)
    if not np.isfinite(out).all():
        raise LarcInputError(f"{source}: {where} must be finite, got {value!r}")
    return out


def scene_from_dict(doc, *, source: str = "<scene>", name: str = "", frame: str | None = None) -> Scene:
    """Build a scene from a parsed YAML mapping; ``frame`` (if given) is the required frame."""
    if not isinstance(doc, dict):
        raise LarcInputError(f"{source}: expected a mapping with 'frame' and 'boxes'")
    scene_frame = doc.get("frame", "base_link")
    if frame is not None and scene_frame != frame:
        raise LarcInputError(
            f"{source}: frame '{scene_frame}' is not the robot base frame '{frame}'"
        )
    units = doc.get("units", "m")
    if units not in ("m", "meter", "meters", "metre", "metres"):
        raise LarcInputError(f"{source}: units '{units}' are not supported (boxes are in metres: use m)")
    boxes = doc.get("boxes", [])
    if boxes is None:
        boxes = []
    if not isinstance(boxes, list):
        raise LarcInputError(f"{source}: boxes must be a list")
    lo, hi, names = [], [], []
    for k, box in enumerate(boxes):
        where = f"boxes[{k}]"
        if not isinstance(box, dict):
            raise LarcInputError(f"{source}: {where} must be a mapping with min and max")
        for key in ("min", "max"):
            if key not in box:
                raise LarcInputError(f"{source}: {where}.{key} is missing")
        b_lo = _vec3(box["min"], source, f"{where}.min")
        b_hi = _vec3(box["max"], source, f"{where}.max")
        if (b_lo > b_hi).any():
            i = int(np.flatnonzero(b_lo > b_hi)[0])
            raise LarcInputError(
                f"{source}: {where}.min[{i}] = {b_lo[i]} exceeds {where}.max[{i}] = {b_hi[i]}"
            )
        lo.append(b_lo)
        hi.append(b_hi)
        names.append(str(box.get("name", f"box{k}")))
    return Scene(
        lo=np.array(lo).reshape(-1, 3), hi=np.array(hi).reshape(-1, 3), box_names=tuple(names),
        name=name or str(doc.get("name", "")), frame=scene_frame, source=source,
    )


def read_scene(path: str | Path, *, frame: str | None = None) -> Scene:
    """Read a scene YAML file (see module docstring)."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise LarcInputError(f"{path}: scene file does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise LarcInputError(f"{path}: cannot read ({exc})") from None
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise LarcInputError(f"{path}: not valid YAML ({exc})".replace("\n", " ")) from None
    if doc is None:
        raise LarcInputError(f"{path}: scene file is empty")
    return scene_from_dict(doc, source=str(path), name=path.stem, frame=frame)


def pad_scenes(scenes: Sequence[Scene], n_boxes: int | None = None):
    """Stack scenes into padded arrays.

    Returns ``lo (S, B, 3)``, ``hi (S, B, 3)``, ``mask (S, B)`` with B = ``n_boxes`` or the
    largest scene (at least 1). Padding boxes are degenerate at the origin and masked out.
    """
    B = max([s.n_boxes for s in scenes] + [1]) if n_boxes is None else n_boxes
    lo = np.zeros((len(scenes), B, 3))
    hi = np.zeros((len(scenes), B, 3))
    mask = np.zeros((len(scenes), B), bool)
    for i, s in enumerate(scenes):
        lo[i, : s.n_boxes] = s.lo
        hi[i, : s.n_boxes] = s.hi
        mask[i, : s.n_boxes] = True
    return lo, hi, mask
