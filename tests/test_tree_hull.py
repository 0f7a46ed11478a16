"""The cascade inside the device tree (larc_jax.engine.tree_hull) against the host frontier's
cascade: the same intervals, leaves, stages and guards; and its step 5 and compaction loop against
their NumPy counterparts on random inputs."""

from __future__ import annotations

import numpy as np
import pytest

from larc_jax.engine.batch import prepare
from larc_jax.engine.certify import _Names, run_spec  # noqa: PLC2701 - the host frontier is the reference
from larc_jax.compilation import tracked_call
from larc_jax.engine import tree as tree_module
from larc_jax.engine.tree import run_tree, supports
from larc_jax.engine.tree_hull import chunked, combine_jnp, hull_sizes
from larc_jax.lazy_jax import jax, jnp
from larc_jax.leaf.cascade import Links, combine, select_pairs
from larc_jax.leaf.interval import trajectory_roundings
from larc_jax.leaf.reference import leaf_enclosures
from larc_jax.leaf.self_collision import curve_ranges, load_separation, self_pairs

from .test_cascade import DEPTH, MARGIN, _posed, near_miss_dataset
from .test_cascade import model  # noqa: F401 - the fixture
from .test_tree import SMALL, _compare


@pytest.fixture(scope="module")
def near_misses(model):  # noqa: F811
    """20 trajectories with a box the hulls clear by rho + 0.5..12 mm: many hull-stage leaves."""
    return near_miss_dataset(*model, 20, 0.5, 12)


def _cascade_batch(model, trajs, scenes, self_collision=False):
    """The trajectories prepared as ``certify`` prepares them for the cascade."""
    robot, capsules, _ = model
    spec = run_spec(margin=MARGIN, self_collision=self_collision)
    enc = leaf_enclosures(robot, capsules.with_padding(spec.padding_m), "hull", None, None, False)
    bounds = trajectory_roundings(trajs, robot, enc.capsules, np.float64, enc.hulls)
    pairs = skips = None
    if self_collision:
        pairs = self_pairs(robot, enc.capsules, spec.self_margin_m, spec.self_skip, proven=load_separation(robot))
        skips = [pairs.skip_mask(*curve_ranges(t, None)) for t in trajs]
    batch = prepare(trajs, scenes, robot, enc.capsules, spec.margin_m, np.float64, bounds, None, hulls=enc.hulls,
                    self_pairs=pairs, self_skip=skips)
    return batch, _Names(scenes)


def test_cascade_tree_matches_host_frontier(model, near_misses):
    """Every interval the host frontier evaluates, the same leaves with the same stage and guard,
    clearances to a few ulps (a leaf the hull stage may have recorded to 1e-13 m: here one differs
    by 2.9e-15 m, 13 ulps; on the posed set below, seven failing leaves by up to 1.2e-14 m); many
    leaves decided by the hull stage."""
    trajs, scenes = near_misses
    batch, names = _cascade_batch(model, trajs, scenes)
    assert supports(batch)
    tree = run_tree(batch, len(trajs), DEPTH)
    _compare(batch, names, len(trajs), tree, ulps=8, max_depth=DEPTH, hull_m=1e-13)
    assert tree.calls == 1 and (tree.record.stage == 2).sum() > 20 and 0 < (tree.record.stage > 0).mean() < 1
    # Every hull-stage leaf went through a hull step, which takes up to 32 at once (20 trajectories:
    # HULL_STEP doubled), and first-stage steps were run besides.
    assert (tree.record.stage == 2).sum() / 32 <= tree.hull_steps < tree.steps


def test_cascade_tree_on_posed_shapes_with_self_test_and_small_buffers(model, near_misses, monkeypatch):
    """Posed boxes (a convex kind of its own), the self test composed after the hull stage, and
    buffers so small the tree continues over many calls: still the host frontier's leaves."""
    trajs, scenes = near_misses
    rng = np.random.default_rng(11)
    posed = [_posed(s, rng) for s in scenes]
    batch, names = _cascade_batch(model, trajs, posed, self_collision=True)
    assert supports(batch)
    tree = run_tree(batch, len(trajs), DEPTH, **SMALL)
    _compare(batch, names, len(trajs), tree, ulps=8, max_depth=DEPTH, hull_m=1e-13)
    assert tree.calls > 1 and (tree.record.stage == 2).sum() > 20
    # Hull steps of 3, with calls that stop holding lanes on the hull queue (asserted below): the
    # same leaves and decisions.
    held = []

    def call(program, args, on_compile):  # what each call leaves on the hull queue
        out = tracked_call(program, args, on_compile)
        held.append(int(out[3]))
        return out

    monkeypatch.setattr(tree_module, "tracked_call", call)
    odd = run_tree(batch, len(trajs), DEPTH, **SMALL, hull=3)
    _compare(batch, names, len(trajs), odd, ulps=8, max_depth=DEPTH, hull_m=1e-13)
    assert odd.calls == len(held) > 1 and odd.steps > tree.steps and max(held) > 0


