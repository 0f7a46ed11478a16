"""Defaults and choices shared by the library and the command line (no JAX import here, so the
CLI can build its parser without loading JAX). Each parameter has this one owner."""

from __future__ import annotations

__all__ = [
    "DEFAULT_MARGIN_M", "DEFAULT_MAX_DEPTH", "DEFAULT_COARSE_DEPTH", "MAX_DEPTH_LIMIT",
    "METHODS", "VELOCITY_MODES", "DEFAULT_PADDING_M", "DEFAULT_CHUNK_SIZE", "POSITION_TOLERANCE",
    "ENCLOSURES", "DEFAULT_ENCLOSURE", "DEFAULT_RUN_PADDING_M", "check_margin", "check_depth", "check_enclosure",
    "check_padding",
]

DEFAULT_MARGIN_M = 0.01
"""Clearance margin ρ, m (the paper's 10 mm)."""
DEFAULT_MAX_DEPTH = 9
"""Deepest bisection: leaves of T / 2**9 = T / 512 (the paper's fixed-fine resolution)."""
DEFAULT_COARSE_DEPTH = 4
"""Depth of the fixed-coarse baseline: 16 intervals."""
MAX_DEPTH_LIMIT = 20
"""Largest accepted ``max_depth`` (2**20 leaves per trajectory)."""
METHODS = ("larc", "fine", "coarse", "reference")
"""``larc`` (batched adaptive), ``fine`` / ``coarse`` (every interval of depth ``max_depth`` /
``DEFAULT_COARSE_DEPTH``), ``reference`` (the paper's Algorithm 1 in NumPy)."""
VELOCITY_MODES = ("recorded", "finite-difference")
"""``recorded``: use the file's velocities (refuse a file without them); ``finite-difference``:
compute them from the positions (:func:`larc_jax.model.trajectory.finite_difference_velocities`)."""
DEFAULT_CHUNK_SIZE = 256
"""Trajectories per chunk when streaming (``certify_stream``, ``larc certify --manifest``): large
enough to keep the frontier kernels busy, small enough that a chunk takes tens of MB."""
POSITION_TOLERANCE = 1e-6
"""Positions may exceed a joint limit by at most this much (rad or m): recorders round. The
motion constants of joints above an active prismatic joint are derived for its limits widened by
twice this (:mod:`larc_jax.enclosure.motion`), so larger excursions are refused
(:func:`larc_jax.model.trajectory.validate_trajectory`), between waypoints too."""
DEFAULT_PADDING_M = 0.001
"""Padding a fitted robot file records: added to its capsule radii on top of the proven containment,
m (the paper's 1 mm). A run may state another (``RunSpec.padding_m``)."""
ENCLOSURES = ("hull", "capsules")
"""``hull``: the cascade (capsule test, then the convex-hull test on what it leaves open;
:mod:`larc_jax.leaf.cascade`); ``capsules``: the capsule test alone (the paper's model)."""
DEFAULT_ENCLOSURE = ENCLOSURES[0]
DEFAULT_RUN_PADDING_M = {"capsules": DEFAULT_PADDING_M, "hull": 0.0}
"""The padding a run adds to every enclosure on top of its proven containment of the link meshes, m,
when the run does not state one (``RunSpec.padding_m``, ``--padding``), per enclosure:

* ``capsules``: the paper's 1 mm (its Stage B model).
* ``hull`` (the cascade, both its stages): 0. Every enclosure of the cascade holds every mesh vertex
  exactly (the capsules' cores and the hull parts are proven to contain them,
  :mod:`larc_jax.enclosure.proof`), so a certificate with no padding states what it always states,
  that every link mesh stays more than rho from every obstacle; rho is where a user puts the
  allowance for what the model does not hold (mesh error, calibration). The padding only widened
  the enclosures and moved the certification boundary away from the true one
  (``results/tightness`` measures the difference)."""


def check_margin(margin, what: str = "margin") -> float:
    """ρ as a float: a finite number > 0 (paper eq. 3); else :class:`LarcInputError` naming ``what``."""
    import math
    import numbers

    from .errors import LarcInputError

    if isinstance(margin, bool) or not isinstance(margin, numbers.Real) or not (math.isfinite(margin) and margin > 0):
        raise LarcInputError(f"{what} {margin!r}: must be a finite number > 0 m (the clearance margin rho, paper eq. 3)")
    return float(margin)


def check_enclosure(enclosure, what: str = "enclosure") -> str:
    """One of :data:`ENCLOSURES`; else :class:`LarcInputError`."""
    from .errors import LarcInputError

    if enclosure not in ENCLOSURES:
        raise LarcInputError(f"{what} {enclosure!r}: one of {', '.join(ENCLOSURES)}")
    return enclosure


def check_depth(depth, what: str = "max_depth") -> int:
    """A bisection depth: an integer in 0..MAX_DEPTH_LIMIT; else :class:`LarcInputError`."""
    import numbers

    from .errors import LarcInputError

    if isinstance(depth, bool) or not isinstance(depth, numbers.Integral) or not 0 <= depth <= MAX_DEPTH_LIMIT:
        raise LarcInputError(f"{what} {depth!r}: must be an integer in 0..{MAX_DEPTH_LIMIT}")
    return int(depth)


def check_padding(padding, what: str = "padding_m") -> float:
    """A padding as a float: a finite number >= 0 m; else :class:`LarcInputError` naming ``what``."""
    import math
    import numbers

    from .errors import LarcInputError

    if hasattr(padding, "item") and getattr(padding, "ndim", 1) == 0:  # a NumPy scalar
        padding = padding.item()
    if isinstance(padding, bool) or not isinstance(padding, numbers.Real) or \
            not (math.isfinite(padding) and padding >= 0):
        raise LarcInputError(f"{what} {padding!r}: must be a finite number >= 0 m (added to every enclosure on top "
                             "of its proven containment)")
    return float(padding)
