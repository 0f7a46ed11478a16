"""Certify a manifest of files into a resumable Parquet dataset (``larc certify --manifest``).

A manifest is a CSV file with a header holding the columns ``trajectory`` and ``scene`` (paths
relative to the manifest's folder; an optional ``id`` column names the trajectory, default the
trajectory path as written); any other column is an error naming it. Rows are taken in chunks of ``chunk_size``; chunk ``k`` (rows
``k*C .. k*C + C - 1``) is certified in one call and written as ``part-<k>.parquet`` into the
results folder (and, with ``leaves``, into the leaves folder) — each a Parquet *dataset*
(a folder of part files that ``pandas.read_parquet(folder)`` reads as one table).

Resuming. Every part is written atomically (a temporary file, then a rename), the leaves part
before the results part, so a results part exists only when its chunk is complete. A rerun
with the same manifest (same SHA-256), robot, run spec (:class:`~larc_jax.run_spec.RunSpec`) and chunk size skips the chunks whose
results part exists and computes the rest: a killed run loses at most the chunks in flight and
never duplicates a row. A rerun with anything different is refused (naming what differs)
rather than mixing results. The state (``_larc_manifest.json`` in the results folder) records
all of it, the spec as :meth:`~larc_jax.run_spec.RunSpec.to_dict` writes it.

Bad rows. A row whose trajectory or scene file is missing or invalid does not stop the run:
its result row has ``certified = False`` and the one-line message in ``error``; the command
line then exits with status 2 after writing everything. Memory is bounded by the chunk size
and the manifest's text (read once, at most :data:`~larc_jax.io.MAX_INPUT_BYTES`, then parsed
as a stream; parsed scenes are cached per chunk).

The chunk function :func:`certify_chunk` is what runs everywhere: in this process
(:func:`certify_manifest`) or on Dask workers (:mod:`larc_jax.drivers.distributed`), so both give
identical results.
"""

from __future__ import annotations

import csv
import dataclasses
import functools
import hashlib
import io
import itertools
import json
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from ..defaults import DEFAULT_CHUNK_SIZE
from ..errors import LarcInputError
from ..io import atomic_write_bytes, atomic_write_json, check_keys, read_input_text
from ..run_spec import RunSpec
from .stream import chunked

__all__ = [
    "ManifestRow", "ManifestJob", "iter_manifest", "certify_manifest", "certify_chunk", "pending_chunks",
    "new_total", "add_summary", "MANIFEST_RESULT_COLUMNS",
]

STATE_FILE = "_larc_manifest.json"
MANIFEST_RESULT_COLUMNS = ("row", "id", "trajectory", "scene", "certified", "evaluations", "min_clearance_m",
                           "guard_m", "duration_s", "method", "enclosure", "margin_m", "padding_m", "swept",
                           "max_depth", "blocked_t0", "blocked_t1",
                           "blocked_capsule", "blocked_box", "error")
"""Columns of a manifest results dataset: one row per manifest row."""


@dataclasses.dataclass(frozen=True)
class ManifestRow:
    row: int
    """0-based data row of the manifest (the header is not counted)."""
    line: int
    """Line number in the manifest file (for messages)."""
    id: str
    trajectory: Path
    scene: Path


def _sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


_MANIFEST_COLUMNS = ("trajectory", "scene", "id")


