"""Capsule enclosures of the link meshes, the capsule file, and motion constants a_lj.

Soundness chain (what this module proves):

1. **Containment** (paper eq. 2 at zero motion). A capsule is the set of points within ``radius``
   of a segment, hence convex. The collision geometry of a link is split into *elements*
   (mesh triangles; box/cylinder/sphere primitives replaced by a circumscribed polyhedron). An
   element lies in a capsule iff each of its vertices does (convexity), so checking every vertex
   proves that the whole mesh lies in the union of the link's capsules. Fitting and checking use
   ``radius - padding``: the stored radius carries ``padding_m`` of extra margin on top.
2. **Finger stroke.** For a movable joint that trajectories do not carry (held at a recorded
   value, e.g. PIPER's prismatic fingers), each element is enclosed together with its copies
   shifted to both ends of the joint's stroke. A prismatic stroke sweeps the element along a
   segment, and the convex hull of the two end copies contains that sweep, so the capsule holds
   the finger at *any* opening.
3. **Held revolute joints** (e.g. a linkage gripper's knuckles, incl. mimic joints) are
   enclosed at their held value only: the capsule file records the values (``held_joints``) and
   loading it refuses a robot held elsewhere. (A rotation's sweep is not the hull of its ends.)
4. **Motion constants** (paper eq. 6), see :func:`motion_constants`.

Meshes are read with trimesh without processing (the vertices are exactly the file's), in any
format it reads (STL, OBJ, PLY, GLB; DAE through pycollada); a COLLADA ``<unit meter="s"/>``
scales the vertices by ``s`` (as ROS tools do), then the URDF ``scale`` applies. The parsed URDF
and the meshes are cached (keyed on the file, its size and modification time).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
from pathlib import Path
from typing import Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import yaml

from .errors import LarcInputError
from .io import parse_yaml, read_input_text, short_repr
from .robot import JointType, Robot, forward_kinematics, forward_kinematics_np, load_urdf_model

__all__ = [
    "CapsuleModel",
    "fit_capsules",
    "load_capsules",
    "save_capsules",
    "verify_containment",
    "motion_constants",
    "link_elements",
    "capsule_segments",
    "capsule_segments_np",
    "default_capsule_path",
]

MODEL_REVISION = "larc-capsules-1"
_ROUND = 1e-6  # radii are rounded *up* to the micrometre (endpoints are stored to it).


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class CapsuleModel:
    """Capsules attached to links, with their motion constants.

    Each capsule is the set of points within ``radius`` of the segment ``[p_link_a, p_link_b]``
    given in its link's frame.
    """

    p_link_a: jax.Array
    """(C, 3) first segment endpoint in the link frame, m."""
    p_link_b: jax.Array
    """(C, 3) second segment endpoint in the link frame, m."""
    radius: jax.Array
    """(C,) capsule radius including padding, m."""
    motion_a: jax.Array
    """(C, n) a_lj: bound on the distance from active joint j's axis to any capsule point over
    all configurations within the limits, m (1 for prismatic joints: m/m)."""

    names: tuple[str, ...] = dataclasses.field(metadata=dict(static=True))
    link_names: tuple[str, ...] = dataclasses.field(metadata=dict(static=True))
    link_index: tuple[int, ...] = dataclasses.field(metadata=dict(static=True))
    """Robot link index carrying each capsule."""
    padding_m: float = dataclasses.field(metadata=dict(static=True))

    @property
    def n_capsules(self) -> int:
        return len(self.names)


def default_capsule_path() -> Path:
    """``configs/piper_capsules.yaml`` of this project checkout."""
    return Path(__file__).resolve().parent.parent / "configs" / "piper_capsules.yaml"


# ----------------------------------------------------------------------------------------------
# Capsule placement (JAX kernel for one configuration + NumPy reference)
# ----------------------------------------------------------------------------------------------


def capsule_segments(robot: Robot, capsules: CapsuleModel, q: jax.Array):
    """World-frame capsule segments at one configuration.

    Args:
      q: (n,) active joint values.

    Returns:
      (p_world_a, p_world_b), each (C, 3) in metres.
    """
    T_world_link = forward_kinematics(robot, q)
    T = T_world_link[jnp.asarray(capsules.link_index)]  # (C, 4, 4)
    R, t = T[:, :3, :3], T[:, :3, 3]
    a = jnp.einsum("cij,cj->ci", R, capsules.p_link_a.astype(R.dtype)) + t
    b = jnp.einsum("cij,cj->ci", R, capsules.p_link_b.astype(R.dtype)) + t
    return a, b


def capsule_segments_np(robot: Robot, capsules: CapsuleModel, q: np.ndarray):
    """NumPy float64 reference of :func:`capsule_segments`."""
    T_world_link = forward_kinematics_np(robot, q)
    out_a, out_b = [], []
    for c, li in enumerate(capsules.link_index):
        T = T_world_link[li]
        out_a.append(T[:3, :3] @ np.asarray(capsules.p_link_a[c], np.float64) + T[:3, 3])
        out_b.append(T[:3, :3] @ np.asarray(capsules.p_link_b[c], np.float64) + T[:3, 3])
    return np.array(out_a), np.array(out_b)


# ----------------------------------------------------------------------------------------------
# Geometry of the collision elements
# ----------------------------------------------------------------------------------------------


def _point_segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances of points ``p`` (..., 3) to the segment [a, b], float64."""
    d = b - a
    dd = float(d @ d)
    t = np.zeros(p.shape[:-1]) if dd == 0.0 else np.clip(((p - a) @ d) / dd, 0.0, 1.0)
    return np.linalg.norm(p - a - t[..., None] * d, axis=-1)


