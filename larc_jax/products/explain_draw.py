"""What an explained leaf holds (:class:`Explanation`) and its picture (:func:`render`).

:func:`~larc_jax.products.explain.explain` fills an :class:`Explanation` with the NumPy float64 reference
numbers of one leaf; :func:`render` draws it (matplotlib, Agg backend, imported lazily) as three
orthographic views (top x-y, side x-z, front y-z) and a clearance timeline. Orthographic views
are exact for capsules: the projection of a capsule (a segment swept by a ball of radius r) is the
projected segment swept by a disc of radius r, so each capsule is drawn as a 2-D "stadium" of its
true radius, and its inflation shell (radius ``r_l + rho + b_l(I)``: the set the interval test keeps
away from every box) as a translucent stadium around it. What is red is what decided the leaf:

- the capsule test: the capsule attaining g(I), its shell and its box; the dashed segment joins
  the closest points of the capsule's axis and the box (the distance the test compares against
  the shell radius);
- the hull test (:mod:`larc_jax.leaf.cascade`): the deciding hull part at ``q(t_m)`` (the 2-D convex
  hull of its projected vertices: the projection of the part, exactly) and its box; its shell is
  the part grown by ``(r_p + b_p + rho)(1 + 2 eps) + G_p`` (padding, motion radius, margin,
  rounding guard: the proven lower bound of the part-box distance must exceed it). A projected
  Minkowski sum with a ball is the projected part grown by a disc of the same radius; its arcs
  are drawn as circumscribed 48-gons (at most 0.22 % of the radius outside the exact outline).
  The dashed segment joins numerically found closest points of the part and the box (the kernel
  returns only its bound, which the text gives);
- the self-collision test: both capsules of the pair, each with a shell grown by half of
  ``b + rho_self + G`` (the pair's relative motion radius, self margin, guard), so that the two
  shells are apart iff the pair passes; no box is red; the dashed segment joins the closest points
  of the two axes.

The gripper path (mean of the capsule axes on the last joint's link and its children) is drawn
over the whole trajectory (dotted) and over the interval (thick).
"""

from __future__ import annotations

import dataclasses
import io
import math
from pathlib import Path

import numpy as np

from ..enclosure.capsule import CapsuleModel, capsule_segments_np
from ..model.hermite import evaluate_np
from ..io import atomic_write_bytes
from ..engine.results import Leaf, TrajectoryResult
from ..model.robot import Robot
from ..model.scene import Scene
from ..model.shapes import outline_2d, shape_mesh, shape_outline
from ..model.trajectory import Trajectory

__all__ = ["Explanation", "DecidingPart", "DecidingPair", "describe_leaf", "tool_capsules", "convex_hull_2d",
           "grown_outline", "figure", "render"]


@dataclasses.dataclass(frozen=True)
class DecidingPart:
    """The hull part whose clearance a leaf records (the hull test decided it), at ``q(t_m)``."""

    index: int
    name: str
    vertices_m: np.ndarray
    """(K, 3) the part's vertices placed at q(t_m), base frame, m: the part is their convex hull
    grown by ``radius_m``."""
    radius_m: float
    """Padding plus containment slack (grown by any tracking tolerance), m."""
    motion_b_m: float
    """The part's motion radius b_p(I), m."""
    lower_bound_m: float
    """The polytope kernel's proven lower bound of the distance from conv(vertices) to the box, m."""
    reach_m: float
    """``(r_p + b_p + rho)(1 + 2 eps)``: what the test subtracts from the bound (g = bound - reach), m."""
    closest: tuple[np.ndarray, np.ndarray]
    """Closest points (on the part, on the box), found numerically (for drawing): their distance
    is never below the true distance, hence never below ``lower_bound_m``."""


