"""Certification results: leaves, per-trajectory and per-dataset results, pandas export.

A :class:`DatasetResult` is *columnar*: one NumPy array per per-trajectory quantity and a
:class:`LeafTable` (one array per leaf field) for every leaf of every trajectory, so a dataset
of 10^5 trajectories with millions of leaves holds a few dozen arrays, not millions of Python
objects. :class:`TrajectoryResult` and :class:`Leaf` objects are built only when asked for
(``result[i]``, iteration, ``result[i].leaves``).

A result carries the parameters that produced it (the margin ρ, the depth, the method, the
rounding guard): one owner per parameter, so a reader (``explain``, the JSON writer) never
takes them again from elsewhere.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import TYPE_CHECKING, Sequence

import numpy as np

from ..leaf.record import LeafColumn, Stage

if TYPE_CHECKING:
    from ..run_spec import RunSpec

__all__ = ["Leaf", "LeafTable", "RunAssumptions", "TrajectoryResult", "DatasetResult", "LEAF_COLUMNS", "RESULT_COLUMNS",
           "STAGES"]

STAGES = tuple(Stage(i).label for i in range(len(Stage)))
"""Which test passed a leaf, by code (:class:`~larc_jax.leaf.record.Stage`): 0 none (not certified), 1
the capsule test, 2 the hull test of the cascade (larc_jax.leaf.cascade)."""

LEAF_COLUMNS = tuple(c.value for c in LeafColumn)
"""Columns of :meth:`DatasetResult.leaves_dataframe` (and of ``larc certify --leaves``)."""

RESULT_COLUMNS = ("id", "scene", "method", "certified", "evaluations", "min_clearance_m", "guard_m", "duration_s",
                  "blocked_t0", "blocked_t1", "blocked_capsule", "blocked_box", "blocked_other_capsule")
"""Columns of :meth:`DatasetResult.to_dataframe`."""


@dataclasses.dataclass(frozen=True)
class Leaf:
    """A terminal interval of the certificate tree."""

    depth: int
    index: int
    """Position among the ``2**depth`` intervals of that depth."""
    t0: float
    """Start, s, in the trajectory's own time axis (the leaves tile its horizon exactly)."""
    t1: float
    clearance_m: float
    """g of the recorded capsule/box pair, m (inf without boxes, nan on non-finite values)."""
    guard_m: float
    """Rounding guard of that pair, m: ``certified == (clearance_m > guard_m)``."""
    certified: bool
    capsule: str
    """The recorded pair: the one minimising clearance - guard over all pairs."""
    box: str
    other_capsule: str = ""
    """With the self-collision test: the second capsule when the recorded pair is a capsule pair
    (then ``box`` is ''); '' for a capsule/box pair."""
    stage: str = ""
    """Which test passed the leaf: ``capsule``, ``hull`` (larc_jax.leaf.cascade), or ``""`` (none)."""


@dataclasses.dataclass(frozen=True)
class LeafTable:
    """Leaves as columns (NumPy arrays of one length), sorted by trajectory, then time.

    ``capsule`` indexes the result's ``capsule_names`` and ``box`` its ``box_names`` (-1: no
    pair, i.e. a scene without boxes, or a self-collision pair); ``other_capsule`` the second
    capsule of a self-collision pair (-1: a capsule/box pair).
    """

    traj: np.ndarray
    """int64 index of the leaf's trajectory in its :class:`DatasetResult`."""
    depth: np.ndarray
    index: np.ndarray
    t0: np.ndarray
    t1: np.ndarray
    clearance_m: np.ndarray
    guard_m: np.ndarray
    """Rounding guard of the recorded pair: ``certified == (clearance_m > guard_m)``."""
    certified: np.ndarray
    capsule: np.ndarray
    box: np.ndarray
    other_capsule: np.ndarray
    stage: np.ndarray
    """int8 index into :data:`STAGES`: 0 none, 1 capsule test, 2 hull test, 4 swept test."""

    def __len__(self) -> int:
        return len(self.traj)

    @staticmethod
    def concatenate(parts: Sequence["LeafTable"]) -> "LeafTable":
        """One table from several, sorted by (trajectory, t0)."""
        cols = {f.name: np.concatenate([getattr(p, f.name) for p in parts]) if parts else np.zeros(0)
                for f in dataclasses.fields(LeafTable)}
        order = np.lexsort((cols["t0"], cols["traj"]))
        return LeafTable(**{k: v[order] for k, v in cols.items()})