def iter_manifest(path: str | Path) -> Iterator[ManifestRow]:
    """The rows of a manifest, parsed as a stream from its text (read once: a FIFO, device or
    a file swapped after a check is never opened again)."""
    path = Path(path)
    text = read_input_text(path, "manifest")  # missing, not a regular file, binary: one clear line
    folder = path.parent
    with io.StringIO(text, newline="") as f:
        reader = csv.reader(f, skipinitialspace=True)
        header = None
        row = 0
        try:
            for cells in reader:
                if not cells or all(not c.strip() for c in cells) or cells[0].lstrip().startswith("#"):
                    continue
                if header is None:
                    header = [c.strip() for c in cells]
                    missing = [c for c in ("trajectory", "scene") if c not in header]
                    if missing:
                        raise LarcInputError(
                            f"{path}:{reader.line_num}: manifest header needs the columns trajectory and scene "
                            f"(missing {missing}; found {header})")
                    check_keys(header, _MANIFEST_COLUMNS, f"{path}:{reader.line_num}", "header", kind="column")
                    col = {c: header.index(c) for c in ("trajectory", "scene")}
                    col_id = header.index("id") if "id" in header else None
                    continue
                if len(cells) != len(header):
                    raise LarcInputError(
                        f"{path}:{reader.line_num}: row has {len(cells)} cells, the header has {len(header)}")
                traj, scene = cells[col["trajectory"]].strip(), cells[col["scene"]].strip()
                for name, value in (("trajectory", traj), ("scene", scene)):
                    if not value:
                        raise LarcInputError(f"{path}:{reader.line_num}: column '{name}' is empty")
                rid = cells[col_id].strip() if col_id is not None else traj
                yield ManifestRow(row=row, line=reader.line_num, id=rid or traj,
                                  trajectory=folder / traj, scene=folder / scene)
                row += 1
        except csv.Error as exc:
            raise LarcInputError(f"{path}:{reader.line_num}: not valid CSV ({exc})") from None
    if header is None:
        raise LarcInputError(f"{path}: manifest is empty (expected a header row: trajectory,scene)")


@dataclasses.dataclass(frozen=True)
class ManifestJob:
    """Everything a chunk needs (picklable: sent to Dask workers)."""

    out: str
    """Results dataset folder."""
    leaves: str | None
    """Leaves dataset folder, or None."""
    robot_file: str | None
    """Robot file (``larc fit-capsules``), or None for PIPER."""
    spec: RunSpec = RunSpec()
    """The run's parameters (validated when built); its model fields (``hold``, ``joints``,
    ``ignore_links``) say how the robot file is loaded."""
    chunk_size: int = DEFAULT_CHUNK_SIZE

    def check(self) -> None:
        if not isinstance(self.spec, RunSpec):
            raise LarcInputError(f"ManifestJob.spec must be a RunSpec, got {type(self.spec).__name__}")
        if isinstance(self.chunk_size, bool) or not isinstance(self.chunk_size, int) or self.chunk_size < 1:
            raise LarcInputError(f"chunk size {self.chunk_size!r}: must be an integer >= 1")


def part_name(k: int) -> str:
    return f"part-{k:06d}.parquet"


@functools.lru_cache(maxsize=4)
def _model(robot_file: str | None, sha256: str | None, hold: tuple, joints: tuple):
    """Robot and capsules, loaded once per process (and reloaded if the file's content changes)."""
    from ..enclosure.robot_file import load_robot_file

    return load_robot_file(robot_file, hold=dict(hold), active_joints=list(joints) or None)


def _load_model(job: ManifestJob):
    from ..model.urdf import file_sha256

    sha256 = None if job.robot_file is None else file_sha256(job.robot_file)
    return _model(job.robot_file, sha256, job.spec.hold, job.spec.joints)


