"""A proven lower bound on the distance between a convex polytope and an axis-aligned box.

The hull stage of the certificate (:mod:`larc_jax.leaf.cascade`) needs, for a link part ``P =
conv(V)`` (its hull vertices, given in the link frame and placed by the link pose ``x -> R x +
t``) and an obstacle box ``B = [lo, hi]``, a number that is *never more* than ``d(P, B) =
min_{p in P, x in B} |x - p|``.

Why any axis gives one. For every non-zero vector ``w`` and all ``p in P``, ``x in B``:
``w . (x - p) <= |w| |x - p|``. Taking the minimum over ``x`` and ``p``::

    d(P, B) >= lb(w) = (min_{x in B} w . x  -  max_{p in P} w . p) / |w|          (S)

(a negative right-hand side is still a true, useless, bound). ``min_B w . x`` is attained at
the box corner taking ``lo_i`` where ``w_i > 0`` and ``hi_i`` elsewhere; ``max_P w . p`` at a
vertex (a linear function on a polytope), computed in the link frame as
``w . t + max_v (R^T w) . v``. Both are exact, so (S) holds for *any* ``w``, however it was
found: how the axes are chosen decides how tight the bound is, never whether it is sound.

Which axes. Strong duality for two convex sets makes (S) exact at the best ``w``: the direction
from the closest point of ``P`` to the closest point of ``B``. We search for it with GJK
(Gilbert, Johnson, Keerthi 1988) on the Minkowski difference ``D = B - P``, whose point of
least ``w``-projection is ``(box corner) - (support vertex)``: the search keeps a simplex of at
most four points of ``D``; each step evaluates (S) at the current ``w``, adds the new point, and
replaces ``w`` by the point of the simplex nearest the origin (:func:`_nearest_in_simplex`:
every face of the simplex is projected on and the nearest projection inside its face is kept;
a tetrahedron holding the origin means the sets may touch). The first axis points from the
part's centre (``centre``, any point: it only seeds the search) to the box. The kernel runs a
fixed number of steps (:data:`GJK_ITERATIONS`, so that it vectorises) and returns the largest
(S) met. On the PIPER link hulls next to random boxes 1-30 mm away, 12 steps come within
0.06 mm of the true distance (python-fcl on the hull mesh) in the worst of 900 cases and match
it in 90 %; tests/test_polytope.py checks the one-sided inequality against FCL and dense
sampling.

Rounding (``u`` the unit roundoff of the dtype). The placed support vertex ``p = fl(R v_k + t)``
is off the exactly placed one by the placement error that the hull part's rounding guard covers
(budget G1 of :mod:`larc_jax.leaf.interval`, with the part's vertices in ``R_p``). What remains is
bounded *a posteriori*, from the numbers of each evaluation, and subtracted from it:

* the support vertex ``k`` is chosen with a rounded axis ``m = fl(R^T w)`` and rounded dot
  products: it may miss the true maximum of ``w . (R v)`` by ``<= 12 u |w| max_j |v_j|``
  (:func:`first_max` chooses it by two reductions, each of which may compute the scores anew:
  the winner scores the maximum in one of them, so the bound holds; should none, the
  evaluation gives -inf, no bound);
* ``s = fl(corner - p)`` (one rounding per component), ``fl(w . s)`` (3 terms) and
  ``fl(sqrt(w . w))`` and the division: ``<= 8 u (sum_i |w_i s_i| / |w| + |lb|)``.

* the winner is the first vertex scoring within ``tol = TIE |w|_1 v_max`` of the best score
  (``v_max >= max_j |v_j|_1``; "One path" below): it may miss the maximum by ``tol`` more, which
  costs (S) at most ``tol / |w| <= sqrt(3) TIE v_max``.

So each evaluation returns ``lb - 32 u (sum_i |w_i s_i| / |w| + |lb| + max_j |v_j|) - 2 TIE v_max``
(constants doubled, then more): never more than (S) for the computed placement. The last
subtraction may itself round away where ``2 TIE v_max`` is below half an ulp of the result
(float32: ``TIE`` is far below ``u``); the 32 u term's own surplus over the 20 u it covers,
``12 u v_max``, is then larger than it, so the bound holds in either dtype.

One path. The kernel and its NumPy reference round differently, and a search that meets a tie
(an axis component that is rounding noise, as when the nearest feature is a box face; two vertices
or two faces equally near) would go on along different simplices in the two, with different
values after a given number of steps. Ties are therefore broken by rules that rounding noise
does not move (:data:`TIE`): an axis component below ``TIE |w|_1`` is set to 0 before the axis is
used (any axis is sound), the support vertex is the first within ``tol`` of the best, and the
nearest face is the first within a relative ``TIE`` of the least (a vertex before the edges
through it, an edge before the triangles). Then both take the same steps (tests/test_polytope.py
compares them after every number of steps), which the hull stage's early rounds rely on.

Several placements (the swept test, :mod:`larc_jax.leaf.swept`). Given poses ``(R_i, t_i)``, the
polytope is ``conv(U_i (R_i V + t_i))``, whose support along ``w`` is the largest of the
placements' supports: ``max_i (w . t_i + max_v (R_i^T w) . v)``, so (S) holds unchanged. The
placement and vertex are chosen with rounded scores that now include ``w . t_i``: the choice may
miss the true maximum by a further ``<= 12 u |w| max_i |t_i|``, so ``max_i |t_i|_1`` joins
``max_j |v_j|`` in the subtracted term (one placement: unchanged). Only box coordinates that
enter with a weight ``w_i`` count, relative to the bound itself; a far or huge box costs
nothing elsewhere. The search itself may be inexact in any way without harm. Degenerate simplices are skipped by their determinant tests
and a zero ``w`` is replaced by a fixed axis, so finite input gives a finite bound; NaN input
gives NaN (never certifies).

An obstacle polytope (a piece of a mesh or point cloud, :mod:`larc_jax.obstacles.convex_shapes`).
For ``O = conv(Y)`` the argument is the same with ``min_{x in O} w . x`` attained at a vertex of
``Y``; that vertex is picked with rounded scores ``fl(w . y_j)`` and may miss the true minimum by
``<= 12 u |w| max_j |y_j|`` (as the part's support vertex does), so ``max_j |y_j|_1`` joins
``max_j |v_j|`` in the subtracted term (:func:`polytope_hull_lower_bound`); the first axis points
from the part's centre to the mean of ``Y``. Both obstacles run the one search :func:`_gjk`, given
the obstacle's point of least ``w . x``.

:func:`polytope_box_lower_bound` is the JAX kernel for one polytope and one box (batch with
``jax.vmap``; it reads the vertices a column at a time, so a gathered vertex table fuses into
the support reduction instead of being copied per pair); :func:`polytope_box_lower_bound_np` is
its NumPy float64 reference, the same steps written with loops.

An upper bound, to stop early (:func:`polytope_box_bounds`). The search's iterate ``w`` is the
point of ``conv(Y)`` nearest the origin, ``Y`` points of ``D`` (0 once a tetrahedron holds the
origin), so ``d(P, B) = min_{z in D} |z| <= |w|`` in exact arithmetic: no later step can raise the
lower bound above ``|w|``. The hull stage uses it only to *stop searching* a pair that cannot pass
(:func:`larc_jax.leaf.rounds.hull_rounds`), never to certify, so it needs no rounding care
beyond a slack that keeps last-bit ties searching on (they would only cost work).
"""

