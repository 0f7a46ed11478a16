"""The leaf composition rule (larc_jax.leaf.record): one rule, NumPy and JAX alike, NaN never passes."""

import math

import numpy as np
import pytest

from larc_jax.leaf.record import LeafRecord, Stage, box_record, compose, needs_hull, passes, self_record


def _records(rng, n):
    g = rng.normal(size=n)
    g[rng.random(n) < 0.1] = np.nan
    gs = rng.normal(size=n)
    gs[rng.random(n) < 0.1] = np.nan
    gs[:5] = g[:5]  # ties of g - guard (the guards are equal)
    guard = np.full(n, 0.25)
    cap = rng.integers(0, 7, n)
    box = rng.integers(0, 4, n)
    boxes = box_record(g, guard, cap, box, Stage.CAPSULE)
    hull_rows = needs_hull(boxes, self_record(gs, guard, cap, cap + 1))
    boxes = boxes.put(np.flatnonzero(hull_rows),
                      box_record(g[hull_rows] + 0.5, guard[hull_rows], cap[hull_rows], box[hull_rows], Stage.HULL))
    return boxes, self_record(gs, guard, cap, cap + 1)


def test_numpy_and_jax_compose_alike():
    jnp = pytest.importorskip("jax.numpy")
    import jax

    boxes, self_test = _records(np.random.default_rng(0), 200)
    with jax.enable_x64(True):
        for s in (self_test, None):
            want = compose(boxes, s)
            got = compose(LeafRecord(*map(jnp.asarray, boxes)),
                          None if s is None else LeafRecord(*map(jnp.asarray, s)), xp=jnp)
            for w, x in zip(want, got):
                np.testing.assert_array_equal(w, np.asarray(x))
        np.testing.assert_array_equal(needs_hull(boxes, self_test),
                                      np.asarray(needs_hull(LeafRecord(*map(jnp.asarray, boxes)),
                                                            LeafRecord(*map(jnp.asarray, self_test)), xp=jnp)))


def _one(g, gs):
    """The composed record of one leaf: capsule test g (guard 0), self test gs (guard 0)."""
    return compose(box_record(g, 0.0, 3, 2, Stage.CAPSULE), self_record(gs, 0.0, 4, 5))


def test_named_cases():
    rec = _one(1.0, 2.0)  # both pass: the capsule record, passed by the capsule stage
    assert (float(rec.clearance_m), int(rec.other), int(rec.box), Stage(rec.stage)) == (1.0, -1, 2, Stage.CAPSULE)
    rec = _one(2.0, 1.0)  # the self pair is the worse: recorded, the leaf still passes
    assert (float(rec.clearance_m), int(rec.capsule), int(rec.other), int(rec.box)) == (1.0, 4, 5, 0)
    assert Stage(rec.stage) is Stage.CAPSULE
    rec = _one(1.0, 1.0)  # a tie keeps the box record
    assert int(rec.other) == -1 and Stage(rec.stage) is Stage.CAPSULE
    rec = _one(1.0, -1.0)  # the self test vetoes
    assert float(rec.clearance_m) == -1.0 and Stage(rec.stage) is Stage.NONE and not passes(rec)
    rec = _one(1.0, math.nan)  # a NaN self clearance is always the worse, and fails
    assert math.isnan(rec.clearance_m) and int(rec.other) == 5 and Stage(rec.stage) is Stage.NONE
    rec = _one(math.nan, 1.0)  # NaN geometry in the box test: recorded (NaN < x is False), fails
    assert math.isnan(rec.clearance_m) and Stage(rec.stage) is Stage.NONE
    hull = compose(box_record(0.5, 0.0, 1, 1, Stage.HULL), self_record(2.0, 0.0, 4, 5))
    assert Stage(hull.stage) is Stage.HULL and float(hull.clearance_m) == 0.5


def test_needs_hull():
    caps = box_record(np.array([1.0, -1.0, -1.0, np.nan]), np.zeros(4), np.zeros(4, int), np.zeros(4, int),
                      Stage.CAPSULE)
    np.testing.assert_array_equal(needs_hull(caps, None), [False, True, True, False])
    self_test = self_record(np.array([1.0, 1.0, np.nan, 1.0]), np.zeros(4), np.zeros(4, int), np.ones(4, int))
    np.testing.assert_array_equal(needs_hull(caps, self_test), [False, True, False, False])


def test_stack_take_put():
    recs = [box_record(float(g), 0.0, 1, 2, Stage.CAPSULE) for g in (1.0, -1.0)]
    table = LeafRecord.stack(recs)
    np.testing.assert_array_equal(table.stage, [Stage.CAPSULE, Stage.NONE])
    assert len(LeafRecord.stack([]).clearance_m) == 0
    np.testing.assert_array_equal(table.take([1]).clearance_m, [-1.0])
    np.testing.assert_array_equal(table.put([1], box_record(np.array([3.0]), np.zeros(1), [0], [0], Stage.HULL))
                                  .stage, [Stage.CAPSULE, Stage.HULL])
    assert [s.label for s in Stage] == ["", "capsule", "hull", "self", "swept"]