def certify_chunk(job: ManifestJob, k: int, rows: list[ManifestRow],
                  progress: Callable[[int], None] | None = None) -> dict:
    """Certify chunk ``k`` (its manifest rows) and write its part files atomically
    (``progress`` as for :func:`~larc_jax.engine.certify.certify`).

    Returns a summary ``{chunk, rows, certified, errors, evaluations, first_error}``.
    """
    import pandas as pd

    from ..engine.certify import certify
    from ..model.scene import read_scene
    from ..model.trajectory_files import read_trajectory

    robot, capsules = _load_model(job)
    spec = job.spec
    capsules = capsules.without_links(robot, spec.ignore_links, what="--ignore-link")
    scenes: dict[Path, object] = {}
    good, errors = [], {}
    items = []
    for r in rows:
        try:
            if r.scene not in scenes:
                scenes[r.scene] = read_scene(r.scene, frame=robot.link_names[0])
            traj = read_trajectory(r.trajectory, robot, velocities=spec.velocities)
            items.append((dataclasses.replace(traj, id=r.id), scenes[r.scene]))
            good.append(r)
        except LarcInputError as exc:
            errors[r.row] = str(exc)
    frame = None
    leaves_frame = None
    if items:
        res = certify([t for t, _ in items], [s for _, s in items], robot, capsules, spec=spec, progress=progress)
        frame = res.to_dataframe()
        frame.insert(0, "row", np.array([r.row for r in good], np.int64))
        frame["trajectory"] = [str(r.trajectory) for r in good]
        frame["scene"] = [str(r.scene) for r in good]
        if job.leaves:
            leaves_frame = res.leaves_dataframe()
            leaves_frame.insert(0, "row", np.array([r.row for r in good], np.int64)[res.leaves.traj])
    bad = [r for r in rows if r.row in errors]
    bad_frame = pd.DataFrame({
        "row": np.array([r.row for r in bad], np.int64), "id": [r.id for r in bad],
        "trajectory": [str(r.trajectory) for r in bad], "scene": [str(r.scene) for r in bad],
        "certified": np.zeros(len(bad), bool), "evaluations": np.zeros(len(bad), np.int64),
        "min_clearance_m": np.full(len(bad), np.nan), "duration_s": np.full(len(bad), np.nan),
    })
    out = pd.concat([f for f in (frame, bad_frame) if f is not None and len(f)], ignore_index=True) \
        if (frame is not None and len(frame)) or len(bad_frame) else bad_frame
    for col in ("method", "enclosure", "margin_m", "padding_m", "swept", "max_depth"):
        out[col] = getattr(spec, col)
    out["error"] = [errors.get(int(r), "") for r in out["row"]]
    for col, fill in (("guard_m", np.nan), ("blocked_t0", np.nan), ("blocked_t1", np.nan), ("blocked_capsule", ""),
                      ("blocked_box", "")):
        if col not in out:
            out[col] = fill
        out[col] = out[col].fillna(fill)
    out = out.sort_values("row", kind="stable")[list(MANIFEST_RESULT_COLUMNS)].reset_index(drop=True)
    if job.leaves:
        if leaves_frame is None:
            from ..engine.results import LEAF_COLUMNS

            leaves_frame = pd.DataFrame({c: [] for c in ("row",) + LEAF_COLUMNS})
        atomic_write_bytes(Path(job.leaves) / part_name(k), _parquet_bytes(leaves_frame))
    atomic_write_bytes(Path(job.out) / part_name(k), _parquet_bytes(out))  # last: marks the chunk done
    first_error = next((f"{errors[r.row]}" for r in rows if r.row in errors), "")
    return dict(chunk=k, rows=len(rows), certified=int(out["certified"].sum()), errors=len(errors),
                evaluations=int(out["evaluations"].sum()), first_error=first_error)


def _parquet_bytes(frame) -> bytes:
    buf = io.BytesIO()
    frame.to_parquet(buf, index=False)
    return buf.getvalue()


def _state(job: ManifestJob, manifest: Path) -> dict:
    robot_sha = _sha256_file(Path(job.robot_file)) if job.robot_file else None
    if job.robot_file is None:
        from ..enclosure.robot_file import default_capsule_path

        robot_sha = _sha256_file(default_capsule_path())
    return {
        "manifest": str(manifest.resolve()), "manifest_sha256": _sha256_file(manifest),
        "robot_file": job.robot_file, "robot_sha256": robot_sha, "chunk_size": job.chunk_size,
        "leaves": job.leaves is not None, "spec": job.spec.to_dict(),
    }


