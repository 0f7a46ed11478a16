"""Error types.

Every problem with user-supplied input (URDF, meshes, capsule files, trajectories, scenes) is
raised as :class:`LarcInputError` with a one-line message that names the file, the field and the
index. The command-line interface turns it into that line on stderr and exit status 2.

A message quotes user text (file names, keys, a scene's ``frame``), which may hold a newline
or another control character: :class:`OneLineError` escapes those (:func:`one_line`) when the
error is built, so every message is one line wherever it is printed.
"""

from __future__ import annotations

import re

__all__ = ["one_line", "OneLineError", "LarcInputError", "GeometryChanged"]

_CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f\u2028\u2029]")


def one_line(text: str) -> str:
    """``text`` with every control character (newline, tab, escape, C1, Unicode line and
    paragraph separators) written as its Python escape (``\\n``, ``\\x1b``, ``\\u2028``)."""
    return _CONTROL.sub(lambda m: repr(m.group())[1:-1], text)


class OneLineError(Exception):
    """An error whose string arguments are made one line (:func:`one_line`) when it is built."""

    def __init__(self, *args):
        super().__init__(*(one_line(a) if isinstance(a, str) else a for a in args))


class LarcInputError(OneLineError, ValueError):
    """Bad input: the message names the file, field and index of the problem."""


class GeometryChanged(LarcInputError):
    """A URDF or collision mesh differs from the one a robot file (or a certificate) was made
    with: the hash recorded then and the file now disagree."""
