"""Stage B tables (paper Tables II and III and companions) and the must-hold checks.

Reads the stage outputs under ``<out>`` (see :class:`experiments.stageB.Layout`) and writes, each
as ``.csv`` and ``.md``:

* ``trajectories`` — one row per trajectory (decisions and evaluations of the three methods,
  audit, LARC minimum clearance, median paired times, paired speedup);
* ``overall`` — the rows of the paper's Table II, ours beside the paper's;
* ``per_scene`` — Table III (N, FCL, Cert., Rej., Eval. ratio, Speed) plus an overall row;
* ``rejection_by_variant`` — conservative rejections of ``ompl_planned`` vs ``direct_smoothstep``;
* ``frontier_levels`` (and ``frontier_levels_by_scene``) — per depth: LARC frontier size, passed,
  inconclusive; fine's ``2^d N`` intervals at that depth and what fine actually evaluates;
* ``batch_timing`` — whole-batch times per method (compile separately) and per-trajectory medians;
* ``generation`` — attempt outcomes per scene (failures kept);
* ``checks`` — the must-hold checks (computed and reported, never asserted here);

and ``README.md`` setting our figures beside the paper's, with notes generated from the data
and the hand-written "Why they differ" section from ``experiments/stageB_discussion.md``.

Definitions (paper, "Sampled MoveIt/FCL Audit"): *sampled-clear* = the audit found no
scene collision at its states; *FCL-detected false-safe* = certified by LARC although the audit
found a scene collision; *conservative rejection* = sampled-clear but not certified by LARC.
Self-collision is reported separately (the certificate concerns link-obstacle separation, A4).
"""

from __future__ import annotations

import platform
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parent.parent
DISCUSSION = ROOT / "experiments" / "stageB_discussion.md"
"""Hand-written "Why they differ" section of the full run's README (an input of the tables stage)."""

__all__ = ["trajectory_table", "make_tables", "table_outputs", "load_checks", "print_checks",
           "PAPER", "TABLES"]

TABLES = ("trajectories", "overall", "per_scene", "rejection_by_variant", "frontier_levels",
          "frontier_levels_by_scene", "batch_timing", "generation", "checks")
SCENE_LABELS = {"open": "Open", "easy_window": "Easy window", "medium_window": "Medium window",
                "easy_shelf": "Easy shelf"}
VARIANTS = ("ompl_planned", "direct_smoothstep")
METHODS = ("larc", "fine", "coarse")

PAPER = dict(
    pairs=80, trajectories=160, certified_larc=112, certified_fine=112, certified_coarse=70,
    disagreement=0, fcl_collision=21, fcl_collision_ompl=0, fcl_collision_direct=21, false_safe=0,
    audit_states=158051, rejection=27, sampled_clear=139, evals_larc=20328, evals_fine=81920,
    eval_ratio=0.248, median_ms_larc=81.8, median_ms_fine=801.4, speedup=10.28,
    per_scene={  # N, FCL, Cert., Rej., Eval., Speed
        "open": (40, 0, 40, 0, 0.002, 260.31),
        "easy_window": (40, 5, 29, 6, 0.223, 11.58),
        "medium_window": (40, 8, 20, 12, 0.376, 3.14),
        "easy_shelf": (40, 8, 23, 9, 0.392, 4.18),
        "overall": (160, 21, 112, 27, 0.248, 10.28),
    },
    by_variant={"ompl_planned": (22, 80), "direct_smoothstep": (5, 59)},  # rejections / sampled-clear
    generation=dict(attempts=115, accepted=80, invalid_start=9, invalid_goal=16, planning_failure=6,
                    hermite_recheck_failure=4),
)
OUTCOMES = ("accepted", "invalid_start", "invalid_goal", "planning_failure", "hermite_recheck_failure")


# ----------------------------------------------------------------------------------------------
# Helpers
# ----------------------------------------------------------------------------------------------