@dataclasses.dataclass(frozen=True)
class DecidingPair:
    """The self-collision pair whose clearance a leaf records."""

    motion_b_m: float
    """Motion radius of the pair's relative motion, m."""
    margin_m: float
    """rho_self, m."""
    distance_m: float
    """Distance between the two capsule axes at q(t_m), m."""
    closest: tuple[np.ndarray, np.ndarray]
    """Closest points of the two axes (first capsule's, second's)."""


@dataclasses.dataclass(frozen=True)
class Explanation:
    """What the interval test saw on one leaf (NumPy float64 reference values)."""

    trajectory_id: str
    certified: bool
    """Whether the whole trajectory is certified."""
    leaf: Leaf
    t_mid: float
    h: float
    """Covering half-width of the interval (what the motion radius used), s."""
    q_mid: np.ndarray
    """(n,) configuration at the interval midpoint."""
    seg_a: np.ndarray
    """(C, 3) capsule segment ends at ``q_mid``, base frame, m."""
    seg_b: np.ndarray
    radius: np.ndarray
    """(C,) capsule radii r_l, m."""
    motion_b: np.ndarray
    """(C,) motion radii b_l(I), m."""
    margin_m: float
    clearance_m: float
    """g(I) of the capsule test, recomputed by the reference kernel, m."""
    capsule: int
    """The recorded capsule: the one attaining the capsule test's g(I); with the hull test, the
    capsule of the blocking link; with a self pair, its first capsule (-1 without boxes)."""
    box: int
    """Index of the recorded box (-1 without boxes or for a self pair)."""
    distance_m: float
    """Distance between that capsule's axis and that box (for a self pair: between the two
    axes), m (nan without boxes)."""
    closest: tuple[np.ndarray, np.ndarray] | None
    """Closest points of that pair (on the axis, on the box or the other axis)."""
    stage: str = "capsule"
    """The test of the result's run spec that decided the leaf, re-evaluated with its enclosure,
    tracking tolerance, self-collision test and dtype (:func:`~larc_jax.leaf.reference.leaf_test_np`):
    ``capsule``, ``hull`` or ``self`` when it passed (``self``: the recorded pair is a capsule pair
    and every test passed), ``""`` when it did not."""
    decided_clearance_m: float = math.nan
    """g of the pair that decided the leaf (that test's), m; the leaf passed iff it exceeds ``guard_m``."""
    guard_m: float = math.nan
    """The rounding guard of that pair, m."""
    other_capsule: int = -1
    """With a self-collision pair deciding the leaf: its second capsule (``capsule`` the first)."""
    part: DecidingPart | None = None
    """The hull part whose clearance the leaf records, if the hull test decided it."""
    pair: DecidingPair | None = None
    """The self-collision pair's numbers, if it decided the leaf."""

    @property
    def shell_radius(self) -> np.ndarray:
        """(C,) radius of the set kept clear of the boxes on the interval: r + rho + b, m."""
        return self.radius + self.margin_m + self.motion_b

    @property
    def pair_shell_radius(self) -> np.ndarray:
        """(2,) shells of a self pair's capsules: each radius grown by half of ``b + rho_self +
        guard`` (apart iff the pair passes), m."""
        half = 0.5 * (self.pair.motion_b_m + self.pair.margin_m + self.guard_m)
        return self.radius[[self.capsule, self.other_capsule]] + half


def describe_leaf(result: TrajectoryResult, leaf: Leaf) -> str:
    """A few words on which leaf this is (for titles and messages)."""
    finite = [lf.clearance_m for lf in result.leaves if not math.isnan(lf.clearance_m)]
    tightest = bool(finite) and leaf.clearance_m == min(finite)
    if leaf == result.first_inconclusive:
        return "first inconclusive interval (blocks the certificate)"
    if not leaf.certified:
        return "inconclusive interval" + (", smallest clearance" if tightest else "")
    return "tightest passed interval (smallest clearance)" if tightest else "passed interval"


def tool_capsules(robot: Robot, capsules: CapsuleModel) -> list[int]:
    """Capsules on the link driven by the last active joint and on its descendants (the
    gripper, for PIPER: link6, link7, link8)."""
    last = robot.q_index.index(robot.n_joints - 1)
    return [c for c, li in enumerate(capsules.link_index) if last in robot.ancestors(li)]