from __future__ import annotations

import itertools
import math

import numpy as np

from ..lazy_jax import jax, jnp

__all__ = ["GJK_ITERATIONS", "polytope_box_lower_bound", "polytope_box_lower_bound_np", "polytope_box_bounds",
           "polytope_box_bounds_np", "polytope_hull_lower_bound", "polytope_hull_lower_bound_np", "polytope_hull_bounds",
           "polytope_hull_bounds_np"]

GJK_ITERATIONS = 12
"""GJK steps per polytope-box pair (fixed: the kernel is vectorised over pairs)."""

_FACES = tuple(s for k in (1, 2, 3) for s in itertools.combinations(range(4), k))
"""Faces of a 4-point simplex tried by the nearest-point step, in a fixed order (ties go to the
first, in the kernel and the reference alike)."""

TIE = 2.0**-30
"""Relative width of a tie (module docstring, "One path"): an axis component below ``TIE`` times
the axis's 1-norm is taken as 0, a vertex scoring within ``TIE |w|_1 v_max`` of the best is a
winner (the first such), a face within ``TIE`` of the least squared distance is a nearest face
(the first such: vertices, then edges, then triangles)."""

_DEGENERATE = 1e-12
"""A triangle whose Gram determinant is below this fraction of ``|e1|^2 |e2|^2`` is skipped
(its nearest point lies on an edge, which is tried anyway)."""


