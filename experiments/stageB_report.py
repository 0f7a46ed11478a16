"""Stage B's tables stage: every table (:mod:`experiments.tables`) as ``.csv`` and ``.md``, and
``README.md``, which sets our figures beside the paper's, with notes generated from the data and
the hand-written "Why they differ" section.

The discussion is a *template*, ``experiments/stageB_discussion.md``: it quotes numbers only as
``{{name}}`` placeholders, filled in from the tables by :func:`discussion_values` (an unknown
name is an error), so rerunning the stage after the data change rewrites every number it quotes.

A full run into ``results/stageB`` also writes ``summary.md``, the short section that the
project's README quotes, and replaces that section of ``README.md`` (between the
``<!-- stageB-summary -->`` markers) with it; ``tests/test_readme.py`` checks they agree.
"""

from __future__ import annotations

import os
import platform
import re
from pathlib import Path

import numpy as np
import pandas as pd

from experiments.common import METHODS, OUTCOMES, ROOT, SCENE_LABELS, VARIANTS
from experiments.tables import (PAPER, TABLES, checks_table, frontier_tables, generation_table, median,
                                overall_table, pct, per_scene_table, rejection_by_variant_table, stats,
                                timing_table, trajectory_table, write_table)

__all__ = ["CODE", "DISCUSSION", "make_tables", "stage_outputs", "discussion_values", "fill_template",
           "summary_markdown", "SUMMARY_BEGIN", "SUMMARY_END", "replace_summary"]

CODE = ("experiments.stageB_report",)
"""Modules whose import closure is the tables stage's code."""
DISCUSSION = ROOT / "experiments" / "stageB_discussion.md"
"""Template of the "Why they differ" section of the full run's README (an input of the stage)."""
PROJECT_README = ROOT / "README.md"
SUMMARY_BEGIN = "<!-- stageB-summary: written by `python -m experiments.stageB` from results/stageB/summary.md -->"
SUMMARY_END = "<!-- /stageB-summary -->"
PLACEHOLDER = re.compile(r"\{\{\s*([A-Za-z_][A-Za-z0-9_]*)\s*\}\}")


def stage_outputs(layout, quick: bool = False) -> list[Path]:
    """Files the tables stage writes under ``layout.out``."""
    return ([layout.out / f"{t}.{ext}" for t in TABLES for ext in ("csv", "md")] + [layout.out / "README.md"]
            + ([] if quick else [layout.out / "summary.md"]))


# ----------------------------------------------------------------------------------------------
# Notes generated from the data
# ----------------------------------------------------------------------------------------------