def _tool_path(robot, capsules, traj, t0, t1, n):
    tool = tool_capsules(robot, capsules) or list(range(capsules.n_capsules))
    out = []
    for t in np.linspace(t0, t1, n):
        q, _ = evaluate_np(traj.t, traj.q, traj.qd, t)
        pa, pb = capsule_segments_np(robot, capsules, q)
        out.append(0.5 * (pa[tool].mean(axis=0) + pb[tool].mean(axis=0)))
    return np.array(out)


def _stadium(p, q, r, n=24):
    """Polygon (k, 2) of the 2-D capsule: points within r of the segment [p, q]."""
    d = q - p
    theta = math.atan2(d[1], d[0]) if np.hypot(*d) > 1e-12 else 0.0
    arc = np.linspace(-math.pi / 2, math.pi / 2, n)
    end_q = q + r * np.c_[np.cos(theta + arc), np.sin(theta + arc)]
    end_p = p + r * np.c_[np.cos(theta + math.pi + arc), np.sin(theta + math.pi + arc)]
    return np.vstack([end_q, end_p])


def convex_hull_2d(points) -> np.ndarray:
    """(m, 2) counter-clockwise vertices of the convex hull of ``points`` (k, 2) (monotone chain;
    collinear and repeated points dropped)."""
    pts = [tuple(p) for p in np.unique(np.asarray(points, np.float64), axis=0)]  # sorted by x, then y
    if len(pts) < 3:
        return np.array(pts).reshape(-1, 2)

    def half(seq):
        out = []
        for x, y in seq:
            while len(out) >= 2 and ((out[-1][0] - out[-2][0]) * (y - out[-2][1])
                                     - (out[-1][1] - out[-2][1]) * (x - out[-2][0])) <= 0:
                out.pop()
            out.append((x, y))
        return out[:-1]

    return np.array(half(pts) + half(pts[::-1]))


def grown_outline(points, r: float, n: int = 48) -> np.ndarray:
    """Outline (m, 2) of the convex hull of ``points`` (k, 2) grown by a disc of radius ``r``, its
    arcs as circumscribed ``n``-gons (it contains the exact outline, at most ``r (1 / cos(pi / n)
    - 1)`` outside it)."""
    angle = 2 * math.pi * np.arange(n) / n
    ring = (r / math.cos(math.pi / n)) * np.c_[np.cos(angle), np.sin(angle)]
    return convex_hull_2d((convex_hull_2d(points)[:, None, :] + ring[None]).reshape(-1, 2))


_VIEWS = (("top view (x–y)", 0, 1), ("side view (x–z)", 0, 2), ("front view (y–z)", 1, 2))
_RED, _BLUE = "#c62828", "#1f5fa8"


def _fmt_mm(x: float) -> str:
    if math.isnan(x):
        return "nan"
    if math.isinf(x):
        return "inf"
    return f"{x * 1000:+.1f} mm"


def _pair_words(ex: Explanation, leaf: Leaf) -> str:
    """The recorded pair, for the title."""
    if ex.pair is not None:
        return f"self pair {leaf.capsule} / {leaf.other_capsule}"
    if ex.part is not None:
        return f"hull part {ex.part.name} vs box {leaf.box}"
    return f"capsule {leaf.capsule} vs box {leaf.box}" if ex.capsule >= 0 else "no boxes in the scene"


