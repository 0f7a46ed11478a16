"""The broad-phase minimum clearance against its all-pairs NumPy reference."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from larc_jax.leaf.clearance import min_clearance, min_clearance_np
from larc_jax.obstacles.geometry import segment_box_distance_np, segment_box_lower_bound
from larc_jax.obstacles import AlignedBoxes


def random_case(rng, S=11, B=5, spread=0.5):
    p_a = rng.uniform(-spread, spread, (S, 3))
    p_b = p_a + rng.normal(0, 0.1, (S, 3))
    lo = rng.uniform(-0.6, 0.6, (B, 3))
    hi = lo + rng.uniform(0.0, 0.4, (B, 3))
    return p_a, p_b, rng.uniform(0.0, 0.08, S), AlignedBoxes(lo, hi, rng.random(B) < 0.85), rng.uniform(0.0, 1e-3, B)


@pytest.mark.parametrize("k", [None, 1, 2, 4])
def test_min_clearance_matches_all_pairs_reference(k):
    rng = np.random.default_rng(11 + (k or 0))
    cases = [random_case(rng) for _ in range(300)]
    stacked = [jax.tree.map(lambda *x: np.stack(x), *c) for c in zip(*cases)]
    with jax.enable_x64(True):
        g, s, b, exact = (np.asarray(x) for x in jax.jit(jax.vmap(lambda *a: min_clearance(*a, k=k)))(*stacked))
    assert exact.mean() > (0.5 if k == 1 else 0.9)
    if k is None:
        assert exact.all()
    for i, case in enumerate(cases):
        g_np, s_np, b_np = min_clearance_np(*case)
        if exact[i]:  # certain results are the all-pairs minimum, pair included
            assert g[i] == pytest.approx(g_np, abs=1e-12) and (s[i], b[i]) == (s_np, b_np), i
        else:  # otherwise the caller recomputes; the value is still an upper bound of nothing
            assert g[i] >= g_np - 1e-12


def test_no_real_boxes_and_lower_bound_edge_cases():
    rng = np.random.default_rng(3)
    p_a, p_b, off, boxes, offb = random_case(rng)
    with jax.enable_x64(True):
        g, _, _, exact = min_clearance(p_a, p_b, off, AlignedBoxes(boxes.lo, boxes.hi, np.zeros(len(offb), bool)), offb)
    assert float(g) == np.inf and bool(exact)
    # The AABB bound never exceeds the exact distance: touching, crossing, inside, parallel.
    cases = [([0, 0, 0], [1, 1, 1], [0.5, 0.5, 0.5], [2, 2, 2]),
             ([-1, 0.5, 0.5], [2, 0.5, 0.5], [0, 0, 0], [1, 1, 1]),
             ([1.5, 0, 0], [1.5, 1, 1], [0, 0, 0], [1, 1, 1]),
             ([2, 2, 2], [3, 3, 3], [0, 0, 0], [1, 1, 1]),
             ([0.2, 0.2, 5], [0.2, 0.2, 5], [0, 0, 0], [1, 1, 1])]
    for _ in range(2000):
        p0, p1 = rng.uniform(-2, 2, 3), rng.uniform(-2, 2, 3)
        l = rng.uniform(-1, 1, 3)
        cases.append((p0, p1, l, l + rng.uniform(0, 1, 3)))
    with jax.enable_x64(True):
        lb = jax.jit(jax.vmap(segment_box_lower_bound))(*(np.array(c, float) for c in zip(*cases)))
    for (p0, p1, l, h), bound in zip(cases, np.asarray(lb)):
        assert bound <= segment_box_distance_np(p0, p1, l, h)


def test_broad_phase_changes_no_result(monkeypatch):
    """certify with the broad-phase kernel (and its all-pairs fallback) gives bit-identical
    leaves to the all-pairs kernel on random trajectories and scenes with many boxes."""
    import larc_jax as lj
    from larc_jax.engine import batch as B
    from larc_jax.engine.results import LEAF_COLUMNS

    from .test_certify import random_scene, random_trajectory

    robot = lj.load_robot()
    capsules = lj.load_capsules(lj.default_capsule_path(), robot)
    rng = np.random.default_rng(5)
    trajs = [random_trajectory(rng, robot, k) for k in range(24)]
    scenes = [random_scene(rng, k) for k in range(24)]
    assert max(s.n_boxes for s in scenes) * capsules.n_capsules > 2 * B.BROAD_PHASE_K
    kw = dict(margin=0.01, max_depth=5, enclosure="capsules")
    broad = lj.certify(trajs, scenes, robot, capsules, **kw).leaves_dataframe()
    monkeypatch.setattr(B.Batch, "use_broad_phase", property(lambda self: False))
    full = lj.certify(trajs, scenes, robot, capsules, **kw).leaves_dataframe()
    assert len(broad) > 100
    for col in LEAF_COLUMNS:
        assert (broad[col].astype(str) == full[col].astype(str)).all(), col