def _bool(s: pd.Series) -> pd.Series:
    if s.dtype == bool:
        return s
    return s.astype(str).str.strip().str.lower().isin(("true", "1", "yes"))


def _md_cell(x) -> str:
    if isinstance(x, float):
        if np.isnan(x):
            return "—"
        return f"{x:.6g}"
    return str(x).replace("|", "\\|").replace("\n", " ")


def to_markdown(df: pd.DataFrame, title: str | None = None) -> str:
    """GitHub-flavoured markdown table (no external dependency)."""
    cols = [str(c) for c in df.columns]
    num = [pd.api.types.is_numeric_dtype(df[c]) for c in df.columns]
    lines = []
    if title:
        lines += [f"# {title}", ""]
    lines.append("| " + " | ".join(cols) + " |")
    lines.append("|" + "|".join("---:" if n else "---" for n in num) + "|")
    for _, row in df.iterrows():
        lines.append("| " + " | ".join(_md_cell(v) for v in row.tolist()) + " |")
    return "\n".join(lines) + "\n"


def _write(out: Path, name: str, df: pd.DataFrame, title: str):
    from larc_jax.io import atomic_write_text

    atomic_write_text(out / f"{name}.csv", df.to_csv(index=False))
    atomic_write_text(out / f"{name}.md", to_markdown(df, title))


def _pct(a: int, b: int) -> str:
    return f"{100.0 * a / b:.1f}%" if b else "—"


def _median(x) -> float:
    x = pd.to_numeric(pd.Series(x), errors="coerce").dropna()
    return float(np.median(x)) if len(x) else float("nan")


def table_outputs(layout) -> list[Path]:
    return [layout.out / f"{t}.{ext}" for t in TABLES for ext in ("csv", "md")] + [layout.out / "README.md"]


# ----------------------------------------------------------------------------------------------
# The per-trajectory table
# ----------------------------------------------------------------------------------------------


def trajectory_table(layout) -> pd.DataFrame:
    """One row per trajectory from the certification, audit and timing outputs."""
    cert = pd.read_csv(layout.cert_results_csv)
    cert["certified"] = _bool(cert["certified"])
    base = cert[cert["method"] == "larc"][["traj_id", "scene", "pair_id", "variant", "duration_s",
                                          "n_waypoints"]].set_index("traj_id")
    for m in METHODS:
        sub = cert[cert["method"] == m].set_index("traj_id")
        base[f"certified_{m}"] = sub["certified"]
        base[f"evals_{m}"] = sub["evaluations"].astype(int)
    audit = pd.read_csv(layout.audit_csv).set_index("traj_id")
    base["audit_states"] = audit["audit_states"].astype(int)
    base["audit_collision"] = _bool(audit["audit_collision"])
    larc = cert[cert["method"] == "larc"].set_index("traj_id")
    fine = cert[cert["method"] == "fine"].set_index("traj_id")
    base["min_clearance_m"] = larc["min_clearance_m"]
    timing = pd.read_csv(layout.timing_summary_csv).set_index("traj_id")
    for m in METHODS:
        base[f"time_{m}_ms"] = timing[f"time_{m}_ms"]
    base["self_collision"] = _bool(audit["self_collision"])
    base["speedup_fine_over_larc"] = timing["speedup_fine_over_larc"]
    base["min_clearance_fine_m"] = fine["min_clearance_m"]
    base["blocked_capsule"] = larc["blocked_capsule"].fillna("")
    base["blocked_box"] = larc["blocked_box"].fillna("")
    base["blocked_t0"] = larc["blocked_t0"]
    base["first_collision_t"] = audit["first_collision_t"] if "first_collision_t" in audit else np.nan
    base = base.reset_index()
    first = ["traj_id", "scene", "pair_id", "variant", "duration_s", "n_waypoints",
             *[f"certified_{m}" for m in METHODS], *[f"evals_{m}" for m in METHODS], "audit_states",
             "audit_collision", "min_clearance_m", *[f"time_{m}_ms" for m in METHODS]]
    return base[first + [c for c in base.columns if c not in first]]