def _numbers(ex: Explanation, capsules: CapsuleModel) -> list[str]:
    """The text panel's lines below the leaf's decision: the recorded pair's test, term by term."""
    mm = lambda x: f"{x * 1000:7.2f} mm"  # noqa: E731
    if ex.pair is not None:
        a, b = ex.capsule, ex.other_capsule
        return ["", f"self pair {capsules.names[a]} / {capsules.names[b]}",
                f"radii          r1 + r2 = {mm(ex.radius[a] + ex.radius[b])}",
                f"self margin        ρ_s = {mm(ex.pair.margin_m)}",
                f"relative motion      b = {mm(ex.pair.motion_b_m)}",
                f"axis-to-axis distance d = {ex.pair.distance_m * 1000:6.2f} mm",
                f"g = d − (r1 + r2 + b + ρ_s) = {_fmt_mm(ex.decided_clearance_m)}"]
    if ex.part is not None:
        p = ex.part
        return ["", f"hull part {p.name}:  padding r = {mm(p.radius_m)}",
                f"margin              ρ = {mm(ex.margin_m)}",
                f"motion radius       b = {mm(p.motion_b_m)}",
                f"guard               G = {mm(ex.guard_m)}",
                f"shell   r + ρ + b + G = {mm(p.reach_m + ex.guard_m)}",
                f"proven bound      lb = {mm(p.lower_bound_m)}",
                f"g = lb − (r + ρ + b) = {_fmt_mm(ex.decided_clearance_m)}"]
    if ex.capsule < 0:
        return []
    c, shell = ex.capsule, ex.shell_radius
    return [
        "",
        f"capsule {capsules.names[c]}:  r = {ex.radius[c] * 1000:7.2f} mm",
        f"margin              ρ = {ex.margin_m * 1000:7.2f} mm",
        f"motion radius       b = {ex.motion_b[c] * 1000:7.2f} mm",
        f"shell       r + ρ + b = {shell[c] * 1000:7.2f} mm",
        f"axis-to-box distance d = {ex.distance_m * 1000:6.2f} mm",
        f"g(I) = d − (r + ρ + b) = {_fmt_mm(ex.clearance_m)}",
    ]


def _draw_part(ax, part: DecidingPart, guard_m: float, i: int, j: int) -> None:
    """The deciding hull part in view (i, j): its projection filled, its shell dashed."""
    from matplotlib.patches import Polygon

    flat = part.vertices_m[:, [i, j]]
    ax.add_patch(Polygon(grown_outline(flat, part.reach_m + guard_m), closed=True, facecolor=_RED, alpha=0.16,
                         edgecolor=_RED, linestyle="--", linewidth=1.2, zorder=4.5, gid="hull_shell"))
    ax.add_patch(Polygon(convex_hull_2d(flat), closed=True, facecolor=_RED, alpha=0.6, edgecolor="#8e0000",
                         linewidth=1.0, zorder=4.6, gid="hull_part"))


