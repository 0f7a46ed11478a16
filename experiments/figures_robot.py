"""Figure: PIPER's official collision meshes and the 11 capsule enclosures at 4 configurations.

``python -m experiments.figures_robot [-o results/figures/piper_capsules.png]``

Meshes are drawn decimated by vertex clustering (4 mm grid) for speed only; capsules are
drawn semi-transparent from the shipped capsule file (``larc_jax/data/piper_capsules.yaml``) (segment ``a..b`` in its link frame,
``radius`` including padding). Orthographic views with equal axis scales.
"""

from __future__ import annotations

import argparse
import io
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_OUT = ROOT / "results" / "figures" / "piper_capsules.png"

CONFIGS = [
    ("zero (home, folded)", [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]),
    ("forward reach", [0.0, 2.2, -2.0, 0.0, 0.0, 0.0]),
    ("reach down", [0.0, 1.8, -1.0, 0.0, 0.6, 0.0]),
    ("raised, wrist turned", [0.8, 1.2, -1.8, 1.0, -0.8, 0.5]),
]

LINK_COLOURS = {
    "base_link": "#7f7f7f", "link1": "#1f77b4", "link2": "#ff7f0e", "link3": "#2ca02c",
    "link4": "#d62728", "link5": "#9467bd", "link6": "#8c564b", "link7": "#e377c2",
    "link8": "#17becf",
}


def decimate(vertices: np.ndarray, faces: np.ndarray, cell: float = 0.004):
    """Vertex-clustering decimation (drawing only): merge vertices in ``cell``-sized voxels."""
    key = np.floor(vertices / cell).astype(np.int64)
    _, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    n = inv.max() + 1
    counts = np.bincount(inv, minlength=n).astype(float)
    v = np.stack([np.bincount(inv, weights=vertices[:, i], minlength=n) for i in range(3)], 1) / counts[:, None]
    f = inv[faces]
    keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    f = np.unique(np.sort(f[keep], axis=1), axis=0) if keep.any() else f[:0]
    # np.unique on sorted rows loses orientation; irrelevant for flat-shaded drawing.
    return v, f


