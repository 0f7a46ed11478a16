"""Pictures that explain a certificate: the interval that blocks it, or its tightest interval.

:func:`explain` takes one trajectory's :class:`~larc_jax.results.TrajectoryResult` and
recomputes, with the NumPy float64 reference kernels, everything the interval test saw on one
leaf ``I = [t_m - h, t_m + h]``: the capsule segments at the midpoint configuration ``q(t_m)``,
the motion radii ``b_l(I) = h * sum_j a_lj * max_I |qdot_j|`` (paper eqs. 5-6) and the
certificate clearance ``g(I)`` with its capsule/box pair, all from one call of
:func:`~larc_jax.interval.evaluate_interval_np` with the margin the result carries. By default
(:func:`choose_leaf`) the leaf is the *first inconclusive* one of an uncertified trajectory (the
one the ``larc certify`` table names) or, for a certified one, the leaf with the smallest
clearance.

:func:`render` draws it (matplotlib, Agg backend, imported lazily) as three orthographic views
(top x-y, side x-z, front y-z) and a clearance timeline. Orthographic views are exact for
capsules: the projection of a capsule (a segment swept by a ball of radius r) is the projected
segment swept by a disc of radius r, so each capsule is drawn as a 2-D "stadium" of its true
radius, and its inflation shell (radius ``r_l + rho + b_l(I)``: the set the interval test keeps
away from every box) as a translucent stadium around it. The blocking capsule, its shell and
the blocking box are red; other boxes are grey; the dashed segment joins the closest points of
the blocking capsule's axis and box (its length is the distance the test compares against the
shell radius). The gripper path (mean of the capsule axes on the last joint's link and its
children) is drawn over the whole trajectory (dotted) and over the interval (thick).
"""

from __future__ import annotations

import dataclasses
import io
import math
from pathlib import Path

import numpy as np

from .enclosure.capsule import CapsuleModel, capsule_segments_np
from .errors import LarcInputError
from .hermite import evaluate_np
from .interval import evaluate_interval_np, trajectory_rounding
from .io import atomic_write_bytes
from .leaf_reference import leaf_enclosures, leaf_test_np
from .results import Leaf, TrajectoryResult
from .robot import Robot
from .run_spec import RunSpec
from .scene import Scene
from .self_collision import curve_ranges, load_separation, self_pairs
from .tracking import check_tracking_tolerance
from .trajectory import Trajectory

__all__ = ["Explanation", "choose_leaf", "describe_leaf", "explain", "render", "segment_box_closest_points",
           "tool_capsules"]


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
    """g(I) recomputed by the reference kernel, m."""
    capsule: int
    """Index of the capsule attaining g(I) (-1 without boxes)."""
    box: int
    """Index of the box attaining g(I) (-1 without boxes)."""
    distance_m: float
    """Distance between that capsule's axis and that box, m (nan without boxes)."""
    closest: tuple[np.ndarray, np.ndarray] | None
    """Closest points (on the axis, on the box) of that pair."""
    stage: str = "capsule"
    """The test of the result's run spec that decided the leaf, re-evaluated with its enclosure,
    tracking tolerance, self-collision test and dtype (:func:`~larc_jax.leaf_reference.leaf_test_np`):
    ``capsule``, ``hull`` or ``self`` when it passed (``self``: the recorded pair is a capsule pair
    and every test passed), ``""`` when it did not."""
    decided_clearance_m: float = math.nan
    """g of the pair that decided the leaf (that test's), m; the leaf passed iff it exceeds ``guard_m``."""
    guard_m: float = math.nan
    """The rounding guard of that pair, m."""
    other_capsule: int = -1
    """With a self-collision pair deciding the leaf: its second capsule (``capsule`` the first)."""

    @property
    def shell_radius(self) -> np.ndarray:
        """(C,) radius of the set kept clear of the boxes on the interval: r + rho + b, m."""
        return self.radius + self.margin_m + self.motion_b