def _circumscribed_sphere_vertices(radius: float) -> np.ndarray:
    import trimesh

    ico = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    # Scale so that every face plane is at least `radius` from the centre: the polyhedron then
    # contains the sphere, so enclosing its vertices encloses the sphere.
    inradius = np.min(np.abs(np.einsum("fi,fi->f", ico.face_normals, ico.triangles_center)))
    return ico.vertices * (radius / inradius)


def _primitive_vertices(geometry) -> np.ndarray | None:
    if geometry.box is not None:
        sx, sy, sz = np.asarray(geometry.box.size, float) / 2
        return np.array([[x, y, z] for x in (-sx, sx) for y in (-sy, sy) for z in (-sz, sz)])
    if geometry.sphere is not None:
        return _circumscribed_sphere_vertices(float(geometry.sphere.radius))
    if geometry.cylinder is not None:
        m = 32
        r = float(geometry.cylinder.radius) / math.cos(math.pi / m)  # circumscribed m-gon
        h = float(geometry.cylinder.length) / 2
        ang = 2 * np.pi * np.arange(m) / m
        ring = np.stack([r * np.cos(ang), r * np.sin(ang)], axis=1)
        return np.concatenate([np.c_[ring, np.full(m, -h)], np.c_[ring, np.full(m, h)]])
    return None


@functools.lru_cache(maxsize=8)
def _model_cached(urdf_path: str, stamp: tuple, package_dirs: tuple):
    return load_urdf_model(urdf_path, dict(package_dirs))


def _file_stamp(path: str | Path) -> tuple:
    st = os.stat(path)
    return (str(path), st.st_size, st.st_mtime_ns)


def _robot_model(robot: Robot):
    """The parsed URDF of ``robot`` (cached; re-parsed if the file changed)."""
    return _model_cached(robot.urdf_path, _file_stamp(robot.urdf_path), tuple(robot.package_dirs))


