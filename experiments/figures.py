"""Stage B figures (matplotlib, Agg) into ``<out>/figures/``.

* ``outcomes_vs_audit.png`` — LARC decision against the sampled FCL audit, per scene (stacked
  counts: certified & sampled-clear, uncertified & sampled-clear = conservative rejection,
  uncertified & audit collision, certified & audit collision = FCL-detected false-safe).
* ``eval_ratio.png`` — LARC / fixed-fine interval evaluations per trajectory, by scene (log axis);
  a bar marks each scene's pooled ratio (sum of LARC evaluations / sum of fine's).
* ``runtime_ratio.png`` — paired fixed-fine / LARC runtime per trajectory on a log axis; circles
  are trajectories, diamonds scene medians.
* ``results.png`` — the three panels above side by side (the paper's results figure).
* ``frontier_levels.png`` — LARC frontier per depth (passed / inconclusive) against fixed-fine's
  ``2^d N`` intervals at that depth (fine evaluates depth 9 only).
* ``scene_replay.png`` — per scene, the trajectory whose LARC evaluation count is closest to the
  scene median (ties: smallest id), in three orthographic views: capsules at t = 0, T/2 and T
  (each capsule projects exactly to a 2-D "stadium": the points within its radius of the
  projected segment), the gripper-base path (the origin of the protocol's
  ``generation.endpoint_point_link``, link7: the point the endpoint regions constrain), world
  axes, the obstacle boxes, and the mounting plane z = 0 of the base (hatched below: the arm's
  base stands on it; the open scene has no boxes, and its poses may reach below it). Poses only:
  no interval motion inflation.
* ``workspace.png`` — ``workspace_samples`` configurations drawn uniformly within the six
  joint limits (URDF) from ``workspace_seed``: positions of the same gripper-base point in three
  projections, with the dashed convex hull of each projection as a visual guide (not a
  reachability bound).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pandas as pd

os.environ.setdefault("MPLBACKEND", "Agg")

from experiments.common import Layout, dataset_index, scene_label, scene_paths

__all__ = ["make_figures", "figure_outputs", "FIGURES", "CODE", "replay_choice", "point_link"]

CODE = ("experiments.figures",)
"""Modules whose import closure is the figures stage's code."""
FIGURES = ("outcomes_vs_audit", "eval_ratio", "runtime_ratio", "results", "frontier_levels",
           "scene_replay", "workspace")
VARIANT_STYLE = {"ompl_planned": dict(color="#1f77b4", label="ompl_planned"),
                 "direct_smoothstep": dict(color="#d62728", label="direct_smoothstep")}
OUTCOME_STYLE = [
    ("certified & sampled-clear", "#2ca02c"),
    ("uncertified & sampled-clear", "#ff7f0e"),
    ("uncertified & audit collision", "#7f7f7f"),
    ("certified & audit collision", "#d62728"),
]
POSE_COLORS = {"t = 0": "#1f77b4", "t = T/2": "#9467bd", "t = T": "#2ca02c"}


def point_link(config: dict) -> str:
    """The gripper-base link whose origin the figures trace: the generation's endpoint point
    (one owner: the protocol's ``generation.endpoint_point_link``)."""
    return str(config["generation"].get("endpoint_point_link", "link7"))


def figure_outputs(layout: Layout) -> list[Path]:
    return [layout.figures_dir / f"{f}.png" for f in FIGURES]


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.rcParams.update({"font.size": 9, "axes.titlesize": 10, "savefig.dpi": 150,
                         "figure.dpi": 100, "axes.grid": False})
    return plt


def _save(fig, path: Path):
    from larc_jax.io import atomic_write_bytes
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", bbox_inches="tight")
    atomic_write_bytes(path, buf.getvalue())


def _log_axis(ax, suffix: str = ""):
    """Log y axis with plain-number tick labels (0.01, 0.1, 1, 10 ...), optional unit suffix."""
    from matplotlib.ticker import FuncFormatter, LogLocator

    ax.set_yscale("log")
    ax.yaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    ax.yaxis.set_minor_locator(LogLocator(base=10, subs=np.arange(2, 10) * 1.0))
    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}{suffix}"))
    ax.yaxis.set_minor_formatter(FuncFormatter(lambda v, _: ""))