@dataclasses.dataclass(frozen=True, kw_only=True)
class RunAssumptions:
    """What a run assumed, as its results (:class:`TrajectoryResult`, :class:`DatasetResult`)
    carry it: keyword-only fields, after each result's own."""

    excluded_links: tuple[str, ...] = ()
    """Links left out of the certificate (:meth:`~larc_jax.enclosure.CapsuleModel.without_links`)."""
    enclosure: str = "capsules"
    """``capsules`` or ``hull`` (the cascade of :mod:`larc_jax.leaf.cascade`): which enclosures
    the certificate used."""
    tracking_tolerance: tuple[tuple[str, float], ...] = ()
    """(active joint, delta_j) the certificate allows as tracking error, rad or m
    (:mod:`larc_jax.enclosure.tracking`); empty: it covers the planned trajectory only."""
    self_margin_m: float | None = None
    """With the self-collision test (:mod:`larc_jax.leaf.self_collision`): its margin rho_self, m;
    None: the certificate says nothing about self-collision."""
    self_skipped: tuple[tuple[str, str, str], ...] = ()
    """With the self-collision test: the link pairs not checked, and why."""
    spec: "RunSpec | None" = None
    """The :class:`~larc_jax.run_spec.RunSpec` that produced the result (its model fields those
    of the robot and capsules certified; ``explain`` re-evaluates with it); None for a result
    built by hand. The loose fields (``method``, ``margin_m``...) are its values as the result's
    readers take them."""

    @property
    def padding_m(self) -> float:
        """The padding the run added to every enclosure on top of its proven containment, m
        (``spec.padding_m``; NaN for a result built by hand without a spec)."""
        return float("nan") if self.spec is None else self.spec.padding_m


@dataclasses.dataclass(frozen=True)
class TrajectoryResult(RunAssumptions):
    id: str
    method: str
    certified: bool
    evaluations: int
    frontier_sizes: tuple[int, ...]
    """Intervals evaluated at each depth 0..max_depth."""
    min_clearance_m: float
    """Smallest g(I) over the leaves, m (> 0 iff certified, up to the rounding guard)."""
    leaves: tuple[Leaf, ...]
    duration_s: float
    scene: str = ""
    margin_m: float = float("nan")
    """The margin ρ the certificate used, m."""
    max_depth: int = -1
    """The deepest bisection allowed."""
    guard_m: float = float("nan")
    """The largest rounding guard of this trajectory (over its capsules), m; each leaf records
    the one it was compared against."""
    time_offset_s: float = 0.0
    """Offset subtracted (exactly) from every time before evaluation (budget T1), s."""
    @property
    def first_inconclusive(self) -> Leaf | None:
        bad = [leaf for leaf in self.leaves if not leaf.certified]
        return min(bad, key=lambda leaf: leaf.t0) if bad else None