def capsule_surface(a: np.ndarray, b: np.ndarray, r: float, n_u: int = 18, n_v: int = 7):
    """(X, Y, Z) grid of a capsule surface (cylinder + hemispherical caps) in world coordinates."""
    axis = b - a
    length = float(np.linalg.norm(axis))
    w = axis / length if length > 1e-12 else np.array([0.0, 0.0, 1.0])
    tmp = np.array([1.0, 0.0, 0.0]) if abs(w[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u1 = np.cross(w, tmp)
    u1 /= np.linalg.norm(u1)
    u2 = np.cross(w, u1)
    theta = np.linspace(0, 2 * np.pi, n_u)
    # profile: (axial offset, radial scale) from the bottom pole to the top pole
    phi_lo = np.linspace(-np.pi / 2, 0, n_v)
    phi_hi = np.linspace(0, np.pi / 2, n_v)
    axial = np.concatenate([r * np.sin(phi_lo), length + r * np.sin(phi_hi)])
    radial = np.concatenate([r * np.cos(phi_lo), r * np.cos(phi_hi)])
    ct, st = np.cos(theta), np.sin(theta)
    P = (a[None, None, :] + axial[:, None, None] * w[None, None, :]
         + radial[:, None, None] * (ct[None, :, None] * u1 + st[None, :, None] * u2))
    return P[..., 0], P[..., 1], P[..., 2]


def draw(out: str | Path = DEFAULT_OUT, capsule_path: str | Path | None = None, dpi: int = 130) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    from experiments.collision import CollisionModel
    from larc_jax.enclosure.robot_file import default_capsule_path, load_capsules
    from larc_jax.io import atomic_write_bytes
    from larc_jax.model.robot import forward_kinematics_np

    model = CollisionModel()
    robot = model.robot
    caps = load_capsules(capsule_path or default_capsule_path(), robot)
    A, B, R = np.asarray(caps.p_link_a), np.asarray(caps.p_link_b), np.asarray(caps.radius)
    dec = {}
    for link, meshes in model.meshes.items():
        V = np.concatenate([m.vertices for m in meshes])
        off = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
        F = np.concatenate([m.faces + o for m, o in zip(meshes, off)])
        dec[link] = decimate(np.asarray(V, float), np.asarray(F))

    fig = plt.figure(figsize=(12, 11))
    light = np.array([0.3, -0.5, 0.8])
    light /= np.linalg.norm(light)
    for k, (title, q) in enumerate(CONFIGS):
        ax = fig.add_subplot(2, 2, k + 1, projection="3d", proj_type="ortho")
        T = forward_kinematics_np(robot, np.asarray(q, float))
        pts = []
        for link, (v, f) in dec.items():
            Tl = T[robot.link_index(link)]
            vw = v @ Tl[:3, :3].T + Tl[:3, 3]
            tri = vw[f]
            nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
            shade = 0.45 + 0.5 * np.abs(nrm @ light)
            cols = np.clip(shade[:, None] * np.array([0.62, 0.62, 0.66]), 0, 1)
            pc = Poly3DCollection(tri, facecolors=cols, edgecolors="none", alpha=1.0)
            ax.add_collection3d(pc)
            pts.append(vw)
        for c in range(len(R)):
            Tl = T[caps.link_index[c]]
            a = Tl[:3, :3] @ A[c] + Tl[:3, 3]
            b = Tl[:3, :3] @ B[c] + Tl[:3, 3]
            X, Y, Z = capsule_surface(a, b, float(R[c]))
            col = LINK_COLOURS.get(caps.link_names[c], "tab:blue")
            ax.plot_surface(X, Y, Z, color=col, alpha=0.22, linewidth=0.3, edgecolor=col,
                            shade=False, rstride=1, cstride=1)
            pts.append(np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1))
        P = np.concatenate(pts)
        centre = (P.max(0) + P.min(0)) / 2
        half = (P.max(0) - P.min(0)).max() / 2 + 0.02
        ax.set_xlim(centre[0] - half, centre[0] + half)
        ax.set_ylim(centre[1] - half, centre[1] + half)
        ax.set_zlim(centre[2] - half, centre[2] + half)
        ax.set_box_aspect((1, 1, 1), zoom=1.2)
        ax.view_init(elev=18, azim=-58)
        ax.set_xlabel("x [m]", labelpad=2)
        ax.set_ylabel("y [m]", labelpad=2)
        ax.set_zlabel("z [m]", labelpad=2)
        ax.tick_params(labelsize=7, pad=0)
        qs = ", ".join(f"{v:g}" for v in q)
        ax.set_title(f"{title}\nq = [{qs}] rad", fontsize=10)
    handles = [plt.Line2D([], [], color=LINK_COLOURS[l], lw=6, alpha=0.5, label=l)
               for l in LINK_COLOURS if l in caps.link_names]
    handles.append(plt.Line2D([], [], color=(0.62, 0.62, 0.66), lw=6, label="official mesh"))
    fig.legend(handles=handles, loc="lower center", ncol=10, fontsize=9, frameon=False)
    fig.suptitle(f"PIPER collision meshes (grey, decimated for drawing) and the {len(R)} capsule "
                 f"enclosures (coloured, radius incl. {caps.padding_m * 1e3:g} mm padding)", fontsize=12)
    fig.subplots_adjust(left=0.0, right=0.97, bottom=0.06, top=0.91, wspace=0.02, hspace=0.2)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    plt.close(fig)
    out = Path(out)
    atomic_write_bytes(out, buf.getvalue())
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("-o", "--output", default=str(DEFAULT_OUT))
    ap.add_argument("--capsules", default=None)
    args = ap.parse_args(argv)
    out = draw(args.output, args.capsules)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
