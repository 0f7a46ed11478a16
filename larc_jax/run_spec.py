"""The run spec: one frozen, validated object holding every parameter that decides a certificate.

:class:`RunSpec` is what :func:`~larc_jax.engine.certify.certify`, :func:`~larc_jax.drivers.stream.certify_stream`,
the manifest (:mod:`larc_jax.drivers.manifest`, its job and its resume state), Dask and the command line
take, and what a :class:`~larc_jax.engine.results.DatasetResult` carries (``result.spec``). It is
validated once, when built (:class:`~larc_jax.errors.LarcInputError` naming the field), and
round-trips exactly through JSON (:meth:`RunSpec.to_json` / :meth:`RunSpec.from_json`; floats are
written as Python's shortest repr, which reads back to the same double). No JAX and no robot
here: a bad option is refused before anything is loaded. What needs the robot (joint and link
names, a tolerance's length) is checked where the robot is known (``certify``).

The model fields (``hold``, ``joints``, ``ignore_links``) say how the robot file is loaded (the
gripper's stated opening, the active joints, the links left out); ``certify`` is given a loaded
robot and checks them against it, and the result's spec records what the model really was.
"""

from __future__ import annotations

import dataclasses
import json
import math
import numbers
from typing import Mapping

from .defaults import (DEFAULT_COARSE_DEPTH, DEFAULT_ENCLOSURE, DEFAULT_MARGIN_M, DEFAULT_MAX_DEPTH,
                       DEFAULT_RUN_PADDING_M, METHODS, VELOCITY_MODES, check_depth, check_enclosure, check_margin,
                       check_padding)
from .errors import LarcInputError
from .io import short_repr as short

__all__ = ["RunSpec", "DTYPES"]

DTYPES = ("float64", "float32")
"""Geometry dtypes (:mod:`larc_jax.leaf.interval`); times and the curve stay float64."""


def _choice(value, choices, what: str) -> str:
    value = getattr(value, "value", value)  # an enum member (larc_jax.engine.certify.Method)
    if not isinstance(value, str) or value not in choices:
        raise LarcInputError(f"{what} {value!r}: one of {', '.join(choices)}")
    return value


def _nonneg(x, what: str, unit: str) -> float:
    if hasattr(x, "item") and getattr(x, "ndim", 1) == 0:  # a NumPy scalar
        x = x.item()
    if isinstance(x, bool) or not isinstance(x, numbers.Real) or not (math.isfinite(x) and x >= 0):
        raise LarcInputError(f"{what} {x!r}: must be a finite number >= 0 {unit}")
    return float(x)


def _names(value, what: str) -> tuple[str, ...]:
    if isinstance(value, str) or not isinstance(value, (list, tuple)):
        raise LarcInputError(f"{what}: expected a list of names, got {type(value).__name__}")
    for i, x in enumerate(value):
        if not isinstance(x, str) or not x:
            raise LarcInputError(f"{what}[{i}] {x!r}: expected a non-empty name")
    return tuple(value)


def _dtype(value) -> str:
    if isinstance(value, str):
        name = value
    else:  # np.float32, np.dtype("float32")
        name = getattr(value, "__name__", None) or getattr(value, "name", None)
        name = name if isinstance(name, str) else None
    if name not in DTYPES:
        raise LarcInputError(f"dtype {name or short(value)} is not supported (one of {', '.join(DTYPES)})")
    return name


def _tolerance(value, what: str = "tracking_tolerance"):
    """None, one number (every active joint), numbers per active joint (a tuple), or a mapping
    joint -> number (a sorted tuple of pairs); every number finite and >= 0."""
    unit = "(rad for a revolute joint, m for a prismatic one)"
    if value is None:
        return None
    if hasattr(value, "tolist"):  # a NumPy array or scalar
        value = value.tolist()
    if isinstance(value, Mapping) or (isinstance(value, tuple) and value and isinstance(value[0], tuple)):
        pairs = dict(value)
        for name in pairs:
            if not isinstance(name, str) or not name:
                raise LarcInputError(f"{what}: joint name {name!r} is not a non-empty string")
        return tuple(sorted((name, _nonneg(x, f"{what}[{name}]", unit)) for name, x in pairs.items()))
    if isinstance(value, (list, tuple)):
        if not value:
            raise LarcInputError(f"{what}: an empty list (give one number per active joint, or null)")
        return tuple(_nonneg(x, f"{what}[{i}]", unit) for i, x in enumerate(value))
    return _nonneg(value, what, unit)


