"""What ``larc view`` shows, in NumPy: the inputs it reads, poses, meshes, colours, one leaf's enclosures.

:func:`read_view_certificate` reads a certificate file (:mod:`larc_jax.products.certificate`) with the
readers ``larc verify`` uses (robot file, scenes, trajectory files by the names it records) and its
leaf cover; it does *not* re-check it (that is ``larc verify``): the view shows what the file
claims. :func:`read_view_files` takes trajectory, scene and robot files as ``larc certify`` does,
and optionally its ``--leaves`` table (CSV or Parquet; capsule and box *names* mapped back to
indices). Both give a :class:`ViewData`.

The rest are pure functions the viewer (:mod:`larc_jax.products.view`) draws from: the robot's collision
meshes per link (:func:`link_meshes`, from :func:`~larc_jax.enclosure.meshes.link_collisions`),
their poses along the trajectory (:func:`link_poses`, the NumPy forward kinematics), leaf colours
and the clearance timeline image, and :func:`leaf_detail`: the capsules at a leaf's midpoint with
their shells (radius + margin + motion radius b, recomputed by the float64 reference
:func:`~larc_jax.leaf.interval.evaluate_interval_np`) and the recorded pair with its closest points.
Nothing here imports JAX.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from pathlib import Path

from ..lazy_jax import defer_jax

defer_jax()

import numpy as np  # noqa: E402

from .certificate import CERTIFICATE_FORMAT, CERTIFICATE_VERSION, unhexf  # noqa: E402
from .certificate_fields import check_certificate_fields  # noqa: E402
from ..enclosure.capsule import CapsuleModel  # noqa: E402
from ..enclosure.hull import HullModel  # noqa: E402
from ..enclosure.meshes import link_collisions, links_with_geometry  # noqa: E402
from ..enclosure.robot_file import load_robot_file  # noqa: E402
from ..errors import LarcInputError  # noqa: E402
from ..engine.results import LEAF_COLUMNS, LeafTable  # noqa: E402
from ..run_spec import RunSpec  # noqa: E402
from ..enclosure.tracking import check_tracking_tolerance  # noqa: E402
from .explain import segment_box_closest_points, segment_segment_closest_points  # noqa: E402
from ..leaf.interval import evaluate_interval_np, trajectory_rounding  # noqa: E402
from ..leaf.record import Stage  # noqa: E402
from ..leaf.reference import leaf_enclosures  # noqa: E402
from ..io import parse_json, read_input_text  # noqa: E402
from ..model.robot import Robot, forward_kinematics_np  # noqa: E402
from ..model.scene import Scene, read_scene  # noqa: E402
from ..model.trajectory import Trajectory  # noqa: E402
from ..model.trajectory_files import read_trajectory_file  # noqa: E402

__all__ = ["ViewData", "ViewItem", "deciding", "LeafDetail", "read_view_certificate", "read_view_files",
           "link_meshes", "link_poses", "leaf_colours", "timeline_image", "leaf_detail", "STAGE_COLOURS"]

STAGE_COLOURS = {"capsule": (46, 125, 50), "hull": (0, 131, 143), "swept": (2, 119, 189), "self": (123, 31, 162),
                 "inconclusive": (211, 47, 47)}
"""RGB of a leaf on the timeline: passed by the capsule test, by the hull test, by the swept test,
recorded pair a self-collision pair (passed), or not passed."""


def deciding(leaves: LeafTable, j: int) -> str:
    """Which test the timeline shows for leaf ``j`` (a key of :data:`STAGE_COLOURS`)."""
    if not leaves.certified[j]:
        return "inconclusive"
    if leaves.other_capsule[j] >= 0:
        return "self"
    return Stage(int(leaves.stage[j])).label


@dataclasses.dataclass(frozen=True)
class ViewItem:
    traj: Trajectory
    scene: Scene
    leaves: LeafTable | None
    """One trajectory's leaves in time order (``capsule``, ``box``, ``other_capsule``: indices into the
    capsules and the item's scene, -1 for none)."""


@dataclasses.dataclass(frozen=True)
class ViewData:
    robot: Robot
    planned: CapsuleModel
    """The capsules as the run placed them (the robot file's, with the run's padding; before the
    tracking tolerance)."""
    items: tuple[ViewItem, ...]
    margin_m: float
    self_margin_m: float | None
    source: str
    enclosure: str = "capsules"
    delta: np.ndarray | None = None
    """Tracking tolerance per active joint (None: none)."""

    @functools.cached_property
    def capsules(self) -> CapsuleModel:
        """The capsules the leaf test used (grown by the tracking tolerance, if any)."""
        return leaf_enclosures(self.robot, self.planned, "capsules", self.delta).capsules

    @functools.cached_property
    def hulls(self) -> HullModel | None:
        """The hull parts of the cascade (built on first use: seconds), or None without it."""
        return leaf_enclosures(self.robot, self.planned, "hull", self.delta).hulls if self.enclosure == "hull" else None