def choose_leaf(result: TrajectoryResult, which: str = "first", at: float | None = None) -> Leaf:
    """The leaf to explain.

    ``which="first"``: the first inconclusive leaf of an uncertified trajectory (the one the
    ``larc certify`` table names), else the leaf with the smallest clearance; ``"worst"``: the
    leaf with the smallest clearance; ``at=t``: the leaf whose interval contains time ``t``.
    """
    if not result.leaves:
        raise LarcInputError(f"{result.id}: the result has no leaves to explain")
    if at is not None:
        for leaf in result.leaves:
            if leaf.t0 <= at <= leaf.t1:
                return leaf
        raise LarcInputError(
            f"{result.id}: time {at} s is outside the horizon "
            f"[{result.leaves[0].t0}, {result.leaves[-1].t1}] s"
        )
    if which not in ("first", "worst"):
        raise LarcInputError(f"leaf choice must be 'first' or 'worst', got {which!r}")
    bad = result.first_inconclusive
    if which == "first" and bad is not None:
        return bad

    def key(leaf):  # NaN (non-finite values) first: it never certifies
        g = leaf.clearance_m
        return (-math.inf if math.isnan(g) else g, leaf.t0)

    return min(result.leaves, key=key)


def describe_leaf(result: TrajectoryResult, leaf: Leaf) -> str:
    """A few words on which leaf this is (for titles and messages)."""
    finite = [lf.clearance_m for lf in result.leaves if not math.isnan(lf.clearance_m)]
    tightest = bool(finite) and leaf.clearance_m == min(finite)
    if leaf == result.first_inconclusive:
        return "first inconclusive interval (blocks the certificate)"
    if not leaf.certified:
        return "inconclusive interval" + (", smallest clearance" if tightest else "")
    return "tightest passed interval (smallest clearance)" if tightest else "passed interval"


def segment_box_closest_points(p0, p1, lo, hi, iters: int = 200):
    """Closest points between segment [p0, p1] and box [lo, hi]: ternary search on the convex
    function s -> dist(p(s), box) (exact up to the search tolerance; for drawing only)."""

    def point(s):
        return p0 + s * (p1 - p0)

    def dist(s):
        x = point(s)
        return float(np.linalg.norm(x - np.clip(x, lo, hi)))

    grid = np.linspace(0.0, 1.0, 65)
    k = int(np.argmin([dist(s) for s in grid]))
    a, b = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
    for _ in range(iters):
        m1, m2 = a + (b - a) / 3, b - (b - a) / 3
        if dist(m1) <= dist(m2):
            b = m2
        else:
            a = m1
    x = point(0.5 * (a + b))
    return x, np.clip(x, lo, hi)