def test_point_cloud_pieces_stay_on_the_host(model, near_misses, monkeypatch):
    """A scene with point-cloud pieces (whose third round the tree does not run) is refused by
    ``supports`` and by ``run_tree``, with the reason."""
    trajs, scenes = near_misses
    batch, _ = _cascade_batch(model, trajs[:2], scenes[:2])
    assert supports(batch)
    monkeypatch.setattr(type(batch.obstacles), "separate_points",
                        lambda self: np.ones(np.shape(self.mask), bool))
    assert not supports(batch)
    with pytest.raises(ValueError, match="point-cloud"):
        run_tree(batch, 2, DEPTH)


def _random_step5(rng, links: Links, F: int, B: int):
    """Step 5's inputs for ``F`` intervals: capsule clearances around their guards (ties, NaN,
    padding items), part upper bounds, and hull clearances for the triples step 3 selects."""
    C, P = len(links.of_capsule), len(links.of_part)
    g_cap = rng.choice([-0.02, -0.01, 0.0, 0.01, 0.03], size=(F, C, B)) + rng.choice([0, 1e-3], size=(F, C, B))
    g_cap[rng.random((F, C, B)) < 0.03] = np.nan
    g_cap[:, :, -1] = np.inf  # a padding item
    G_c = rng.uniform(0, 1e-3, (F, C))
    upper = rng.normal(0.01, 0.02, (F, P, B))
    tried, triples = select_pairs(links, g_cap - G_c[:, :, None], upper)
    i, p, k = triples.T
    guard_t = rng.uniform(0, 1e-3, len(triples))
    g_t = rng.choice([-0.01, 0.0, 0.005, 0.02], size=len(triples))
    g_t[rng.random(len(triples)) < 0.05] = np.nan
    dense_g, dense_guard = np.full((F, P, B), np.inf), np.zeros((F, P, B))
    dense_g[i, p, k], dense_guard[i, p, k] = g_t, guard_t
    return g_cap, G_c, tried, triples, g_t, guard_t, dense_g, dense_guard


def test_step5_on_dense_arrays_matches_combine():
    """:func:`combine_jnp` picks what the NumPy ``combine`` picks (the blocking pair, capsule, part
    and their values) on random inputs with NaN, ties and padding items."""
    rng = np.random.default_rng(5)
    links = Links(np.array([0, 0, 1, 2, 2, 3]), np.array([0, 1, 1, 2, 3, 3, 3]), 4)
    for _ in range(5):
        g_cap, G_c, tried, triples, g_t, guard_t, dense_g, dense_guard = _random_step5(rng, links, 40, 4)
        want = combine(links, g_cap, G_c, tried, triples, g_t, guard_t)[:4]
        with jax.enable_x64(True):
            got = jax.jit(combine_jnp, static_argnums=2)(jnp.asarray(links.of_capsule), jnp.asarray(links.of_part),
                                                         links.n_links, g_cap, G_c, tried, dense_g, dense_guard)
        for name, w, g in zip(("g", "guard", "capsule", "item"), want, got):
            np.testing.assert_array_equal(np.asarray(g), w, err_msg=name)
        assert np.isnan(want[0]).any() and (want[0] == np.asarray(got[0])).any()


def test_chunked_loop_visits_every_entry_once():
    """Every true entry is run once, whatever the chunk size (smaller, equal or larger than their
    count), and the others keep their value."""
    rng = np.random.default_rng(3)
    mask = rng.random(37) < 0.4
    with jax.enable_x64(True):
        for size in (1, 3, int(mask.sum()), 64):
            counts, = chunked(jnp.asarray(mask), size, lambda src: (src * 2 + 1,), (jnp.zeros(37, jnp.int32),))
            np.testing.assert_array_equal(np.asarray(counts), np.where(mask, 2 * np.arange(37) + 1, 0))


def test_hull_sizes_take_a_hull_step_at_once():
    """The lanes and round widths of a hull step: step 2 on every lane of the step, the rounds
    positive, the later rounds no wider than the first, the first round twice the lanes."""
    for lanes in (1, 3, 16, 32):
        h, m0, m1, m2 = hull_sizes(lanes)
        assert h == lanes and 1 <= m2 <= m1 <= m0 == 2 * h