def _jitter(n: int, seed: int, width: float = 0.28) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-width, width, n)


def _load(layout, config):
    df = pd.read_csv(layout.trajectories_csv)
    for c in ("certified_larc", "certified_fine", "certified_coarse", "audit_collision", "self_collision"):
        if df[c].dtype != bool:
            df[c] = df[c].astype(str).str.lower().eq("true")
    scenes = [s for s in (config.get("scene_order") or config["scenes"]) if s in set(df["scene"])]
    return df, scenes


# ----------------------------------------------------------------------------------------------
# Result panels
# ----------------------------------------------------------------------------------------------


def draw_outcomes(ax, df, scenes):
    groups = scenes + ["all"]
    counts = []
    for g in groups:
        sub = df if g == "all" else df[df["scene"] == g]
        c, a = sub["certified_larc"], sub["audit_collision"]
        counts.append([int((c & ~a).sum()), int((~c & ~a).sum()), int((~c & a).sum()), int((c & a).sum())])
    counts = np.array(counts)
    x = np.arange(len(groups))
    bottom = np.zeros(len(groups))
    for k, (label, color) in enumerate(OUTCOME_STYLE):
        ax.bar(x, counts[:, k], bottom=bottom, color=color, label=f"{label}", edgecolor="white", width=0.7)
        for i, v in enumerate(counts[:, k]):
            if not v:
                continue
            if v >= 0.05 * counts.sum(axis=1).max():
                ax.text(x[i], bottom[i] + v / 2, str(v), ha="center", va="center", fontsize=8,
                        color="white" if k != 1 else "black")
            else:  # too thin for a label inside: write it beside the bar
                ax.text(x[i] + 0.37, bottom[i] + v / 2, str(v), ha="left", va="center", fontsize=7, color=color)
        bottom += counts[:, k]
    ax.set_xticks(x, [scene_label(g) if g != "all" else "All" for g in groups], rotation=20, ha="right")
    ax.set_ylabel("trajectories")
    from matplotlib.ticker import MaxNLocator

    ax.yaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_title("(a) LARC decision vs sampled FCL audit")
    ax.set_ylim(0, bottom.max() * 1.32 + 1)
    ax.legend(loc="upper left", fontsize=7, frameon=False, ncol=1)


def draw_eval_ratio(ax, df, scenes, fine_n: int):
    for i, sc in enumerate(scenes):
        sub = df[df["scene"] == sc]
        jit = _jitter(len(sub), 11 + i)
        for v, st in VARIANT_STYLE.items():
            m = (sub["variant"] == v).values
            ax.scatter(i + jit[m], sub["evals_larc"].values[m] / fine_n, s=14, alpha=0.75,
                       color=st["color"], label=st["label"] if i == 0 else None, linewidths=0)
        pooled = sub["evals_larc"].sum() / sub["evals_fine"].sum()
        ax.plot([i - 0.38, i + 0.38], [pooled, pooled], color="black", lw=1.5)
        ax.text(i + 0.40, pooled, f"{pooled:.3f}", va="center", fontsize=7)
    ax.axhline(1.0, color="grey", ls=":", lw=1)
    ax.text(-0.55, 1.04, f"fixed-fine ({fine_n} per trajectory)", va="bottom", ha="left", fontsize=7, color="grey")
    _log_axis(ax)
    ax.set_xticks(range(len(scenes)), [scene_label(s) for s in scenes], rotation=20, ha="right")
    ax.set_xlim(-0.6, len(scenes) - 0.1)
    ax.set_ylabel("LARC / fixed-fine evaluations")
    ax.set_title("(b) Interval-evaluation ratio (bar: pooled)")
    ax.legend(loc="lower right", fontsize=7, frameon=False)


