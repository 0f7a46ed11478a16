"""The fields of a certificate document (:mod:`larc_jax.products.certificate` writes them), level by
level, and the check that a document holds no other (:func:`check_certificate_fields`): the
checker (:mod:`larc_jax.products.verify`) refuses a field it does not know rather than skip it, since a
field it skipped could carry a claim it never checked. No JAX, no NumPy: ``larc verify`` imports
it.

Mappings keyed by names rather than fields (``robot.geometry``, ``robot.held_joints``,
``robot.stated_joints``, ``parameters.hold``, ``parameters.tracking_tolerance``: link and joint
names) are not checked here; the checker compares them with what it derives. ``parameters`` is a
:class:`~larc_jax.run_spec.RunSpec` (its fields, which
:meth:`~larc_jax.run_spec.RunSpec.from_dict` also holds to).
"""

from __future__ import annotations

import dataclasses

from ..io import check_keys
from ..run_spec import RunSpec

__all__ = ["CERTIFICATE_FIELDS", "check_certificate_fields"]

_TRAJECTORY = {
    "id", "file", "sha256", "arrays_sha256", "velocities", "scene", "certified", "t_start", "t_end", "rounding",
    "leaves",
}
CERTIFICATE_FIELDS = {
    "": {"format", "version", "float_encoding", "parameters", "robot", "scenes", "trajectories"},
    "parameters": {f.name for f in dataclasses.fields(RunSpec)},
    "robot": {"file", "sha256", "urdf", "urdf_sha256", "geometry", "active_joints", "held_joints", "stated_joints",
              "capsules", "enclosures_sha256"},
    "scenes[]": {"file", "sha256", "arrays_sha256", "name", "boxes", "assumes"},
    "trajectories[]": _TRAJECTORY,
    "trajectories[].rounding": {"offset_s", "tau_s", "omega_slack", "guard_m", "hull_guard_m"},
    "trajectories[].leaves": {"depth", "index", "t0", "t1", "clearance_m", "guard_m", "certified", "capsule", "box",
                              "other_capsule", "stage"},
}
"""The fields at each level: ``a.b`` is the mapping at ``b`` in the one at ``a``; ``x[]`` each
mapping of the list ``x``."""


def check_certificate_fields(doc, source: str) -> None:
    """:class:`~larc_jax.errors.LarcInputError` ``"<source>: <where>: unknown field '<key>'"``
    for a field of ``doc`` that :data:`CERTIFICATE_FIELDS` does not list. Levels that are not
    mappings (or lists of mappings) are left to the checker's type checks."""
    pending = [("", "", doc)]   # (level in CERTIFICATE_FIELDS, path in the document, value)
    while pending:
        level, path, value = pending.pop()
        if not isinstance(value, dict) or level not in CERTIFICATE_FIELDS:
            continue
        check_keys(value, CERTIFICATE_FIELDS[level], source, path)
        for key, sub in value.items():
            child, child_path = (f"{level}.{key}", f"{path}.{key}") if level else (key, key)
            if f"{child}[]" in CERTIFICATE_FIELDS and isinstance(sub, list):
                pending.extend((f"{child}[]", f"{child_path}[{k}]", item) for k, item in enumerate(sub))
            else:
                pending.append((child, child_path, sub))