def _notes(df: pd.DataFrame, gen: pd.DataFrame, timing: pd.DataFrame, config: dict, layout) -> list[str]:
    s = stats(df)
    out = []
    out.append(f"{s['n']} trajectories from {s['pairs']} pairs in {df['scene'].nunique()} scenes. LARC certified "
               f"{s['cert']['larc']}, fixed-fine {s['cert']['fine']}, fixed-coarse {s['cert']['coarse']}.")
    out.append("LARC and fixed-fine agreed on every decision." if not s["disagree"] else
               f"LARC and fixed-fine disagreed on {len(s['disagree'])}: {', '.join(s['disagree'])}.")
    by_var = df.groupby("variant")["audit_collision"].sum()
    out.append(f"The audit checked {s['states']} states ({config['audit_hz']} Hz grid plus every waypoint) and "
               f"found a scene collision in {s['fcl']} trajectories ("
               + ", ".join(f"{v} {int(by_var.get(v, 0))}" for v in VARIANTS)
               + f"); LARC certified {len(s['false_safe'])} of them"
               + (f" ({', '.join(s['false_safe'])})" if s["false_safe"] else "")
               + f". Fixed-coarse certified {s['false_safe_coarse']} of them. {s['self_coll']} trajectories had a "
               "disallowed self-contact at some audited state (reported separately; outside the certificate).")
    parts = []
    for v in VARIANTS:
        sub = df[df["variant"] == v]
        clear = ~sub["audit_collision"]
        rej = int((clear & ~sub["certified_larc"]).sum())
        parts.append(f"{v} {rej}/{int(clear.sum())} ({pct(rej, int(clear.sum()))})")
    out.append(f"Conservative rejections: {s['rej']}/{s['clear']} sampled-clear trajectories "
               f"({pct(s['rej'], s['clear'])}); by variant: {'; '.join(parts)}.")
    unc = df[~df["certified_larc"]]
    if len(unc):
        pairs = (unc["blocked_capsule"].astype(str) + " vs " + unc["blocked_box"].astype(str)).value_counts()
        top = ", ".join(f"{k} ({v})" for k, v in pairs.head(4).items())
        out.append(f"For each of the {len(unc)} uncertified trajectories, the capsule–box pair attaining the "
                   f"minimum of g at its earliest inconclusive depth-{config['max_depth']} leaf: {top}.")
    cert = df[df["certified_larc"]]
    if len(cert):
        g = pd.to_numeric(cert["min_clearance_m"], errors="coerce")
        g = g[np.isfinite(g)]
        if len(g):
            out.append(f"Smallest certificate clearance g over the leaves of certified trajectories with obstacles: "
                       f"median {1e3 * g.median():.1f} mm, minimum {1e3 * g.min():.2f} mm.")
    ratios = df.groupby("scene", sort=False).apply(
        lambda x: x["evals_larc"].sum() / x["evals_fine"].sum(), include_groups=False)
    out.append("LARC/fine evaluation ratio by scene: " + ", ".join(f"{k} {v:.3f}" for k, v in ratios.items())
               + f" (overall {s['ratio']:.3f}); per trajectory LARC used {int(df['evals_larc'].min())} to "
               f"{int(df['evals_larc'].max())} evaluations.")
    sp = pd.to_numeric(df["speedup_fine_over_larc"])
    med_sc = df.groupby("scene", sort=False)["speedup_fine_over_larc"].median()
    out.append(f"Paired per-trajectory timing (one trajectory per call, median of {config['timing_repeats']} "
               f"repeats): LARC median {s['med_ms']['larc']:.1f} ms, fine {s['med_ms']['fine']:.1f} ms, "
               f"coarse {s['med_ms']['coarse']:.1f} ms; fine/LARC ratio from {sp.min():.2f}× to {sp.max():.2f}×, "
               "scene medians " + ", ".join(f"{k} {v:.2f}×" for k, v in med_sc.items()) + ".")
    t = timing.set_index("method")
    out.append("Whole-batch (all trajectories in one call, median of warm calls, compile excluded): "
               + ", ".join(f"{m} {t.loc[m, 'batch_s_median']:.3f} s (compile {t.loc[m, 'compile_s']:.2f} s)"
                           for m in METHODS) + ".")
    try:
        raw = pd.read_csv(layout.timing_raw_csv)
        nc = int(raw.loc[raw["kind"] == "timed", "compiles"].sum())
        out.append(f"XLA compilations inside timed per-trajectory calls: {nc} (warm-up calls excluded).")
    except (OSError, KeyError, pd.errors.EmptyDataError):
        pass
    tot = gen[gen["scene"] == "total"].iloc[0]
    out.append(f"Generation: {int(tot['attempts'])} attempts, {int(tot['accepted'])} accepted, "
               + ", ".join(f"{int(tot[o])} {o.replace('_', ' ')}" for o in OUTCOMES[1:]) + ".")
    for v in VARIANTS:
        sub = df[df["variant"] == v]
        if len(sub):
            out.append(f"{v}: duration median {sub['duration_s'].median():.2f} s (range "
                       f"{sub['duration_s'].min():.2f}–{sub['duration_s'].max():.2f} s), waypoints median "
                       f"{int(sub['n_waypoints'].median())}.")
    return out


def _machine() -> str:
    import os

    try:
        import jax

        jv = jax.__version__
    except Exception:  # noqa: BLE001
        jv = "?"
    return (f"{platform.system()} {platform.machine()}, {os.cpu_count()} CPUs, Python "
            f"{platform.python_version()}, jax {jv}")