# ----------------------------------------------------------------------------------------------
# JAX kernel
# ----------------------------------------------------------------------------------------------


_FACE_I = np.array([f[0] for f in _FACES])
_FACE_J = np.array([f[1] if len(f) > 1 else f[0] for f in _FACES])
_FACE_K = np.array([f[2] if len(f) > 2 else f[0] for f in _FACES])
_FACE_SIZE = np.array([len(f) for f in _FACES])


def _dot(a, b):
    """IEEE product. The rounding bounds (module docstring) assume IEEE arithmetic, but a
    float32 product on a GPU defaults to TF32 (a 10-bit mantissa), which they do not cover; on a
    CPU this changes nothing (tests/test_polytope.py checks every product of the kernel)."""
    return jnp.matmul(a, b, precision=jax.lax.Precision.HIGHEST)


def _nearest_in_simplex(Y: jax.Array, active: jax.Array):
    """Point of conv(active rows of ``Y`` (4, 3)) nearest the origin, and its weights (4,).

    Every face (vertex, edge, triangle; all 14 at once, from the Gram matrix ``G = Y Y^T``) is
    projected on; among the projections inside their face the shortest is the answer (the
    nearest point lies in the relative interior of some face, and every candidate is a point of
    the simplex). A full tetrahedron holding the origin gives the origin (weights from signed
    volumes)."""
    dtype = Y.dtype
    G = _dot(Y, Y.T)
    i, j, k = jnp.asarray(_FACE_I), jnp.asarray(_FACE_J), jnp.asarray(_FACE_K)
    size = jnp.asarray(_FACE_SIZE)
    gii, gij, gik, gjj, gjk, gkk = G[i, i], G[i, j], G[i, k], G[j, j], G[j, k], G[k, k]
    # Edges (i, j): mu = (G_ii - G_ij) / |Y_j - Y_i|^2.
    den = gii - 2 * gij + gjj
    mu = (gii - gij) / jnp.where(den > 0, den, 1)
    # Triangles (i, j, k): the 2x2 normal equations of the projection, by Cramer's rule.
    a11, a22 = gjj - 2 * gij + gii, gkk - 2 * gik + gii
    a12 = gjk - gij - gik + gii
    r1, r2 = gii - gij, gii - gik
    det = a11 * a22 - a12 * a12
    safe = jnp.where(det > 0, det, 1)
    mu1, mu2 = (r1 * a22 - r2 * a12) / safe, (r2 * a11 - r1 * a12) / safe
    one, zero = jnp.ones_like(mu), jnp.zeros_like(mu)
    lam = jnp.where((size == 1)[:, None], jnp.stack([one, zero, zero], 1),
                    jnp.where((size == 2)[:, None], jnp.stack([1 - mu, mu, zero], 1),
                              jnp.stack([1 - mu1 - mu2, mu1, mu2], 1)))  # (14, 3) on (i, j, k)
    usable = jnp.where(size == 1, True, jnp.where(size == 2, den > 0, det > _DEGENERATE * a11 * a22))
    ok = usable & active[i] & active[j] & active[k] & jnp.all(lam >= 0, axis=1)
    # (14, 4) weights on the rows of Y (the unused slots of vertices and edges have weight 0).
    W = (jax.nn.one_hot(i, 4, dtype=dtype) * lam[:, :1] + jax.nn.one_hot(j, 4, dtype=dtype) * lam[:, 1:2]
         + jax.nn.one_hot(k, 4, dtype=dtype) * lam[:, 2:])
    norm2 = jnp.where(ok, jnp.einsum("fa,ab,fb->f", W, G, W, precision=jax.lax.Precision.HIGHEST), jnp.inf)
    least = jnp.min(norm2)
    lam4 = W[jnp.argmax(norm2 <= least + TIE * jnp.abs(least))]  # the first nearest face (TIE)
    e1, e2, e3 = Y[1] - Y[0], Y[2] - Y[0], Y[3] - Y[0]
    vol = _triple(e1, e2, e3)
    sub = jnp.stack([_triple(-Y[0], e2, e3), _triple(e1, -Y[0], e3), _triple(e1, e2, -Y[0])])
    tmu = sub / jnp.where(vol != 0, vol, 1)
    tet = jnp.concatenate([(1 - tmu.sum())[None], tmu])
    inside = jnp.all(active) & (vol != 0) & jnp.all(tet >= 0)
    lam4 = jnp.where(inside, tet, lam4)
    x = jnp.where(inside, jnp.zeros(3, dtype), _dot(lam4, Y))
    return x, lam4