@functools.lru_cache(maxsize=256)
def _mesh_cached(stamp: tuple, link: str) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    path = stamp[0]
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # noqa: BLE001
        raise LarcInputError(f"{path}: cannot read mesh of link '{link}' ({exc})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise LarcInputError(f"{path}: mesh of link '{link}' has no triangles")
    v = np.array(mesh.vertices, dtype=np.float64)
    if getattr(mesh, "units", None):
        try:
            v *= float(trimesh.units.unit_conversion(mesh.units, "meters"))
        except Exception:  # noqa: BLE001
            raise LarcInputError(f"{path}: mesh of link '{link}' has unknown units {mesh.units!r}") from None
    if not np.isfinite(v).all():
        raise LarcInputError(f"{path}: mesh of link '{link}' has non-finite vertices")
    f = np.array(mesh.faces, dtype=np.int64)
    v.flags.writeable = False
    f.flags.writeable = False
    return v, f


def link_elements(robot: Robot, link: str) -> np.ndarray:
    """Collision elements of ``link`` in its own frame: (E, P, 3) vertex sets, float64.

    An element is one mesh triangle (P = 3) or one whole primitive. If the link hangs on a held
    (non-active) prismatic joint, every element also carries its copies shifted to both stroke
    ends (see module docstring), so P is tripled.
    """
    from .robot import _resolve_uri  # same resolution as the loader

    model = _robot_model(robot)
    dirs = dict(robot.package_dirs)
    i = robot.link_index(link)
    ulink = model.link_map[link]
    groups: list[np.ndarray] = []
    for col in ulink.collisions:
        origin = np.asarray(col.origin if col.origin is not None else np.eye(4), float)
        geom = col.geometry
        if geom is None:
            raise LarcInputError(f"{robot.urdf_path}: link '{link}' has a <collision> without geometry")
        if geom.mesh is not None:
            path = _resolve_uri(geom.mesh.filename, Path(robot.urdf_path), dirs)
            if not path.is_file():
                raise LarcInputError(
                    f"{robot.urdf_path}: link '{link}' collision mesh '{geom.mesh.filename}' "
                    f"resolves to {path}, which does not exist"
                )
            v, faces = _mesh_cached(_file_stamp(path), link)
            scale = np.asarray(geom.mesh.scale if geom.mesh.scale is not None else 1.0, float)
            elems = (v * scale)[faces]  # (F, 3, 3)
        else:
            v = _primitive_vertices(geom)
            if v is None:
                raise LarcInputError(f"{robot.urdf_path}: link '{link}' has an unsupported collision geometry")
            elems = v[None]
        elems = elems @ origin[:3, :3].T + origin[:3, 3]
        if groups and groups[0].shape[1] != elems.shape[1]:
            # Mixed element sizes: pad by repeating the first vertex (same hull, same test).
            p = max(groups[0].shape[1], elems.shape[1])
            groups = [np.concatenate([g, np.repeat(g[:, :1], p - g.shape[1], 1)], 1) for g in groups]
            elems = np.concatenate([elems, np.repeat(elems[:, :1], p - elems.shape[1], 1)], 1)
        groups.append(elems)
    if not groups:
        return np.zeros((0, 3, 3))
    elems = np.concatenate(groups)
    if robot.q_index[i] < 0 and robot.joint_type[i] == JointType.PRISMATIC:
        lo, hi = _joint_limits(model, robot.joint_names[i])
        ax = np.asarray(robot.axis[i], float)
        held = float(robot.q_held[i])
        elems = np.concatenate(
            [elems, elems + (lo - held) * ax, elems + (hi - held) * ax], axis=1
        )
    return elems


def _joint_limits(model, joint: str) -> tuple[float, float]:
    j = model.joint_map[joint]
    return float(j.limit.lower), float(j.limit.upper)


# ----------------------------------------------------------------------------------------------
# Fitting
# ----------------------------------------------------------------------------------------------


def _capsule_volume(length: float, r: float) -> float:
    return math.pi * r * r * length + 4.0 / 3.0 * math.pi * r**3


def _hull_points(points: np.ndarray) -> np.ndarray:
    from scipy.spatial import ConvexHull, QhullError

    pts = np.unique(points.reshape(-1, 3), axis=0)
    try:
        return pts[ConvexHull(pts).vertices]
    except (QhullError, ValueError):
        return pts  # degenerate (flat) sets: every point is kept, still exact


def _hull_volume(points: np.ndarray) -> float:
    from scipy.spatial import ConvexHull, QhullError

    try:
        return float(ConvexHull(np.unique(points.reshape(-1, 3), axis=0)).volume)
    except (QhullError, ValueError):
        return 0.0


def _fit_one(points: np.ndarray, maxiter: int = 3000) -> tuple[np.ndarray, np.ndarray, float]:
    """Minimum-volume capsule (core radius, no padding) around ``points`` (hull vertices)."""
    from scipy.optimize import minimize

    centre = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centre, full_matrices=False)

    def volume(x: np.ndarray) -> float:
        a, b = x[:3], x[3:]
        return _capsule_volume(float(np.linalg.norm(b - a)), float(_point_segment_distance(points, a, b).max()))

    best = None
    for u in vt:  # a start along each principal direction
        s = (points - centre) @ u
        r0 = float(np.linalg.norm((points - centre) - np.outer(s, u), axis=1).max())
        half = max(0.0, (s.max() - s.min()) / 2 - r0 * 0.5)
        mid = centre + u * (s.max() + s.min()) / 2
        x0 = np.concatenate([mid - half * u, mid + half * u])
        res = minimize(volume, x0, method="Nelder-Mead",
                       options=dict(maxiter=maxiter, xatol=1e-6, fatol=1e-12))
        if best is None or res.fun < best.fun:
            best = res
    return best.x[:3], best.x[3:], volume(best.x)