# ----------------------------------------------------------------------------------------------
# Summaries
# ----------------------------------------------------------------------------------------------


def _stats(df: pd.DataFrame) -> dict:
    clear = ~df["audit_collision"]
    s = dict(
        n=len(df),
        pairs=df["pair_id"].nunique(),
        cert={m: int(df[f"certified_{m}"].sum()) for m in METHODS},
        disagree=df.loc[df["certified_larc"] != df["certified_fine"], "traj_id"].tolist(),
        fcl=int(df["audit_collision"].sum()),
        false_safe=df.loc[df["certified_larc"] & df["audit_collision"], "traj_id"].tolist(),
        false_safe_coarse=int((df["certified_coarse"] & df["audit_collision"]).sum()),
        clear=int(clear.sum()),
        rej=int((clear & ~df["certified_larc"]).sum()),
        states=int(df["audit_states"].sum()),
        evals={m: int(df[f"evals_{m}"].sum()) for m in METHODS},
        med_ms={m: _median(df[f"time_{m}_ms"]) for m in METHODS},
        speedup=_median(df["speedup_fine_over_larc"]),
        self_coll=int(df["self_collision"].sum()),
    )
    s["ratio"] = s["evals"]["larc"] / s["evals"]["fine"] if s["evals"]["fine"] else float("nan")
    return s


def overall_table(df: pd.DataFrame, P=PAPER) -> pd.DataFrame:
    s = _stats(df)
    by_var = {v: int(df.loc[df["variant"] == v, "audit_collision"].sum()) for v in VARIANTS}
    per_scene_n = ", ".join(f"{n} {sc}" for sc, n in df.groupby("scene", sort=False).size().items())
    both = df.groupby("pair_id")["variant"].nunique().eq(2).sum()
    rows = [
        ("Independent pairs", s["pairs"], f"{both} with both variants", P["pairs"], "Two trajectories per pair"),
        ("Trajectories", s["n"], per_scene_n, P["trajectories"], "40 per scene"),
        ("Certified (LARC)", s["cert"]["larc"], f"Fine {s['cert']['fine']}; coarse {s['cert']['coarse']}",
         P["certified_larc"], f"Fine {P['certified_fine']}; coarse {P['certified_coarse']}"),
        ("Disagreement with fine", f"{len(s['disagree'])}/{s['n']}", "Same certificate model",
         f"{P['disagreement']}/{P['trajectories']}", "Same certificate model"),
        ("FCL-detected collision", s["fcl"], f"OMPL {by_var['ompl_planned']}; direct {by_var['direct_smoothstep']}",
         P["fcl_collision"], "Direct controls only"),
        ("FCL-detected false-safe", f"{len(s['false_safe'])}/{s['fcl']}", f"{s['states']} audited states",
         f"{P['false_safe']}/{P['fcl_collision']}", f"{P['audit_states']} audited states"),
        ("Conservative rejection", f"{s['rej']}/{s['clear']} ({_pct(s['rej'], s['clear'])})",
         "Relative to the sampled audit",
         f"{P['rejection']}/{P['sampled_clear']} ({_pct(P['rejection'], P['sampled_clear'])})",
         "Relative to the sampled audit"),
        ("Interval evaluations", s["evals"]["larc"], f"Fine {s['evals']['fine']}; ratio {s['ratio']:.3f}",
         P["evals_larc"], f"Fine {P['evals_fine']}; ratio {P['eval_ratio']:.3f}"),
        ("Marginal median runtime", f"{s['med_ms']['larc']:.1f} ms", f"Fine {s['med_ms']['fine']:.1f} ms",
         f"{P['median_ms_larc']:.1f} ms", f"Fine {P['median_ms_fine']:.1f} ms"),
        ("Median paired speedup", f"{s['speedup']:.2f}×", "Median trajectory-level ratio",
         f"{P['speedup']:.2f}×", "Median trajectory-level ratio"),
        ("Audit self-collision (separate)", s["self_coll"], "Trajectories with a disallowed self-contact",
         "—", "Not reported"),
        ("Coarse certified with audit collision", s["false_safe_coarse"], "Fixed-coarse false-safe",
         "—", "Not reported"),
    ]
    return pd.DataFrame(rows, columns=["metric", "ours", "ours_detail", "paper", "paper_detail"]).astype(str)


