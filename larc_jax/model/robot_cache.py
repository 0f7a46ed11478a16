"""What the loaders build from a robot's files, kept on disk while the compilation cache is on.

With the cache on (:func:`larc_jax.compilation.enable_compile_cache`), three products are kept in
the cache folder, each keyed by :func:`larc_jax.compilation.library_hash` (the library's source
and the versions of the packages that built it) and by the SHA-256 of the bytes it was built
from, so a changed file, library or package never meets a stale entry:

* the robot model (:func:`cached_robot`, :func:`keep_robot`): the arrays and static structure
  :func:`larc_jax.model.urdf.load_robot` builds, keyed also by the loader's arguments (the
  mesh files the URDF names are still checked to exist);
* the URDF's parse (:func:`kept_text`, :func:`keep_text`: :mod:`larc_jax.model.urdf_tree`'s JSON,
  keyed by the file's SHA-256): a process that loads the robot with other held values, or
  reads its collision geometry, skips importing yourdfpy and trimesh;
* the hull parts (:func:`kept_arrays`, :func:`keep_arrays`, written by
  :func:`larc_jax.enclosure.hull.hull_model`, keyed by the SHA-256 of the URDF and of every
  collision mesh as read now, and by the robot's content): a process skips reading the meshes
  and Qhull.

An entry is trusted as the compiled kernels beside it are: whoever can write the cache folder
can change what runs. ``larc verify`` trusts none of them: it re-proves the enclosures from the
files (:mod:`larc_jax.enclosure.proof`). A missing, unreadable or unwritable entry only costs
the work it would have saved.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

from ..compilation import export_dir, library_hash

__all__ = ["cached_robot", "keep_robot", "kept_text", "keep_text", "kept_arrays", "keep_arrays"]


def _entry_path(kind: str, key_parts: dict, suffix: str) -> Path | None:
    """Where the ``kind`` entry for ``key_parts`` lives, or None while the cache is off."""
    folder = export_dir()
    if folder is None:
        return None
    import json

    key = hashlib.sha256((library_hash() + json.dumps(key_parts, sort_keys=True, default=str)).encode()).hexdigest()
    return folder.parent / kind / f"{key[:40]}{suffix}"


def _write(path: Path | None, data: bytes) -> None:
    if path is None:
        return
    from ..io import atomic_write_bytes

    try:
        atomic_write_bytes(path, data)
    except OSError:
        pass


def kept_text(kind: str, key_parts: dict) -> str | None:
    """The text :func:`keep_text` kept for ``(kind, key_parts)``, or None."""
    path = _entry_path(kind, key_parts, ".json")
    try:
        return None if path is None else path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return None


def keep_text(kind: str, key_parts: dict, text: str) -> None:
    """Keep ``text`` for :func:`kept_text` (atomically; nothing while the cache is off)."""
    _write(_entry_path(kind, key_parts, ".json"), text.encode("utf-8"))


def kept_arrays(kind: str, key_parts: dict) -> dict | None:
    """The arrays :func:`keep_arrays` kept for ``(kind, key_parts)`` (name -> array), or None."""
    path = _entry_path(kind, key_parts, ".npz")
    if path is None or not path.is_file():
        return None
    import numpy as np

    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: np.array(z[k]) for k in z.files}
    except Exception:  # noqa: BLE001 - unreadable: build again
        return None


def keep_arrays(kind: str, key_parts: dict, arrays: dict) -> None:
    """Keep ``arrays`` (name -> array, no objects) for :func:`kept_arrays`."""
    path = _entry_path(kind, key_parts, ".npz")
    if path is None:
        return
    import io

    import numpy as np

    buf = io.BytesIO()
    np.savez(buf, **arrays)
    _write(path, buf.getvalue())


def cached_robot(key_parts: dict):
    """The :class:`~larc_jax.model.robot.Robot` kept by :func:`keep_robot` for these loader inputs
    (which must include the URDF's SHA-256), or None (cache off, not kept yet, unreadable, or a
    mesh file it names has gone)."""
    kept = kept_arrays("robots", key_parts)
    if kept is None:
        return None
    import json

    from .robot import JointType, Robot

    try:
        meta = json.loads(str(kept.pop("meta")))
        arrays = {k: kept[k] for k in _ROBOT_ARRAYS}
    except (KeyError, ValueError):
        return None
    if not all(Path(m).is_file() for m in meta.pop("meshes")):
        return None  # let the loader name the missing file
    meta = {k: tuple(tuple(x) if isinstance(x, list) else x for x in v) if isinstance(v, list) else v
            for k, v in meta.items()}
    meta["joint_type"] = tuple(JointType(t) for t in meta["joint_type"])
    return Robot(**arrays, **meta)


_ROBOT_ARRAYS = ("T_parent_joint", "axis", "q_held", "q_lower", "q_upper")


def keep_robot(key_parts: dict, robot, meshes) -> None:
    """Keep ``robot`` (built from ``key_parts``) for :func:`cached_robot`; ``meshes`` are the
    mesh files its URDF names."""
    if export_dir() is None:
        return
    import dataclasses
    import json

    import numpy as np

    meta = {f.name: getattr(robot, f.name) for f in dataclasses.fields(robot) if f.metadata.get("static")}
    meta["joint_type"] = [int(t) for t in meta["joint_type"]]
    meta["meshes"] = [str(m) for m in meshes]
    keep_arrays("robots", key_parts, {"meta": np.array(json.dumps(meta)),
                                      **{k: np.asarray(getattr(robot, k)) for k in _ROBOT_ARRAYS}})
