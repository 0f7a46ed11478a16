"""One leaf test: its stages, their record, and the one rule that composes them.

A leaf (an interval of the certificate tree) is placed once (:mod:`larc_jax.leaf.placement`) and
then put through the stages the run asked for, each a one-item kernel with a NumPy float64 twin:

- :attr:`Stage.CAPSULE`: the capsule-box test (:func:`~larc_jax.leaf.interval.evaluate_placed`);
- :attr:`Stage.HULL`: where the capsules fail a box (and the self test passes), the convex-hull
  test of the link parts (:mod:`larc_jax.leaf.cascade`);
- :attr:`Stage.SWEPT`: where the leaf is still open (and the self test passes), the swept test
  (:mod:`larc_jax.leaf.swept`): every enclosure's midpoint and swept clearances, the better of
  the two per pair (run with ``RunSpec.swept``);
- :attr:`Stage.SELF`: the self-collision test of the checked capsule pairs
  (:func:`~larc_jax.leaf.self_collision.self_stage`), which can only veto a leaf.

Each stage returns a :class:`LeafRecord` (scalars for one leaf, or arrays for many);
:func:`needs_hull` says where the hull stage runs and :func:`compose` keeps the worse record.
The JAX schedulers (:mod:`larc_jax.engine.batch`) and the NumPy reference scheduler and checker
(:mod:`larc_jax.leaf.reference`, :mod:`larc_jax.products.verify`) compose with these same functions
(``xp``: NumPy, or ``jax.numpy``). This module imports neither JAX nor the rest of the library.
"""

from __future__ import annotations

import enum
from typing import Any, NamedTuple, Sequence

import numpy as np

__all__ = ["Stage", "LeafColumn", "LeafRecord", "box_record", "self_record", "passes", "needs_hull", "compose",
           "CULL_SLACK_M"]

CULL_SLACK_M = 0.02
"""A culled scene's cluster is dropped from a node where its ``g - guard`` exceeds this, m; a leaf
records the all-pairs clearance wherever that one's ``g - guard`` is at most this, and above it
may record a lower bound (:mod:`larc_jax.engine.cull`; ``larc verify`` checks stored clearances
both ways below half of it, :mod:`larc_jax.products.verify`)."""


class Stage(enum.IntEnum):
    """A stage of the leaf test. A leaf's recorded stage (the ``stage`` column) is the one that
    passed it: NONE (not certified), CAPSULE, HULL or SWEPT; SELF only vetoes, so it is never
    recorded (a record decided by the self test is told by ``other >= 0``)."""

    NONE = 0
    CAPSULE = 1
    HULL = 2
    SELF = 3
    SWEPT = 4

    @property
    def label(self) -> str:
        """The name written in results and certificates (``""`` for NONE)."""
        return "" if self is Stage.NONE else self.name.lower()


class LeafColumn(str, enum.Enum):
    """Columns of a leaf in tables (:meth:`~larc_jax.engine.results.DatasetResult.leaves_dataframe`,
    ``larc certify --leaves``)."""

    ID = "id"
    DEPTH = "depth"
    INDEX = "index"
    T0 = "t0"
    T1 = "t1"
    CLEARANCE_M = "clearance_m"
    GUARD_M = "guard_m"
    CERTIFIED = "certified"
    CAPSULE = "capsule"
    BOX = "box"
    OTHER_CAPSULE = "other_capsule"
    STAGE = "stage"


class LeafRecord(NamedTuple):
    """What a stage (or the composed leaf test) found on one leaf, or on many (arrays); a pytree."""

    clearance_m: Any
    """Certificate clearance g of the recorded pair, m (+inf: nothing to hit; NaN: non-finite
    geometry, never certifies)."""
    guard_m: Any
    """Rounding guard of the recorded pair, m: the stage passed iff ``clearance_m > guard_m``."""
    capsule: Any
    """The recorded pair's capsule (the first capsule of a self pair)."""
    box: Any
    """The recorded pair's box (0 for a self pair)."""
    other: Any
    """The second capsule of a self pair; -1 for a capsule/box pair."""
    stage: Any
    """:class:`Stage` that passed the leaf (NONE: not passed)."""

    @staticmethod
    def stack(records: Sequence["LeafRecord"]) -> "LeafRecord":
        """One record of arrays from one-leaf records (NumPy)."""
        if not records:
            return LeafRecord(np.zeros(0), np.zeros(0), np.zeros(0, np.int64), np.zeros(0, np.int64),
                              np.full(0, -1, np.int64), np.zeros(0, np.int8))
        return LeafRecord(*(np.asarray(col) for col in zip(*records)))

    def take(self, rows) -> "LeafRecord":
        """The record of the leaves ``rows`` (NumPy index or mask)."""
        return LeafRecord(*(np.asarray(x)[rows] for x in self))

    def put(self, rows, sub: "LeafRecord") -> "LeafRecord":
        """A copy with the leaves ``rows`` replaced by ``sub`` (NumPy)."""
        out = [np.array(x, copy=True) for x in self]
        for col, new in zip(out, sub):
            col[rows] = new
        return LeafRecord(*out)


def box_record(g, guard, capsule, box, stage: Stage, xp=np) -> LeafRecord:
    """The record of an enclosure-box stage (CAPSULE, HULL or SWEPT): passed iff ``g > guard``."""
    return LeafRecord(g, guard, capsule, box, xp.full(xp.shape(g), -1, np.int64),
                      xp.where(g > guard, int(stage), int(Stage.NONE)).astype(np.int8))


def self_record(g, guard, capsule, other, xp=np) -> LeafRecord:
    """The record of the self test: capsule pair (``capsule``, ``other``)."""
    return LeafRecord(g, guard, capsule, xp.zeros(xp.shape(g), np.int64), other,
                      xp.full(xp.shape(g), int(Stage.NONE), np.int8))


def passes(rec: LeafRecord):
    """Whether the record's test passed: ``g > guard`` (NaN fails)."""
    return rec.clearance_m > rec.guard_m


def needs_hull(capsule: LeafRecord, self_test: LeafRecord | None, xp=np):
    """Where a later box stage (the hull stage, then the swept stage) runs: the box stages so far
    (``capsule``: their record) fail a box, on finite geometry, and the self test (if any) passes."""
    out = ~passes(capsule) & ~xp.isnan(capsule.clearance_m)
    return out if self_test is None else out & passes(self_test)


def compose(boxes: LeafRecord, self_test: LeafRecord | None, xp=np) -> LeafRecord:
    """The leaf's record from its box stages' (``boxes``: the capsule record, with the hull
    stage's where it ran) and the self test's: the one with the smaller ``g - guard`` (a NaN
    self clearance is always the worse); the leaf passes (keeps ``boxes.stage``) only where the
    self test passes too."""
    if self_test is None:
        return boxes
    worse = (self_test.clearance_m - self_test.guard_m < boxes.clearance_m - boxes.guard_m) \
        | xp.isnan(self_test.clearance_m)
    pick = [xp.where(worse, s, b) for s, b in zip(self_test[:5], boxes[:5])]
    return LeafRecord(*pick, xp.where(passes(self_test), boxes.stage, int(Stage.NONE)).astype(np.int8))