def per_scene_table(df: pd.DataFrame, scenes) -> pd.DataFrame:
    rows = []
    for sc in list(scenes) + ["overall"]:
        sub = df if sc == "overall" else df[df["scene"] == sc]
        if not len(sub):
            continue
        s = _stats(sub)
        rows.append(dict(
            scene=SCENE_LABELS.get(sc, sc.replace("_", " ").capitalize()) if sc != "overall" else "Overall",
            N=s["n"], FCL=s["fcl"], Cert=s["cert"]["larc"], Rej=s["rej"],
            Eval=round(s["ratio"], 3), Speed=round(s["speedup"], 2),
            cert_fine=s["cert"]["fine"], cert_coarse=s["cert"]["coarse"], sampled_clear=s["clear"],
            false_safe=len(s["false_safe"]), evals_larc=s["evals"]["larc"], evals_fine=s["evals"]["fine"],
            median_ms_larc=round(s["med_ms"]["larc"], 2), median_ms_fine=round(s["med_ms"]["fine"], 2),
            median_ms_coarse=round(s["med_ms"]["coarse"], 2),
        ))
    return pd.DataFrame(rows)


def rejection_by_variant_table(df: pd.DataFrame) -> pd.DataFrame:
    rows = []
    for v in list(VARIANTS) + ["all"]:
        sub = df if v == "all" else df[df["variant"] == v]
        clear = ~sub["audit_collision"]
        rej = int((clear & ~sub["certified_larc"]).sum())
        pv = PAPER["by_variant"].get(v, (PAPER["rejection"], PAPER["sampled_clear"]))
        rows.append(dict(
            variant=v, trajectories=len(sub), audit_collision=int(sub["audit_collision"].sum()),
            sampled_clear=int(clear.sum()), certified_larc=int(sub["certified_larc"].sum()),
            rejections=rej, rejection_rate=f"{rej}/{int(clear.sum())} ({_pct(rej, int(clear.sum()))})",
            paper=f"{pv[0]}/{pv[1]} ({_pct(*pv)})",
        ))
    return pd.DataFrame(rows)


def frontier_tables(layout, df: pd.DataFrame, config: dict):
    lv = pd.read_csv(layout.cert_levels_csv)
    max_depth, coarse_depth = int(config["max_depth"]), int(config["coarse_depth"])

    def agg(sub, n):
        g = sub.groupby("depth")[["frontier", "passed", "inconclusive"]].sum().reindex(
            range(max_depth + 1), fill_value=0)
        out = pd.DataFrame(dict(
            depth=g.index, larc_frontier=g["frontier"].values, larc_passed=g["passed"].values,
            larc_inconclusive=g["inconclusive"].values,
            fine_intervals_at_depth=[n * 2**d for d in g.index],
            fine_evaluated=[n * 2**max_depth if d == max_depth else 0 for d in g.index],
            coarse_evaluated=[n * 2**coarse_depth if d == coarse_depth else 0 for d in g.index],
        ))
        out["larc_cumulative"] = out["larc_frontier"].cumsum()
        return out

    overall = agg(lv, len(df))
    by_scene = []
    for sc, sub in lv.groupby("scene", sort=False):
        t = agg(sub, sub["traj_id"].nunique())
        t.insert(0, "scene", sc)
        by_scene.append(t)
    return overall, pd.concat(by_scene, ignore_index=True)