def readme(df, overall, per_scene, rej, frontier, timing, gen, checks, config, quick, layout, values) -> str:
    P = PAPER
    L = []
    L.append("# Stage B results")
    L.append("")
    L.append(f"Generated by `python -m experiments.stageB{' --quick' if quick else ''}` "
             f"({'quick run: ' + str(config.get('quick_pairs_per_scene', 2)) + ' pairs per scene' if quick else 'full run'}). "
             "Every number below is computed from the files in this folder; the paper's values are "
             "from `../shared/paper/larc_paper.tex` (Tables II and III, text).")
    L.append("")
    L.append(f"Protocol (`configs/stageB.yaml`): margin ρ = {1e3 * float(config['margin_m']):.0f} mm, "
             f"d_max = {config['max_depth']}, coarse depth {config['coarse_depth']}, audit {config['audit_hz']} Hz "
             f"+ waypoints, recheck {config['recheck_hz']} Hz, timing seed {config['timing_seed']}, "
             f"{config['timing_repeats']} repeats. Machine: {_machine()}.")
    L.append("")
    L.append("## Overall (paper Table II)")
    L.append("")
    L.append("| Metric | Ours | Ours: detail | Paper | Paper: detail |")
    L.append("|---|---:|---|---:|---|")
    for _, r in overall.iterrows():
        L.append(f"| {r['metric']} | {r['ours']} | {r['ours_detail']} | {r['paper']} | {r['paper_detail']} |")
    L.append("")
    L.append("## By scene (paper Table III)")
    L.append("")
    L.append("FCL: audit-detected collisions; Cert.: certified by LARC; Rej.: conservative rejections; "
             "Eval.: LARC/fine evaluation ratio; Speed: median paired speedup. Each cell: ours (paper).")
    L.append("")
    L.append("| Scene | N | FCL | Cert. | Rej. | Eval. | Speed |")
    L.append("|---|---:|---:|---:|---:|---:|---:|")
    keys = {v: k for k, v in SCENE_LABELS.items()}
    for _, r in per_scene.iterrows():
        k = "overall" if r["scene"] == "Overall" else keys.get(r["scene"], r["scene"])
        p = P["per_scene"].get(k)
        ps = (lambda i, f="{}": f" ({f.format(p[i])})" if p else "")
        L.append(f"| {r['scene']} | {r['N']}{ps(0)} | {r['FCL']}{ps(1)} | {r['Cert']}{ps(2)} | {r['Rej']}{ps(3)} | "
                 f"{r['Eval']:.3f}{ps(4, '{:.3f}')} | {r['Speed']:.2f}×{ps(5, '{:.2f}×')} |")
    L.append("")
    L.append("## Conservative rejection by variant")
    L.append("")
    L.append("| Variant | Trajectories | Audit collisions | Sampled-clear | Certified | Rejections (ours) | Paper |")
    L.append("|---|---:|---:|---:|---:|---|---|")
    for _, r in rej.iterrows():
        L.append(f"| {r['variant']} | {r['trajectories']} | {r['audit_collision']} | {r['sampled_clear']} | "
                 f"{r['certified_larc']} | {r['rejection_rate']} | {r['paper']} |")
    L.append("")
    L.append("## Generation attempts")
    L.append("")
    L.append("| Scene | Attempts | Accepted | Invalid start | Invalid goal | Planning failure | Hermite recheck failure |")
    L.append("|---|---:|---:|---:|---:|---:|---:|")
    for _, r in gen.iterrows():
        L.append(f"| {r['scene']} | {r['attempts']} | {r['accepted']} | {r['invalid_start']} | {r['invalid_goal']} | "
                 f"{r['planning_failure']} | {r['hermite_recheck_failure']} |")
    L.append("")
    L.append("## Interval work per depth (LARC frontier vs fixed-fine)")
    L.append("")
    L.append("| Depth | LARC frontier | passed | inconclusive | fine intervals at depth (2^d·N) | fine evaluated |")
    L.append("|---:|---:|---:|---:|---:|---:|")
    for _, r in frontier.iterrows():
        L.append(f"| {r['depth']} | {r['larc_frontier']} | {r['larc_passed']} | {r['larc_inconclusive']} | "
                 f"{r['fine_intervals_at_depth']} | {r['fine_evaluated']} |")
    L.append("")
    L.append("## Timing")
    L.append("")
    L.append("Whole batch = all trajectories in ONE `certify` call (median of warm calls; the first call, "
             "which compiles, is reported separately; methods run in the order larc, fine, coarse, and a kernel "
             "shape compiled for an earlier method is reused by a later one, so its compile time is attributed "
             "to the earlier method). Paired = one trajectory per call, the paper's protocol (median of the "
             "repeats per trajectory and method; the first call per trajectory and method is an untimed warm-up).")
    L.append("")
    L.append("| Method | Evaluations | Batch (s) | First call (s) | Compile (s) | Batch ms/trajectory | "
             "Paired median (ms) |")
    L.append("|---|---:|---:|---:|---:|---:|---:|")
    for _, r in timing.iterrows():
        L.append(f"| {r['method']} | {r['evaluations']} | {r['batch_s_median']:.3f} | {r['first_call_s']:.2f} | "
                 f"{r['compile_s']:.2f} | {r['batch_ms_per_trajectory']:.2f} | {r['paired_median_ms']:.2f} |")
    L.append("")
    L.append("## Must-hold checks")
    L.append("")
    L.append("| Check | Expected | Observed | OK |")
    L.append("|---|---|---|---|")
    for _, r in checks.iterrows():
        L.append(f"| {r['check']} | {r['expected']} | {r['observed']} | {'yes' if r['ok'] else '**NO**'} |")
    L.append("")
    L.append("## Notes (generated from the data)")
    L.append("")
    for n in _notes(df, gen, timing, config, layout):
        L.append(f"- {n}")
    L.append("")
    L.append("## Why they differ")
    L.append("")
    if quick:
        L.append("Quick run (2 pairs per scene): too few trajectories to compare with the paper; see the "
                 "full run's `results/stageB/README.md`.")
    elif DISCUSSION.is_file():
        L.append(f"_Written by hand (`{DISCUSSION.relative_to(ROOT)}`); every number in it is filled in from "
                 "the tables above when this file is generated._")
        L.append("")
        L.append(fill_template(DISCUSSION.read_text().strip(), values, str(DISCUSSION.relative_to(ROOT))))
    else:
        L.append(f"No discussion yet: write `{DISCUSSION.relative_to(ROOT)}` and rerun the tables stage.")
    L.append("")
    L.append("## Files")
    L.append("")
    L.append("- `trajectories.csv` — one row per trajectory; `overall`, `per_scene`, `rejection_by_variant`, "
             "`frontier_levels`, `frontier_levels_by_scene`, `batch_timing`, `generation`, `checks` (`.csv` and `.md`).")
    L.append("- `dataset/` — trajectory files and `attempts.csv`; `audit/audit.csv`; `certification/` "
             "(per-method results, LARC levels, batch timing); `timing/` (raw paired timings and medians); "
             "`figures/`.")
    L.append("")
    return "\n".join(L)




