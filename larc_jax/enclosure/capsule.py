"""The capsule model of a robot's links, and its placement at a configuration.

A capsule is the set of points within ``radius`` of a segment ``[p_link_a, p_link_b]`` given in
its link's frame: convex, and placed by one rigid transform (the link pose from forward
kinematics). :func:`capsule_segments` is the JAX kernel for one configuration (batch it with
``jax.vmap``); :func:`capsule_segments_np` its NumPy float64 reference. Why the capsules enclose
the link meshes is proven in :mod:`larc_jax.enclosure.fit`; the motion constants ``motion_a``
are derived in :mod:`larc_jax.enclosure.motion`.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Iterable

import numpy as np

from ..errors import LarcInputError
from ..lazy_jax import jax, jnp, pytree_dataclass
from ..model.kinematics import link_poses
from ..model.robot import Robot, forward_kinematics_np

__all__ = ["CapsuleModel", "capsule_segments", "capsule_segments_np"]


@pytree_dataclass
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
    excluded_links: tuple[str, ...] = dataclasses.field(default=(), metadata=dict(static=True))
    """Links whose capsules were removed (:meth:`without_links`): the certificate says nothing
    about them, and every result made with this model names them."""
    hull_parts: tuple[tuple[str, tuple[float, float, float], float], ...] = dataclasses.field(
        default=(), metadata=dict(static=True))
    """How the robot file splits links into hull parts for the cascade: ``(link, normal,
    offset)`` planes in the link frame (:mod:`larc_jax.enclosure.hull`); other links are one part."""

    @property
    def n_capsules(self) -> int:
        return len(self.names)

    def with_padding(self, padding_m: float) -> "CapsuleModel":
        """This model with ``padding_m`` instead of its own padding on every capsule.

        Each radius is its proven core ``radius - self.padding_m`` plus ``padding_m``, rounded up
        until ``radius' - padding_m`` is at least that core in exact rational arithmetic, and at
        least the core as float64 computed it for the robot file's proof. So the containment proof
        (:mod:`larc_jax.enclosure.proof`), which checks the core ``radius - padding_m``, holds for it
        as for the original. The same padding returns this model, unchanged (bit for bit).

        The motion constants ``motion_a`` stay this model's. The interval test needs them to bound
        the speed of every *mesh* point (:mod:`larc_jax.enclosure.motion`); a mesh point lies in
        the core, within ``radius - self.padding_m`` of the segment, for which this model's
        constants (derived for the larger ``radius``) are already sound. So a mesh point ``x(t)``
        of the interval lies within ``b`` of the core placed at the midpoint, and a test passed
        with the padded radius ``r' = core + padding_m`` gives ``dist(x(t), box) > rho +
        padding_m``: every link mesh grown by ``padding_m`` clears rho, for any ``padding_m``."""
        from ..defaults import check_padding

        padding_m = check_padding(padding_m)
        if padding_m == self.padding_m:
            return self
        radius = np.asarray(self.radius, dtype=np.float64)
        out = np.frombuffer(_padded_radii(radius.tobytes(), float(self.padding_m), padding_m), np.float64).copy()
        if not np.isfinite(out).all():
            raise LarcInputError(f"padding_m {padding_m!r}: gives capsule radii that are not finite")
        return dataclasses.replace(self, radius=out, padding_m=padding_m)

    def without_links(self, robot: Robot, links: Iterable[str], what: str = "ignore_links") -> "CapsuleModel":
        """This model without the capsules of ``links``, recorded in :attr:`excluded_links`.

        For a link that never moves and may touch the scene by design, e.g. a fixed base standing
        on its table (MoveIt's allowed collision matrix does the same for scene objects). Only a
        link with no active joint between it and the root may be excluded: a moving link is
        refused, as are unknown links, links without a capsule, and removing every capsule
        (:class:`LarcInputError` naming ``what``)."""
        links = list(dict.fromkeys(str(x) for x in links))
        for name in links:
            if name not in robot.link_names:
                raise LarcInputError(f"{what} {name}: not a link of {robot.urdf_path} ({', '.join(robot.link_names)})")
            i = robot.link_index(name)
            k = i
            while k > 0:  # the joints between the root and the link
                if robot.q_index[k] >= 0:
                    raise LarcInputError(
                        f"{what} {name}: the link moves (active joint '{robot.joint_names[k]}' is between it and "
                        f"the root); only links that never move can be left out of a certificate")
                k = robot.parent[k]
            if name not in self.link_names:
                raise LarcInputError(f"{what} {name}: the link has no capsule in this model")
        keep = [c for c, name in enumerate(self.link_names) if name not in links]
        if not keep:
            raise LarcInputError(f"{what}: excluding {', '.join(links)} leaves no capsule to certify")
        if not links:
            return self
        sel = np.asarray(keep)
        return dataclasses.replace(
            self,
            p_link_a=np.asarray(self.p_link_a)[sel], p_link_b=np.asarray(self.p_link_b)[sel],
            radius=np.asarray(self.radius)[sel], motion_a=np.asarray(self.motion_a)[sel],
            names=tuple(self.names[c] for c in keep), link_names=tuple(self.link_names[c] for c in keep),
            link_index=tuple(self.link_index[c] for c in keep),
            excluded_links=tuple(dict.fromkeys(self.excluded_links + tuple(links))),
        )


def capsule_segments(robot: Robot, capsules: CapsuleModel, q: jax.Array):
    """World-frame capsule segments at one configuration.

    Args:
      q: (n,) active joint values.

    Returns:
      (p_world_a, p_world_b), each (C, 3) in metres.
    """
    T = link_poses(robot, q)[jnp.asarray(capsules.link_index)]  # (C, 3, 4)
    R, t = T[:, :3, :3], T[:, :3, 3]
    # Full precision: float32 products on GPUs default to TF32 (see larc_jax.leaf.interval, G1).
    full = jax.lax.Precision.HIGHEST
    a = jnp.einsum("cij,cj->ci", R, capsules.p_link_a.astype(R.dtype), precision=full) + t
    b = jnp.einsum("cij,cj->ci", R, capsules.p_link_b.astype(R.dtype), precision=full) + t
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


@functools.lru_cache(maxsize=64)
def _padded_radii(radius_bytes: bytes, old_padding_m: float, padding_m: float) -> bytes:
    """:meth:`CapsuleModel.with_padding`'s radii (float64 bytes) for the radii ``radius_bytes``
    padded by ``old_padding_m``, re-padded by ``padding_m``: the core ``radius - old_padding_m``
    plus ``padding_m``, each rounded up until ``radius' - padding_m`` is at least that core in
    exact rational arithmetic and at least the core as float64 computed it. A pure function of its
    arguments, kept per process: certifying one trajectory per call would otherwise redo the
    rational arithmetic every call (a few tenths of a millisecond)."""
    from fractions import Fraction

    radius = np.frombuffer(radius_bytes, np.float64)
    out = (radius - old_padding_m) + padding_m
    for c, r in enumerate(radius):
        core = max(Fraction(float(r)) - Fraction(old_padding_m), Fraction(float(r - old_padding_m)))
        while Fraction(float(out[c])) - Fraction(padding_m) < core:
            out[c] = np.nextafter(out[c], np.inf)
    return out.tobytes()
