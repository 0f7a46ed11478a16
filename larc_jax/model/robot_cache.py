"""The robot model a loader built, kept on disk while the compilation cache is on.

With the cache on (:func:`larc_jax.compilation.enable_compile_cache`),
:func:`larc_jax.model.urdf.load_robot` keeps the arrays and static structure of the robot it
builds, keyed by :func:`larc_jax.compilation.library_hash`, the URDF's SHA-256 and the loader's
arguments: a later process skips parsing the URDF and importing its parser (yourdfpy, trimesh).
The mesh files the URDF names are still checked to exist.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

from ..compilation import export_dir, library_hash

__all__ = ["cached_robot", "keep_robot"]


def _robot_path(key_parts: dict) -> Path | None:
    folder = export_dir()
    if folder is None:
        return None
    import json

    key = hashlib.sha256((library_hash() + json.dumps(key_parts, sort_keys=True, default=str)).encode()).hexdigest()
    return folder.parent / "robots" / f"{key[:40]}.npz"


def cached_robot(key_parts: dict):
    """The :class:`~larc_jax.model.robot.Robot` kept by :func:`keep_robot` for these loader inputs
    (which must include the URDF's SHA-256), or None (cache off, not kept yet, unreadable, or a
    mesh file it names has gone)."""
    path = _robot_path(key_parts)
    if path is None or not path.is_file():
        return None
    import json

    import numpy as np

    from .robot import JointType, Robot

    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            arrays = {k: np.array(z[k]) for k in ("T_parent_joint", "axis", "q_held", "q_lower", "q_upper")}
    except Exception:  # noqa: BLE001 - unreadable: build the robot again
        return None
    if not all(Path(m).is_file() for m in meta.pop("meshes")):
        return None  # let the loader name the missing file
    meta = {k: tuple(tuple(x) if isinstance(x, list) else x for x in v) if isinstance(v, list) else v
            for k, v in meta.items()}
    meta["joint_type"] = tuple(JointType(t) for t in meta["joint_type"])
    return Robot(**arrays, **meta)


def keep_robot(key_parts: dict, robot, meshes) -> None:
    """Keep ``robot`` (built from ``key_parts``) for :func:`cached_robot`; ``meshes`` are the
    mesh files its URDF names."""
    path = _robot_path(key_parts)
    if path is None:
        return
    import dataclasses
    import io
    import json

    import numpy as np

    from ..io import atomic_write_bytes

    meta = {f.name: getattr(robot, f.name) for f in dataclasses.fields(robot) if f.metadata.get("static")}
    meta["joint_type"] = [int(t) for t in meta["joint_type"]]
    meta["meshes"] = [str(m) for m in meshes]
    buf = io.BytesIO()
    np.savez(buf, meta=np.array(json.dumps(meta)), **{k: np.asarray(getattr(robot, k)) for k in (
        "T_parent_joint", "axis", "q_held", "q_lower", "q_upper")})
    try:
        atomic_write_bytes(path, buf.getvalue())
    except OSError:
        pass
