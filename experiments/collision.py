"""Mesh collision model of the robot with python-fcl (the audit / MoveIt-style checker).

This is the *reference* checker of the experiments: it uses the official collision meshes of the
URDF (not the capsule enclosures that LARC certifies with), as MoveIt's FCL plugin does.

* Every ``<collision>`` element of every link becomes one ``fcl.CollisionObject`` (a BVH of the
  mesh triangles in the link frame, or an FCL primitive for box/cylinder/sphere), with the
  collision origin applied. The objects are built once per process (~0.5 s) and re-placed with
  ``setTransform`` from :func:`larc_jax.model.robot.forward_kinematics_np` for each state.
* Scene boxes are solid ``fcl.Box`` objects at their centres; meshes are surfaces. A mesh that
  touches or lies inside a box collides; a box entirely inside a (hollow) mesh does not — the
  same semantics as MoveIt/FCL.
* Self-collision is checked for every pair of links with geometry that is not an allowed pair
  (see :mod:`experiments.self_collision`).

Geometry comes from the library, so the audit and the capsule fit see the same shapes: scenes
are read by :func:`larc_jax.model.scene.read_scene` (YAML or MoveIt ``.scene``, base frame, metres) and
meshes by :func:`larc_jax.enclosure.meshes.link_collisions` (COLLADA units and URDF scale applied).
"""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

__all__ = [
    "CollisionModel",
    "SceneBoxes",
    "scene_boxes",
    "normalise_pairs",
    "geometry_files",
]


# ----------------------------------------------------------------------------------------------
# Scenes
# ----------------------------------------------------------------------------------------------


class SceneBoxes:
    """FCL objects of a scene's obstacles (built once, reused for every state): axis-aligned boxes
    (``lo``, ``hi``), then any posed shapes (:meth:`add_shapes`)."""

    def __init__(self, lo: np.ndarray, hi: np.ndarray, names: Sequence[str] | None = None):
        import fcl

        self.lo = np.asarray(lo, dtype=np.float64).reshape(-1, 3)
        self.hi = np.asarray(hi, dtype=np.float64).reshape(-1, 3)
        if self.lo.shape != self.hi.shape:
            raise ValueError("box lo/hi shapes differ")
        self.names = tuple(names) if names is not None else tuple(f"box{k}" for k in range(len(self.lo)))
        self.objects = []
        for a, b in zip(self.lo, self.hi):
            size = np.maximum(b - a, 0.0)
            self.objects.append(
                fcl.CollisionObject(fcl.Box(*size), fcl.Transform(np.eye(3), (a + b) / 2.0))
            )

    def __len__(self) -> int:
        return len(self.objects)

    def add_shapes(self, shapes) -> "SceneBoxes":
        """Add the posed shapes of a scene (:class:`larc_jax.model.shapes.Shapes`) as solid FCL
        primitives with their rotations (``fcl.Box``, ``Sphere``, ``Cylinder``, ``Cone``: FCL's
        geometry, independent of the certifier's bounds); their names follow the boxes'."""
        import fcl

        make = {"box": lambda d: fcl.Box(*d), "sphere": lambda d: fcl.Sphere(d[0]),
                "cylinder": lambda d: fcl.Cylinder(d[0], d[1]), "cone": lambda d: fcl.Cone(d[0], d[1])}
        for kind, d, p, R in zip(shapes.kinds, shapes.dims, shapes.p_world_shape, shapes.R_world_shape):
            self.objects.append(fcl.CollisionObject(make[kind](d), fcl.Transform(R, p)))
        self.names = self.names + tuple(shapes.names)
        return self

    @classmethod
    def from_scene(cls, scene) -> "SceneBoxes":
        """The obstacles of a :class:`larc_jax.model.scene.Scene`: its boxes, then its posed shapes.
        Meshes and point clouds are refused (the audit would otherwise miss them)."""
        if scene.point_sets.count:
            raise ValueError(f"{scene.source or scene.name}: the FCL audit does not read meshes or point clouds")
        return cls(scene.lo, scene.hi, scene.box_names or None).add_shapes(scene.shapes)

    @classmethod
    def from_file(cls, path: str | Path, frame: str = "base_link") -> "SceneBoxes":
        """The boxes of a scene file (:func:`larc_jax.model.scene.read_scene`: YAML or MoveIt
        ``.scene``; its frame must be ``frame``, the robot's root link)."""
        from larc_jax.model.scene import read_scene

        return cls.from_scene(read_scene(path, frame=frame))


