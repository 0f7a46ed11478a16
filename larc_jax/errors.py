"""Error types.

Every problem with user-supplied input (URDF, meshes, capsule files, trajectories, scenes) is
raised as :class:`LarcInputError` with a one-line message that names the file, the field and the
index. The command-line interface turns it into that line on stderr and exit status 2.
"""

from __future__ import annotations


class LarcInputError(ValueError):
    """Bad input: the message names the file, field and index of the problem."""


class GeometryChanged(LarcInputError):
    """A URDF or collision mesh differs from the one a robot file (or a certificate) was made
    with: the hash recorded then and the file now disagree."""