def _floats(values, where: str) -> np.ndarray:
    try:
        return np.array([unhexf(s) for s in values], np.float64)
    except (TypeError, ValueError, OverflowError):
        raise LarcInputError(f"{where}: not a list of float.hex() numbers") from None


def _cert_leaves(lv: dict, where: str) -> LeafTable:
    try:
        n = len(lv["t0"])
        ints = {k: np.asarray(lv[k], np.int64) for k in ("depth", "index", "capsule", "box", "other_capsule", "stage")}
        return LeafTable(traj=np.zeros(n, np.int64), t0=_floats(lv["t0"], f"{where}.t0"),
                         t1=_floats(lv["t1"], f"{where}.t1"),
                         clearance_m=_floats(lv["clearance_m"], f"{where}.clearance_m"),
                         guard_m=_floats(lv["guard_m"], f"{where}.guard_m"), certified=np.asarray(lv["certified"], bool),
                         **ints)
    except (KeyError, TypeError, ValueError, OverflowError) as exc:
        raise LarcInputError(f"{where}: malformed leaf columns ({exc})") from None


def read_view_certificate(path) -> ViewData:
    """The robot, scenes, trajectories and leaf cover a certificate file names (not re-checked)."""
    source = str(path)
    doc = parse_json(read_input_text(Path(path), "certificate"), source)
    if not isinstance(doc, dict) or doc.get("format") != CERTIFICATE_FORMAT:
        raise LarcInputError(f"{source}: not a larc certificate (format {CERTIFICATE_FORMAT!r} expected)")
    if doc.get("version") != CERTIFICATE_VERSION:
        raise LarcInputError(f"{source}: certificate version {str(doc.get('version'))[:20]}, this viewer reads version "
                             f"{CERTIFICATE_VERSION} (re-certify with larc certify --certificate)")
    check_certificate_fields(doc, source)
    rdoc, spec = doc["robot"], RunSpec.from_dict(doc["parameters"], f"{source}: parameters")
    stated = {str(j): unhexf(v) for j, v in (rdoc.get("stated_joints") or {}).items()}
    robot, capsules = load_robot_file(rdoc.get("file"), hold=stated,
                                      active_joints=rdoc.get("active_joints"))
    more = [x for x in spec.ignore_links if x not in capsules.excluded_links]
    if more:
        capsules = capsules.without_links(robot, more, what="certificate excluded_links:")
    capsules = capsules.with_padding(spec.padding_m)  # as certified (RunSpec.padding_m)
    delta = check_tracking_tolerance(spec.tolerance_arg(), robot, f"{source}: parameters.tracking_tolerance")
    scenes = []
    for k, sdoc in enumerate(doc["scenes"]):
        if sdoc.get("file") is None:
            raise LarcInputError(f"{source}: scenes[{k}] was certified from arrays (no file to show)")
        scenes.append(read_scene(sdoc["file"], frame=robot.link_names[0]))
    items = []
    for k, tdoc in enumerate(doc["trajectories"]):
        if tdoc.get("file") is None:
            raise LarcInputError(f"{source}: trajectories[{k}] was certified from arrays (no file to show)")
        traj = read_trajectory_file(tdoc["file"], robot, velocities=tdoc.get("velocities") or spec.velocities).trajectory
        items.append(ViewItem(traj, scenes[int(tdoc["scene"])], _cert_leaves(tdoc["leaves"], f"{source}: "
                                                                                     f"trajectories[{k}].leaves")))
    return ViewData(robot, capsules, tuple(items), spec.margin_m, spec.self_margin_m if spec.self_collision else None,
                    source, spec.enclosure, delta)