def first_max(scores, tol=0.0):
    """``(k, found)``: the first index scoring at least the largest of ``scores`` (n,) less ``tol``
    (with ``tol = 0``, the vertex ``jnp.argmax`` picks; the search passes its tie width, module
    docstring "One path"), found by two plain reductions (a max, then a min over those indices):
    XLA's CPU backend runs ``argmax``'s variadic value-and-index reduce slower, and this is the
    search's inner loop (every step scans the part's vertices): 4,608 PIPER pairs of 691 columns,
    12 steps, took 165 ms with this choice against 264 ms with ``argmax`` (one call each, a loaded
    2-core machine, before ``v_max`` was taken per part).

    XLA may compute ``scores`` once for each reduction. Whatever rounding each computation has,
    the winner scores the maximum less ``tol`` in one of them, so the choice misses the true
    maximum by no more than ``tol`` and two computations' rounding (the module docstring's ``12 u``
    and tie terms). Should no index qualify (NaN scores, or two computations that disagree by
    more than ``tol``), ``found`` is False and ``k`` 0:
    the caller then gives no bound (-inf) rather than one from an arbitrary vertex."""
    n = scores.shape[0]
    k = jnp.min(jnp.where(scores >= jnp.max(scores) - tol, jnp.arange(n), n))
    found = k < n
    return jnp.where(found, k, 0), found


def _triple(a, b, c):
    return _dot(a, jnp.cross(b, c))


def polytope_box_lower_bound(vertices: jax.Array, part: jax.Array, centre: jax.Array, R: jax.Array,
                             t: jax.Array, lo: jax.Array, hi: jax.Array,
                             iterations: int = GJK_ITERATIONS) -> jax.Array:
    """Lower bound on the distance between the placed polytope ``conv(R V + t)``, ``V =
    vertices[part]``, and the box ``[lo, hi]`` (module docstring).

    Args:
      vertices: (P, K, 3) vertex table of all polytopes in their link frames, m (finite; rows
        may repeat: padding). Indexed inside the support step so that under ``vmap`` the table
        is read in place, never copied per pair.
      part: scalar index of the polytope.
      centre: (3,) any point in the link frame (seeds the search; the part's centre is best).
      R, t: (3, 3), (3,) link pose in the box frame (rotation, translation m); or (m, 3, 3), (m, 3):
        m placements, the polytope being the hull of their union (module docstring).
      lo, hi: (3,) box corners, m, ``lo <= hi``.
      iterations: GJK steps (static).

    Returns:
      Scalar, m: never more than the true distance (exact up to rounding once the search has
      converged); <= 0 when the sets may touch; NaN for non-finite input.
    """
    return _box_search(vertices, part, centre, R, t, lo, hi, iterations, upper=False)


def polytope_box_bounds(vertices: jax.Array, part: jax.Array, centre: jax.Array, R: jax.Array,
                        t: jax.Array, lo: jax.Array, hi: jax.Array, iterations: int = GJK_ITERATIONS):
    """``(lower, upper)``: :func:`polytope_box_lower_bound` and the norm of the search's last
    iterate, an upper bound on the distance up to rounding (module docstring: for stopping a
    search early, never for certifying); both NaN for non-finite input."""
    return _box_search(vertices, part, centre, R, t, lo, hi, iterations, upper=True)


def _box_search(vertices, part, centre, R, t, lo, hi, iterations, upper):
    dtype = R.dtype
    lo, hi = lo.astype(dtype), hi.astype(dtype)

    def lowest(w):  # the box corner of least w . x: exact, no choice error
        return jnp.where(w > 0, lo, hi)

    finite = jnp.isfinite(lo).all() & jnp.isfinite(hi).all()
    return _gjk(vertices, part, centre, R, t, lowest, lambda c: jnp.clip(c, lo, hi) - c, None, finite, iterations,
                upper)