def draw_runtime_ratio(ax, df, scenes):
    r = pd.to_numeric(df["time_fine_ms"]) / pd.to_numeric(df["time_larc_ms"])
    for i, sc in enumerate(scenes):
        m = (df["scene"] == sc).values
        sub, rr = df[m], r[m].values
        jit = _jitter(len(sub), 23 + i)
        for v, st in VARIANT_STYLE.items():
            k = (sub["variant"] == v).values
            ax.scatter(i + jit[k], rr[k], s=14, alpha=0.75, color=st["color"], marker="o",
                       label=st["label"] if i == 0 else None, linewidths=0)
        med = float(np.median(rr))
        ax.scatter([i], [med], marker="D", s=60, color="black", zorder=5,
                   label="scene median" if i == 0 else None)
        ax.text(i + 0.33, med, f"{med:.2f}×", va="center", fontsize=7)
    ax.axhline(1.0, color="grey", ls=":", lw=1)
    _log_axis(ax, "×")
    ax.set_xticks(range(len(scenes)), [scene_label(s) for s in scenes], rotation=20, ha="right")
    ax.set_xlim(-0.6, len(scenes) - 0.1)
    ax.set_ylabel("fixed-fine / LARC runtime (paired)")
    ax.set_title(f"(c) Paired runtime ratio (overall median {np.median(r):.2f}×)")
    ax.legend(loc="upper right", fontsize=7, frameon=False)


def draw_frontier(ax, levels: pd.DataFrame):
    d = levels["depth"].values
    ax.bar(d, levels["larc_passed"], color="#2ca02c", label="LARC: passed")
    ax.bar(d, levels["larc_inconclusive"], bottom=levels["larc_passed"], color="#ff7f0e",
           label="LARC: inconclusive (split, or failed at d_max)")
    ax.plot(d, levels["fine_intervals_at_depth"], "k--", marker="o", ms=3,
            label="fixed-fine: 2^d·N intervals at depth d")
    last = levels[levels["fine_evaluated"] > 0]
    ax.scatter(last["depth"], last["fine_evaluated"], marker="s", s=60, facecolors="none", edgecolors="black",
               label="fixed-fine evaluates (depth 9 only)", zorder=5)
    for x, f in zip(d, levels["larc_frontier"]):
        if f:
            ax.text(x, f * 1.15, str(int(f)), ha="center", va="bottom", fontsize=7,
                    bbox=dict(boxstyle="round,pad=0.1", facecolor="white", edgecolor="none", alpha=0.8), zorder=6)
    ax.set_yscale("log")
    ax.set_xlabel("depth d")
    ax.set_ylabel("intervals (all trajectories)")
    ax.set_xticks(d)
    ax.set_title(f"LARC frontier per depth: {int(levels['larc_frontier'].sum())} evaluations vs fine "
                 f"{int(levels['fine_evaluated'].sum())}")
    ax.set_ylim(0.8, levels["fine_intervals_at_depth"].max() * 3)
    ax.legend(loc="upper left", fontsize=7, frameon=False)


# ----------------------------------------------------------------------------------------------
# Scene replay
# ----------------------------------------------------------------------------------------------


def replay_choice(df: pd.DataFrame, scene: str) -> str:
    """Trajectory id whose LARC evaluation count is closest to the scene median; ties by id."""
    sub = df[df["scene"] == scene]
    med = float(np.median(sub["evals_larc"]))
    sub = sub.assign(_d=(sub["evals_larc"] - med).abs()).sort_values(["_d", "traj_id"])
    return str(sub["traj_id"].iloc[0])


def stadium(p: np.ndarray, q: np.ndarray, r: float, n: int = 24) -> np.ndarray:
    """Polygon (M, 2) of the points within ``r`` of the 2-D segment [p, q] (exact projection of a
    capsule onto a coordinate plane)."""
    d = q - p
    L = float(np.hypot(*d))
    if L < 1e-12:
        a = np.linspace(0, 2 * np.pi, 2 * n, endpoint=False)
        return p + r * np.stack([np.cos(a), np.sin(a)], axis=1)
    base = np.arctan2(d[1], d[0])
    a1 = base + np.linspace(-np.pi / 2, np.pi / 2, n)  # cap around q
    a0 = base + np.linspace(np.pi / 2, 3 * np.pi / 2, n)  # cap around p
    return np.concatenate([q + r * np.stack([np.cos(a1), np.sin(a1)], 1),
                           p + r * np.stack([np.cos(a0), np.sin(a0)], 1)])