# ----------------------------------------------------------------------------------------------
# The discussion template and the project README's summary
# ----------------------------------------------------------------------------------------------


def _num(x: float, digits: int) -> str:
    return f"{x:.{digits}f}"


def _thousands(n: int) -> str:
    return f"{int(n):,}".replace(",", "\u202f")  # narrow no-break space: 32 820


def discussion_values(df: pd.DataFrame, timing: pd.DataFrame, gen: pd.DataFrame, config: dict) -> dict[str, str]:
    """Every number the discussion template (and the project README's summary) may quote, as
    formatted text, computed from the tables; ``paper_*`` are the paper's (:data:`PAPER`)."""
    P = PAPER
    s = stats(df)
    max_depth = int(config["max_depth"])
    v: dict[str, str] = {}
    v.update(n=str(s["n"]), pairs=str(s["pairs"]), scenes=str(df["scene"].nunique()),
             pairs_per_scene=str(int(config["pairs_per_scene"])), margin_mm=f"{1e3 * float(config['margin_m']):g}",
             max_depth=str(max_depth), fine_intervals=str(2**max_depth), audit_hz=str(config["audit_hz"]),
             padding_cm=f"{100 * float(config['generation']['planning_padding_m']):g}",
             padding_mm=f"{1e3 * float(config['generation']['planning_padding_m']):g}",
             cpus=str(os.cpu_count()))
    for m in METHODS:
        v[f"cert_{m}"] = str(s["cert"][m])
        v[f"paper_cert_{m}"] = str(P[f"certified_{m}"])
        v[f"evals_{m}"] = _thousands(s["evals"][m])
        v[f"median_ms_{m}"] = _num(s["med_ms"][m], 1)
    v.update(disagree=str(len(s["disagree"])), fcl=str(s["fcl"]), false_safe=str(len(s["false_safe"])),
             false_safe_coarse=str(s["false_safe_coarse"]), clear=str(s["clear"]), rej=str(s["rej"]),
             rej_pct=pct(s["rej"], s["clear"]).replace("%", " %"), states=_thousands(s["states"]),
             ratio=_num(s["ratio"], 3), speedup=_num(s["speedup"], 2), self_collisions=str(s["self_coll"]),
             eval_saving=_num(1 / s["ratio"], 1) if s["ratio"] else "–")
    v.update(paper_n=str(P["trajectories"]), paper_fcl=str(P["fcl_collision"]), paper_rej=str(P["rejection"]),
             paper_clear=str(P["sampled_clear"]), paper_rej_pct=pct(P["rejection"], P["sampled_clear"]).replace("%", " %"),
             paper_ratio=_num(P["eval_ratio"], 3), paper_speedup=_num(P["speedup"], 2),
             paper_median_ms_larc=_num(P["median_ms_larc"], 1), paper_median_ms_fine=_num(P["median_ms_fine"], 1),
             paper_fine_ms_per_interval=_num(P["median_ms_fine"] / 2**max_depth, 1),
             paper_states=_thousands(P["audit_states"]), paper_evals_larc=_thousands(P["evals_larc"]),
             paper_evals_fine=_thousands(P["evals_fine"]), paper_false_safe=str(P["false_safe"]))
    for var in VARIANTS:
        sub = df[df["variant"] == var]
        clear = ~sub["audit_collision"]
        short = "ompl" if var == "ompl_planned" else "direct"
        v[f"fcl_{short}"] = str(int(sub["audit_collision"].sum()))
        v[f"rej_{short}"] = str(int((clear & ~sub["certified_larc"]).sum()))
        v[f"clear_{short}"] = str(int(clear.sum()))
        v[f"ratio_{short}"] = _num(sub["evals_larc"].sum() / max(1, sub["evals_fine"].sum()), 2)
        v[f"duration_median_{short}"] = _num(sub["duration_s"].median(), 1)
        v[f"duration_max_{short}"] = _num(sub["duration_s"].max(), 1)
    v["duration_median"] = _num(df["duration_s"].median(), 1)
    v["duration_max"] = _num(df["duration_s"].max(), 1)
    v["leaf_ms_min"] = _num(1e3 * df["duration_s"].min() / 2**max_depth, 0)
    v["leaf_ms_max"] = _num(1e3 * df["duration_s"].max() / 2**max_depth, 0)
    for sc, sub in df.groupby("scene", sort=False):
        direct = sub[sub["variant"] == "direct_smoothstep"]
        v[f"fcl_direct_{sc}"] = str(int(direct["audit_collision"].sum()))
        v[f"pairs_{sc}"] = str(len(direct))
        v[f"ratio_{sc}"] = _num(sub["evals_larc"].sum() / max(1, sub["evals_fine"].sum()), 3)
        v[f"speedup_{sc}"] = _num(float(pd.to_numeric(sub["speedup_fine_over_larc"]).median()), 2)
        v[f"median_ms_larc_{sc}"] = _num(median(sub["time_larc_ms"]), 2)
        if sc in P["per_scene"]:
            v[f"paper_ratio_{sc}"] = _num(P["per_scene"][sc][4], 3)
            v[f"paper_speedup_{sc}"] = _num(P["per_scene"][sc][5], 2)
            v[f"paper_fcl_{sc}"] = str(P["per_scene"][sc][1])
    obstacle = [sc for sc in df["scene"].unique() if sc != "open"]
    ratios = [float(v[f"ratio_{sc}"]) for sc in obstacle]
    paper_ratios = [P["per_scene"][sc][4] for sc in obstacle if sc in P["per_scene"]]
    if ratios:
        v.update(ratio_obstacle_min=_num(min(ratios), 2), ratio_obstacle_max=_num(max(ratios), 2))
    if paper_ratios:
        v.update(paper_ratio_obstacle_min=_num(min(paper_ratios), 2), paper_ratio_obstacle_max=_num(max(paper_ratios), 2))
    windows = [sc for sc in obstacle if "window" in sc]
    shelves = [sc for sc in obstacle if "shelf" in sc]
    for name, group in (("window", windows), ("shelf", shelves)):
        v[f"fcl_direct_{name}"] = str(sum(int(v[f"fcl_direct_{sc}"]) for sc in group))
        v[f"pairs_{name}"] = str(sum(int(v[f"pairs_{sc}"]) for sc in group))
    # OMPL-planned rejections: how close they came (depth-d_max clearance) and on which capsule.
    rej = df[(df["variant"] == "ompl_planned") & ~df["audit_collision"] & ~df["certified_larc"]]
    g = pd.to_numeric(rej["min_clearance_m"], errors="coerce")
    v["ompl_rej_g_min_mm"] = _num(-1e3 * g.max(), 0) if len(g) else "–"  # closest to certified
    v["ompl_rej_g_max_mm"] = _num(-1e3 * g.min(), 0) if len(g) else "–"
    caps = rej["blocked_capsule"].astype(str)
    gripper = caps.str.match(r"^link[678]")
    v["ompl_rej_gripper"] = str(int(gripper.sum()))
    # Timing.
    t = timing.set_index("method")
    for m in METHODS:
        v[f"batch_{m}_s"] = _num(float(t.loc[m, "batch_s_median"]), 2)
        v[f"compile_{m}_s"] = _num(float(t.loc[m, "compile_s"]), 1)
    v["batch_speedup"] = _num(float(t.loc["fine", "batch_s_median"]) / float(t.loc["larc", "batch_s_median"]), 1)
    fine_evals = float(t.loc["fine", "evaluations"])
    v["fine_us_per_interval"] = _num(1e6 * float(t.loc["fine", "batch_s_median"]) / fine_evals, 0)
    v["fine_paired_ms"] = _num(median(df["time_fine_ms"]), 1)
    open_ = df[df["scene"] == "open"]
    v["open_larc_ms"] = _num(median(open_["time_larc_ms"]), 2) if len(open_) else "–"
    # Generation.
    tot = gen[gen["scene"] == "total"].iloc[0]
    v["attempts"] = str(int(tot["attempts"]))
    v["paper_attempts"] = str(P["generation"]["attempts"])
    for o in OUTCOMES:
        v[o] = str(int(tot[o]))
        v[f"paper_{o}"] = str(P["generation"][o])
    return v