def polytope_hull_lower_bound(vertices: jax.Array, part: jax.Array, centre: jax.Array, R: jax.Array,
                              t: jax.Array, Y: jax.Array, iterations: int = GJK_ITERATIONS) -> jax.Array:
    """Lower bound on the distance between the placed polytope ``conv(R V + t)`` (as in
    :func:`polytope_box_lower_bound`) and the obstacle polytope ``conv(Y)``, ``Y`` (K', 3) in the
    same frame (rows may repeat). The obstacle's point of least ``w . x`` is a vertex picked with
    rounded scores, which may miss the true minimum by ``<= 12 u |w| max_j |y_j|``: ``max_j |y_j|_1``
    joins the subtracted term (module docstring), so (S) still holds for any axis."""
    return _hull_search(vertices, part, centre, R, t, Y, iterations, upper=False)


def polytope_hull_bounds(vertices: jax.Array, part: jax.Array, centre: jax.Array, R: jax.Array,
                         t: jax.Array, Y: jax.Array, iterations: int = GJK_ITERATIONS):
    """``(lower, upper)``: :func:`polytope_hull_lower_bound` and the norm of the search's last
    iterate (as :func:`polytope_box_bounds`: for stopping a search early, never for certifying)."""
    return _hull_search(vertices, part, centre, R, t, Y, iterations, upper=True)


def _hull_search(vertices, part, centre, R, t, Y, iterations, upper):
    dtype = R.dtype
    Y = Y.astype(dtype)

    def lowest(w):
        return Y[jnp.argmin(Y[:, 0] * w[0] + Y[:, 1] * w[1] + Y[:, 2] * w[2])]

    scale = jnp.max(jnp.abs(Y).sum(axis=1))
    return _gjk(vertices, part, centre, R, t, lowest, lambda c: jnp.mean(Y, axis=0) - c, scale,
                jnp.isfinite(Y).all(), iterations, upper)