VIEWS = (("top", (0, 1), "x (m)", "y (m)"), ("side", (0, 2), "x (m)", "z (m)"), ("front", (1, 2), "y (m)", "z (m)"))


def _replay_data(path, scene_path, robot, caps, link: str):
    from larc_jax.enclosure.capsule import capsule_segments_np
    from larc_jax.model.hermite import evaluate_np
    from larc_jax.model.robot import forward_kinematics_np
    from larc_jax.model.scene import read_scene
    from larc_jax.model.trajectory_files import read_trajectory

    tr = read_trajectory(path, robot)
    sc = read_scene(scene_path, frame=robot.link_names[0])
    T0, T1 = float(tr.t[0]), float(tr.t[-1])
    poses = {}
    for label, t in (("t = 0", T0), ("t = T/2", 0.5 * (T0 + T1)), ("t = T", T1)):
        q, _ = evaluate_np(tr.t, tr.q, tr.qd, t)
        poses[label] = capsule_segments_np(robot, caps, np.asarray(q))
    li = robot.link_index(link)
    ts = np.linspace(T0, T1, 240)
    path_pts = np.array([forward_kinematics_np(robot, np.asarray(evaluate_np(tr.t, tr.q, tr.qd, t)[0]))[li][:3, 3]
                         for t in ts])
    return tr, sc, poses, path_pts


def draw_replay_row(axes, tr, sc, poses, path_pts, caps, title: str):
    from matplotlib.patches import Polygon, Rectangle

    radius = np.asarray(caps.radius, float)
    pts = np.concatenate([np.concatenate([a, b]) for a, b in poses.values()] + [path_pts])
    rmax = float(radius.max())
    lo_r, hi_r = pts.min(0) - rmax - 0.08, pts.max(0) + rmax + 0.08
    # Show boxes near the robot; clip far-reaching ones (a floor) to the view.
    blo = np.minimum(lo_r, np.maximum(sc.lo.min(0) if sc.n_boxes else lo_r, lo_r - 0.25)) if sc.n_boxes else lo_r
    bhi = np.maximum(hi_r, np.minimum(sc.hi.max(0) if sc.n_boxes else hi_r, hi_r + 0.25)) if sc.n_boxes else hi_r
    blo, bhi = blo - 0.03, bhi + 0.03
    blo[2] = min(blo[2], -0.06)  # keep the mounting plane z = 0 and a strip below it in view
    for ax, (name, (i, j), xl, yl) in zip(axes, VIEWS):
        if j == 2:  # side and front views: the mounting plane of the base, hatched below
            ax.axhspan(blo[2] - 1.0, 0.0, facecolor="none", edgecolor="#9e9e9e", hatch="////", lw=0, zorder=0)
            ax.axhline(0.0, color="#616161", lw=1.0, zorder=1)
        for k in range(sc.n_boxes):
            ax.add_patch(Rectangle((sc.lo[k, i], sc.lo[k, j]), sc.hi[k, i] - sc.lo[k, i], sc.hi[k, j] - sc.lo[k, j],
                                   facecolor=(0.55, 0.34, 0.29, 0.12), edgecolor="#5a3a2f", lw=0.9,
                                   zorder=1))
        for label, (A, B) in poses.items():
            col = POSE_COLORS[label]
            for c in range(len(radius)):
                poly = stadium(A[c, [i, j]], B[c, [i, j]], radius[c])
                ax.add_patch(Polygon(poly, closed=True, facecolor=col, alpha=0.22, edgecolor=col, lw=0.6, zorder=2))
                ax.plot([A[c, i], B[c, i]], [A[c, j], B[c, j]], color=col, lw=0.8, zorder=3)
        ax.plot(path_pts[:, i], path_pts[:, j], color="black", lw=1.2, zorder=4)
        ax.scatter(path_pts[0, i], path_pts[0, j], s=18, color="black", marker="o", zorder=5)
        ax.scatter(path_pts[-1, i], path_pts[-1, j], s=24, color="black", marker="x", zorder=5)
        L = 0.08  # world axes at the base origin
        for k, col in enumerate(("#d62728", "#2ca02c", "#1f77b4")):
            e = np.zeros(3)
            e[k] = L
            if abs(e[i]) + abs(e[j]) > 0:
                ax.annotate("", xy=(e[i], e[j]), xytext=(0, 0),
                            arrowprops=dict(arrowstyle="->", color=col, lw=1.2), zorder=6)
        ax.set_xlim(blo[i], bhi[i])
        ax.set_ylim(blo[j], bhi[j])
        ax.set_aspect("equal")
        ax.set_xlabel(xl, labelpad=1)
        ax.set_ylabel(yl, labelpad=1)
        ax.tick_params(labelsize=7)
        ax.set_title(f"{name} ({xl[0]}–{yl[0]})", fontsize=8)