def _hold(value) -> tuple[tuple[str, float], ...]:
    pairs = dict(value) if isinstance(value, (Mapping, list, tuple)) else None
    if pairs is None:
        raise LarcInputError(f"hold: expected a mapping joint -> value, got {type(value).__name__}")
    out = []
    for name, x in pairs.items():
        if not isinstance(name, str) or not name:
            raise LarcInputError(f"hold: joint name {name!r} is not a non-empty string")
        if hasattr(x, "item"):
            x = x.item()
        if isinstance(x, bool) or not isinstance(x, numbers.Real) or not math.isfinite(x):
            raise LarcInputError(f"hold[{name}] {x!r}: must be a finite number (rad or m)")
        out.append((name, float(x)))
    return tuple(sorted(out))


@dataclasses.dataclass(frozen=True)
class RunSpec:
    """Everything that decides a certificate (module docstring). Build it with keyword
    arguments; every field is validated and normalised in ``__post_init__``."""

    method: str = METHODS[0]
    """``larc``, ``fine``, ``coarse`` or ``reference`` (:data:`~larc_jax.defaults.METHODS`)."""
    margin_m: float = DEFAULT_MARGIN_M
    """Clearance margin rho to every box, m."""
    max_depth: int = DEFAULT_MAX_DEPTH
    coarse_depth: int = DEFAULT_COARSE_DEPTH
    """Depth of ``method="coarse"``."""
    enclosure: str = DEFAULT_ENCLOSURE
    """``hull`` (the cascade) or ``capsules``."""
    padding_m: float | None = None
    """Padding added to every enclosure (capsules and hull parts) on top of its proven containment
    of the link meshes, m: the certificate states that every link mesh grown by it stays more than
    ``margin_m`` from every obstacle. None (not stated): the enclosure's default,
    :data:`~larc_jax.defaults.DEFAULT_RUN_PADDING_M` (1 mm for ``capsules``, 0 for ``hull``); the
    spec then records the value."""
    swept: bool = False
    """Whether the swept stage (:mod:`larc_jax.leaf.swept`) runs where the midpoint tests leave a
    leaf open: each enclosure's hull at the two ends of the interval grown by a second-order
    motion radius."""
    dtype: str = DTYPES[0]
    """Geometry dtype; ``method="reference"`` always runs float64 (normalised here)."""
    velocities: str = VELOCITY_MODES[0]
    """How trajectory files are read: their recorded velocities or finite differences."""
    tracking_tolerance: float | tuple | None = None
    """None (the plan only), one number for every active joint, one per active joint (a tuple),
    or (joint, value) pairs (joints not named: 0); rad, m for a prismatic joint."""
    self_collision: bool = False
    self_margin_m: float = 0.0
    """Self-collision margin rho_self, m (with ``self_collision`` only)."""
    self_skip: tuple[str, ...] = ()
    """Link pairs ``"LINK:LINK"`` not checked (with ``self_collision`` only)."""
    hold: tuple[tuple[str, float], ...] = ()
    """Stated values of held joints (the gripper opening), sorted (joint, value) pairs."""
    joints: tuple[str, ...] = ()
    """The active joints; empty: the robot file's."""
    ignore_links: tuple[str, ...] = ()
    """Links left out of the certificate (only links that never move)."""

    def __post_init__(self):
        put = _setter(self)
        put("method", _choice(self.method, METHODS, "method"))
        put("margin_m", check_margin(self.margin_m, "margin_m"))
        put("max_depth", check_depth(self.max_depth, "max_depth"))
        put("coarse_depth", check_depth(self.coarse_depth, "coarse_depth"))
        put("enclosure", check_enclosure(self.enclosure, "enclosure"))
        put("padding_m", DEFAULT_RUN_PADDING_M[self.enclosure] if self.padding_m is None
            else check_padding(self.padding_m, "padding_m"))
        if not isinstance(self.swept, bool):
            raise LarcInputError(f"swept {self.swept!r}: must be true or false")
        dtype = _dtype(self.dtype)
        put("dtype", DTYPES[0] if self.method == "reference" else dtype)  # the reference is NumPy float64
        put("velocities", _choice(self.velocities, VELOCITY_MODES, "velocities"))
        put("tracking_tolerance", _tolerance(self.tracking_tolerance))
        if not isinstance(self.self_collision, bool):
            raise LarcInputError(f"self_collision {self.self_collision!r}: must be true or false")
        put("self_margin_m", _nonneg(self.self_margin_m, "self_margin_m", "m (the self-collision margin)"))
        put("self_skip", _names(self.self_skip, "self_skip"))
        if not self.self_collision and (self.self_margin_m or self.self_skip):
            raise LarcInputError("self_margin_m and self_skip need self_collision")
        put("hold", _hold(self.hold))
        put("joints", _names(self.joints, "joints"))
        put("ignore_links", tuple(dict.fromkeys(_names(self.ignore_links, "ignore_links"))))

    # -- the forms other code takes --------------------------------------------------------

    def tolerance_arg(self):
        """The tracking tolerance as :func:`~larc_jax.enclosure.tracking.check_tracking_tolerance` takes it."""
        tol = self.tracking_tolerance
        if isinstance(tol, tuple) and tol and isinstance(tol[0], tuple):
            return dict(tol)
        return list(tol) if isinstance(tol, tuple) else tol

    def to_dict(self) -> dict:
        """A JSON-ready mapping (every field; tuples as lists, pairs as mappings)."""
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.name == "hold" or (f.name == "tracking_tolerance" and isinstance(v, tuple) and v
                                    and isinstance(v[0], tuple)):
                v = dict(v)
            elif isinstance(v, tuple):
                v = list(v)
            out[f.name] = v
        return out

    def to_json(self) -> str:
        """The spec as one JSON object (sorted keys; :meth:`from_json` reads it back exactly)."""
        return json.dumps(self.to_dict(), sort_keys=True, allow_nan=False)

    @classmethod
    def from_dict(cls, doc, source: str = "run spec") -> "RunSpec":
        """A spec from :meth:`to_dict`'s form; unknown keys and bad values raise
        :class:`LarcInputError` naming ``source`` and the field."""
        if not isinstance(doc, dict):
            raise LarcInputError(f"{source}: expected a JSON object, got {type(doc).__name__}")
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(doc) - known)
        if unknown:
            raise LarcInputError(f"{source}: unknown field '{unknown[0]}' (known: {', '.join(sorted(known))})")
        doc = dict(doc)
        tol = doc.get("tracking_tolerance")
        if isinstance(tol, list):
            doc["tracking_tolerance"] = tuple(tol)
        for key in ("self_skip", "joints", "ignore_links"):
            if isinstance(doc.get(key), list):
                doc[key] = tuple(doc[key])
        try:
            return cls(**doc)
        except LarcInputError as exc:
            raise LarcInputError(f"{source}: {exc}") from None

    @classmethod
    def from_json(cls, text: str, source: str = "run spec") -> "RunSpec":
        """Inverse of :meth:`to_json` (LarcInputError on malformed JSON, unknown keys, bad values)."""
        try:
            doc = json.loads(text)
        except (TypeError, ValueError) as exc:
            raise LarcInputError(f"{source}: not valid JSON ({exc})") from None
        return cls.from_dict(doc, source)

    def differences(self, other: "RunSpec") -> list[str]:
        """The names of the fields in which ``other`` differs."""
        return [f.name for f in dataclasses.fields(self) if getattr(self, f.name) != getattr(other, f.name)]


def _setter(obj):
    """A setter for a frozen dataclass's fields inside its own ``__post_init__``."""
    return lambda name, value: object.__setattr__(obj, name, value)
