"""The report's tables: the pooled summary, the paired changes against 0 s, the per-task view and the episode
list, with their cell formatting."""

from __future__ import annotations

import numpy as np
import pandas as pd

from lq_ros.core.wording import counted
from lq_ros.report import episode_media as media
from lq_ros.report.figures import FIGURE_KEYS
from lq_ros.scoring import aggregate as agg
from lq_ros.scoring.budget import budget_note
from lq_ros.scoring.paired_tests import ALPHA

#: (header, metric, decimals, scale) of the pooled summary table.
SUMMARY_COLUMNS = (
    ("success %", "success", 0, 100.0),
    ("time s (succ.)", "completion_time_s", 2, 1.0),
    ("time s (KM)", "completion_time_rmst", 2, 1.0),
    ("jerk m/s³ (succ.)", "jerk_mean", 2, 1.0),
    ("jerk P90 (succ.)", "jerk_p90", 2, 1.0),
    ("EE-Osc mm (succ.)", "ee_osc", 2, 1000.0),
    ("EE-Osc detrended mm (succ.)", "ee_osc_detrended", 2, 1000.0),
    ("J/step (succ.)", "energy_per_step_j", 2, 1.0),
    ("energy J (succ.)", "energy_total_j", 0, 1.0),
    ("actions/chunk", "actions_per_chunk_mean", 1, 1.0),
)


def summary_table(pooled: pd.DataFrame) -> pd.DataFrame:
    rows = []
    for _, r in pooled.sort_values(list(FIGURE_KEYS)).iterrows():
        row = {"policy": r["policy"], "mode": r["mode"], "latency": agg.cell_latency_label(r),
               "sampling": agg.sampling_label(r), "n": int(r["n"]), "errors": int(r["n_error"])}  # fmt: skip
        for header, metric, decimals, scale in SUMMARY_COLUMNS:
            row[header] = agg.ci_text(r, metric, decimals, scale)
            if metric == "success":
                row["success 95% (tasks)"] = cluster_text(r)
        row["budget"] = budget_note(r)
        row["note"] = f"⚠ degenerate in {counted(int(r['n_degenerate']), 'episode')}" if r.get("n_degenerate") else ""
        rows.append(row)
    return pd.DataFrame(rows)


#: (header, metric, decimals, scale) of the paired table: cell minus zero latency over pairs succeeding in both.
PAIRED_COLUMNS = (
    ("Δ time to success s (all pairs)", "time_to_success_s", 2, 1.0),
    ("Δ time s (both succeed, untested)", "completion_time_s", 2, 1.0),
    ("Δ action ticks", "action_ticks", 0, 1.0),
    ("Δ jerk m/s³", "jerk_mean", 2, 1.0),
    ("Δ EE-Osc mm", "ee_osc", 1, 1000.0),
    ("Δ EE-Osc detrended mm", "ee_osc_detrended", 1, 1000.0),
    ("Δ actuator energy J", "energy_actuator_j", 0, 1.0),
    ("Δ energy J (total, untested)", "energy_total_j", 0, 1.0),
    ("Δ J/step", "energy_per_step_j", 2, 1.0),
)


def paired_table(paired: pd.DataFrame) -> pd.DataFrame:
    """One row per latency > 0 cell: its successes against the zero-latency cell's and the paired changes."""
    rows = []
    for _, r in paired.iterrows():
        zero = f"{r['zero_n_success']}/{r['zero_n']}"
        row = {"policy": r["policy"], "mode": r["mode"], "latency": r.get("latency_label") or agg.cell_latency_label(r),
               "sampling": agg.sampling_label(r),
               "success vs 0 s": f"{count_text(r, 'cell_n_success')}/{outcomes_text(r)} vs {zero}",
               "pairs (all / both succeed)": f"{_count(r.get('n_pairs_all'))} / {int(r['n_pairs'])}"}  # fmt: skip
        for header, metric, decimals, scale in PAIRED_COLUMNS:
            row[header] = agg.ci_text(r, f"{metric}_diff", decimals, scale, signed=True) + _star(r, metric)
        rows.append(row)
    return pd.DataFrame(rows)


#: Marks a paired change whose Benjamini-Hochberg adjusted p (over every change of the report) is below ALPHA.
ADJUSTED_HIT = " *"