def draw_scene_replay(layout, config, df, scenes, robot, caps):
    plt = _plt()
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    link = point_link(config)
    idx = {r["traj_id"]: r for r in dataset_index(layout, config)}
    spaths = scene_paths(config)
    fig = plt.figure(figsize=(11, 3.6 * len(scenes) + 0.6), layout="constrained")
    subfigs = np.atleast_1d(fig.subfigures(len(scenes), 1))
    for row, sc_name in enumerate(scenes):
        tid = replay_choice(df, sc_name)
        rec = df[df["traj_id"] == tid].iloc[0]
        tr, sc, poses, path_pts = _replay_data(idx[tid]["path"], spaths[sc_name], robot, caps, link)
        status = "certified" if rec["certified_larc"] else "uncertified"
        audit = "audit collision" if rec["audit_collision"] else "sampled-clear"
        axes = subfigs[row].subplots(1, 3)
        draw_replay_row(axes, tr, sc, poses, path_pts, caps, scene_label(sc_name))
        subfigs[row].suptitle(f"{scene_label(sc_name)}: {tid}, T = {tr.duration:.2f} s, {int(rec['evals_larc'])} LARC "
                              f"evaluations, {status}, {audit}", fontsize=9, fontweight="bold")
    handles = [Line2D([], [], color=c, lw=4, alpha=0.5, label=f"capsules at {k}") for k, c in POSE_COLORS.items()]
    handles += [Line2D([], [], color="black", lw=1.2, label=f"gripper-base path ({link} origin; o start, x end)"),
                Line2D([], [], color="#5a3a2f", lw=4, alpha=0.3, label="obstacle boxes (AABB)"),
                Patch(facecolor="none", edgecolor="#9e9e9e", hatch="////",
                      label="below the base's mounting plane z = 0 (side, front views)")]
    fig.legend(handles=handles, loc="outside lower center", ncol=3, fontsize=8, frameon=False)
    fig.suptitle("Recorded trajectories per scene (LARC evaluation count closest to the scene median; "
                 "poses only, no motion inflation)", fontsize=10)
    _save(fig, layout.figures_dir / "scene_replay.png")
    plt.close(fig)


# ----------------------------------------------------------------------------------------------
# Workspace
# ----------------------------------------------------------------------------------------------


def workspace_points(robot, n: int, seed: int, link: str) -> np.ndarray:
    """``n`` configurations uniform within the active joints' URDF limits (``seed``) → positions
    of ``link``'s origin in the base frame, (n, 3)."""
    import jax
    import jax.numpy as jnp

    from larc_jax.model.robot import forward_kinematics

    rng = np.random.default_rng(int(seed))
    Q = rng.uniform(np.asarray(robot.q_lower, float), np.asarray(robot.q_upper, float), (int(n), robot.n_joints))
    li = robot.link_index(link)
    with jax.enable_x64(True):
        fk = jax.jit(jax.vmap(lambda q: forward_kinematics(robot, q)[li, :3, 3]))
        return np.asarray(fk(jnp.asarray(Q, jnp.float64)))