def _split_parts(elements: np.ndarray, cut_fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """Split elements (whole, never clipped) by their centroid along the principal axis."""
    c = elements.mean(axis=1)
    centre = c.mean(axis=0)
    _, _, vt = np.linalg.svd(c - centre, full_matrices=False)
    s = (c - centre) @ vt[0]
    cut = np.quantile(s, cut_fraction)
    mask = s <= cut
    return mask, ~mask


@dataclasses.dataclass
class _Fitted:
    name: str
    link: str
    a: np.ndarray
    b: np.ndarray
    radius: float
    volume_m3: float
    hull_volume_m3: float
    n_elements: int


def _finalise(name, link, elems, a, b, padding) -> _Fitted:
    # Store endpoints to the micrometre, then take the radius from the *stored* endpoints so the
    # file itself is what containment is proven for; round the radius up, never down.
    a = np.array([round(float(x), 6) for x in a])  # exactly the values the file will hold
    b = np.array([round(float(x), 6) for x in b])
    core = float(_point_segment_distance(elems.reshape(-1, 3), a, b).max())
    radius = round(math.ceil((core + padding) / _ROUND) * _ROUND, 6)
    while radius - padding < core:  # the decimal the file holds must not undercut the proof
        radius = round(radius + _ROUND, 6)
    return _Fitted(
        name, link, a, b, radius,
        _capsule_volume(float(np.linalg.norm(b - a)), radius),
        _hull_volume(elems), len(elems),
    )


def fit_capsules(
    robot: Robot,
    *,
    n_capsules: int | None = None,
    capsules_per_link: Mapping[str, int] | None = None,
    padding_m: float = 0.001,
    links: Sequence[str] | None = None,
    progress=None,
) -> list[_Fitted]:
    """Fit minimum-volume capsules to every link with collision geometry.

    Each link gets one capsule; links listed in ``capsules_per_link`` with 2 get two, as do the
    links that gain most volume from a split until ``n_capsules`` is reached. With two capsules
    the link's elements (triangles) are split whole along the principal axis, at the cut that
    minimises the total volume.
    """
    per_link = dict(capsules_per_link or {})
    for k, v in per_link.items():
        if v not in (1, 2):
            raise LarcInputError(f"capsules_per_link: link '{k}' asks for {v} capsules (1 or 2)")
    names = list(links) if links is not None else list(robot.link_names)
    elements = {}
    for link in names:
        e = link_elements(robot, link)
        if len(e):
            elements[link] = e
    if not elements:
        raise LarcInputError(f"{robot.urdf_path}: no link has collision geometry")

    single, double = {}, {}
    for link, e in elements.items():
        if progress:
            progress(f"fitting {link}")
        hull = _hull_points(e)
        single[link] = _fit_one(hull)
        if per_link.get(link, 2 if n_capsules else 1) == 2:
            best = None
            for frac in (0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8):
                m1, m2 = _split_parts(e, frac)
                f1 = _fit_one(_hull_points(e[m1]), maxiter=600)
                f2 = _fit_one(_hull_points(e[m2]), maxiter=600)
                if best is None or f1[2] + f2[2] < best[0]:
                    best = (f1[2] + f2[2], frac)
            m1, m2 = _split_parts(e, best[1])
            double[link] = (m1, m2, _fit_one(_hull_points(e[m1])), _fit_one(_hull_points(e[m2])))

    split = {l for l, v in per_link.items() if v == 2}
    if n_capsules is not None:
        budget = n_capsules - len(elements) - len(split)
        if budget < 0 or budget > len(elements) - len(split):
            raise LarcInputError(
                f"cannot fit {n_capsules} capsules to {len(elements)} links with collision geometry"
            )
        gains = sorted(
            ((single[l][2] - double[l][2][2] - double[l][3][2], l) for l in double
             if l not in split and per_link.get(l) != 1),
            reverse=True,
        )
        split |= {l for _, l in gains[:budget]}

    out = []
    for link, e in elements.items():
        if link in split:
            m1, m2, f1, f2 = double[link]
            out.append(_finalise(f"{link}_a", link, e[m1], f1[0], f1[1], padding_m))
            out.append(_finalise(f"{link}_b", link, e[m2], f2[0], f2[1], padding_m))
        else:
            a, b, _ = single[link]
            out.append(_finalise(link, link, e, a, b, padding_m))
    return out


# ----------------------------------------------------------------------------------------------
# Containment check
# ----------------------------------------------------------------------------------------------


def verify_containment(robot: Robot, capsules: CapsuleModel, *, source: str = "capsule file") -> dict:
    """Prove that every collision element of every link lies inside one of its link's capsules
    shrunk by the padding. Raises :class:`LarcInputError` naming the link and element otherwise.

    Returns ``{link: number of elements checked}``.
    """
    checked = {}
    for link in dict.fromkeys(capsules.link_names):
        elems = link_elements(robot, link)
        idx = [c for c, l in enumerate(capsules.link_names) if l == link]
        inside = np.zeros(len(elems), bool)
        for c in idx:
            a = np.asarray(capsules.p_link_a[c], np.float64)
            b = np.asarray(capsules.p_link_b[c], np.float64)
            core = float(capsules.radius[c]) - capsules.padding_m
            inside |= (_point_segment_distance(elems, a, b) <= core).all(axis=1)
        if not inside.all():
            bad = int(np.flatnonzero(~inside)[0])
            raise LarcInputError(
                f"{source}: link '{link}' element {bad} (of {len(elems)}) is not inside any of "
                f"its capsules {[capsules.names[c] for c in idx]} shrunk by the padding"
            )
        checked[link] = len(elems)
    for i, link in enumerate(robot.link_names):
        if link not in checked and len(link_elements(robot, link)):
            raise LarcInputError(f"{source}: link '{link}' has collision geometry but no capsule")
    return checked


# ----------------------------------------------------------------------------------------------
# Motion constants (paper eq. 6)
# ----------------------------------------------------------------------------------------------


def motion_constants(
    robot: Robot, link_index: Sequence[int], p_link_a: np.ndarray, p_link_b: np.ndarray,
    radius: np.ndarray,
) -> np.ndarray:
    """Sound a_lj for every capsule l and active joint j: (C, n), float64.

    Every point p of capsule l moves with velocity ``sum_j qd_j * v_j(p)`` where
    ``v_j = axis_j x (p - o_j)`` for a revolute joint (``|v_j| = dist(p, axis_j)``) and
    ``v_j = axis_j`` for a prismatic joint (``|v_j| = 1``). Hence ``|p_dot| <= sum_j a_lj |qd_j|``
    whenever ``a_lj >= dist(p, axis_j)`` for all configurations, which is what we bound:

    * joint j not an ancestor of the capsule's link: a_lj = 0;
    * prismatic j: a_lj = 1;
    * revolute j with no active joint between it and the link: the capsule is rigid in the frame
      F_j of j's child link, so ``dist(p, axis_j) <= max_{e in {a,b}} |P_j e_Fj| + r`` exactly
      (``P_j = I - axis axis^T``; distance to a line is convex along the segment, and a ball of
      radius r adds at most r);
    * otherwise (triangle inequality along the chain): let k_1 be the next active joint, with
      joint-frame origin c_1 in F_j (constant: only fixed/held joints lie between). Then
      ``dist(p, axis_j) <= |P_j c_1| + |p - o_{k1}|`` (for a prismatic k_1 the first term is the
      max over the stroke ends of ``|P_j (c_1 + q R_1 axis_k1)|``, convex in q). The norm
      ``|p - o_{k1}|`` is invariant to k_1's rotation, and is bounded the same way, link by link,
      with ``|c_i|`` in place of ``|P_j c_i|``, ending with ``max_e |e_F| + r`` at the last
      active joint.
    """
    n = robot.n_joints
    T_pj = np.asarray(robot.T_parent_joint, np.float64)
    axis = np.asarray(robot.axis, np.float64)
    q_held = np.asarray(robot.q_held, np.float64)
    lower = np.asarray(robot.q_lower, np.float64)
    upper = np.asarray(robot.q_upper, np.float64)

    def held_motion(i: int) -> np.ndarray:
        M = np.eye(4)
        if robot.joint_type[i] == JointType.REVOLUTE:
            from scipy.spatial.transform import Rotation

            M[:3, :3] = Rotation.from_rotvec(axis[i] * q_held[i]).as_matrix()
        elif robot.joint_type[i] == JointType.PRISMATIC:
            M[:3, 3] = axis[i] * q_held[i]
        return M

    def is_active(i: int) -> bool:
        return robot.q_index[i] >= 0

    out = np.zeros((len(link_index), n))
    for c, li in enumerate(link_index):
        path = robot.ancestors(li)[1:]  # link indices whose joint lies on the way to li
        ends = np.stack([np.asarray(p_link_a[c], float), np.asarray(p_link_b[c], float)])
        r = float(radius[c])
        for pos, i in enumerate(path):
            if not is_active(i):
                continue
            j = robot.q_index[i]
            if robot.joint_type[i] == JointType.PRISMATIC:
                out[c, j] = 1.0
                continue
            P = np.eye(3) - np.outer(axis[i], axis[i])
            proj = P  # first step measures perpendicular distance, later steps full norms
            total = 0.0
            A = np.eye(4)  # frame of the current active joint's child link -> walked frame
            for k in path[pos + 1:]:
                if not is_active(k):
                    A = A @ T_pj[k] @ held_motion(k)
                    continue
                J = A @ T_pj[k]
                c1, ax = J[:3, 3], J[:3, :3] @ axis[k]
                if robot.joint_type[k] == JointType.PRISMATIC:
                    qk = robot.q_index[k]
                    total += max(np.linalg.norm(proj @ (c1 + lower[qk] * ax)),
                                 np.linalg.norm(proj @ (c1 + upper[qk] * ax)))
                else:
                    total += np.linalg.norm(proj @ c1)
                proj = np.eye(3)
                A = np.eye(4)
            e = ends @ A[:3, :3].T + A[:3, 3]
            total += float(np.linalg.norm(e @ proj.T, axis=1).max()) + r
            out[c, j] = total
    return out


# ----------------------------------------------------------------------------------------------
# The capsule file
# ----------------------------------------------------------------------------------------------


def save_capsules(path: str | Path, robot: Robot, fitted: Sequence[_Fitted], *,
                  padding_m: float, urdf: str | None = None,
                  package_dirs: Mapping[str, str] | None = None) -> None:
    """Write the capsule file atomically.

    ``urdf`` and ``package_dirs`` (written only when ``urdf`` is given) let ``larc certify
    --robot FILE`` rebuild the robot; relative paths there are relative to the file's folder.
    """
    held = {
        robot.joint_names[i]: float(robot.q_held[i])
        for i in range(1, robot.n_links)
        if robot.q_index[i] < 0 and robot.joint_type[i] != JointType.FIXED
    }
    finger_joints = [j for j in held if robot.joint_type[robot.joint_names.index(j)] == JointType.PRISMATIC]
    doc = {
        "urdf_sha256": robot.urdf_sha256,
        "padding_m": padding_m,
        "revision": MODEL_REVISION,
        "gripper_opening_m": float(sum(abs(held[j]) for j in finger_joints)) if finger_joints else None,
        "active_joints": list(robot.active_joint_names),
        "held_joints": held,
        "held_prismatic_stroke_enclosed": True,
        "capsules": [
            {
                "name": f.name,
                "link": f.link,
                "a": [round(float(x), 6) for x in f.a],
                "b": [round(float(x), 6) for x in f.b],
                "radius": round(f.radius, 6),
                "volume_m3": float(f"{f.volume_m3:.6g}"),
                "hull_volume_m3": float(f"{f.hull_volume_m3:.6g}"),
            }
            for f in fitted
        ],
    }
    if urdf is not None:
        extra = {"package_dirs": dict(package_dirs)} if package_dirs else {}
        doc = {"urdf": urdf, **extra, **doc}
    from .io import atomic_write_text

    header = (
        "# Capsules fitted by `larc fit-capsules`; containment of every collision-mesh vertex is\n"
        "# proven at load time by the tests. Link frames, metres; radius includes padding_m.\n"
    )
    atomic_write_text(path, header + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=120))


