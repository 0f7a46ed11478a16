"""Certification results: leaves, per-trajectory and per-dataset results, pandas export.

A result carries the parameters that produced it (the margin ρ, the depth, the method, the
rounding guard): one owner per parameter, so a reader (``explain``, the JSON writer) never
takes them again from elsewhere.
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["Leaf", "TrajectoryResult", "DatasetResult", "LEAF_COLUMNS"]

LEAF_COLUMNS = ("id", "depth", "index", "t0", "t1", "clearance_m", "certified", "capsule", "box")
"""Columns of :meth:`DatasetResult.leaves_dataframe` (and of ``larc certify --leaves``)."""


@dataclasses.dataclass(frozen=True)
class Leaf:
    """A terminal interval of the certificate tree."""

    depth: int
    index: int
    """Position among the ``2**depth`` intervals of that depth."""
    t0: float
    t1: float
    clearance_m: float
    """g(I), m (inf without boxes, nan on non-finite values)."""
    certified: bool
    capsule: str
    box: str


@dataclasses.dataclass(frozen=True)
class TrajectoryResult:
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
    """The rounding guard every leaf's clearance was compared against, m."""

    @property
    def first_inconclusive(self) -> Leaf | None:
        bad = [leaf for leaf in self.leaves if not leaf.certified]
        return min(bad, key=lambda leaf: leaf.t0) if bad else None


@dataclasses.dataclass(frozen=True)
class DatasetResult:
    method: str
    trajectories: tuple[TrajectoryResult, ...]
    frontier_sizes: tuple[int, ...]
    """Dataset frontier size per depth (sum over trajectories)."""
    margin_m: float
    max_depth: int
    wall_time_s: float

    def __iter__(self):
        return iter(self.trajectories)

    def __len__(self) -> int:
        return len(self.trajectories)

    def __getitem__(self, i) -> TrajectoryResult:
        return self.trajectories[i]

    def to_dataframe(self):
        """One row per trajectory (pandas)."""
        import pandas as pd

        rows = []
        for r in self.trajectories:
            bad = r.first_inconclusive
            rows.append(dict(
                id=r.id, scene=r.scene, method=r.method, certified=r.certified,
                evaluations=r.evaluations, min_clearance_m=r.min_clearance_m,
                duration_s=r.duration_s,
                blocked_t0=bad.t0 if bad else np.nan, blocked_t1=bad.t1 if bad else np.nan,
                blocked_capsule=bad.capsule if bad else "", blocked_box=bad.box if bad else "",
            ))
        return pd.DataFrame(rows)

    def leaves_dataframe(self):
        """Every leaf of every trajectory (pandas; columns :data:`LEAF_COLUMNS`)."""
        import pandas as pd

        rows = [dict(id=r.id, **dataclasses.asdict(leaf)) for r in self.trajectories for leaf in r.leaves]
        return pd.DataFrame(rows, columns=list(LEAF_COLUMNS))