def explain(robot: Robot, capsules: CapsuleModel, traj: Trajectory, scene: Scene,
            result: TrajectoryResult, leaf: Leaf | None = None) -> Explanation:
    """Recompute the interval test on ``leaf`` (default: ``choose_leaf(result)``) of ``traj``
    with the run spec of the result (``result.spec``: margin, enclosure, tracking tolerance,
    self-collision test, dtype; a result without one: the capsule test at ``result.margin_m``).
    The leaf's decision is that of the whole test (:attr:`Explanation.stage`); the picture's
    numbers are the capsule test's.

    ``traj`` must already be in the robot's joint order (``read_trajectory(path, robot)``).
    """
    leaf = leaf or choose_leaf(result)
    spec = result.spec or RunSpec(method="reference", margin_m=result.margin_m, enclosure="capsules")
    delta = check_tracking_tolerance(spec.tolerance_arg(), robot)
    enc = leaf_enclosures(robot, capsules, spec.enclosure, delta)
    bounds = trajectory_rounding(traj, robot, enc.capsules, spec.dtype, enc.hulls)
    pairs, skip = None, None
    if spec.self_collision:
        pairs = self_pairs(robot, capsules, spec.self_margin_m, spec.self_skip, proven=load_separation(robot))
        pairs = pairs if pairs.n_pairs else None
        skip = None if pairs is None else pairs.skip_mask(*curve_ranges(traj, delta))
    g, guard, c_dec, k_dec, other, stage = leaf_test_np(robot, enc, traj, scene, leaf.t0, leaf.t1, spec.margin_m,
                                                        bounds, pairs, skip)
    # The picture: the capsule test's placed capsules (radii grown by any tracking tolerance).
    ev = evaluate_interval_np(robot, enc.capsules, traj, scene, leaf.t0, leaf.t1, spec.margin_m, bounds)
    c, k = int(ev.capsule), int(ev.box)
    closest, dist = None, math.nan
    if other >= 0:  # a self-collision pair decided the leaf: draw its two capsules
        c, k = int(c_dec), -1
    elif scene.n_boxes:
        closest = segment_box_closest_points(ev.p_world_a[c], ev.p_world_b[c], scene.lo[k], scene.hi[k])
        dist = float(np.linalg.norm(closest[0] - closest[1]))
    else:
        c = k = -1
    passed = stage > 0
    stage_name = "" if not passed else "self" if other >= 0 else ("capsule", "hull")[stage - 1]
    return Explanation(
        trajectory_id=result.id, certified=result.certified, leaf=leaf, t_mid=float(ev.t_mid) + float(bounds.offset_s),
        h=float(ev.h_cov),
        q_mid=ev.q_mid, seg_a=ev.p_world_a, seg_b=ev.p_world_b, radius=np.asarray(enc.capsules.radius, np.float64),
        motion_b=ev.motion_b, margin_m=float(spec.margin_m), clearance_m=float(ev.g), capsule=c,
        box=k, distance_m=dist, closest=closest, stage=stage_name, decided_clearance_m=float(g),
        guard_m=float(guard), other_capsule=int(other),
    )


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


_VIEWS = (("top view (x–y)", 0, 1), ("side view (x–z)", 0, 2), ("front view (y–z)", 1, 2))
_RED, _BLUE = "#c62828", "#1f5fa8"


def _fmt_mm(x: float) -> str:
    if math.isnan(x):
        return "nan"
    if math.isinf(x):
        return "inf"
    return f"{x * 1000:+.1f} mm"


