"""The true clearance of a trajectory: the smallest python-fcl distance between the official link
meshes and the obstacles over its Hermite reconstruction (the truth of :mod:`experiments.tightness`
and :mod:`experiments.tightness_kinds`).

The trajectory is replayed as a controller does (``scipy`` ``CubicHermiteSpline``) with the
fingers closed (joint7 = joint8 = 0, the stated opening): a 1 kHz grid, then a bounded scalar
minimisation around every grid minimum within 1 mm of the best (1e-7 s tolerance).

Obstacles come as *groups* (:class:`TruthObstacles`): each a box that holds it, axis-aligned in
the group's own frame, and the FCL objects it is made of (a solid box, sphere, cylinder; the
triangles of a mesh, a surface as in MoveIt/FCL; a ball per cloud point). A group's distance is
the least over its objects.

Pruning never changes the minimum: a (state, link, group) is measured with FCL only when its
lower bound, the distance from the link's capsules to the group's box (the capsules are proven to
contain the meshes and the box contains the group), is below the best distance known. That starts
from an upper bound, the distance of the links' hull vertices (points of the meshes) at 100 Hz to
the groups that *are* their box (solid boxes), or +inf, and only decreases.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

__all__ = ["HOLD", "TRUTH_HZ", "COARSE_HZ", "TruthObstacles", "MeshTruth", "mesh_truth"]

HOLD = {"joint7": 0.0, "joint8": 0.0}
"""The gripper opening the truth is measured at (fingers closed)."""
TRUTH_HZ = 1000.0
COARSE_HZ = 100.0


@dataclasses.dataclass(frozen=True)
class TruthObstacles:
    """Obstacle groups for :func:`mesh_truth` (module docstring)."""

    names: tuple[str, ...]
    lo: np.ndarray
    """(G, 3) minimum corner of each group's box in the group's frame, m."""
    hi: np.ndarray
    objects: tuple[tuple, ...]
    """Per group, its ``fcl.CollisionObject`` s (placed in the world)."""
    is_box: np.ndarray
    """(G,) bool: the group is exactly its box (a solid ``fcl.Box``)."""
    R_world_group: np.ndarray | None = None
    """(G, 3, 3) rotation of each group's frame; None: every frame is the world's."""
    p_world_group: np.ndarray | None = None
    """(G, 3) origin of each group's frame, m."""

    def __post_init__(self):
        g = len(self.names)
        if not (self.lo.shape == self.hi.shape == (g, 3) and len(self.objects) == g == len(self.is_box)):
            raise ValueError(f"TruthObstacles: {g} names, lo {self.lo.shape}, hi {self.hi.shape}, "
                             f"{len(self.objects)} object lists, {len(self.is_box)} is_box flags")
        if not all(len(o) for o in self.objects):
            raise ValueError("TruthObstacles: every group needs at least one FCL object")
        if (self.R_world_group is None) != (self.p_world_group is None):
            raise ValueError("TruthObstacles: give both R_world_group and p_world_group, or neither")

    def framed(self) -> np.ndarray:
        """(G,) bool: the groups whose frame is not the world's."""
        if self.R_world_group is None:
            return np.zeros(len(self.names), bool)
        return ~(np.all(self.R_world_group == np.eye(3), axis=(1, 2)) & np.all(self.p_world_group == 0, axis=1))

    def to_group(self, g: int, x: np.ndarray) -> np.ndarray:
        """World points ``x`` (..., 3) in group ``g``'s frame."""
        return (x - self.p_world_group[g]) @ self.R_world_group[g]

    @classmethod
    def from_boxes(cls, boxes) -> "TruthObstacles":
        """Axis-aligned boxes of an :class:`experiments.collision.SceneBoxes` (no posed shapes)."""
        if len(boxes.objects) != len(boxes.lo):
            raise ValueError("TruthObstacles.from_boxes: the scene has posed shapes; build its groups instead")
        return cls(tuple(boxes.names), boxes.lo, boxes.hi, tuple((o,) for o in boxes.objects),
                   np.ones(len(boxes.lo), bool))