def scene_boxes(boxes) -> SceneBoxes:
    """Coerce ``boxes`` (a :class:`SceneBoxes`, a scene path, or a ``(lo, hi)`` / ``(names, lo,
    hi)`` tuple) into a :class:`SceneBoxes`."""
    if isinstance(boxes, SceneBoxes):
        return boxes
    if boxes is None:
        return SceneBoxes(np.zeros((0, 3)), np.zeros((0, 3)))
    if isinstance(boxes, (str, Path)):
        return SceneBoxes.from_file(boxes)
    if isinstance(boxes, tuple) and len(boxes) == 3:
        return SceneBoxes(boxes[1], boxes[2], boxes[0])
    if isinstance(boxes, tuple) and len(boxes) == 2:
        return SceneBoxes(boxes[0], boxes[1])
    raise TypeError(f"cannot interpret {type(boxes).__name__} as scene boxes")


def normalise_pairs(pairs: Iterable) -> frozenset:
    """Allowed pairs as a frozenset of sorted name 2-tuples (accepts tuples, lists, frozensets,
    or ``{a:, b:}`` mappings)."""
    out = set()
    for p in pairs:
        if isinstance(p, dict):
            a, b = p["a"], p["b"]
        else:
            a, b = tuple(p)
        out.add(tuple(sorted((str(a), str(b)))))
    return frozenset(out)


# ----------------------------------------------------------------------------------------------
# Robot model
# ----------------------------------------------------------------------------------------------


def geometry_files(robot) -> list[Path]:
    """The URDF and every mesh file of the robot's collision geometry: the data an FCL model of
    ``robot`` is built from (for fingerprints)."""
    from larc_jax.enclosure.meshes import robot_urdf_model
    from larc_jax.model.urdf import resolve_uri

    model = robot_urdf_model(robot)
    urdf = Path(robot.urdf_path)
    files = {urdf}
    for link in robot.link_names:
        for col in model.link_map[link].collisions:
            if col.geometry is not None and col.geometry.mesh is not None:
                files.add(resolve_uri(col.geometry.mesh.filename, urdf, dict(robot.package_dirs)))
    return sorted(files)


def _fcl_geometry(robot, link: str, geometry, mesh):
    """An FCL geometry for one collision element (see
    :func:`larc_jax.enclosure.meshes.link_collisions`): a BVH of the mesh triangles, or the
    FCL primitive."""
    import fcl

    if mesh is not None:
        verts, faces = np.asarray(mesh[0], np.float64), np.asarray(mesh[1], np.int32)
        bvh = fcl.BVHModel()
        bvh.beginModel(len(verts), len(faces))
        bvh.addSubModel(verts, faces)
        bvh.endModel()
        return bvh
    if geometry.box is not None:
        return fcl.Box(*np.asarray(geometry.box.size, float))
    if geometry.cylinder is not None:
        return fcl.Cylinder(float(geometry.cylinder.radius), float(geometry.cylinder.length))
    if geometry.sphere is not None:
        return fcl.Sphere(float(geometry.sphere.radius))
    raise ValueError(f"{robot.urdf_path}: link '{link}' has an unsupported collision geometry")


