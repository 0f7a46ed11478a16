"""Human- and machine-readable reports of a certification result: the terminal table, the
per-trajectory JSON document and the leaf table (Parquet or CSV bytes). Used by the command
line; usable from Python (:func:`table_lines`, :func:`result_json`, :func:`leaves_bytes`,
:func:`leaves_format`)."""

from __future__ import annotations

import io
import math
from pathlib import Path

from ..errors import LarcInputError
from ..engine.results import DatasetResult

__all__ = ["format_clearance", "table_lines", "result_json", "leaves_bytes", "leaves_format", "gripper_text"]


def gripper_text(result: DatasetResult) -> str:
    """What the certificate assumes about the held joints, in words (the table's last line)."""
    if not result.held_joints:
        return "no held joints"
    parts = []
    for name, state, lo, hi in result.held_joints:
        if state == "stroke":
            parts.append(f"{name} anywhere in [{lo:g}, {hi:g}] (no --hold: whole stroke enclosed)")
        else:
            parts.append(f"{name} = {lo:g} ({'stated' if state == 'stated' else 'held'})")
    return "gripper: " + ", ".join(parts)


def format_clearance(g: float) -> str:
    if g != g:
        return "nan"
    if g == float("inf"):
        return "inf (no boxes)"
    return f"{g * 1000:+.2f} mm"


def table_lines(result: DatasetResult) -> list[str]:
    """The terminal table: one row per trajectory, then a summary line."""
    width = max([len("trajectory")] + [len(r.id) for r in result])
    head = (f"{'trajectory':<{width}}  {'status':<11}  {'evals':>6}  {'min clearance':>14}  "
            "first inconclusive interval: time span, capsule / box")
    lines = [head]
    for r in result:
        bad = r.first_inconclusive
        other = f"{bad.other_capsule} (self)" if bad and bad.other_capsule else (bad.box or "-") if bad else ""
        blocked = f"t=[{bad.t0:.4f}, {bad.t1:.4f}] s  {bad.capsule or '-'} / {other}" if bad else ""
        lines.append(f"{r.id:<{width}}  {'CERTIFIED' if r.certified else 'UNCERTIFIED':<11}  "
                     f"{r.evaluations:>6}  {format_clearance(r.min_clearance_m):>14}  {blocked}".rstrip())
    n_ok = sum(r.certified for r in result)
    compiling = f" of which {result.compile_time_s:.2f} s compiling" if result.compile_time_s >= 0.005 else ""
    enclosure = "capsules then hulls" if result.enclosure == "hull" else "capsules"
    if result.spec is not None and result.spec.swept:
        enclosure += ", swept stage"
    lines.append(f"{n_ok} of {len(result)} certified ({result.method}, {enclosure}, margin {result.margin_m * 1000:g} mm, "
                 + (f"padding {result.padding_m * 1000:g} mm, " if math.isfinite(result.padding_m) else "") +
                 f"{sum(r.evaluations for r in result)} interval evaluations, {result.wall_time_s:.2f} s{compiling})")
    lines.append(gripper_text(result))
    if result.self_margin_m is not None:
        lines.append(f"self-collision checked (margin {result.self_margin_m * 1000:g} mm); link pairs not checked: "
                     + (", ".join(f"{a}:{b} ({why})" for a, b, why in result.self_skipped) or "none"))
    if result.tracking_tolerance:
        lines.append("the certificate allows a tracking error of " + ", ".join(
            f"{name} {x:g}" for name, x in result.tracking_tolerance) + " (rad; m for prismatic joints)")
    if result.excluded_links:
        lines.append(f"the certificate excludes links: {', '.join(result.excluded_links)} (never checked against "
                     "the boxes)")
    return lines


def result_json(result: DatasetResult, scene_path) -> dict:
    def num(x):
        return x if math.isfinite(x) else None

    return {
        "method": result.method, "enclosure": result.enclosure, "margin_m": result.margin_m,
        "padding_m": None if math.isnan(result.padding_m) else result.padding_m,
        "swept": None if result.spec is None else result.spec.swept,
        "max_depth": result.max_depth, "scene": str(scene_path), "excluded_links": list(result.excluded_links),
        "tracking_tolerance": dict(result.tracking_tolerance) or None,
        "self_collision": None if result.self_margin_m is None else {
            "margin_m": result.self_margin_m,
            "skipped_pairs": [{"a": a, "b": b, "reason": why} for a, b, why in result.self_skipped]},
        "wall_time_s": result.wall_time_s, "compile_time_s": result.compile_time_s,
        "held_joints": {name: ({"state": state, "value": lo} if state != "stroke" else
                               {"state": state, "range": [lo, hi]})
                        for name, state, lo, hi in result.held_joints},
        "frontier_sizes": list(result.frontier_sizes),
        "trajectories": [
            {"id": r.id, "certified": r.certified, "evaluations": r.evaluations,
             "frontier_sizes": list(r.frontier_sizes), "min_clearance_m": num(r.min_clearance_m),
             "guard_m": num(r.guard_m), "time_offset_s": r.time_offset_s,
             "leaves_by_stage": {stage: sum(leaf.stage == stage for leaf in r.leaves) for stage in ("capsule", "hull", "swept")},
             "first_inconclusive": (
                 {"t0": r.first_inconclusive.t0, "t1": r.first_inconclusive.t1,
                  "capsule": r.first_inconclusive.capsule, "box": r.first_inconclusive.box,
                  "other_capsule": r.first_inconclusive.other_capsule,
                  "clearance_m": num(r.first_inconclusive.clearance_m),
                  "guard_m": num(r.first_inconclusive.guard_m)}
                 if r.first_inconclusive else None)}
            for r in result
        ],
    }


def leaves_bytes(result: DatasetResult, fmt: str) -> bytes:
    """The leaf table as ``csv`` or ``parquet`` bytes."""
    df = result.leaves_dataframe()
    if fmt == "csv":
        return df.to_csv(index=False).encode("utf-8")  # floats as shortest round-trip repr
    buf = io.BytesIO()
    df.to_parquet(buf, index=False)
    return buf.getvalue()


_LEAF_FORMATS = {".parquet": "parquet", ".pq": "parquet", ".csv": "csv"}


def leaves_format(path, what: str = "--leaves") -> str:
    """The format of a leaf-table file (``parquet`` or ``csv``) from its name's suffix, for
    :func:`leaves_bytes`; checked before any work is done (a Parquet name needs pyarrow).
    :class:`LarcInputError` naming ``what`` and the path otherwise."""
    fmt = _LEAF_FORMATS.get(Path(path).suffix.lower())
    if fmt is None:
        raise LarcInputError(f"{what} {path}: unknown file type (use a .parquet or .csv name)")
    if fmt == "parquet":
        try:
            import pyarrow  # noqa: F401
        except ImportError:
            raise LarcInputError(
                f"{what} {path}: writing Parquet needs pyarrow (pip install pyarrow); or give a .csv file name"
            ) from None
    return fmt