class MeshTruth:
    """python-fcl distances of the official meshes, pruned by proven bounds (module docstring)."""

    CHUNK = 2048

    def __init__(self):
        import fcl

        from experiments.collision import CollisionModel
        from larc_jax.enclosure import default_capsule_path, load_capsules
        from larc_jax.enclosure.hull import build_parts
        from larc_jax.model.urdf import load_robot

        self.fcl = fcl
        self.robot = load_robot(held_joint_values=HOLD, stated_joints=list(HOLD))  # fingers closed
        self.capsules = load_capsules(default_capsule_path(), self.robot)
        self.model = CollisionModel(self.robot)
        links = list(dict.fromkeys(self.capsules.link_names))
        self.links = links
        self.obj_link = np.array([links.index(self.robot.link_names[i]) for i in self.model.object_link])
        self.cap_link = np.array([links.index(l) for l in self.capsules.link_names])
        # Mesh vertices on each link's hull: points of the mesh, so their distance to a box is an
        # upper bound of the mesh's (the hull vertices are a subset of the mesh vertices).
        parts = build_parts(self.robot)
        self.vertices = {links.index(p.link): p.vertices for p in parts}
        self.request = fcl.DistanceRequest()

    def _padded(self, Q):
        for start in range(0, len(Q), self.CHUNK):
            chunk = Q[start:start + self.CHUNK]
            yield len(chunk), np.concatenate([chunk, np.repeat(chunk[-1:], self.CHUNK - len(chunk), 0)])

    def capsule_lower_bounds(self, Q: np.ndarray, obstacles: TruthObstacles) -> np.ndarray:
        """(N, L, G) capsule distance of each link to each group's box at each state (<= mesh
        distance: the capsules are proven to contain the meshes)."""
        import jax

        from larc_jax.enclosure import capsule_segments
        from larc_jax.obstacles.geometry import segment_box_distances

        lo, hi, framed = obstacles.lo, obstacles.hi, obstacles.framed()
        out = []
        with jax.enable_x64(True):
            seg = jax.jit(jax.vmap(capsule_segments, in_axes=(None, None, 0)))
            for n, chunk in self._padded(Q):
                a, b = seg(self.robot, self.capsules, chunk)
                d = np.array(segment_box_distances(a, b, lo[None], hi[None]))[:n]
                for g in np.flatnonzero(framed):  # the segments in the group's frame
                    a_g, b_g = obstacles.to_group(g, np.asarray(a)), obstacles.to_group(g, np.asarray(b))
                    d[:, :, g] = np.asarray(segment_box_distances(a_g, b_g, lo[None, g:g + 1], hi[None, g:g + 1]))[:n, :, 0]
                out.append(d - np.asarray(self.capsules.radius)[None, :, None])
        d = np.concatenate(out)
        lb = np.full((len(Q), len(self.links), len(lo)), np.inf)
        for c, l in enumerate(self.cap_link):
            lb[:, l] = np.minimum(lb[:, l], d[:, c])
        return lb

    def vertex_upper_bound(self, Q: np.ndarray, obstacles: TruthObstacles) -> float:
        """Smallest distance of any hull vertex (a mesh point) to any group that is its box, over
        the states ``Q`` (+inf if none is)."""
        from larc_jax.model.robot import forward_kinematics_np

        best = math.inf
        is_box = np.asarray(obstacles.is_box, bool)
        framed = obstacles.framed()
        plain = is_box & ~framed
        lo, hi = obstacles.lo[plain], obstacles.hi[plain]
        for q in Q if is_box.any() else ():
            T = forward_kinematics_np(self.robot, q)
            for l, V in self.vertices.items():
                Tl = T[self.robot.link_index(self.links[l])]
                W = V @ Tl[:3, :3].T + Tl[:3, 3]
                for g in [None] + list(np.flatnonzero(is_box & framed)):
                    if g is None:
                        W_g, lo_g, hi_g = W, lo, hi
                    else:
                        W_g, lo_g, hi_g = obstacles.to_group(g, W), obstacles.lo[g:g + 1], obstacles.hi[g:g + 1]
                    if not len(lo_g):
                        continue
                    gap = np.maximum(np.maximum(lo_g[None] - W_g[:, None], W_g[:, None] - hi_g[None]), 0.0)
                    best = min(best, float(np.sqrt((gap * gap).sum(axis=2)).min()))
        return best

    def distance(self, q, obstacles: TruthObstacles, mask: np.ndarray | None = None) -> tuple[np.ndarray, int]:
        """(L, G) smallest mesh-obstacle distance per link and group at ``q`` (inf where ``mask``
        is False), and the number of FCL queries."""
        fcl = self.fcl
        self.model.set_configuration(q)
        out = np.full((len(self.links), len(obstacles.names)), np.inf)
        n = 0
        for k, obj in enumerate(self.model.objects):
            l = self.obj_link[k]
            for g, members in enumerate(obstacles.objects):
                if mask is not None and not mask[l, g]:
                    continue
                for other in members:
                    out[l, g] = min(out[l, g], float(fcl.distance(obj, other, self.request, fcl.DistanceResult())))
                n += len(members)
        return out, n