def _table_leaves(df, tid: str, capsules: CapsuleModel, scene: Scene, source: str) -> LeafTable | None:
    rows = df[df["id"].astype(str) == tid].sort_values("t0")
    if not len(rows):
        return None
    caps = {n: i for i, n in enumerate(capsules.names)}
    boxes = {n: i for i, n in enumerate(scene.obstacle_names)}

    def index(names, table, what):
        out = []
        for n in names.astype(object).where(names.notna(), "").astype(str):
            if n and n not in table:
                raise LarcInputError(f"{source}: trajectory '{tid}': {what} '{n}' is not in the robot file / scene")
            out.append(table.get(n, -1))
        return np.array(out, np.int64)

    stage = rows["stage"].astype(object).where(rows["stage"].notna(), "").astype(str).map({s.label: int(s) for s in Stage}).fillna(0)
    return LeafTable(traj=np.zeros(len(rows), np.int64), depth=rows["depth"].to_numpy(np.int64),
                     index=rows["index"].to_numpy(np.int64), t0=rows["t0"].to_numpy(float),
                     t1=rows["t1"].to_numpy(float), clearance_m=rows["clearance_m"].to_numpy(float),
                     guard_m=rows["guard_m"].to_numpy(float), certified=rows["certified"].to_numpy(bool),
                     capsule=index(rows["capsule"], caps, "capsule"), box=index(rows["box"], boxes, "box"),
                     other_capsule=index(rows["other_capsule"], caps, "capsule"), stage=stage.to_numpy(np.int64))


def read_view_files(trajectories, scene, robot_file=None, leaves=None, *, margin_m: float | None = None,
                    velocities: str = "recorded", enclosure: str | None = None,
                    padding_m: float | None = None) -> ViewData:
    """Trajectory files, one scene file and the robot file (``None``: PIPER), as ``larc certify``
    reads them (its defaults: margin, enclosure, the enclosure's padding); ``leaves``: its
    ``--leaves`` table (CSV or Parquet) for the leaf cover."""
    from ..defaults import DEFAULT_ENCLOSURE, DEFAULT_MARGIN_M

    spec = RunSpec(enclosure=enclosure or DEFAULT_ENCLOSURE, padding_m=padding_m)
    robot, capsules = load_robot_file(robot_file)
    capsules = capsules.with_padding(spec.padding_m)
    sc = read_scene(scene, frame=robot.link_names[0])
    trajs = [read_trajectory_file(p, robot, velocities=velocities).trajectory for p in trajectories]
    df = None
    if leaves is not None:
        import pandas as pd

        try:
            df = pd.read_parquet(leaves) if str(leaves).endswith(".parquet") else pd.read_csv(leaves)
        except (OSError, ValueError) as exc:
            raise LarcInputError(f"{leaves}: cannot read the leaf table ({exc})") from None
        missing = set(LEAF_COLUMNS) - set(df)
        if missing:
            raise LarcInputError(f"{leaves}: not a `larc certify --leaves` table (missing {sorted(missing)})")
    items = tuple(ViewItem(t, sc, None if df is None else _table_leaves(df, t.id, capsules, sc, str(leaves)))
                  for t in trajs)
    return ViewData(robot, capsules, items, DEFAULT_MARGIN_M if margin_m is None else margin_m, None,
                    str(leaves or trajectories[0]), spec.enclosure)


def _primitive_mesh(geom):
    import trimesh

    if geom.box is not None:
        return trimesh.creation.box(extents=geom.box.size)
    if geom.sphere is not None:
        return trimesh.creation.icosphere(subdivisions=2, radius=geom.sphere.radius)
    return trimesh.creation.cylinder(radius=geom.cylinder.radius, height=geom.cylinder.length)


