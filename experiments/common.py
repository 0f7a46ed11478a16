"""What the Stage B drivers share: paths, the protocol file, the output layout, one schema per
table, CSV helpers.

Every stage module (:mod:`~experiments.generate`, :mod:`~experiments.audit`,
:mod:`~experiments.timing`, :mod:`~experiments.tables`, :mod:`~experiments.figures`) imports
this module, so it is part of every stage's code fingerprint (:mod:`experiments.fingerprints`):
it holds no computation, and imports nothing of the library beyond atomic writes.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import re
from pathlib import Path
from typing import Sequence

ROOT = Path(__file__).resolve().parent.parent
CONFIG_PATH = ROOT / "configs" / "stageB.yaml"
"""The frozen Stage B protocol."""

METHODS = ("larc", "fine", "coarse")
"""The certification methods Stage B compares (LARC and the two fixed-resolution baselines)."""
VARIANTS = ("ompl_planned", "direct_smoothstep")
"""The two trajectories of each start-goal pair."""
OUTCOMES = ("accepted", "invalid_start", "invalid_goal", "planning_failure", "hermite_recheck_failure")
"""Outcomes of a generation attempt."""
AUDIT_FIELDS = ("traj_id", "scene", "audit_states", "audit_collision", "audit_collision_states",
                "first_collision_t", "collision_contacts", "self_collision", "self_collision_states",
                "first_self_collision_t", "self_contacts", "key")
"""Columns of an audit table (one row per trajectory): the one schema of ``audit/audit.csv`` and
of ``python -m experiments.audit``. Times are seconds from the first waypoint; contacts are
``link~box`` (scene) or ``link~link`` (self), the first found; ``key`` is the hash of the
audit's inputs (reuse check). No wall times: auditing the same inputs writes the same bytes."""
SCENE_LABELS = {"open": "Open", "easy_window": "Easy window", "medium_window": "Medium window",
                "easy_shelf": "Easy shelf"}
TRAJ_RE = re.compile(rf"^(?P<pair>(?P<scene>.+)_p(?P<num>\d+))_(?P<variant>{'|'.join(VARIANTS)})$")
"""Trajectory ids: ``<scene>_p<NN>_<variant>``."""

__all__ = ["ROOT", "CONFIG_PATH", "METHODS", "VARIANTS", "OUTCOMES", "AUDIT_FIELDS", "SCENE_LABELS", "TRAJ_RE",
           "Layout", "load_config", "resolve", "scene_paths", "scene_label", "dataset_index", "read_csv",
           "write_csv", "csv_text"]


def load_config(path: str | Path = CONFIG_PATH) -> dict:
    """Parse the protocol file (a mapping with ``scenes``)."""
    import yaml

    path = Path(path)
    doc = yaml.safe_load(path.read_text())
    if not isinstance(doc, dict) or "scenes" not in doc:
        raise ValueError(f"{path}: expected a mapping with 'scenes'")
    return doc


def resolve(path: str | Path) -> Path:
    """A path of the protocol file: absolute, or relative to the repository root."""
    p = Path(path)
    return p if p.is_absolute() else ROOT / p


def scene_paths(config: dict) -> dict[str, Path]:
    """Scene name → scene file, in the protocol's order."""
    order = config.get("scene_order") or list(config["scenes"])
    return {s: resolve(config["scenes"][s]["file"]) for s in order}


def scene_label(scene: str) -> str:
    return SCENE_LABELS.get(scene, scene.replace("_", " ").capitalize())


@dataclasses.dataclass(frozen=True)
class Layout:
    """Where every stage reads and writes, under one output folder."""

    out: Path

    @property
    def dataset(self) -> Path:
        return self.out / "dataset"

    @property
    def trajectories_dir(self) -> Path:
        return self.dataset / "trajectories"

    @property
    def attempts_csv(self) -> Path:
        return self.dataset / "attempts.csv"

    @property
    def audit_csv(self) -> Path:
        return self.out / "audit" / "audit.csv"

    @property
    def cert_dir(self) -> Path:
        return self.out / "certification"

    @property
    def cert_results_csv(self) -> Path:
        return self.cert_dir / "results.csv"

    @property
    def cert_levels_csv(self) -> Path:
        return self.cert_dir / "larc_levels.csv"

    @property
    def cert_batch_csv(self) -> Path:
        return self.cert_dir / "batch_timing.csv"

    @property
    def timing_dir(self) -> Path:
        return self.out / "timing"

    @property
    def timing_raw_csv(self) -> Path:
        return self.timing_dir / "raw.csv"

    @property
    def timing_summary_csv(self) -> Path:
        return self.timing_dir / "per_trajectory.csv"

    @property
    def trajectories_csv(self) -> Path:
        return self.out / "trajectories.csv"

    @property
    def figures_dir(self) -> Path:
        return self.out / "figures"

    @property
    def stages_dir(self) -> Path:
        return self.out / "_stages"


def dataset_index(layout: Layout, config: dict) -> list[dict]:
    """Trajectory files of the dataset: one dict per file (traj_id, scene, pair_id, variant,
    path), scenes in the configured order, then by id."""
    rows = []
    for scene in scene_paths(config):
        for p in sorted((layout.trajectories_dir / scene).glob("*.yaml")):
            m = TRAJ_RE.match(p.stem)
            if m and m["scene"] == scene:
                rows.append(dict(traj_id=p.stem, scene=scene, pair_id=m["pair"], variant=m["variant"], path=p))
    return rows


def csv_text(rows: Sequence[dict], fields: Sequence[str] | None = None) -> str:
    """CSV text of ``rows`` (columns ``fields``, default the first row's keys; missing cells
    empty, ``None`` empty, other keys ignored)."""
    fields = list(fields or (rows[0].keys() if rows else []))
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n", extrasaction="ignore")
    w.writeheader()
    for r in rows:
        w.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in fields})
    return buf.getvalue()


def write_csv(path: Path, rows: Sequence[dict], fields: Sequence[str] | None = None) -> None:
    """Write :func:`csv_text` atomically."""
    from larc_jax.io import atomic_write_text

    atomic_write_text(path, csv_text(rows, fields))


def read_csv(path: Path) -> list[dict]:
    """Rows of a CSV file as dicts of strings; [] if the file does not exist."""
    if not Path(path).is_file():
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))