class CollisionModel:
    """FCL collision model of a robot's official collision geometry.

    Build once per process (FCL objects cannot be pickled); every query re-places the same
    objects. Not thread-safe.
    """

    def __init__(self, robot=None):
        import fcl
        import trimesh

        from larc_jax.enclosure.meshes import link_collisions
        from larc_jax.model.urdf import load_robot

        self._fcl = fcl
        self.robot = robot if robot is not None else load_robot()
        self.link_names = tuple(self.robot.link_names)
        self.objects = []  # fcl.CollisionObject per collision element
        self.object_link = []  # link index of each object
        self.object_origin = []  # T_link_geometry of each object
        self.meshes = {}  # link name -> list of trimesh (link frame) for drawing / tests
        for li, link in enumerate(self.link_names):
            for origin, geometry, mesh in link_collisions(self.robot, link):
                geom = _fcl_geometry(self.robot, link, geometry, mesh)
                self.objects.append(fcl.CollisionObject(geom, fcl.Transform()))
                self.object_link.append(li)
                self.object_origin.append(origin)
                if mesh is not None:
                    tm = trimesh.Trimesh(np.asarray(mesh[0]), np.asarray(mesh[1]), process=False)
                    self.meshes.setdefault(link, []).append(tm.apply_transform(origin))
        self.object_link = np.asarray(self.object_link, dtype=int)
        self.object_origin = np.asarray(self.object_origin, dtype=np.float64).reshape(-1, 4, 4)
        self.links_with_geometry = tuple(
            sorted({self.link_names[i] for i in self.object_link}, key=self.link_names.index)
        )
        self._request = fcl.CollisionRequest()
        self._self_pairs_cache: dict[frozenset, list[tuple[int, int]]] = {}
        self._last_allowed: tuple = (object(), [])
        self._q = None

    # -- placement ------------------------------------------------------------------------------

    def set_configuration(self, q) -> np.ndarray:
        """Place every collision object at configuration ``q`` (n,); returns the link poses."""
        fcl = self._fcl
        q = np.asarray(q, dtype=np.float64)
        from larc_jax.model.robot import forward_kinematics_np

        T_link = forward_kinematics_np(self.robot, q)
        T = T_link[self.object_link] @ self.object_origin
        for obj, Tk in zip(self.objects, T):
            obj.setTransform(fcl.Transform(Tk[:3, :3], Tk[:3, 3]))
        self._q = q
        return T_link

    def _collide(self, o1, o2) -> bool:
        res = self._fcl.CollisionResult()
        return self._fcl.collide(o1, o2, self._request, res) > 0

    # -- queries at the configuration last set --------------------------------------------------

    def scene_hits(self, boxes: SceneBoxes, first_only: bool = True) -> list[tuple[str, str]]:
        """(link, box) pairs in contact at the configuration last set (the first one only, by
        default)."""
        hits = []
        for k, obj in enumerate(self.objects):
            for b, box in enumerate(boxes.objects):
                if self._collide(obj, box):
                    hits.append((self.link_names[self.object_link[k]], boxes.names[b]))
                    if first_only:
                        return hits
        return hits

    def _pairs_to_check(self, allowed_pairs) -> list[tuple[int, int]]:
        if allowed_pairs is self._last_allowed[0]:
            return self._last_allowed[1]
        key = normalise_pairs(allowed_pairs or ())
        pairs = self._self_pairs_cache.get(key)
        if pairs is None:
            pairs = []
            for i, j in itertools.combinations(range(len(self.objects)), 2):
                a, b = self.link_names[self.object_link[i]], self.link_names[self.object_link[j]]
                if a == b or tuple(sorted((a, b))) in key:
                    continue
                pairs.append((i, j))
            self._self_pairs_cache[key] = pairs
        if isinstance(allowed_pairs, (frozenset, tuple)):  # immutable: safe to memoise by identity
            self._last_allowed = (allowed_pairs, pairs)
        return pairs

    def self_hits(self, allowed_pairs, first_only: bool = True) -> list[tuple[str, str]]:
        """Link pairs not in ``allowed_pairs`` in contact at the configuration last set (the
        first one only, by default)."""
        hits = []
        for i, j in self._pairs_to_check(allowed_pairs):
            if self._collide(self.objects[i], self.objects[j]):
                hits.append((self.link_names[self.object_link[i]], self.link_names[self.object_link[j]]))
                if first_only:
                    return hits
        return hits

    # -- public API ---------------------------------------------------------------------------

    def scene_collision(self, q, boxes) -> bool:
        """True if any link's collision geometry intersects any scene box at ``q``."""
        boxes = scene_boxes(boxes)
        if len(boxes) == 0:
            return False
        self.set_configuration(q)
        return bool(self.scene_hits(boxes))

    def scene_contacts(self, q, boxes) -> list[tuple[str, str]]:
        """All (link, box) pairs in contact at ``q``."""
        boxes = scene_boxes(boxes)
        self.set_configuration(q)
        return self.scene_hits(boxes, first_only=False)

    def self_collision(self, q, allowed_pairs=()) -> bool:
        """True if any pair of links not in ``allowed_pairs`` intersects at ``q``."""
        self.set_configuration(q)
        return bool(self.self_hits(allowed_pairs))

    def self_contacts(self, q, allowed_pairs=()) -> list[tuple[str, str]]:
        """All link pairs (not allowed) in contact at ``q``."""
        self.set_configuration(q)
        return self.self_hits(allowed_pairs, first_only=False)

    def link_pair_contacts(self, q, pairs: Sequence[tuple[int, int]]) -> np.ndarray:
        """(len(pairs),) bool: contact of each (link index, link index) pair at ``q``."""
        self.set_configuration(q)
        by_link: dict[int, list[int]] = {}
        for k, li in enumerate(self.object_link):
            by_link.setdefault(int(li), []).append(k)
        out = np.zeros(len(pairs), dtype=bool)
        for p, (a, b) in enumerate(pairs):
            out[p] = any(
                self._collide(self.objects[i], self.objects[j])
                for i in by_link.get(a, ()) for j in by_link.get(b, ())
            )
        return out

    def state_valid(self, q, boxes, allowed_pairs=()) -> bool:
        """No scene collision and no disallowed self-collision at ``q`` (MoveIt's validity)."""
        boxes = scene_boxes(boxes)
        self.set_configuration(q)
        if len(boxes) and self.scene_hits(boxes):
            return False
        return not self.self_hits(allowed_pairs)

    def min_distance(self, q, boxes) -> float:
        """Smallest FCL distance between any link geometry and any box at ``q`` (m; <= 0 in
        contact; +inf without boxes)."""
        fcl = self._fcl
        boxes = scene_boxes(boxes)
        self.set_configuration(q)
        best = np.inf
        req = fcl.DistanceRequest()
        for obj in self.objects:
            for box in boxes.objects:
                res = fcl.DistanceResult()
                d = fcl.distance(obj, box, req, res)
                best = min(best, float(d))
        return best

    def states_in_collision(self, Q, boxes, allowed_pairs=None) -> np.ndarray:
        """(N,) bool: scene collision of each row of ``Q`` (N, n); with ``allowed_pairs`` given
        (not None), disallowed self-collision counts too."""
        boxes = scene_boxes(boxes)
        Q = np.asarray(Q, dtype=np.float64).reshape(-1, self.robot.n_joints)
        out = np.zeros(len(Q), dtype=bool)
        for k, q in enumerate(Q):
            self.set_configuration(q)
            hit = bool(len(boxes)) and bool(self.scene_hits(boxes))
            if not hit and allowed_pairs is not None:
                hit = bool(self.self_hits(allowed_pairs))
            out[k] = hit
        return out

    def scene_and_self(self, Q, boxes, allowed_pairs=()) -> tuple[np.ndarray, np.ndarray]:
        """Per state of ``Q`` (N, n): (scene collision (N,), disallowed self-collision (N,))."""
        boxes = scene_boxes(boxes)
        Q = np.asarray(Q, dtype=np.float64).reshape(-1, self.robot.n_joints)
        scene = np.zeros(len(Q), dtype=bool)
        selfc = np.zeros(len(Q), dtype=bool)
        for k, q in enumerate(Q):
            self.set_configuration(q)
            scene[k] = bool(len(boxes)) and bool(self.scene_hits(boxes))
            selfc[k] = bool(self.self_hits(allowed_pairs))
        return scene, selfc

    def world_meshes(self, q) -> dict:
        """Link name → trimesh of its collision mesh(es) in the base frame at ``q`` (drawing)."""
        import trimesh

        from larc_jax.model.robot import forward_kinematics_np

        T = forward_kinematics_np(self.robot, np.asarray(q, dtype=np.float64))
        out = {}
        for link, meshes in self.meshes.items():
            m = trimesh.util.concatenate([mm.copy() for mm in meshes])
            out[link] = m.apply_transform(T[self.link_names.index(link)])
        return out