def link_meshes(robot: Robot) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Collision geometry of every link that has some: link index -> (vertices (V, 3) in the link
    frame, faces (F, 3)), all ``<collision>`` elements of the link in one mesh."""
    out = {}
    for link in links_with_geometry(robot):
        vs, fs, n = [], [], 0
        for origin, geom, mesh in link_collisions(robot, link):
            if mesh is None:
                prim = _primitive_mesh(geom)
                mesh = (np.asarray(prim.vertices, float), np.asarray(prim.faces, np.int64))
            v = mesh[0] @ origin[:3, :3].T + origin[:3, 3]
            vs.append(v)
            fs.append(mesh[1] + n)
            n += len(v)
        out[robot.link_index(link)] = (np.vstack(vs).astype(np.float32), np.vstack(fs).astype(np.uint32))
    return out


def wxyz(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a 3x3 rotation matrix."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(rotation).as_quat()
    return np.array([w, x, y, z])


def link_poses(robot: Robot, traj: Trajectory, t: float) -> np.ndarray:
    """(L, 4, 4) base-frame poses of every link at time ``t`` (the Hermite curve the certificate covers)."""
    from ..model.hermite import evaluate_np

    q, _ = evaluate_np(traj.t, traj.q, traj.qd, float(np.clip(t, traj.t[0], traj.t[-1])))
    return forward_kinematics_np(robot, np.asarray(q, np.float64))


def leaf_colours(leaves: LeafTable) -> np.ndarray:
    """(K, 3) uint8 RGB of each leaf (:data:`STAGE_COLOURS`)."""
    return np.array([STAGE_COLOURS[deciding(leaves, j)] for j in range(len(leaves))], np.uint8).reshape(-1, 3)


def timeline_image(leaves: LeafTable, t_start: float, t_end: float, width: int = 480, height: int = 28,
                   selected: int | None = None, t_now: float | None = None) -> np.ndarray:
    """(height, width, 3) uint8 picture of the leaf cover: each leaf's time span in its colour,
    the selected leaf outlined in black, the current time as a white line."""
    img = np.full((height, width, 3), 235, np.uint8)
    span = max(t_end - t_start, 1e-12)

    def col(t):
        return int(np.clip(round((t - t_start) / span * width), 0, width))

    colours = leaf_colours(leaves)
    for j in range(len(leaves)):
        a, b = col(leaves.t0[j]), max(col(leaves.t1[j]), col(leaves.t0[j]) + 1)
        img[4:-4, a:b] = colours[j]
    if selected is not None:
        a, b = col(leaves.t0[selected]), max(col(leaves.t1[selected]), col(leaves.t0[selected]) + 1)
        img[:4, a:b] = img[-4:, a:b] = 0
    if t_now is not None:
        c = min(col(t_now), width - 1)
        img[:, c] = 255
    return img


@dataclasses.dataclass(frozen=True)
class LeafDetail:
    """The capsules of one leaf at its midpoint, their shells, and the recorded pair."""

    t_mid: float
    seg_a: np.ndarray
    """(C, 3) capsule axis starts at q(t_mid), base frame, m."""
    seg_b: np.ndarray
    radius: np.ndarray
    shell_radius: np.ndarray
    """(C,) radius + margin + motion radius b, m: what the test keeps clear of the boxes."""
    capsule: int
    box: int
    other: int
    closest: tuple[np.ndarray, np.ndarray] | None
    """Closest points (capsule axis, box or other axis) of the recorded pair."""
    hull_parts: tuple[np.ndarray, ...] = ()
    """Leaf passed by the hull test: the vertices (K, 3), base frame, of each hull part of the
    recorded capsule's link at q(t_mid) (each part is their convex hull, padded by a few mm)."""


def leaf_detail(data: ViewData, item: ViewItem, j: int) -> LeafDetail:
    """Recompute leaf ``j`` of ``item`` with the float64 reference (capsule test) for drawing."""
    lv, caps, scene = item.leaves, data.capsules, item.scene
    bounds = trajectory_rounding(item.traj, data.robot, caps)
    ev = evaluate_interval_np(data.robot, caps, item.traj, scene, float(lv.t0[j]), float(lv.t1[j]), data.margin_m,
                              bounds)
    pa, pb = np.asarray(ev.p_world_a, float), np.asarray(ev.p_world_b, float)
    radius = np.asarray(caps.radius, float)
    c, k, o = int(lv.capsule[j]), int(lv.box[j]), int(lv.other_capsule[j])
    closest = None
    if c >= 0 and o >= 0:
        closest = segment_segment_closest_points(pa[c], pb[c], pa[o], pb[o])
    elif c >= 0 and 0 <= k < scene.n_boxes:
        closest = segment_box_closest_points(pa[c], pb[c], scene.lo[k], scene.hi[k])
    margin = data.self_margin_m if o >= 0 and data.self_margin_m is not None else data.margin_m
    t_mid = float(ev.t_mid) + float(bounds.offset_s)
    if not math.isfinite(t_mid):
        t_mid = 0.5 * float(lv.t0[j] + lv.t1[j])
    parts = ()
    if lv.stage[j] == Stage.HULL and c >= 0 and data.hulls is not None:
        hulls, link = data.hulls, caps.link_index[c]
        T = forward_kinematics_np(data.robot, np.asarray(ev.q_mid, np.float64))
        parts = tuple(np.asarray(hulls.vertices[p][: hulls.n_vertices[p]], float) @ T[link, :3, :3].T + T[link, :3, 3]
                      for p in range(len(hulls.names)) if hulls.link_index[p] == link)
    return LeafDetail(t_mid=t_mid, seg_a=pa, seg_b=pb, radius=radius,
                      shell_radius=radius + margin + np.asarray(ev.motion_b, float), capsule=c, box=k, other=o,
                      closest=closest, hull_parts=parts)