def render(ex: Explanation, robot: Robot, capsules: CapsuleModel, traj: Trajectory, scene: Scene,
           result: TrajectoryResult, path: str | Path, *, dpi: int = 110) -> Path:
    """Draw ``ex`` (module doc) to an image file (format from the suffix, e.g. ``.png``)."""
    from matplotlib.figure import Figure  # no pyplot: no GUI backend, no global figure state
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch, Polygon, Rectangle

    leaf = ex.leaf
    C = len(ex.radius)
    blocking_c, blocking_k = ex.capsule, ex.box
    full_path = _tool_path(robot, capsules, traj, float(traj.t[0]), float(traj.t[-1]), 160)
    leaf_path = _tool_path(robot, capsules, traj, leaf.t0, leaf.t1, 25)
    mid_tool = _tool_path(robot, capsules, traj, ex.t_mid, ex.t_mid, 1)[0]

    # Axis limits: the robot with its shells, the gripper path and the boxes, boxes clipped to
    # at most 0.4 m beyond the robot so a floor or wall does not shrink the arm to a dot.
    shell = ex.shell_radius
    pts = np.vstack([ex.seg_a - shell[:, None], ex.seg_a + shell[:, None],
                     ex.seg_b - shell[:, None], ex.seg_b + shell[:, None], full_path])
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    if scene.n_boxes:
        lo = np.minimum(lo, np.maximum(scene.lo.min(axis=0), lo - 0.4))
        hi = np.maximum(hi, np.minimum(scene.hi.max(axis=0), hi + 0.4))
    pad = 0.04
    lo, hi = lo - pad, hi + pad

    fig = Figure(figsize=(15, 9.2), dpi=dpi, layout="constrained")
    grid = fig.add_gridspec(2, 3, height_ratios=[2.3, 1.0])
    status = "CERTIFIED" if ex.certified else "NOT CERTIFIED"
    what = describe_leaf(result, leaf)
    pair = (f"capsule {leaf.capsule} vs box {leaf.box}" if blocking_c >= 0 else "no boxes in the scene")
    fig.suptitle(
        f"{ex.trajectory_id}: {status} — {what}\n"
        f"t = [{leaf.t0:.4f}, {leaf.t1:.4f}] s (depth {leaf.depth}), {pair}, "
        f"clearance g(I) = {_fmt_mm(leaf.clearance_m)}",
        fontsize=13, fontweight="bold",
    )

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
        order = [c for c in range(C) if c != blocking_c] + ([blocking_c] if blocking_c >= 0 else [])
        for c in order:
            mine = c == blocking_c
            p, q = ex.seg_a[c, [i, j]], ex.seg_b[c, [i, j]]
            ax.add_patch(Polygon(_stadium(p, q, shell[c]), closed=True,
                                 facecolor=_RED if mine else _BLUE, alpha=0.16 if mine else 0.06,
                                 edgecolor=_RED if mine else "none", linestyle="--",
                                 linewidth=1.2, zorder=3))
            ax.add_patch(Polygon(_stadium(p, q, ex.radius[c]), closed=True,
                                 facecolor=_RED if mine else _BLUE, alpha=0.55 if mine else 0.28,
                                 edgecolor="#8e0000" if mine else "#173f6e", linewidth=1.0 if mine else 0.6,
                                 zorder=4))
            ax.plot([p[0], q[0]], [p[1], q[1]], color="k", linewidth=0.6, alpha=0.6, zorder=5)
        ax.plot(full_path[:, i], full_path[:, j], ":", color="#6a1b9a", linewidth=1.2, zorder=5)
        ax.plot(leaf_path[:, i], leaf_path[:, j], "-", color="#6a1b9a", linewidth=3.5, zorder=6)
        ax.plot(mid_tool[i], mid_tool[j], "*", color="#6a1b9a", markersize=13,
                markeredgecolor="white", markeredgewidth=0.8, zorder=8)
        ax.plot(full_path[0, i], full_path[0, j], "o", color="#6a1b9a", markersize=5, zorder=6)
        ax.plot(full_path[-1, i], full_path[-1, j], "s", color="#6a1b9a", markersize=5, zorder=6)
        if ex.closest is not None:
            a_pt, b_pt = ex.closest
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
               "self": "passed; nearest: the self-collision pair"}[ex.stage]
    lines += [f"leaf {decided}: g = {_fmt_mm(ex.decided_clearance_m)}, guard {_fmt_mm(ex.guard_m)}"]
    if ex.other_capsule >= 0:
        lines += [f"self pair {capsules.names[ex.capsule]} / {capsules.names[ex.other_capsule]}"]
    elif blocking_c >= 0:
        c = blocking_c
        lines += [
            "",
            f"capsule {capsules.names[c]}:  r = {ex.radius[c] * 1000:7.2f} mm",
            f"margin              ρ = {ex.margin_m * 1000:7.2f} mm",
            f"motion radius       b = {ex.motion_b[c] * 1000:7.2f} mm",
            f"shell       r + ρ + b = {shell[c] * 1000:7.2f} mm",
            f"axis-to-box distance d = {ex.distance_m * 1000:6.2f} mm",
            f"g(I) = d − (r + ρ + b) = {_fmt_mm(ex.clearance_m)}",
        ]
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
    fig.legend(handles=handles, loc="outside lower center", ncol=4, fontsize=9.5, frameon=False)

    path = Path(path)
    buf = io.BytesIO()
    fig.savefig(buf, dpi=dpi, format=path.suffix.lstrip(".").lower() or "png")
    atomic_write_bytes(path, buf.getvalue())
    return path