@dataclasses.dataclass(frozen=True)
class DatasetResult(RunAssumptions):
    """Results of one certification call, columnar (module docstring)."""

    method: str
    ids: tuple[str, ...]
    scene_names: tuple[str, ...]
    certified: np.ndarray
    """(N,) bool."""
    evaluations: np.ndarray
    """(N,) int64 intervals evaluated."""
    frontier: np.ndarray
    """(N, D + 1) int64 intervals evaluated per depth."""
    min_clearance_m: np.ndarray
    """(N,) smallest leaf clearance g(I), m (NaN if any leaf is NaN)."""
    duration_s: np.ndarray
    """(N,) trajectory durations, s."""
    guard_m: np.ndarray
    """(N,) largest rounding guard of each trajectory (over its capsules), m; each leaf
    records the one it was compared against."""
    leaves: LeafTable
    capsule_names: tuple[str, ...]
    box_names: tuple[str, ...]
    margin_m: float
    max_depth: int
    wall_time_s: float
    """Seconds the whole call took, compilation included."""
    time_offset_s: np.ndarray | None = None
    """(N,) offset subtracted (exactly) from each trajectory's times (budget T1), s; None: 0."""
    compile_time_s: float = 0.0
    """Of ``wall_time_s``, seconds JAX spent tracing, lowering and compiling kernels (or loading
    them from the persistent cache, :mod:`larc_jax.compilation`)."""
    held_joints: tuple = ()
    """What the certificate assumes about every held joint (the gripper): ``(joint, state, lo,
    hi)`` with state ``stated`` (held at lo == hi, as the user said), ``stroke`` (anywhere in
    [lo, hi]: enclosed over the whole stroke) or ``held`` (a held revolute joint, at lo == hi)."""
    dtype: str = "float64"
    """Geometry dtype of the run (``certify(dtype=...)``; the guard accounts for it)."""

    # -- per-trajectory access ---------------------------------------------------------------

    @functools.cached_property
    def _leaf_bounds(self) -> np.ndarray:
        return np.searchsorted(self.leaves.traj, np.arange(len(self.ids) + 1))

    def leaf_slice(self, i: int) -> slice:
        """Rows of :attr:`leaves` that belong to trajectory ``i``."""
        lo, hi = self._leaf_bounds[i], self._leaf_bounds[i + 1]
        return slice(int(lo), int(hi))

    def _leaf(self, row: int) -> Leaf:
        lv = self.leaves
        c, b, o = int(lv.capsule[row]), int(lv.box[row]), int(lv.other_capsule[row])
        return Leaf(depth=int(lv.depth[row]), index=int(lv.index[row]), t0=float(lv.t0[row]),
                    t1=float(lv.t1[row]), clearance_m=float(lv.clearance_m[row]),
                    guard_m=float(lv.guard_m[row]), certified=bool(lv.certified[row]),
                    capsule=self.capsule_names[c] if c >= 0 else "", box=self.box_names[b] if b >= 0 else "",
                    other_capsule=self.capsule_names[o] if o >= 0 else "", stage=STAGES[int(lv.stage[row])])

    def trajectory(self, i: int) -> TrajectoryResult:
        """The :class:`TrajectoryResult` of trajectory ``i`` (built on demand)."""
        sl = self.leaf_slice(i)
        return TrajectoryResult(
            id=self.ids[i], method=self.method, certified=bool(self.certified[i]),
            evaluations=int(self.evaluations[i]), frontier_sizes=tuple(int(x) for x in self.frontier[i]),
            min_clearance_m=float(self.min_clearance_m[i]),
            leaves=tuple(self._leaf(r) for r in range(sl.start, sl.stop)),
            duration_s=float(self.duration_s[i]), scene=self.scene_names[i], margin_m=self.margin_m,
            max_depth=self.max_depth, guard_m=float(self.guard_m[i]), enclosure=self.enclosure,
            time_offset_s=0.0 if self.time_offset_s is None else float(self.time_offset_s[i]),
            excluded_links=self.excluded_links, tracking_tolerance=self.tracking_tolerance,
            self_margin_m=self.self_margin_m, self_skipped=self.self_skipped, spec=self.spec,
        )

    @functools.cached_property
    def trajectories(self) -> tuple[TrajectoryResult, ...]:
        return tuple(self.trajectory(i) for i in range(len(self.ids)))

    @property
    def frontier_sizes(self) -> tuple[int, ...]:
        """Dataset frontier size per depth (sum over trajectories)."""
        return tuple(int(x) for x in self.frontier.sum(axis=0))

    def __iter__(self):
        return iter(self.trajectories)

    def __len__(self) -> int:
        return len(self.ids)

    def __getitem__(self, i) -> TrajectoryResult:
        return self.trajectories[i]

    # -- columnar export ---------------------------------------------------------------------

    def first_inconclusive_rows(self) -> np.ndarray:
        """(N,) row in :attr:`leaves` of each trajectory's earliest uncertified leaf (-1: none)."""
        lv = self.leaves
        rows = np.full(len(self.ids), -1, np.int64)
        bad = np.flatnonzero(~lv.certified)
        # Leaves are sorted by (trajectory, t0): the first bad row per trajectory is the earliest.
        traj, first = np.unique(lv.traj[bad], return_index=True)
        rows[traj] = bad[first]
        return rows

    def to_dataframe(self):
        """One row per trajectory (pandas; columns :data:`RESULT_COLUMNS`)."""
        import pandas as pd

        rows = self.first_inconclusive_rows()
        has = rows >= 0
        r = np.where(has, rows, 0)
        lv = self.leaves
        names = np.array(("",) + self.capsule_names, dtype=object)
        boxes = np.array(("",) + self.box_names, dtype=object)
        take = (lambda col: col[r]) if len(lv) else (lambda col: np.zeros(len(r), col.dtype))
        return pd.DataFrame({
            "id": list(self.ids), "scene": list(self.scene_names), "method": self.method,
            "certified": self.certified.astype(bool), "evaluations": self.evaluations.astype(np.int64),
            "min_clearance_m": self.min_clearance_m, "guard_m": self.guard_m, "duration_s": self.duration_s,
            "blocked_t0": np.where(has, take(lv.t0), np.nan), "blocked_t1": np.where(has, take(lv.t1), np.nan),
            "blocked_capsule": np.where(has, names[take(lv.capsule) + 1], ""),
            "blocked_box": np.where(has, boxes[take(lv.box) + 1], ""),
            "blocked_other_capsule": np.where(has, names[take(lv.other_capsule) + 1], ""),
        }, columns=list(RESULT_COLUMNS))

    def leaves_dataframe(self):
        """Every leaf of every trajectory (pandas; columns :data:`LEAF_COLUMNS`)."""
        import pandas as pd

        lv = self.leaves
        names = np.array(("",) + self.capsule_names, dtype=object)
        boxes = np.array(("",) + self.box_names, dtype=object)
        return pd.DataFrame({
            "id": np.array(self.ids, dtype=object)[lv.traj] if len(lv) else np.zeros(0, object),
            "depth": lv.depth.astype(np.int64), "index": lv.index.astype(np.int64),
            "t0": lv.t0, "t1": lv.t1, "clearance_m": lv.clearance_m, "guard_m": lv.guard_m,
            "certified": lv.certified.astype(bool),
            "capsule": names[lv.capsule + 1], "box": boxes[lv.box + 1], "other_capsule": names[lv.other_capsule + 1],
            "stage": np.array(STAGES, dtype=object)[lv.stage.astype(np.int64)] if len(lv) else np.zeros(0, object),
        }, columns=list(LEAF_COLUMNS))
