"""Stage B tables (paper Tables II and III and companions) and the must-hold checks.

Computes, from the stage outputs under ``<out>`` (see :class:`experiments.common.Layout`), each
as a DataFrame (written as ``.csv`` and ``.md``):

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

(:mod:`experiments.stageB_report` writes them, with ``README.md``, as the tables stage).

Definitions (paper, "Sampled MoveIt/FCL Audit"): *sampled-clear* = the audit found no
scene collision at its states; *FCL-detected false-safe* = certified by LARC although the audit
found a scene collision; *conservative rejection* = sampled-clear but not certified by LARC.
Self-collision is reported separately (the certificate concerns link-obstacle separation, A4).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from experiments.common import METHODS, OUTCOMES, VARIANTS, scene_label

__all__ = ["trajectory_table", "overall_table", "per_scene_table", "rejection_by_variant_table",
           "frontier_tables", "timing_table", "generation_table", "checks_table",
           "load_checks", "print_checks", "stats", "as_bool", "pct", "median", "to_markdown", "write_table",
           "PAPER", "TABLES"]

TABLES = ("trajectories", "overall", "per_scene", "rejection_by_variant", "frontier_levels",
          "frontier_levels_by_scene", "batch_timing", "generation", "checks")

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


# ----------------------------------------------------------------------------------------------
# Helpers
# ----------------------------------------------------------------------------------------------


def as_bool(s: pd.Series) -> pd.Series:
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


def write_table(out: Path, name: str, df: pd.DataFrame, title: str):
    from larc_jax.io import atomic_write_text

    atomic_write_text(out / f"{name}.csv", df.to_csv(index=False))
    atomic_write_text(out / f"{name}.md", to_markdown(df, title))


def pct(a: int, b: int) -> str:
    return f"{100.0 * a / b:.1f}%" if b else "—"


def median(x) -> float:
    x = pd.to_numeric(pd.Series(x), errors="coerce").dropna()
    return float(np.median(x)) if len(x) else float("nan")


# ----------------------------------------------------------------------------------------------
# The per-trajectory table
# ----------------------------------------------------------------------------------------------


def trajectory_table(layout) -> pd.DataFrame:
    """One row per trajectory from the certification, audit and timing outputs."""
    cert = pd.read_csv(layout.cert_results_csv)
    cert["certified"] = as_bool(cert["certified"])
    base = cert[cert["method"] == "larc"][["traj_id", "scene", "pair_id", "variant", "duration_s",
                                          "n_waypoints"]].set_index("traj_id")
    for m in METHODS:
        sub = cert[cert["method"] == m].set_index("traj_id")
        base[f"certified_{m}"] = sub["certified"]
        base[f"evals_{m}"] = sub["evaluations"].astype(int)
    audit = pd.read_csv(layout.audit_csv).set_index("traj_id")
    base["audit_states"] = audit["audit_states"].astype(int)
    base["audit_collision"] = as_bool(audit["audit_collision"])
    larc = cert[cert["method"] == "larc"].set_index("traj_id")
    fine = cert[cert["method"] == "fine"].set_index("traj_id")
    base["min_clearance_m"] = larc["min_clearance_m"]
    timing = pd.read_csv(layout.timing_summary_csv).set_index("traj_id")
    for m in METHODS:
        base[f"time_{m}_ms"] = timing[f"time_{m}_ms"]
    base["self_collision"] = as_bool(audit["self_collision"])
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


def stats(df: pd.DataFrame) -> dict:
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
        med_ms={m: median(df[f"time_{m}_ms"]) for m in METHODS},
        speedup=median(df["speedup_fine_over_larc"]),
        self_coll=int(df["self_collision"].sum()),
    )
    s["ratio"] = s["evals"]["larc"] / s["evals"]["fine"] if s["evals"]["fine"] else float("nan")
    return s


def overall_table(df: pd.DataFrame, P=PAPER) -> pd.DataFrame:
    s = stats(df)
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
        ("Conservative rejection", f"{s['rej']}/{s['clear']} ({pct(s['rej'], s['clear'])})",
         "Relative to the sampled audit",
         f"{P['rejection']}/{P['sampled_clear']} ({pct(P['rejection'], P['sampled_clear'])})",
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
        s = stats(sub)
        rows.append(dict(
            scene=scene_label(sc) if sc != "overall" else "Overall",
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
            rejections=rej, rejection_rate=f"{rej}/{int(clear.sum())} ({pct(rej, int(clear.sum()))})",
            paper=f"{pv[0]}/{pv[1]} ({pct(*pv)})",
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
            paired_median_ms=round(median(df[f"time_{m}_ms"]), 3),
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
        ok = as_bool(pd.Series([r["ok"]])).iloc[0]
        print(f"[check] {'PASS' if ok else 'FAIL'}  {r['check']}: {r['observed']}", flush=True)