def fill_template(text: str, values: dict[str, str], source: str = "template") -> str:
    """Replace every ``{{name}}`` in ``text`` by ``values[name]``; an unknown name is an error."""
    unknown = sorted({m.group(1) for m in PLACEHOLDER.finditer(text)} - set(values))
    if unknown:
        raise KeyError(f"{source}: unknown placeholders {unknown} (known: {sorted(values)})")
    return PLACEHOLDER.sub(lambda m: values[m.group(1)], text)


SUMMARY_TEMPLATE = """\
{{n}} PIPER trajectories ({{scenes}} scenes × {{pairs_per_scene}} start–goal pairs × {OMPL-planned, direct
smoothstep control}), ρ = {{margin_mm}} mm, depth {{max_depth}}, audited with FCL on the official meshes at
{{audit_hz}} Hz plus every waypoint; {{cpus}}-core CPU, no GPU. The paper's figures are beside ours. Full tables,
figures and an explanation of every difference: [`results/stageB/README.md`](results/stageB/README.md).

| Metric | Ours | Paper |
|---|---|---|
| Certified (LARC / fine / coarse) | {{cert_larc}} / {{cert_fine}} / {{cert_coarse}} | \
{{paper_cert_larc}} / {{paper_cert_fine}} / {{paper_cert_coarse}} |
| Disagreement LARC vs fine | {{disagree}} / {{n}} | 0 / {{paper_n}} |
| FCL-detected collisions | {{fcl}} (OMPL-planned {{fcl_ompl}}, direct {{fcl_direct}}) | {{paper_fcl}} (direct only) |
| False-safe (certified but audit collides) | **{{false_safe}} / {{fcl}}** ({{states}} states) | \
{{paper_false_safe}} / {{paper_fcl}} ({{paper_states}} states) |
| Conservative rejection | {{rej}} / {{clear}} sampled-clear ({{rej_pct}}) | {{paper_rej}} / {{paper_clear}} ({{paper_rej_pct}}) |
| Interval evaluations | {{evals_larc}}, ratio {{ratio}} to fine's {{evals_fine}} | \
{{paper_evals_larc}}, ratio {{paper_ratio}} |
| Median paired speedup fine / LARC | {{speedup}}× (open {{speedup_open}}×) | \
{{paper_speedup}}× (open {{paper_speedup_open}}×) |
| Whole dataset in one call | LARC {{batch_larc_s}} s, fine {{batch_fine_s}} s (compile {{compile_larc_s}} s, separate) | – |

Our fixed-fine baseline evaluates its {{fine_intervals}} intervals in one vectorised call, so per trajectory it
costs little more than LARC's level-by-level calls; the paper's fine cost {{paper_fine_ms_per_interval}} ms per
interval. The savings show in evaluations ({{eval_saving}}× fewer) and in whole-dataset batches
({{batch_speedup}}×)."""