def _star(r, metric: str) -> str:
    adjusted = r.get(f"{metric}_diff_p_adjusted")
    return ADJUSTED_HIT if adjusted is not None and not pd.isna(adjusted) and adjusted < ALPHA else ""


def cluster_text(r) -> str:
    """The task-clustered success interval in %, or – with fewer than MIN_N_INTERVAL tasks."""
    lo, hi = r.get("success_cluster_ci_lo"), r.get("success_cluster_ci_hi")
    if lo is None or hi is None or pd.isna(lo) or pd.isna(hi):
        return "–"
    return f"[{100 * lo:.0f}, {100 * hi:.0f}]"


def comparison_table(comparisons: pd.DataFrame) -> pd.DataFrame:
    """paired_policies.csv as a table: A against B over shared episodes, McNemar p and its Holm adjustment (none for a
    comparison whose discordant pairs cannot reach p < 0.05: it is outside the Holm family)."""
    rows = []
    for _, r in comparisons.iterrows():
        latency = agg.cell_latency_label(r)
        rows.append({
            "suite": r["suite"], "latency": latency, "budget": r["budget_counts"], "A": f"{r['arm_a']} · {r['mode_a']}",
            "B": f"{r['arm_b']} · {r['mode_b']}", "pairs": int(r["n_pairs"]), "tasks": int(r["n_tasks"]),
            "A only / B only": f"{int(r['a_only'])} / {int(r['b_only'])}",
            "success A − B (points)": _points(r["diff"], r["diff_ci_lo"], r["diff_ci_hi"]),
            "family": r.get("family", "exploratory"),
            "McNemar p (these tasks)": f"{r['mcnemar_p']:.2g}",
            "Holm p": _holm_text(r),
            "task-level p (other tasks)": _p_text(r.get("cluster_p")),
            "time to success A − B s (RMST)": _seconds(r["rmst_diff_s"], r["rmst_ci_lo"], r["rmst_ci_hi"]),
        })  # fmt: skip
    return pd.DataFrame(rows)


def _p_text(p) -> str:
    return "–" if p is None or pd.isna(p) else f"{p:.2g}"


def _holm_text(r) -> str:
    if not pd.isna(r["p_adjusted"]):
        return f"{r['p_adjusted']:.2g}"
    return "– (identical episodes)" if r.get("family") == "none" else "– (too few discordant)"


def _points(diff: float, lo: float, hi: float) -> str:
    if pd.isna(diff):
        return "–"
    text = f"{100 * diff:+.0f}"
    return text + (f" [{100 * lo:+.0f}, {100 * hi:+.0f}]" if not pd.isna(lo) else " (too few tasks: no interval)")


def _seconds(diff: float, lo: float, hi: float) -> str:
    if pd.isna(diff):
        return "–"
    return f"{diff:+.2f}" + (f" [{lo:+.2f}, {hi:+.2f}]" if not pd.isna(lo) else "")


def _count(value) -> str:
    return "–" if value is None or pd.isna(value) else str(int(value))


def count_text(r, key: str) -> str:
    value = r.get(key)
    return "?" if value is None or pd.isna(value) else str(int(value))


def outcomes_text(r) -> str:
    n = [r.get("cell_n_success"), r.get("n_failure")]
    return "?" if any(v is None or pd.isna(v) for v in n) else str(int(n[0] + n[1]))


EPISODE_COLUMNS = ("policy", "mode", "latency_s", "suite", "task", "init", "seed", "status", "completion_steps",
                   "action_ticks", "hold_ticks", "budget_limited", "jerk_mean", "ee_osc", "ee_osc_detrended",
                   "energy_total_j", "error_reason")  # fmt: skip


def episode_table(episodes: pd.DataFrame) -> pd.DataFrame:
    cols = [c for c in EPISODE_COLUMNS if c in episodes]
    return episodes.sort_values([c for c in ("policy", "mode", "latency_s", "suite", "task", "init", "seed")
                                 if c in episodes])[[*cols, "bag", *media.table_columns(episodes)]]  # fmt: skip


def fmt_cell(v) -> str:
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "–"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def per_task_view(per_task: pd.DataFrame) -> pd.DataFrame:
    cols = [*agg.GROUP_KEYS, "n", "n_error"]
    view = per_task[cols].copy()
    for header, metric, decimals, scale in SUMMARY_COLUMNS:
        view[header] = [agg.ci_text(r, metric, decimals, scale) for _, r in per_task.iterrows()]
    return view