def _gjk(vertices, part, centre, R, t, lowest, seed, obstacle_scale, obstacle_finite, iterations, upper=False):
    """The GJK search of the module docstring between the placed polytope and an obstacle given by
    ``lowest(w)`` (its point of least ``w . x``) and ``seed(c)`` (the first axis from the placed
    centre ``c``); ``obstacle_scale`` (None: exact) is the obstacle's part of the choice error.
    ``upper`` (static): also return ``|w|`` of the last iterate (module docstring)."""
    dtype = R.dtype
    centre, t = (x.astype(dtype) for x in (centre, t))
    table = vertices.astype(dtype)
    unit_x = jnp.array([1.0, 0.0, 0.0], dtype)
    u = float(jnp.finfo(dtype).eps) / 2
    # >= max_j |v_j| (1-norm >= 2-norm). Taken per part over the whole table, then indexed: under
    # vmap the table is shared, so this is one pass over it, not one per pair.
    v_max = jnp.max(jnp.abs(table).sum(axis=2), axis=1)[part]
    union = R.ndim == 3  # static: several placements
    if union:
        v_max = v_max + jnp.max(jnp.abs(t).sum(axis=1))  # the translations enter the choice
    if obstacle_scale is not None:
        v_max = v_max + obstacle_scale

    def bound(w, part):
        """(S) at ``w`` less its rounding bound (module docstring), and the point of D = B - P
        attaining it."""
        w = jnp.where(_dot(w, w) > 0, w, unit_x)  # any axis is sound; this one avoids 0/0
        w_1 = jnp.abs(w).sum()
        w = jnp.where(jnp.abs(w) <= TIE * w_1, 0, w)  # one path: a noise component is 0 (docstring)
        tol = TIE * w_1 * v_max  # a vertex this close to the best is a winner
        V = table[part]  # read by the reductions only (fused); the winner is fetched apart
        if union:
            m = jnp.einsum("pij,i->pj", R, w, precision=jax.lax.Precision.HIGHEST)  # the axis per placement
            scores = V[:, None, 0] * m[:, 0] + V[:, None, 1] * m[:, 1] + V[:, None, 2] * m[:, 2] + _dot(t, w)
            flat, found = first_max(scores.reshape(-1), tol)
            k, i = flat // R.shape[0], flat % R.shape[0]
            placed = _dot(R[i], table[part, k]) + t[i]
        else:
            m = _dot(R.T, w)  # the axis in the link frame
            k, found = first_max(V[:, 0] * m[0] + V[:, 1] * m[1] + V[:, 2] * m[2], tol)
            placed = _dot(R, table[part, k]) + t
        s = lowest(w) - placed
        norm = jnp.sqrt(_dot(w, w))
        lb = _dot(w, s) / norm
        lb = lb - 32 * u * (_dot(jnp.abs(w), jnp.abs(s)) / norm + jnp.abs(lb) + v_max) - 2 * TIE * v_max
        return jnp.where(found, lb, -jnp.inf), s  # no winner found: no bound, never more than (S)

    if union:
        c = jnp.mean(jnp.einsum("pij,j->pi", R, centre, precision=jax.lax.Precision.HIGHEST) + t, axis=0)
    else:
        c = _dot(R, centre) + t
    best, s = bound(seed(c), part)
    Y = jnp.zeros((4, 3), dtype).at[0].set(s)
    active = jnp.array([True, False, False, False])

    def step(_, carry):
        Y, active, w, best = carry
        # The barrier keeps XLA from hoisting the loop-invariant table[part] out of the loop,
        # which would copy the whole vertex table once per pair (memory, not arithmetic).
        _, p = jax.lax.optimization_barrier((w, part))
        lb, s = bound(w, p)
        best = jnp.maximum(best, lb)
        room = ~jnp.all(active)  # a full simplex holds the origin: nothing left to improve
        slot = jnp.argmax(~active)
        Y = jnp.where(room, Y.at[slot].set(s), Y)
        active = jnp.where(room, active.at[slot].set(True), active)
        w_new, lam = _nearest_in_simplex(Y, active)
        return Y, jnp.where(room, lam > 0, active), jnp.where(room, w_new, w), best

    _, active, w, best = jax.lax.fori_loop(0, iterations, step, (Y, active, s, best))
    finite = jnp.isfinite(R).all() & jnp.isfinite(t).all() & obstacle_finite
    if not upper:
        return jnp.where(finite, best, jnp.nan)
    reach = jnp.where(jnp.all(active), 0.0, jnp.sqrt(_dot(w, w)))  # a full simplex holds the origin
    return jnp.where(finite, best, jnp.nan), jnp.where(finite, reach, jnp.nan)


# ----------------------------------------------------------------------------------------------
# NumPy float64 reference
# ----------------------------------------------------------------------------------------------


def _nearest_in_simplex_np(Y: np.ndarray, active: np.ndarray):
    G = Y @ Y.T
    candidates = []
    for face in _FACES:
        if not all(active[i] for i in face):
            continue
        if len(face) == 1:
            lam = np.array([1.0])
        elif len(face) == 2:
            i, j = face
            den = G[i, i] - 2 * G[i, j] + G[j, j]
            if not den > 0:
                continue
            mu = (G[i, i] - G[i, j]) / den
            lam = np.array([1 - mu, mu])
        else:
            i, j, k = face
            a11 = G[j, j] - 2 * G[i, j] + G[i, i]
            a22 = G[k, k] - 2 * G[i, k] + G[i, i]
            a12 = G[j, k] - G[i, j] - G[i, k] + G[i, i]
            r1, r2 = G[i, i] - G[i, j], G[i, i] - G[i, k]
            det = a11 * a22 - a12 * a12
            if not det > _DEGENERATE * a11 * a22:
                continue
            mu1, mu2 = (r1 * a22 - r2 * a12) / det, (r2 * a11 - r1 * a12) / det
            lam = np.array([1 - mu1 - mu2, mu1, mu2])
        if (lam < 0).any():
            continue
        full = np.zeros(4)
        full[list(face)] = lam
        candidates.append((float(full @ G @ full), full))
    least = min(n2 for n2, _ in candidates)
    best_lam = next((full for n2, full in candidates if n2 <= least + TIE * abs(least)),  # the first nearest face
                    candidates[0][1])
    if active.all():
        e1, e2, e3 = Y[1] - Y[0], Y[2] - Y[0], Y[3] - Y[0]
        vol = float(e1 @ np.cross(e2, e3))
        if vol != 0:
            mu = np.array([-Y[0] @ np.cross(e2, e3), e1 @ np.cross(-Y[0], e3), e1 @ np.cross(e2, -Y[0])]) / vol
            tet = np.r_[1 - mu.sum(), mu]
            if (tet >= 0).all():
                return np.zeros(3), tet
    return best_lam @ Y, best_lam