def figure(ex: Explanation, robot: Robot, capsules: CapsuleModel, traj: Trajectory, scene: Scene,
           result: TrajectoryResult, *, dpi: int = 110):
    """The matplotlib :class:`~matplotlib.figure.Figure` of ``ex`` (module doc)."""
    from matplotlib.figure import Figure  # no pyplot: no GUI backend, no global figure state
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch, Polygon, Rectangle

    leaf = ex.leaf
    C = len(ex.radius)
    blocking_c, blocking_k = ex.capsule, ex.box
    red = [] if ex.part is not None else [blocking_c, ex.other_capsule] if ex.pair is not None else [blocking_c]
    red = [c for c in red if c >= 0]
    full_path = _tool_path(robot, capsules, traj, float(traj.t[0]), float(traj.t[-1]), 160)
    leaf_path = _tool_path(robot, capsules, traj, leaf.t0, leaf.t1, 25)
    mid_tool = _tool_path(robot, capsules, traj, ex.t_mid, ex.t_mid, 1)[0]

    # Axis limits: the robot with its shells, the gripper path and the boxes, boxes clipped to
    # at most 0.4 m beyond the robot so a floor or wall does not shrink the arm to a dot.
    shell = ex.shell_radius
    pts = np.vstack([ex.seg_a - shell[:, None], ex.seg_a + shell[:, None],
                     ex.seg_b - shell[:, None], ex.seg_b + shell[:, None], full_path])
    if ex.part is not None:
        grow = ex.part.reach_m + ex.guard_m
        pts = np.vstack([pts, ex.part.vertices_m - grow, ex.part.vertices_m + grow])
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    if scene.n_boxes:
        lo = np.minimum(lo, np.maximum(scene.lo.min(axis=0), lo - 0.4))
        hi = np.maximum(hi, np.minimum(scene.hi.max(axis=0), hi + 0.4))
    extents = [shape_mesh(scene.shapes, s).bounds for s in range(scene.shapes.count)]
    extents += [np.array([v.min(axis=0), v.max(axis=0)]) for v in scene.point_sets.pieces]
    for bounds in extents:
        lo, hi = np.minimum(lo, np.maximum(bounds[0], lo - 0.4)), np.maximum(hi, np.minimum(bounds[1], hi + 0.4))
    pad = 0.04
    lo, hi = lo - pad, hi + pad

    fig = Figure(figsize=(15, 9.2), dpi=dpi, layout="constrained")
    grid = fig.add_gridspec(2, 3, height_ratios=[2.3, 1.0])
    status = "CERTIFIED" if ex.certified else "NOT CERTIFIED"
    what = describe_leaf(result, leaf)
    fig.suptitle(
        f"{ex.trajectory_id}: {status} — {what}\n"
        f"t = [{leaf.t0:.4f}, {leaf.t1:.4f}] s (depth {leaf.depth}), {_pair_words(ex, leaf)}, "
        f"clearance g(I) = {_fmt_mm(leaf.clearance_m)}",
        fontsize=13, fontweight="bold",
    )
    closest = ex.part.closest if ex.part is not None else ex.closest

    for col, (title, i, j) in enumerate(_VIEWS):
        ax = fig.add_subplot(grid[0, col])
        for k in range(scene.n_boxes):
            mine = k == blocking_k
            ax.add_patch(Rectangle(
                (scene.lo[k, i], scene.lo[k, j]), scene.hi[k, i] - scene.lo[k, i],
                scene.hi[k, j] - scene.lo[k, j],
                facecolor=_RED if mine else "0.55", alpha=0.45 if mine else 0.18,
                edgecolor="#8e0000" if mine else "0.45", linewidth=2.0 if mine else 0.8,
                zorder=1 if not mine else 2,
            ))
            name = scene.box_names[k] if k < len(scene.box_names) else f"box{k}"
            cx = 0.5 * (max(scene.lo[k, i], lo[i]) + min(scene.hi[k, i], hi[i]))
            cy = min(scene.hi[k, j], hi[j])
            ax.annotate(name, (cx, cy), xytext=(0, 2), textcoords="offset points", ha="center",
                        va="bottom", fontsize=9, color="#8e0000" if mine else "0.35",
                        fontweight="bold" if mine else "normal", clip_on=True, zorder=6)
        shape_count = scene.shapes.count
        for s in range(shape_count + scene.point_sets.count):  # shapes, pieces: their projected outlines
            mine = scene.n_boxes + s == blocking_k
            if s >= shape_count and not mine:  # pieces of meshes and clouds: filled, unnamed
                ax.add_patch(Polygon(outline_2d(scene.point_sets.pieces[s - shape_count][:, [i, j]]), closed=True,
                                     facecolor="0.55", alpha=0.18, edgecolor="none", zorder=1))
                continue
            if s < shape_count:
                flat = shape_outline(scene.shapes, s, (i, j))
            else:  # the blocking piece: the bounding box the capsule test measured, around its hull
                piece = scene.point_sets.pieces[s - shape_count][:, [i, j]]
                (x0, y0), (x1, y1) = piece.min(axis=0), piece.max(axis=0)
                ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, edgecolor="#8e0000", linewidth=1.0,
                                       linestyle="--", zorder=2))
                flat = outline_2d(piece)
            ax.add_patch(Polygon(flat, closed=True, facecolor=_RED if mine else "0.55", alpha=0.45 if mine else 0.18,
                                 edgecolor="#8e0000" if mine else "0.45", linewidth=2.0 if mine else 0.8,
                                 zorder=1 if not mine else 2))
            ax.annotate(scene.obstacle_names[scene.n_boxes + s], (float(flat[:, 0].mean()), float(flat[:, 1].max())), xytext=(0, 2),
                        textcoords="offset points", ha="center", va="bottom", fontsize=9,
                        color="#8e0000" if mine else "0.35", fontweight="bold" if mine else "normal",
                        clip_on=True, zorder=6)
        order = [c for c in range(C) if c not in red] + red
        for c in order:
            mine = c in red
            p, q = ex.seg_a[c, [i, j]], ex.seg_b[c, [i, j]]
            grown = ex.pair_shell_radius[red.index(c)] if mine and ex.pair is not None else shell[c]
            ax.add_patch(Polygon(_stadium(p, q, grown), closed=True,
                                 facecolor=_RED if mine else _BLUE, alpha=0.16 if mine else 0.06,
                                 edgecolor=_RED if mine else "none", linestyle="--",
                                 linewidth=1.2, zorder=3))
            ax.add_patch(Polygon(_stadium(p, q, ex.radius[c]), closed=True,
                                 facecolor=_RED if mine else _BLUE, alpha=0.55 if mine else 0.28,
                                 edgecolor="#8e0000" if mine else "#173f6e", linewidth=1.0 if mine else 0.6,
                                 zorder=4))
            ax.plot([p[0], q[0]], [p[1], q[1]], color="k", linewidth=0.6, alpha=0.6, zorder=5)
        if ex.part is not None:
            _draw_part(ax, ex.part, ex.guard_m, i, j)
        ax.plot(full_path[:, i], full_path[:, j], ":", color="#6a1b9a", linewidth=1.2, zorder=5)
        ax.plot(leaf_path[:, i], leaf_path[:, j], "-", color="#6a1b9a", linewidth=3.5, zorder=6)
        ax.plot(mid_tool[i], mid_tool[j], "*", color="#6a1b9a", markersize=13,
                markeredgecolor="white", markeredgewidth=0.8, zorder=8)
        ax.plot(full_path[0, i], full_path[0, j], "o", color="#6a1b9a", markersize=5, zorder=6)
        ax.plot(full_path[-1, i], full_path[-1, j], "s", color="#6a1b9a", markersize=5, zorder=6)
        if closest is not None:
            a_pt, b_pt = closest
            ax.plot([a_pt[i], b_pt[i]], [a_pt[j], b_pt[j]], "--", color="k", linewidth=1.4, zorder=7)
            ax.plot([a_pt[i], b_pt[i]], [a_pt[j], b_pt[j]], "o", color="k", markersize=3, zorder=7)
        ax.set_xlim(lo[i], hi[i])
        ax.set_ylim(lo[j], hi[j])
        ax.set_aspect("equal", adjustable="box")
        ax.set_title(title, fontsize=11)
        ax.set_xlabel(f"{'xyz'[i]} (m)")
        ax.set_ylabel(f"{'xyz'[j]} (m)")
        ax.grid(True, color="0.9", linewidth=0.6, zorder=0)
        ax.tick_params(labelsize=8)

    # Clearance timeline: g(I) of every leaf, the explained one shaded.
    ax = fig.add_subplot(grid[1, :2])
    for lf in result.leaves:
        if math.isfinite(lf.clearance_m):
            ax.plot([lf.t0, lf.t1], [lf.clearance_m * 1000] * 2, color="#2e7d32" if lf.certified else _RED,
                    linewidth=2.2, solid_capstyle="butt")
    ax.axhline(0.0, color="k", linewidth=0.8)
    ax.axvspan(leaf.t0, leaf.t1, color="#6a1b9a", alpha=0.25, linewidth=0)
    ax.axvline(ex.t_mid, color="#6a1b9a", linewidth=1.0)
    ax.set_xlim(float(traj.t[0]), float(traj.t[-1]))
    ax.set_xlabel("time (s)")
    ax.set_ylabel("clearance g(I) (mm)")
    ax.set_title(f"leaf clearances ({len(result.leaves)} leaves, {result.evaluations} evaluations): "
                 "green = passed, red = inconclusive; purple = the interval drawn above", fontsize=10)
    ax.grid(True, color="0.9", linewidth=0.6)
    ax.tick_params(labelsize=8)

    # Numbers and legend.
    ax = fig.add_subplot(grid[1, 2])
    ax.axis("off")
    lines = [f"midpoint t_m = {ex.t_mid:.4f} s",
             f"half-width h = {ex.h * 1000:.2f} ms",
             "q(t_m) = [" + " ".join(f"{v:.2f}" for v in ex.q_mid) + "]"]
    decided = {"": "no test passed it", "capsule": "passed by the capsule test", "hull": "passed by the hull test",
               "swept": "passed by the swept test",
               "self": "passed; nearest: the self-collision pair"}[ex.stage]
    lines += [f"leaf {decided}: g = {_fmt_mm(ex.decided_clearance_m)}, guard {_fmt_mm(ex.guard_m)}"]
    lines += _numbers(ex, capsules)
    ax.text(0.02, 1.0, "\n".join(lines), va="top", ha="left", fontsize=10, family="monospace",
            transform=ax.transAxes)
    handles = [
        Patch(facecolor=_BLUE, alpha=0.4, edgecolor="#173f6e", label="capsule at q(t_m)"),
        Patch(facecolor=_BLUE, alpha=0.15, label="shell r + ρ + b (kept clear of boxes)"),
        Patch(facecolor=_RED, alpha=0.55, edgecolor="#8e0000", label="capsule, shell and box attaining g(I)"),
        Patch(facecolor="0.55", alpha=0.25, edgecolor="0.45", label="other boxes"),
        Line2D([], [], color="#6a1b9a", linewidth=3.5, marker="*", markersize=10,
               label="gripper on the interval (★ t_m)"),
        Line2D([], [], color="#6a1b9a", linestyle=":", label="gripper path (● start, ■ end)"),
        Line2D([], [], color="k", linestyle="--", marker="o", markersize=3,
               label="closest points (distance d)"),
    ]
    if ex.pair is not None:
        handles[2] = Patch(facecolor=_RED, alpha=0.55, edgecolor="#8e0000",
                           label="self pair: capsules, shells r + (b + ρ_s + G)/2 (apart iff it passes)")
    if ex.part is not None:
        handles[2:3] = [
            Patch(facecolor=_RED, alpha=0.6, edgecolor="#8e0000", label="deciding hull part at q(t_m), its box"),
            Patch(facecolor=_RED, alpha=0.16, edgecolor=_RED, linestyle="--",
                  label="hull shell r + ρ + b + G (arcs as 48-gons, ≤ 0.22 % outside)"),
        ]
        handles[-1] = Line2D([], [], color="k", linestyle="--", marker="o", markersize=3,
                             label="closest points of part and box (numerical; ≥ lb)")
    fig.legend(handles=handles, loc="outside lower center", ncol=4, fontsize=9.5, frameon=False)
    return fig


def render(ex: Explanation, robot: Robot, capsules: CapsuleModel, traj: Trajectory, scene: Scene,
           result: TrajectoryResult, path: str | Path, *, dpi: int = 110) -> Path:
    """Draw ``ex`` (module doc) to an image file (format from the suffix, e.g. ``.png``)."""
    fig = figure(ex, robot, capsules, traj, scene, result, dpi=dpi)
    path = Path(path)
    buf = io.BytesIO()
    fig.savefig(buf, dpi=dpi, format=path.suffix.lstrip(".").lower() or "png")
    atomic_write_bytes(path, buf.getvalue())
    return path
