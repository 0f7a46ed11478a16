"""Option values written as text (``JOINT=VALUE``, ``J1,J2``, ``NAME=PATH``, ``LINK=N``) as Python values.

The ``larc`` command line reads ``--hold``, ``--joints``, ``--package-dir`` and
``--capsules-per-link`` with these; Python callers may too (``load_robot_file(path,
hold=parse_hold(["joint7=0"]))``). Each raises :class:`~larc_jax.errors.LarcInputError` naming
the option (``option``, e.g. ``"hold"`` from Python) and the bad item. A repeatable option takes
a list of items (a single string is one item); a name given twice is refused, never silently
overridden. No NumPy or JAX here: the command line parses before it loads either.
"""

from __future__ import annotations

import math
import re
from typing import Iterable, Iterator

from .errors import LarcInputError

__all__ = ["parse_hold", "parse_joints", "parse_package_dirs", "parse_capsules_per_link", "parse_tracking_tolerance"]


def _named_items(items: Iterable[str] | str | None, option: str, form: str) -> Iterator[tuple[str, str, str]]:
    """``(name, value, item)`` of each ``NAME=VALUE`` item; a malformed item or a name given
    twice is refused."""
    seen = set()
    for item in [items] if isinstance(items, str) else (items or []):
        if not isinstance(item, str):
            raise LarcInputError(f"{option} {item!r}: expected a string {form}")
        name, sep, value = item.partition("=")
        if not sep or not name or not value:
            raise LarcInputError(f"{option} '{item}': expected {form}")
        if name in seen:
            raise LarcInputError(f"{option} {name} is given twice")
        seen.add(name)
        yield name, value, item


def parse_hold(items: Iterable[str] | str | None, option: str = "--hold") -> dict[str, float]:
    """``JOINT=VALUE`` items (``--hold joint7=0``) as ``{joint: value}``; values finite numbers."""
    held = {}
    for joint, value, item in _named_items(items, option, "JOINT=VALUE with a finite number"):
        try:
            number = float(value)
        except ValueError:
            number = math.nan
        if not math.isfinite(number):
            raise LarcInputError(f"{option} '{item}': expected JOINT=VALUE with a finite number")
        held[joint] = number
    return held


def parse_joints(value: str | None, option: str = "--joints") -> list[str] | None:
    """``j1,j2,...`` (``--joints``) as a list of joint names; ``None`` or empty: ``None`` (the
    robot file's active joints)."""
    if not value:
        return None
    if not isinstance(value, str):
        raise LarcInputError(f"{option} {value!r}: expected comma-separated joint names")
    names = [n.strip() for n in value.split(",")]
    if not all(names):
        raise LarcInputError(f"{option} '{value}': expected comma-separated joint names")
    return names


def parse_package_dirs(items: Iterable[str] | str | None, option: str = "--package-dir") -> dict[str, str]:
    """``NAME=PATH`` items (``--package-dir piper_description=/opt/piper``) as ``{package: folder}``."""
    return {name: path for name, path, _ in _named_items(items, option, "NAME=PATH")}


def parse_capsules_per_link(items: Iterable[str] | str | None, option: str = "--capsules-per-link") -> dict[str, int]:
    """``LINK=N`` items (``--capsules-per-link link6=2``) as ``{link: N}``; N is 1 or 2."""
    out = {}
    for link, count, item in _named_items(items, option, "LINK=1 or LINK=2"):
        if not re.fullmatch(r"[12]", count):
            raise LarcInputError(f"{option} '{item}': expected LINK=1 or LINK=2")
        out[link] = int(count)
    return out


def parse_tracking_tolerance(text: str, option: str = "--tracking-tolerance") -> float | dict[str, float]:
    """``RAD`` (every joint) as a float, or ``JOINT=VALUE,JOINT=VALUE,...`` as a dict (a joint
    given twice is refused); :attr:`~larc_jax.run_spec.RunSpec.tracking_tolerance` and
    :func:`~larc_jax.enclosure.tracking.check_tracking_tolerance` check the values."""
    text = text.strip()
    if "=" not in text:
        try:
            return float(text)
        except ValueError:
            raise LarcInputError(f"{option} '{text}': expected a number or JOINT=VALUE,...") from None
    out = {}
    for name, value, item in _named_items([part.strip() for part in text.split(",")], option, "JOINT=VALUE"):
        try:
            out[name] = float(value)
        except ValueError:
            raise LarcInputError(f"{option} '{item}': expected JOINT=VALUE (a number)") from None
    return out