def polytope_box_lower_bound_np(V, centre, R, t, lo, hi, iterations: int = GJK_ITERATIONS) -> float:
    """NumPy float64 reference of :func:`polytope_box_lower_bound` (same steps, loops)."""
    return polytope_box_bounds_np(V, centre, R, t, lo, hi, iterations)[0]


def polytope_box_bounds_np(V, centre, R, t, lo, hi, iterations: int = GJK_ITERATIONS) -> tuple[float, float]:
    """NumPy float64 reference of :func:`polytope_box_bounds`."""
    lo, hi = (np.asarray(x, np.float64) for x in (lo, hi))
    if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
        return math.nan, math.nan
    return _gjk_np(V, centre, R, t, lambda w: np.where(w > 0, lo, hi), lambda c: np.clip(c, lo, hi) - c, 0.0,
                   iterations)


def polytope_hull_lower_bound_np(V, centre, R, t, Y, iterations: int = GJK_ITERATIONS) -> float:
    """NumPy float64 reference of :func:`polytope_hull_lower_bound`."""
    return polytope_hull_bounds_np(V, centre, R, t, Y, iterations)[0]


def polytope_hull_bounds_np(V, centre, R, t, Y, iterations: int = GJK_ITERATIONS) -> tuple[float, float]:
    """NumPy float64 reference of :func:`polytope_hull_bounds`."""
    Y = np.asarray(Y, np.float64)
    if not np.isfinite(Y).all():
        return math.nan, math.nan
    return _gjk_np(V, centre, R, t, lambda w: Y[int(np.argmin(Y @ w))], lambda c: Y.mean(axis=0) - c,
                   float(np.abs(Y).sum(axis=1).max()), iterations)


def _gjk_np(V, centre, R, t, lowest, seed, obstacle_scale: float, iterations: int) -> tuple[float, float]:
    """``(lower, upper)`` of :func:`_gjk` (``upper=True``)."""
    V, centre, R, t = (np.asarray(x, np.float64) for x in (V, centre, R, t))
    if not all(np.isfinite(x).all() for x in (V, R, t)):
        return math.nan, math.nan

    u = float(np.finfo(np.float64).eps) / 2
    union = R.ndim == 3
    Rs, ts = (R, t) if union else (R[None], t[None])
    v_max = float(np.abs(V).sum(axis=1).max()) + (float(np.abs(t).sum(axis=1).max()) if union else 0.0)
    v_max += obstacle_scale

    def bound(w):
        if not w @ w > 0:
            w = np.array([1.0, 0.0, 0.0])
        w_1 = float(np.abs(w).sum())
        w = np.where(np.abs(w) <= TIE * w_1, 0.0, w)
        if union:
            scores = np.stack([V @ (Ri.T @ w) + ti @ w for Ri, ti in zip(Rs, ts)], axis=1)  # (K, m)
        else:
            scores = (V @ (R.T @ w))[:, None]
        flat = int(np.argmax(scores.reshape(-1) >= scores.max() - TIE * w_1 * v_max))  # the first winner
        k, i = np.unravel_index(flat, scores.shape)
        s = lowest(w) - (Rs[i] @ V[k] + ts[i])
        norm = math.sqrt(w @ w)
        lb = float(w @ s) / norm
        return lb - 32 * u * (float(np.abs(w) @ np.abs(s)) / norm + abs(lb) + v_max) - 2 * TIE * v_max, s

    c = np.mean([Ri @ centre + ti for Ri, ti in zip(Rs, ts)], axis=0) if union else R @ centre + t
    best, s = bound(seed(c))
    Y = np.zeros((4, 3))
    Y[0] = s
    active = np.array([True, False, False, False])
    w = s
    for _ in range(iterations):
        lb, s = bound(w)
        best = max(best, lb)
        if active.all():
            continue
        slot = int(np.argmax(~active))
        Y[slot] = s
        active[slot] = True
        w, lam = _nearest_in_simplex_np(Y, active)
        active = lam > 0
    return best, (0.0 if active.all() else math.sqrt(float(w @ w)))