def timing_table(layout, df: pd.DataFrame) -> pd.DataFrame:
    b = pd.read_csv(layout.cert_batch_csv).set_index("method")
    rows = []
    for m in METHODS:
        r = b.loc[m]
        rows.append(dict(
            method=m, trajectories=int(r["trajectories"]), evaluations=int(r["evaluations"]),
            batch_s_median=round(float(r["batch_s_median"]), 4), batch_s_min=round(float(r["batch_s_min"]), 4),
            batch_s_max=round(float(r["batch_s_max"]), 4), warm_repeats=int(r["warm_repeats"]),
            first_call_s=round(float(r["first_call_s"]), 3), compile_s=round(float(r["compile_s"]), 3),
            xla_compile_s=round(float(r["xla_compile_s_first_call"]), 3),
            batch_ms_per_trajectory=round(float(r["ms_per_trajectory"]), 3),
            evaluations_per_s=round(float(r["evaluations_per_s"]), 0),
            paired_median_ms=round(_median(df[f"time_{m}_ms"]), 3),
            paired_sum_of_medians_s=round(float(pd.to_numeric(df[f"time_{m}_ms"]).sum()) / 1e3, 3),
        ))
    return pd.DataFrame(rows)


def generation_table(layout, scenes) -> pd.DataFrame:
    rows = []
    att = pd.read_csv(layout.attempts_csv) if layout.attempts_csv.is_file() else pd.DataFrame(
        columns=["scene", "outcome"])
    for sc in list(scenes) + ["total"]:
        sub = att if sc == "total" else att[att["scene"] == sc]
        row = dict(scene=sc, attempts=len(sub))
        for o in OUTCOMES:
            row[o] = int((sub["outcome"] == o).sum())
        rows.append(row)
    rows.append(dict(scene="paper (total)", **PAPER["generation"]))
    return pd.DataFrame(rows)


# ----------------------------------------------------------------------------------------------
# Must-hold checks
# ----------------------------------------------------------------------------------------------


def checks_table(df: pd.DataFrame, gen: pd.DataFrame, config: dict, quick: bool) -> pd.DataFrame:
    n_scenes = len(config.get("scene_order") or config["scenes"])
    pps = int(config.get("quick_pairs_per_scene", 2)) if quick else int(config["pairs_per_scene"])
    fine_n = 2 ** int(config["max_depth"])
    per_scene = df.groupby("scene").size()
    both = df.groupby("pair_id")["variant"].nunique()
    rows = []

    def add(name, expected, observed, ok):
        rows.append(dict(check=name, expected=expected, observed=observed, ok=bool(ok)))

    add(f"{n_scenes} × {2 * pps} trajectories from {n_scenes * pps} accepted pairs",
        f"{n_scenes} scenes × {2 * pps}; {n_scenes * pps} pairs with both variants",
        f"{len(per_scene)} scenes ({', '.join(f'{k} {v}' for k, v in per_scene.items())}); "
        f"{int(both.eq(2).sum())} complete pairs of {len(both)}",
        len(per_scene) == n_scenes and (per_scene == 2 * pps).all() and len(both) == n_scenes * pps
        and both.eq(2).all())
    acc = gen.loc[gen["scene"] == "total", "accepted"]
    acc = int(acc.iloc[0]) if len(acc) else -1
    add("attempts.csv records the accepted pairs", n_scenes * pps, acc, acc == n_scenes * pps)
    bad = df.loc[df["evals_fine"] != fine_n, "traj_id"].tolist()
    add(f"evals_fine = {fine_n} for each trajectory", "all", "all" if not bad else f"{len(bad)} differ: {bad}",
        not bad)
    dis = df.loc[df["certified_larc"] != df["certified_fine"], "traj_id"].tolist()
    add("LARC and fine disagree on no trajectory", "none", ", ".join(dis) if dis else "none", not dis)
    fs = df.loc[df["certified_larc"] & df["audit_collision"], "traj_id"].tolist()
    add("zero FCL-detected false-safe (LARC)", 0, f"{len(fs)}" + (f": {fs}" if fs else ""), not fs)
    op = df[df["scene"] == "open"]
    notroot = op.loc[op["evals_larc"] != 1, "traj_id"].tolist()
    add("every open-scene trajectory passes at the root (evals_larc = 1)", f"{len(op)} of {len(op)}",
        f"{len(op) - len(notroot)} of {len(op)}" + (f"; not: {notroot}" if notroot else ""),
        len(op) > 0 and not notroot)
    return pd.DataFrame(rows)