def mesh_truth(truth: MeshTruth, traj, obstacles: TruthObstacles) -> dict:
    """The smallest mesh-obstacle distance over the trajectory (module docstring).

    Pruning is exact: a (state, link, group) is measured with FCL only when its capsule lower
    bound is below the best distance known, which starts from an upper bound (mesh vertices at
    100 Hz, to the groups that are boxes) and only decreases."""
    from scipy.interpolate import CubicHermiteSpline
    from scipy.optimize import minimize_scalar

    spline = CubicHermiteSpline(traj.t, traj.q, traj.qd, axis=0)
    t = traj.t[0] + np.arange(int(math.floor(traj.duration * TRUTH_HZ)) + 1) / TRUTH_HZ
    t = np.union1d(t[t <= traj.t[-1]], [traj.t[-1]])
    Q = spline(t)
    lb = truth.capsule_lower_bounds(Q, obstacles)  # (N, L, G)
    step = max(1, int(round(TRUTH_HZ / COARSE_HZ)))
    best = truth.vertex_upper_bound(Q[::step], obstacles)
    queries = 0
    dist = np.full(lb.shape, np.inf)
    for i in np.argsort(lb.min(axis=(1, 2)), kind="stable"):
        if not lb[i].min() < best:
            break
        d, n = truth.distance(Q[i], obstacles, lb[i] < best)
        queries += n
        dist[i] = d
        best = min(best, float(d.min()))
    per_state = dist.min(axis=(1, 2))
    i_best = int(np.argmin(per_state))
    t_best, arg = float(t[i_best]), np.unravel_index(int(np.argmin(dist[i_best])), dist[i_best].shape)
    # Refine each (link, group) pair around its grid minima within 1 mm of the best.
    for l, b in zip(*np.nonzero(dist.min(axis=0) <= best + 1e-3)):
        d = dist[:, l, b]
        mask = np.zeros(dist.shape[1:], bool)
        mask[l, b] = True
        cands = [i for i in range(len(t)) if d[i] <= best + 1e-3 and (i == 0 or not d[i - 1] < d[i])
                 and (i == len(t) - 1 or not d[i + 1] < d[i])]
        for i in cands[:10]:
            lo_t, hi_t = t[max(i - 1, 0)], t[min(i + 1, len(t) - 1)]
            if not hi_t > lo_t:
                continue
            res = minimize_scalar(lambda x: truth.distance(spline(x), obstacles, mask)[0][l, b], bounds=(lo_t, hi_t),
                                  method="bounded", options=dict(xatol=1e-7))
            queries += int(res.nfev)
            if res.fun < best:
                best, t_best, arg = float(res.fun), float(res.x), (l, b)
    return dict(truth_m=best, truth_t=t_best, truth_link=truth.links[arg[0]], truth_box=obstacles.names[arg[1]],
                fcl_queries=queries)