def _field(doc: Mapping, key: str, source: str, where: str = ""):
    if key not in doc:
        raise LarcInputError(f"{source}: missing field '{where}{key}'")
    return doc[key]


_MAX_CAPSULE_M = 1e6
"""Capsule coordinates and radii beyond this (m) are refused as implausible (squares overflow)."""


def _number(value, source: str, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise LarcInputError(f"{source}: {where} must be a number, got {short_repr(value)}")
    try:
        return float(value)
    except OverflowError:
        raise LarcInputError(f"{source}: {where} is too large ({short_repr(value)})") from None


def _vec3(value, source: str, where: str) -> np.ndarray:
    try:
        v = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise LarcInputError(f"{source}: {where} is not a list of 3 numbers, got {short_repr(value)}") from None
    if v.shape != (3,) or not np.isfinite(v).all():
        raise LarcInputError(f"{source}: {where} must be 3 finite numbers, got {short_repr(value)}")
    if np.abs(v).max() > _MAX_CAPSULE_M:
        raise LarcInputError(f"{source}: {where} = {short_repr(value)} is beyond {_MAX_CAPSULE_M:g} m of its link frame")
    return v


def load_capsules(path: str | Path, robot: Robot, *, check_hash: bool = True) -> CapsuleModel:
    """Read a capsule file for ``robot`` and compute its motion constants.

    Fails with :class:`LarcInputError` if the file was fitted to another URDF (hash mismatch),
    names unknown links, or holds malformed numbers.
    """
    path = Path(path)
    source = str(path)
    doc = parse_yaml(read_input_text(path, "capsule file"), source)
    if not isinstance(doc, dict):
        raise LarcInputError(f"{source}: expected a mapping with 'capsules'")
    if check_hash and _field(doc, "urdf_sha256", source) != robot.urdf_sha256:
        raise LarcInputError(
            f"{source}: fitted to a URDF with sha256 {short_repr(doc['urdf_sha256'])}, but {robot.urdf_path} "
            f"has sha256 {robot.urdf_sha256}; refit with `larc fit-capsules {robot.urdf_path} -o {source}`"
        )
    padding = _number(_field(doc, "padding_m", source), source, "padding_m")
    if not (np.isfinite(padding) and padding >= 0):
        raise LarcInputError(f"{source}: padding_m must be a finite number >= 0")
    active = doc.get("active_joints")
    if active is not None and (not isinstance(active, list) or active != list(robot.active_joint_names)):
        raise LarcInputError(
            f"{source}: active_joints {short_repr(active)} differ from the robot's {list(robot.active_joint_names)}"
        )
    held = doc.get("held_joints") or {}
    if not isinstance(held, dict):
        raise LarcInputError(f"{source}: held_joints must be a mapping JOINT: VALUE")
    if "held_joints" in doc:
        # The capsules of links on held joints are valid at the recorded values only: every
        # joint the robot holds must be recorded (and equal, below).
        for i in range(1, robot.n_links):
            jname = robot.joint_names[i]
            if robot.q_index[i] < 0 and robot.joint_type[i] != JointType.FIXED and jname not in held:
                raise LarcInputError(
                    f"{source}: held_joints does not record joint '{jname}', which the robot holds "
                    f"at {float(robot.q_held[i])}"
                )
    for jname, value in held.items():
        if jname not in robot.joint_names:
            raise LarcInputError(f"{source}: held_joints names unknown joint '{jname}'")
        i = robot.joint_names.index(jname)
        value = _number(value, source, f"held_joints.{jname}")
        if not abs(float(robot.q_held[i]) - value) <= 1e-12:
            raise LarcInputError(
                f"{source}: held_joints.{jname} = {value} but the robot holds it at {float(robot.q_held[i])}"
            )
    entries = _field(doc, "capsules", source)
    if not isinstance(entries, list) or not entries:
        raise LarcInputError(f"{source}: 'capsules' must be a non-empty list")
    names, links, idx, A, B, R = [], [], [], [], [], []
    for k, e in enumerate(entries):
        where = f"capsules[{k}]"
        if not isinstance(e, dict):
            raise LarcInputError(f"{source}: {where} must be a mapping")
        link = _field(e, "link", source, where + ".")
        if not isinstance(link, str):
            raise LarcInputError(f"{source}: {where}.link must be a link name, got {short_repr(link)}")
        if link not in robot.link_names:
            raise LarcInputError(f"{source}: {where}.link '{link}' is not a link of {robot.urdf_path}")
        r = _number(e.get("radius"), source, f"{where}.radius")
        if not np.isfinite(r) or r <= padding or r > _MAX_CAPSULE_M:
            raise LarcInputError(
                f"{source}: {where}.radius must be a finite number > padding_m and <= {_MAX_CAPSULE_M:g} m, got {r!r}")
        name = e.get("name", f"{link}_{k}")
        if not isinstance(name, (str, int)) or isinstance(name, bool):
            raise LarcInputError(f"{source}: {where}.name must be a string, got {short_repr(name)}")
        names.append(str(name))
        links.append(link)
        idx.append(robot.link_names.index(link))
        A.append(_vec3(_field(e, "a", source, where + "."), source, where + ".a"))
        B.append(_vec3(_field(e, "b", source, where + "."), source, where + ".b"))
        R.append(float(r))
    A, B, R = np.array(A), np.array(B), np.array(R)
    return CapsuleModel(
        p_link_a=A,
        p_link_b=B,
        radius=R,
        motion_a=motion_constants(robot, idx, A, B, R),
        names=tuple(names),
        link_names=tuple(links),
        link_index=tuple(idx),
        padding_m=padding,
    )