def load_checks(layout) -> pd.DataFrame:
    p = layout.out / "checks.csv"
    return pd.read_csv(p) if p.is_file() else pd.DataFrame(columns=["check", "expected", "observed", "ok"])


def print_checks(checks: pd.DataFrame):
    print("[stageB] must-hold checks (reported, not asserted):", flush=True)
    for _, r in checks.iterrows():
        ok = _bool(pd.Series([r["ok"]])).iloc[0]
        print(f"[check] {'PASS' if ok else 'FAIL'}  {r['check']}: {r['observed']}", flush=True)


# ----------------------------------------------------------------------------------------------
# README
# ----------------------------------------------------------------------------------------------


def _notes(df: pd.DataFrame, gen: pd.DataFrame, timing: pd.DataFrame, config: dict, layout) -> list[str]:
    s = _stats(df)
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
        parts.append(f"{v} {rej}/{int(clear.sum())} ({_pct(rej, int(clear.sum()))})")
    out.append(f"Conservative rejections: {s['rej']}/{s['clear']} sampled-clear trajectories "
               f"({_pct(s['rej'], s['clear'])}); by variant: {'; '.join(parts)}.")
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


def readme(df, overall, per_scene, rej, frontier, timing, gen, checks, config, quick, layout) -> str:
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
        L.append(f"_Written by hand from the full run's figures (`{DISCUSSION.relative_to(ROOT)}`)._")
        L.append("")
        L.append(DISCUSSION.read_text().strip())
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
# Entry point
# ----------------------------------------------------------------------------------------------


def make_tables(layout, config: dict, quick: bool = False) -> dict:
    from larc_jax.io import atomic_write_text

    out = layout.out
    scenes = list(config.get("scene_order") or config["scenes"])
    df = trajectory_table(layout)
    df["scene"] = pd.Categorical(df["scene"], categories=scenes, ordered=True)
    df = df.sort_values(["scene", "traj_id"]).reset_index(drop=True)
    df["scene"] = df["scene"].astype(str)
    _write(out, "trajectories", df, "Stage B trajectories")
    overall = overall_table(df)
    _write(out, "overall", overall, "Overall results (paper Table II)")
    per_scene = per_scene_table(df, scenes)
    _write(out, "per_scene", per_scene, "Results by scene (paper Table III)")
    rej = rejection_by_variant_table(df)
    _write(out, "rejection_by_variant", rej, "Conservative rejection by variant")
    frontier, frontier_sc = frontier_tables(layout, df, config)
    _write(out, "frontier_levels", frontier, "LARC frontier per depth vs fixed-fine")
    _write(out, "frontier_levels_by_scene", frontier_sc, "LARC frontier per depth and scene")
    timing = timing_table(layout, df)
    _write(out, "batch_timing", timing, "Certification timing: whole batch (compile separately) and paired medians")
    gen = generation_table(layout, scenes)
    _write(out, "generation", gen, "Generation attempts")
    checks = checks_table(df, gen, config, quick)
    _write(out, "checks", checks, "Must-hold checks (reported, not asserted)")
    atomic_write_text(out / "README.md", readme(df, overall, per_scene, rej, frontier, timing, gen, checks,
                                                config, quick, layout))
    return dict(checks_failed=int((~checks["ok"]).sum()))