def draw_workspace(layout, config, robot):
    plt = _plt()
    from scipy.spatial import ConvexHull

    n, seed = int(config.get("workspace_samples", 6000)), int(config.get("workspace_seed", 20270823))
    link = point_link(config)
    P = workspace_points(robot, n, seed, link)
    fig, axes = plt.subplots(1, 3, figsize=(12, 4.2))
    for ax, (name, (i, j), xl, yl) in zip(axes, VIEWS):
        ax.scatter(P[:, i], P[:, j], s=1.5, alpha=0.35, color="#1f77b4", linewidths=0)
        hull = ConvexHull(P[:, [i, j]])
        v = np.append(hull.vertices, hull.vertices[0])
        ax.plot(P[v, i], P[v, j], "k--", lw=1, label="convex hull of projection (visual guide)")
        ax.scatter([0], [0], marker="+", s=60, color="black", label="base origin")
        ax.set_aspect("equal")
        ax.set_xlabel(xl)
        ax.set_ylabel(yl)
        ax.set_title(f"{name} view ({xl[0]}–{yl[0]})")
    h, lab = axes[0].get_legend_handles_labels()
    fig.legend(h, lab, loc="lower center", ncol=2, fontsize=8, frameon=False, bbox_to_anchor=(0.5, -0.02))
    r = np.linalg.norm(P, axis=1)
    fig.suptitle(f"PIPER workspace: {link} origin for {n} configurations uniform within the six joint "
                 f"limits (seed {seed}); |p| from {r.min():.2f} to {r.max():.2f} m, z from {P[:, 2].min():.2f} "
                 f"to {P[:, 2].max():.2f} m", fontsize=9)
    fig.tight_layout(rect=(0, 0.05, 1, 1))
    _save(fig, layout.figures_dir / "workspace.png")
    plt.close(fig)


# ----------------------------------------------------------------------------------------------
# Entry point
# ----------------------------------------------------------------------------------------------


def make_figures(layout, config: dict) -> dict:
    plt = _plt()
    from experiments.models import robot_and_capsules

    layout.figures_dir.mkdir(parents=True, exist_ok=True)
    df, scenes = _load(layout, config)
    fine_n = 2 ** int(config["max_depth"])
    out = layout.figures_dir

    fig, ax = plt.subplots(figsize=(5.2, 4.2))
    draw_outcomes(ax, df, scenes)
    fig.tight_layout()
    _save(fig, out / "outcomes_vs_audit.png")
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(5.6, 4.2))
    draw_eval_ratio(ax, df, scenes, fine_n)
    fig.tight_layout()
    _save(fig, out / "eval_ratio.png")
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(5.6, 4.2))
    draw_runtime_ratio(ax, df, scenes)
    fig.tight_layout()
    _save(fig, out / "runtime_ratio.png")
    plt.close(fig)

    fig, axes = plt.subplots(1, 3, figsize=(16, 4.6))
    draw_outcomes(axes[0], df, scenes)
    draw_eval_ratio(axes[1], df, scenes, fine_n)
    draw_runtime_ratio(axes[2], df, scenes)
    fig.suptitle(f"Stage B results for {len(df)} PIPER trajectories", fontsize=11)
    fig.tight_layout()
    _save(fig, out / "results.png")
    plt.close(fig)

    levels = pd.read_csv(layout.out / "frontier_levels.csv")
    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    draw_frontier(ax, levels)
    fig.tight_layout()
    _save(fig, out / "frontier_levels.png")
    plt.close(fig)

    robot, caps = robot_and_capsules(config)
    draw_scene_replay(layout, config, df, scenes, robot, caps)
    draw_workspace(layout, config, robot)
    return dict(figures=len(FIGURES))
