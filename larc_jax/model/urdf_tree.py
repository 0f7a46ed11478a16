"""What the loaders read of a URDF's parse, as plain frozen data that round-trips through JSON.

yourdfpy parses the file (:func:`larc_jax.model.urdf.load_urdf_model`); the loaders read each
robot's name, each link's name and ``<collision>`` elements and each joint's name, type, parent, child, origin,
axis, limits and mimic, and nothing else. :func:`urdf_tree` copies exactly those fields, under
yourdfpy's own names (``joint.limit.lower``, ``collision.geometry.mesh.filename``), into the frozen
dataclasses below; every loader reads the copy, never yourdfpy's objects.

Why a copy: it is the part of the parse worth keeping across processes. :func:`tree_to_json` and
:func:`tree_from_json` are exact inverses (floats are written by ``repr``, which round-trips
float64; NaN and infinities are kept, and the loaders refuse them as before), so with the
compilation cache on (:mod:`larc_jax.model.robot_cache`) a later process that reads the same
bytes (same SHA-256) finds the parse without importing yourdfpy, trimesh and SciPy (about 0.6 s on
a 2-core machine). tests/test_robot_cache.py checks the round trip on every URDF the tests use.
"""

from __future__ import annotations

import dataclasses
import functools
import json

import numpy as np

__all__ = ["UrdfTree", "urdf_tree", "tree_to_json", "tree_from_json"]

_STR, _NUM, _ARRAY = "str", "num", "array"


def _f(kind):
    """A field of ``kind``: ``str``, ``num`` (float or None), ``array`` (float64 array or None), a
    dataclass (one, or None) or ``(dataclass,)`` (a tuple of them)."""
    return dataclasses.field(metadata={"kind": kind})


@dataclasses.dataclass(frozen=True)
class Mesh:
    filename: str = _f(_STR)
    scale: np.ndarray | None = _f(_ARRAY)


@dataclasses.dataclass(frozen=True)
class Box:
    size: np.ndarray = _f(_ARRAY)


@dataclasses.dataclass(frozen=True)
class Sphere:
    radius: float = _f(_NUM)


@dataclasses.dataclass(frozen=True)
class Cylinder:
    radius: float = _f(_NUM)
    length: float = _f(_NUM)


@dataclasses.dataclass(frozen=True)
class Geometry:
    box: Box | None = _f(Box)
    cylinder: Cylinder | None = _f(Cylinder)
    sphere: Sphere | None = _f(Sphere)
    mesh: Mesh | None = _f(Mesh)


@dataclasses.dataclass(frozen=True)
class Collision:
    origin: np.ndarray | None = _f(_ARRAY)
    geometry: Geometry | None = _f(Geometry)


@dataclasses.dataclass(frozen=True)
class Link:
    name: str = _f(_STR)
    collisions: tuple = _f((Collision,))


@dataclasses.dataclass(frozen=True)
class Limit:
    lower: float | None = _f(_NUM)
    upper: float | None = _f(_NUM)


@dataclasses.dataclass(frozen=True)
class Mimic:
    joint: str = _f(_STR)
    multiplier: float | None = _f(_NUM)
    offset: float | None = _f(_NUM)


@dataclasses.dataclass(frozen=True)
class Joint:
    name: str = _f(_STR)
    type: str = _f(_STR)
    parent: str = _f(_STR)
    child: str = _f(_STR)
    origin: np.ndarray | None = _f(_ARRAY)
    axis: np.ndarray | None = _f(_ARRAY)
    limit: Limit | None = _f(Limit)
    mimic: Mimic | None = _f(Mimic)


@dataclasses.dataclass(frozen=True)
class UrdfTree:
    """The robot's name, links and joints, in file order (yourdfpy's ``model.robot.name``,
    ``.links``, ``.joints``)."""

    name: str = _f(_STR)
    links: tuple = _f((Link,))
    joints: tuple = _f((Joint,))

    @functools.cached_property
    def link_map(self) -> dict:
        return {link.name: link for link in self.links}

    @functools.cached_property
    def joint_map(self) -> dict:
        return {j.name: j for j in self.joints}


def _copy(source, cls, get):
    """``cls`` with each field read from ``source`` by ``get(source, name)`` and converted by its kind."""
    if source is None:
        return None
    values = {}
    for field in dataclasses.fields(cls):
        kind, value = field.metadata["kind"], get(source, field.name)
        if value is None:
            values[field.name] = None
        elif kind == _STR:
            values[field.name] = str(value)
        elif kind == _NUM:
            values[field.name] = float(value)
        elif kind == _ARRAY:
            array = np.array(value, dtype=np.float64)
            array.flags.writeable = False
            values[field.name] = array
        elif isinstance(kind, tuple):
            values[field.name] = tuple(_copy(item, kind[0], get) for item in value)
        else:
            values[field.name] = _copy(value, kind, get)
    return cls(**values)


def urdf_tree(model) -> UrdfTree:
    """The fields of a ``yourdfpy.URDF`` parse that the loaders read (module docstring)."""
    return _copy(model.robot, UrdfTree, getattr)


def _plain(value):
    if dataclasses.is_dataclass(value):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, tuple):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    return value


def tree_to_json(tree: UrdfTree) -> str:
    """``tree`` as JSON text (:func:`tree_from_json` gives it back exactly)."""
    return json.dumps(_plain(tree))


def tree_from_json(text: str) -> UrdfTree:
    """The :class:`UrdfTree` that :func:`tree_to_json` wrote."""
    return _copy(json.loads(text), UrdfTree, lambda d, name: d[name])
