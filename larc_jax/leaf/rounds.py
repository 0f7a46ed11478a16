"""Step 4 of the enclosure cascade in rounds (:mod:`larc_jax.leaf.cascade`): which GJK search
decides each (interval, part, obstacle) triple, and what it records.

The rules are NumPy, shared by every scheduler (the batched host frontier, the reference): each
takes the rounds' values and asks for the next round only on the triples still undecided.

* The first round is the search's first axis alone (``iterations=0``), on every triple.
* The middle round (:data:`EARLY_ITERATIONS` steps, every obstacle kind) decides a triple that
  passes, and one that cannot pass: its upper bound (the searches' last iterates,
  :func:`larc_jax.obstacles.polytope.polytope_box_bounds`; both obstacle kinds give one, the
  protocol's default ``+inf`` never stops) at or below its guard less :func:`early_stop_slack`. No later step raises a lower bound above the
  upper one, so the full search would fail that triple too, up to rounding, which the slack covers
  many times over (a tie within it is searched in full: work, never a decision).
* The full round (:data:`~larc_jax.obstacles.polytope.GJK_ITERATIONS` steps) takes the rest.
* A third round (:func:`point_round`) searches a point cloud's piece point by point.

Every round's value is a sound lower bound, so stopping early never certifies anything: it only
records a looser bound (the round that decided the triple) than the full search would.
"""

from __future__ import annotations

import numpy as np

from ..obstacles.polytope import GJK_ITERATIONS

__all__ = ["EARLY_ITERATIONS", "early_stop_slack", "hull_rounds", "point_round"]

EARLY_ITERATIONS = 5
"""GJK steps of step 4's middle round (module docstring). On the Stage B set (LARC, the cascade)
the first axis decides 3,244 of 4,948 triples; of the other 1,704, five steps pass 533 and show
1,060 unable to pass, and 111 go on to the full search. The hull rounds' kernel time fell by about
a fifth (fixed-fine: a third) against the first axis then the full search, measured while
developing; 4 and 6 steps were no faster, 3 slower (each round is a further call per vertex class)."""


def early_stop_slack(dtype) -> float:
    """How far (m) below its guard a triple's upper bound must be for step 4 to stop searching it:
    4096 roundoffs of the geometry ``dtype`` on a metre, far above the bound's own rounding (a few
    ulps of the coordinates), so a last-bit tie is searched in full (it costs work only)."""
    return 4096 * float(np.finfo(dtype).eps)


def hull_rounds(g_first: np.ndarray, guard: np.ndarray, full, early=None, slack: float = 0.0):
    """Step 4's rule: ``(g, steps)``, the clearances of T triples and the GJK steps of the round that
    gave each, from their first-round values ``g_first`` (T,) (the first axis alone), their guards
    ``guard`` (T,), ``early(redo)``, the ``(clearances, upper bounds)`` of the triples ``redo``
    (indices) after :data:`EARLY_ITERATIONS` steps (None: no middle round), and ``full(redo)``,
    the full search's clearances. A triple keeps its first value iff it exceeds its guard, else its
    middle value iff that exceeds the guard or its upper bound is at or below ``guard - slack``;
    else it gets the full search (NaN is never kept early: its full search is NaN too)."""
    g = np.array(g_first, np.float64)
    steps = np.zeros(len(g), np.int64)
    redo = np.flatnonzero(~(g > guard))
    if len(redo) and early is not None:
        lower, upper = (np.asarray(x, np.float64) for x in early(redo))
        g[redo], steps[redo] = lower, EARLY_ITERATIONS
        redo = redo[~((lower > guard[redo]) | (upper <= guard[redo] - slack))]
    if len(redo):
        g[redo], steps[redo] = np.asarray(full(redo), np.float64), GJK_ITERATIONS
    return g, steps


def point_round(g: np.ndarray, guard: np.ndarray, separate: np.ndarray, points) -> np.ndarray:
    """Step 4's last round: the triples (T,) at or below their ``guard`` after the GJK rounds whose
    obstacle is made of ``separate`` (T,) points get the larger of their value ``g`` and
    ``points(redo)``, the per-point clearances of those triples ``redo`` (indices). Both are sound
    lower bounds, so is the larger; a NaN stays NaN (and is not searched again)."""
    g = np.array(g, np.float64)
    redo = np.flatnonzero(~(g > guard) & ~np.isnan(g) & np.asarray(separate, bool))
    if len(redo):
        g[redo] = np.maximum(g[redo], np.asarray(points(redo), np.float64))
    return g
