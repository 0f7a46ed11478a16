"""The whole leaf test in NumPy float64: what the reference scheduler and ``larc verify`` run.

A certificate's leaf passes when every test the run asked for passes on it:

1. the capsule test (:func:`~larc_jax.leaf.interval.evaluate_interval_np`, paper eqs. 4-7);
2. with ``enclosure="hull"``, where the capsules fail a box, the convex-hull test of the link
   parts (:func:`~larc_jax.leaf.cascade.cascade_np`) — tried only where the self test passes, as the
   batched schedulers do;
2'. with ``swept``, where the leaf is still open (and the self test passes), the swept test
   (:func:`~larc_jax.leaf.swept.swept_stage_np`);
3. with the self-collision test, every checked capsule pair
   (:func:`~larc_jax.leaf.self_collision.self_clearance_np`);

all with the enclosures grown by the tracking tolerance (:func:`~larc_jax.enclosure.tracking.tracked_capsules`,
hull parts alike). The leaf is placed once (:func:`~larc_jax.leaf.placement.place_np`) and its stages
composed by :func:`~larc_jax.leaf.record.compose`, the rule the batched schedulers use: the leaf records
the ``(g, guard)`` of the worst test; it passed iff ``g > guard``.

:func:`leaf_enclosures` builds the enclosures a run uses from its parameters, so that
:func:`~larc_jax.engine.certify.certify` and the checker (:mod:`larc_jax.products.verify`) build the same ones.
Nothing here imports JAX (the modules it calls reach it through :mod:`larc_jax.lazy_jax`).
"""

from __future__ import annotations

import dataclasses

from .cascade import Links, cascade_np
from ..enclosure.capsule import CapsuleModel
from ..enclosure.hull import HullModel, hull_model
from .interval import evaluate_placed_np, rebase_ends
from .record import LeafRecord, Stage, box_record, compose, needs_hull
from ..obstacles import scene_obstacles
from .placement import place_np
from ..model.robot import Robot
from .self_collision import SelfPairs, self_stage_np
from .swept import SweptTables, swept_links, swept_stage_np, swept_tables
from ..enclosure.tracking import tracked_capsules

__all__ = ["LeafEnclosures", "leaf_enclosures", "leaf_test_np"]


@dataclasses.dataclass(frozen=True)
class LeafEnclosures:
    """The enclosures one run tests with."""

    capsules: CapsuleModel
    """The capsules, radii grown by the tracking tolerance."""
    hulls: HullModel | None
    """The hull parts of the cascade (grown alike), or None for the capsule test alone."""
    links: Links | None
    """Which link each capsule and part belongs to (with ``hulls``)."""
    swept: SweptTables | None = None
    """The swept stage's chain tables (:mod:`larc_jax.leaf.swept`), or None: no swept stage."""


def leaf_enclosures(robot: Robot, capsules: CapsuleModel, enclosure: str, delta=None,
                    hulls: HullModel | None = None, swept: bool = False) -> LeafEnclosures:
    """The enclosures of a run: ``capsules`` as given to certify (planned), ``enclosure``
    ``"capsules"`` or ``"hull"``, ``delta`` the tracking tolerance per active joint (or None),
    ``hulls`` the hull parts if given (else built from the robot file's ``hull_parts``),
    ``swept`` whether the swept stage runs (``RunSpec.swept``)."""
    if enclosure == "hull":
        hulls = hulls if hulls is not None else hull_model(robot, capsules.hull_parts, capsules.padding_m)
        hulls = hulls.on_links(capsules.link_names)  # links a capsule model excludes are excluded here too
        links = Links.of(capsules, hulls)  # the same links, or a clear error
        hulls = tracked_capsules(hulls, delta)  # the parts' radii grow as the capsules' do
    else:
        hulls, links = None, None
    capsules = tracked_capsules(capsules, delta)
    tables = swept_tables(robot, capsules, hulls) if swept else None
    return LeafEnclosures(capsules=capsules, hulls=hulls, links=links, swept=tables)


def leaf_test_np(robot: Robot, enc: LeafEnclosures, traj, obstacles, t0: float, t1: float, margin: float, bounds,
                 pairs: SelfPairs | None = None, skip=None) -> LeafRecord:
    """The :class:`~larc_jax.leaf.record.LeafRecord` of the leaf ``[t0, t1]`` (the trajectory's own time
    axis) against ``obstacles`` (an obstacle set, or a Scene: :func:`~larc_jax.obstacles.scene_obstacles`):
    placed once, its stages composed by :func:`~larc_jax.leaf.record.compose` (as the batched
    schedulers do); ``pairs``, ``skip``: the self test's pairs and the ones proven apart."""
    capsules = enc.capsules
    obstacles = scene_obstacles(obstacles)
    a, b = (float(x) for x in rebase_ends(t0, t1, float(bounds.offset_s)))
    placed = place_np(robot, capsules, traj, a, b, bounds)
    ev = evaluate_placed_np(placed, capsules, obstacles, margin, bounds)
    record = box_record(ev.g, ev.guard, ev.capsule, ev.box, Stage.CAPSULE)
    self_test = None if pairs is None else self_stage_np(placed, capsules.radius, bounds, pairs, skip)
    if enc.links is not None and needs_hull(record, self_test):
        g, guard, cap, box, _ = cascade_np(robot, capsules, enc.hulls, enc.links, traj, obstacles, t0, t1, margin,
                                           bounds, ev)
        record = box_record(g, guard, cap, box, Stage.HULL)
    if enc.swept is not None and needs_hull(record, self_test):
        g, guard, cap, box = swept_stage_np(robot, capsules, enc.hulls, enc.swept, swept_links(capsules, enc.links),
                                            traj, obstacles, t0, t1, margin, bounds)
        record = box_record(g, guard, cap, box, Stage.SWEPT)
    return compose(record, self_test)
