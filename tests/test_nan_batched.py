"""NaN never certifies in the batched kernels, at the widths where it matters: on this JAX's CPU
backend, an XLA min-reduction over an axis may return a number beside a NaN operand (a vmapped
``jnp.min`` over 28 values, 256 rows: every NaN row came back finite). The broad phase
(:func:`~larc_jax.leaf.clearance.min_clearance`) picks its pairs with such reductions, so a NaN
segment can leave it a finite pick; what keeps a NaN curve from certifying is the placement's
finiteness check (:mod:`larc_jax.leaf.placement`), which every stage applies to its record.
These tests poison one trajectory's curve inside a prepared batch (a :class:`Trajectory` refuses
NaN, so only the kernel level can be tested this way) and evaluate it at a 256-interval width."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from larc_jax.engine.batch import prepare
from larc_jax.engine.certify import run_spec
from larc_jax.engine.tree import run_tree
from larc_jax.lazy_jax import jax, jnp
from larc_jax.leaf.clearance import min_clearance
from larc_jax.leaf.interval import trajectory_roundings
from larc_jax.leaf.reference import leaf_enclosures
from larc_jax.obstacles import AlignedBoxes

from .test_certify import random_scene, random_trajectory

DEPTH = 8
"""256 intervals of the poisoned trajectory per call (a bucket where the reductions drop NaN)."""


def _poisoned_batch(robot, capsules, enclosure: str):
    """Two trajectories in a four-box scene (the broad phase on), prepared as ``certify`` prepares
    them; trajectory 1's knot positions NaN."""
    rng = np.random.default_rng(5)
    trajs = [random_trajectory(rng, robot, k) for k in range(2)]
    scene = random_scene(rng, 0, max_boxes=4)
    while scene.n_boxes < 4:
        scene = random_scene(rng, 0, max_boxes=4)
    spec = run_spec(enclosure=enclosure)
    enc = leaf_enclosures(robot, capsules.with_padding(spec.padding_m), enclosure, None, None, False)
    bounds = trajectory_roundings(trajs, robot, enc.capsules, np.float64, enc.hulls)
    batch = prepare(trajs, [scene, scene], robot, enc.capsules, spec.margin_m, np.float64, bounds, None,
                    hulls=enc.hulls)
    assert batch.use_broad_phase
    with jax.enable_x64(True):
        q = np.array(batch.splines.q_knots)
        q[1] = np.nan
        splines = dataclasses.replace(batch.splines, q_knots=jnp.asarray(q))
    return dataclasses.replace(batch, splines=splines)


def test_the_broad_phase_matches_all_pairs_on_finite_segments():
    """The broad phase vmapped over 256 configurations, some with a NaN segment: on the finite
    ones it picks what every pair gives; on a NaN one every pair gives NaN (``argmin`` propagates
    it), while the broad phase's reductions may not (the hazard the tests below guard against)."""
    rng = np.random.default_rng(0)
    S, B, N = 7, 4, 256
    lo = rng.uniform(-1, 0.5, (B, 3))
    hi = lo + rng.uniform(0.05, 0.3, (B, 3))
    p_a = rng.uniform(-1, 1, (N, S, 3))
    p_b = p_a + rng.uniform(-0.1, 0.1, (N, S, 3))
    bad = rng.random((N, S)) < 0.05
    p_a[bad, 0] = np.nan
    with jax.enable_x64(True):
        boxes = AlignedBoxes(jnp.asarray(lo), jnp.asarray(hi), jnp.ones(B, bool))

        def run(k):
            return np.asarray(jax.jit(jax.vmap(lambda a, b: min_clearance(a, b, jnp.full(S, 0.01), boxes,
                                                                            jnp.zeros(B), k=k)[0]))(p_a, p_b))
        every, broad = run(None), run(4)
    rows = bad.any(axis=1)
    assert np.isnan(every[rows]).all()  # all pairs: argmin propagates NaN
    assert np.array_equal(every[~rows], broad[~rows])  # finite rows: the same pick


@pytest.mark.parametrize("enclosure", ["capsules", "hull"])
def test_a_nan_curve_never_certifies_in_a_wide_call(robot, capsules, enclosure):
    batch = _poisoned_batch(robot, capsules, enclosure)
    n = 1 << DEPTH
    traj = np.concatenate([np.ones(n, np.int64), np.zeros(n, np.int64)])
    depth = np.full(2 * n, DEPTH)
    index = np.concatenate([np.arange(n), np.arange(n)])
    if enclosure == "hull":  # LARC's path: step 1 with the screen, then the hull stage
        _, _, rec = batch.evaluate_cascade(traj, depth, index, may_bisect=np.ones(2 * n, bool))
    else:
        _, _, rec = batch.evaluate(traj, depth, index)
    poisoned = traj == 1
    assert not (rec.stage[poisoned] > 0).any()
    assert np.isnan(rec.clearance_m[poisoned]).all()
    assert (rec.stage[~poisoned] > 0).any()  # the healthy trajectory is evaluated in the same call


def test_a_nan_curve_never_certifies_in_the_device_tree(robot, capsules):
    """The same through the device tree (its kernels compiled inside its loop, with their own fusions)."""
    batch = _poisoned_batch(robot, capsules, "capsules")
    tree = run_tree(batch, 2, 9)  # the poisoned tree fails everywhere: its stack fills wide steps
    poisoned = tree.traj == 1
    assert poisoned.any() and not (tree.record.stage[poisoned] > 0).any()
    assert np.isnan(tree.record.clearance_m[poisoned]).all()
    assert tree.frontier[1].sum() == 2 ** 10 - 1  # every interval evaluated, none passed