def summary_markdown(values: dict[str, str]) -> str:
    """The project README's "Stage B results" section body (from :func:`discussion_values`)."""
    return fill_template(SUMMARY_TEMPLATE, values, "summary") + "\n"


def replace_summary(readme_text: str, summary: str) -> str:
    """``readme_text`` with the block between :data:`SUMMARY_BEGIN` and :data:`SUMMARY_END`
    replaced by ``summary``."""
    i, j = readme_text.find(SUMMARY_BEGIN), readme_text.find(SUMMARY_END)
    if i < 0 or j < i:
        raise ValueError(f"README.md has no {SUMMARY_BEGIN} ... {SUMMARY_END} block")
    return readme_text[: i + len(SUMMARY_BEGIN)] + "\n" + summary + readme_text[j:]


# ----------------------------------------------------------------------------------------------
# Entry point
# ----------------------------------------------------------------------------------------------


def make_tables(layout, config: dict, quick: bool = False) -> dict:
    """The tables stage (module docstring)."""
    from larc_jax.io import atomic_write_text

    out = layout.out
    scenes = list(config.get("scene_order") or config["scenes"])
    df = trajectory_table(layout)
    df["scene"] = pd.Categorical(df["scene"], categories=scenes, ordered=True)
    df = df.sort_values(["scene", "traj_id"]).reset_index(drop=True)
    df["scene"] = df["scene"].astype(str)
    write_table(out, "trajectories", df, "Stage B trajectories")
    overall = overall_table(df)
    write_table(out, "overall", overall, "Overall results (paper Table II)")
    per_scene = per_scene_table(df, scenes)
    write_table(out, "per_scene", per_scene, "Results by scene (paper Table III)")
    rej = rejection_by_variant_table(df)
    write_table(out, "rejection_by_variant", rej, "Conservative rejection by variant")
    frontier, frontier_sc = frontier_tables(layout, df, config)
    write_table(out, "frontier_levels", frontier, "LARC frontier per depth vs fixed-fine")
    write_table(out, "frontier_levels_by_scene", frontier_sc, "LARC frontier per depth and scene")
    timing = timing_table(layout, df)
    write_table(out, "batch_timing", timing, "Certification timing: whole batch (compile separately) and paired medians")
    gen = generation_table(layout, scenes)
    write_table(out, "generation", gen, "Generation attempts")
    checks = checks_table(df, gen, config, quick)
    write_table(out, "checks", checks, "Must-hold checks (reported, not asserted)")
    values = discussion_values(df, timing, gen, config)
    atomic_write_text(out / "README.md", readme(df, overall, per_scene, rej, frontier, timing, gen, checks,
                                                config, quick, layout, values))
    if not quick:
        summary = summary_markdown(values)
        atomic_write_text(out / "summary.md", summary)
        if out.resolve() == (ROOT / "results" / "stageB").resolve() and PROJECT_README.is_file():
            atomic_write_text(PROJECT_README, replace_summary(PROJECT_README.read_text(), summary))
    return dict(checks_failed=int((~checks["ok"]).sum()))
