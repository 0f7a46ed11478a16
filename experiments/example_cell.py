"""Writes the data files of the example camera cell (``configs/examples/cell_camera.yaml``).

    python -m experiments.example_cell [--out configs/examples]

* ``bracket.stl``: an L-shaped bracket (two boxes, 24 triangles; not convex), in its own frame;
* ``table_cloud.npy``: a synthetic depth-camera point cloud (float64, (N, 3), base frame, m) of a
  table top in front of the arm with a box and a can on it, as a camera at (0.95, 0, 0.65)
  looking at (0.35, 0, 0) sees them: one ray per pixel of a 96 x 72 image (60 x 45 degree field),
  the first hit kept (trimesh's ray casting), so only visible surfaces have points.

Deterministic: the committed files are what this writes (``tests/test_point_sets.py`` checks).
"""

from __future__ import annotations

import argparse
import io
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
CAMERA = np.array([0.95, 0.0, 0.65])
TARGET = np.array([0.35, 0.0, 0.0])
PIXELS = (96, 72)
FIELD_DEG = (60.0, 45.0)

__all__ = ["bracket_mesh", "table_cloud", "main"]


def bracket_mesh():
    """The L bracket (trimesh), 0.3 x 0.3 m, 0.05 m thick, 0.2 m tall, its corner at the origin."""
    import trimesh

    a = trimesh.creation.box([0.3, 0.05, 0.2])
    a.apply_translation([0.15, 0.025, 0.1])
    b = trimesh.creation.box([0.05, 0.3, 0.2])
    b.apply_translation([0.025, 0.15, 0.1])
    return trimesh.util.concatenate([a, b])


def _cell_meshes():
    import trimesh

    table = trimesh.creation.box([0.5, 0.9, 0.04])
    table.apply_translation([0.45, 0.0, -0.02])  # top face at z = 0
    box = trimesh.creation.box([0.08, 0.08, 0.08])
    box.apply_translation([0.38, -0.18, 0.04])
    can = trimesh.creation.cylinder(radius=0.035, height=0.12, sections=32)
    can.apply_translation([0.42, 0.2, 0.06])
    return trimesh.util.concatenate([table, box, can])


def table_cloud() -> np.ndarray:
    """The visible points of the table, box and can (module docstring)."""
    from trimesh.ray.ray_triangle import RayMeshIntersector

    forward = TARGET - CAMERA
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    w, h = PIXELS
    tx, ty = (np.tan(np.radians(f / 2)) for f in FIELD_DEG)
    u = (np.arange(w) + 0.5) / w * 2 - 1
    v = (np.arange(h) + 0.5) / h * 2 - 1
    U, V = np.meshgrid(u * tx, v * ty)
    dirs = forward + U.reshape(-1, 1) * right + V.reshape(-1, 1) * up
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    origins = np.broadcast_to(CAMERA, dirs.shape)
    hits, rays, _ = RayMeshIntersector(_cell_meshes()).intersects_location(origins, dirs, multiple_hits=False)
    order = np.argsort(rays, kind="stable")
    return np.ascontiguousarray(hits[order], dtype=np.float64)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default=str(ROOT / "configs" / "examples"))
    args = p.parse_args(argv)
    from larc_jax.io import atomic_write_bytes

    out = Path(args.out)
    atomic_write_bytes(out / "bracket.stl", bracket_mesh().export(file_type="stl"))
    buf = io.BytesIO()
    np.save(buf, table_cloud(), allow_pickle=False)
    atomic_write_bytes(out / "table_cloud.npy", buf.getvalue())
    print(f"wrote {out / 'bracket.stl'} and {out / 'table_cloud.npy'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