def _differences(old: dict, state: dict) -> list[str]:
    """What a results folder's state ``old`` says differently from ``state`` (spec fields by name)."""
    diff = sorted(k for k in state if old.get(k) != state[k] and k not in ("manifest", "spec"))
    if old.get("spec") != state["spec"]:
        try:
            diff += [f"spec.{k}" for k in RunSpec.from_dict(old.get("spec"), STATE_FILE).differences(
                RunSpec.from_dict(state["spec"]))]
        except LarcInputError:  # a state written before run specs, or edited by hand
            diff.append("spec")
        missing = sorted(set(state["spec"]) - set(old.get("spec") or {}))
        if missing and not diff:  # written before these fields were stated (their defaults then may differ)
            diff += [f"spec.{k}" for k in missing]
    return diff


def pending_chunks(manifest: str | Path, job: ManifestJob) -> tuple[Iterator[tuple[int, list[ManifestRow]]], int]:
    """Check/write the results folder's state and return the chunks still to do (a lazy
    iterator of ``(k, rows)``) and the number of chunks already done. Refuses a folder written
    for another manifest, robot or parameters."""
    manifest = Path(manifest)
    job.check()
    out = Path(job.out)
    if out.exists() and not out.is_dir():
        raise LarcInputError(f"--out {out}: exists and is not a folder (a Parquet dataset is a folder of parts)")
    if job.leaves and Path(job.leaves).exists() and not Path(job.leaves).is_dir():
        raise LarcInputError(f"--leaves {job.leaves}: exists and is not a folder")
    rows = iter_manifest(manifest)
    first = next(rows, None)  # a bad header or first row is refused before anything is written
    state = _state(job, manifest)
    state_path = out / STATE_FILE
    if state_path.exists():
        old = json.loads(state_path.read_text())
        diff = _differences(old, state)
        if diff:
            raise LarcInputError(
                f"{out}: holds results for another run (different {', '.join(diff)}); remove the folder "
                f"or write to another --out")
    else:
        stray = sorted(out.glob("part-*.parquet")) if out.is_dir() else []
        if stray:
            raise LarcInputError(f"{out}: holds part files but no {STATE_FILE}; remove it or choose another --out")
        atomic_write_json(state_path, state)
    if job.leaves:
        Path(job.leaves).mkdir(parents=True, exist_ok=True)
    done = {p.name for p in out.glob("part-*.parquet")}

    def todo():
        every = itertools.chain([first], rows) if first is not None else iter(())
        for k, chunk in enumerate(chunked(every, job.chunk_size)):
            if part_name(k) not in done:
                yield k, chunk

    return todo(), len(done)


def certify_manifest(manifest: str | Path, job: ManifestJob, on_chunk: Callable[[dict], None] | None = None,
                     progress: Callable[[int], None] | None = None, runner=None) -> dict:
    """Certify every pending chunk of ``manifest`` (module docstring): the one manifest loop.

    ``runner(job, todo)`` certifies the pending chunks ``todo`` (an iterator of ``(k, rows)``) and
    yields their summaries as they finish (default: one after the other in this process, with
    ``progress`` called with interval counts as for :func:`~larc_jax.engine.certify.certify`;
    :mod:`larc_jax.drivers.distributed` passes one that runs them on Dask). It is called only after the
    results folder's state was checked. ``on_chunk`` gets each chunk's summary.

    Returns ``{rows, certified, errors, evaluations, chunks_done, chunks_skipped, first_error}``:
    counts over the chunks computed now, and how many were already done.
    """
    todo, skipped = pending_chunks(manifest, job)
    total = new_total(skipped)
    summaries = runner(job, todo) if runner is not None else (
        certify_chunk(job, k, rows, progress=progress) for k, rows in todo)
    for summary in summaries:
        add_summary(total, summary)
        if on_chunk:
            on_chunk(summary)
    return total


def new_total(skipped: int) -> dict:
    return dict(rows=0, certified=0, errors=0, evaluations=0, chunks_done=0, chunks_skipped=skipped, first_error="")


def add_summary(total: dict, summary: dict) -> None:
    """Accumulate a chunk summary (from :func:`certify_chunk`) into ``total``."""
    for key in ("rows", "certified", "errors", "evaluations"):
        total[key] += summary[key]
    total["chunks_done"] += 1
    if summary["first_error"] and not total["first_error"]:
        total["first_error"] = summary["first_error"]
