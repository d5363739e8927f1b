"""``lq report``: the paper's figures (Figs. 4-7) with 95 % CIs, tables, provenance, an HTML and a markdown page.

Input is a sweep folder (its ``results/`` store, see lq_ros/run/sweep/store.py) or any folder of episode bags
(scored on the fly). Figures pool every task and init state of a (policy, mode, latency) cell; the
per-task aggregate table is written beside them. Aggregation rules and CIs come from lq_ros/scoring/aggregate.py.
"""

from __future__ import annotations

import html
import json
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only, never a display

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from lq_ros.core.suite_constants import CONTROL_DT_S  # noqa: E402
from lq_ros.report import async_figures as report_async
from lq_ros.report import episode_media as media  # noqa: E402
from lq_ros.scoring import aggregate as agg  # noqa: E402
from lq_ros.scoring import metrics  # noqa: E402

#: Figures pool tasks and init states: one point per (policy, protocol, latency) at one sampling of the
#: trajectory and energy metrics (rates never pool: jerk at 20 Hz and at 500 Hz differ ~4x).
FIGURE_KEYS = ("policy", "mode", "latency_s", "latency_dist", "trajectory_rate_hz", "energy_sampling")
#: One line of a figure.
SERIES_KEYS = ("policy", "mode", "trajectory_rate_hz", "energy_sampling")
MODE_STYLE = {"sync": "--", "async": "-"}
MODE_MARKER = {"sync": "s", "async": "o"}
#: Stacked segments of Fig. 6: (per-episode column, label, colour).
ENERGY_PARTS = (
    ("energy_mech_j", "mechanical", "#4c72b0"),
    ("energy_elec_j", "electrical loss", "#dd8452"),
    ("energy_overhead_j", "overhead", "#8c8c8c"),
)
FIGURES = {
    "fig4_success": "Fig. 4 - success rate vs injected latency",
    "fig5_trajectory": "Fig. 5 - trajectory quality vs injected latency",
    "fig6_energy_decomposition": "Fig. 6 - per-step energy decomposition",
    "fig7_energy": "Fig. 7 - per-step and total energy",
    report_async.NAME: report_async.TITLE,
    "fig9_time_to_success": "Fig. 9 - time to success (Kaplan-Meier; failures censored at their end)",
}
#: Legend names of the two step budgets (``budget_counts``), and the line style of the action budget (the paper
#: budget keeps its protocol's style).
BUDGET_LABEL = {"all": "paper budget (holds count)", "action": "action budget"}
ACTION_BUDGET_STYLE = ":"
#: Footnote of a figure that marks budget-decided cells.
BUDGET_FOOTNOTE = (
    "hollow marker: budget-decided cell, at least half of its timeouts budget-limited (holds spent the paper budget "
    "before the policy had the action ticks it needs; see the report's notes)"
)
#: (metric, sentence name, decimals, scale, unit) of the paired changes the report's sentences name.
PAIRED_SENTENCE = (
    ("completion_time_s", "completion time", 2, 1.0, "s"),
    ("action_ticks", "action ticks", 0, 1.0, ""),
    ("jerk_mean", "mean jerk", 2, 1.0, "m/s³"),
    ("ee_osc", "paper EE-Osc", 1, 1000.0, "mm"),
    ("ee_osc_detrended", "detrended EE-Osc", 1, 1000.0, "mm"),
    ("energy_total_j", "total energy", 0, 1.0, "J"),
)


# -- data ------------------------------------------------------------------------------------


def sweep_manifest(results_dir: Path) -> set[str] | None:
    """Episode keys of the sweep's current spec (None: not a sweep folder)."""
    path = Path(results_dir) / "manifest.json"
    return set(json.loads(path.read_text())["episodes"]) if path.exists() else None


def load_episodes(results_dir: Path, *, all_episodes: bool = False) -> pd.DataFrame:
    """Per-episode rows of a sweep folder (from its store) or of every bag below ``results_dir``.

    In a sweep folder only the episodes of its current spec (manifest.json) are used, so every
    series pools the same tasks; ``all_episodes`` takes every finished record in the store.
    ``bag`` is kept relative to ``results_dir`` so the report's links survive moving the folder.
    """
    from lq_ros.run.sweep import ResultStore

    results_dir = Path(results_dir)
    store = ResultStore(results_dir)
    if store.results.is_dir():
        wanted = None if all_episodes else sweep_manifest(results_dir)
        rows = []
        for record in store.records():
            if wanted is not None and record["key"] not in wanted:
                continue
            row = dict(record["row"])
            row.update(bag=record.get("bag"), key=record["key"], attempts=len(record.get("attempts", [])))
            row["log"] = record["attempts"][-1].get("log") if record.get("attempts") else None
            rows.append(row)
        for row in rows:
            versions = row.get("versions") or {}
            row["git_commit"] = versions.get("git_commit") if isinstance(versions, dict) else None
            for key in ("versions", "null_reasons", "warnings"):
                if key in row and not isinstance(row[key], str):
                    row[key] = json.dumps(row[key], sort_keys=True, default=str)
        frame = agg.episodes_frame(rows)
    else:
        frame = agg.score_directory(results_dir)
        if "bag" in frame:
            frame["bag"] = [os.path.relpath(b, results_dir) if isinstance(b, str) else b for b in frame["bag"]]
    if frame.empty or frame["status"].isna().all():
        raise FileNotFoundError(f"no scored episodes in {results_dir} (neither results/*.json nor bags)")
    return add_energy_parts_per_step(frame)


def add_energy_parts_per_step(episodes: pd.DataFrame) -> pd.DataFrame:
    """``<part>_per_step_j`` = part x (energy_per_step_j / energy_total_j): the scorer's own step count;
    ``energy_actuator_per_step_j`` = mechanical + electrical loss per step."""
    out = episodes.copy()
    total = pd.to_numeric(out.get("energy_total_j"), errors="coerce")
    per_step = pd.to_numeric(out.get("energy_per_step_j"), errors="coerce")
    ratio = per_step / total.where(total > 0)
    for col, _, _ in ENERGY_PARTS:
        out[col.replace("_j", "_per_step_j")] = pd.to_numeric(out.get(col), errors="coerce") * ratio
    out["energy_actuator_per_step_j"] = out["energy_mech_per_step_j"] + out["energy_elec_per_step_j"]
    return out


def figure_aggregates(episodes: pd.DataFrame, *, n_boot: int = 2000, seed: int = 0) -> pd.DataFrame:
    """aggregate() pooled per FIGURE_KEYS, plus the per-step energy parts of Fig. 6 (over successful
    episodes, like every energy and trajectory mean; see lq_ros/scoring/aggregate.py)."""
    pooled = agg.aggregate(episodes, by=FIGURE_KEYS, n_boot=n_boot, seed=seed)
    with_outcome = episodes["status"] == "success"
    for name in [c.replace("_j", "_per_step_j") for c, _, _ in ENERGY_PARTS] + ["energy_actuator_per_step_j"]:
        means, lows, highs = [], [], []
        for _, row in pooled.iterrows():
            mask = with_outcome.copy()
            for k in FIGURE_KEYS:
                mask &= episodes[k] == row[k]
            values = pd.to_numeric(episodes.loc[mask, name], errors="coerce").to_numpy(dtype=np.float64)
            values = values[np.isfinite(values)]
            if len(values):
                lo, hi = metrics.bootstrap_ci(values, 0.95, n_boot, seed)
                means.append(float(values.mean()))
                lows.append(lo)
                highs.append(hi)
            else:
                means.append(math.nan)
                lows.append(math.nan)
                highs.append(math.nan)
        pooled[f"{name}_mean"], pooled[f"{name}_ci_lo"], pooled[f"{name}_ci_hi"] = means, lows, highs
    # The series a cell belongs to whatever its budget (Fig. 4 draws both budgets of a variant in one colour).
    series = dict(zip(episodes["policy"], agg.base_labels(episodes, ("budget_counts",)), strict=True))
    pooled["series_policy"] = pooled["policy"].map(series)
    pooled["latency_label"] = [agg.cell_latency_label(r) for _, r in pooled.iterrows()]
    return pooled


def paired_aggregates(episodes: pd.DataFrame, pooled: pd.DataFrame, *, n_boot: int = 2000, seed: int = 0):
    """agg.paired_differences per figure cell, with each cell's latency label and budget attribution."""
    paired = agg.paired_differences(episodes, by=FIGURE_KEYS, n_boot=n_boot, seed=seed)
    if paired.empty:
        return paired
    extra = ["latency_label", "series_policy", "budget_counts", "budget_decided", "n_success", "n_failure",
             "n_budget_limited", "n_policy_limited", "n_budget_unattributed", "action_budget_n",
             "action_budget_success_rate"]  # fmt: skip
    cells = pooled[[*FIGURE_KEYS, *extra]].rename(columns={"n_success": "cell_n_success"})
    paired = paired.merge(cells, on=list(FIGURE_KEYS), how="left")
    # Read in order: per variant and protocol, the paper budget before the action budget, latency ascending.
    paired["_budget_order"] = (paired["budget_counts"] != "all").astype(int)
    paired["_variant"] = paired["series_policy"].astype(str).str.replace(r"(, )?latency=\w+", "", regex=True)
    order = ["_variant", "mode", "_budget_order", "latency_s", "latency_dist"]
    paired = paired.sort_values(order, kind="stable").drop(columns=["_budget_order", "_variant"])
    return paired.reset_index(drop=True)


# -- figures ---------------------------------------------------------------------------------


def _series(pooled: pd.DataFrame) -> list[tuple[str, str, pd.DataFrame]]:
    """(policy label, mode, rows sorted by latency) for every series present. The policy label names
    the sampling too when the report mixes samplings (the axis labels name it otherwise)."""
    mixed = len(_samplings(pooled)) > 1
    out = []
    for key, rows in pooled.groupby(list(SERIES_KEYS), sort=True, dropna=False):
        policy, mode = str(key[0]), str(key[1])
        label = f"{policy} ({agg.sampling_label(rows.iloc[0])})" if mixed else policy
        out.append((label, mode, rows.sort_values("latency_s")))
    return out


def _samplings(pooled: pd.DataFrame) -> list[str]:
    return sorted({agg.sampling_label(r) for _, r in pooled.iterrows()})


def _degenerate_points(ax, rows: pd.DataFrame, y, scale: float = 1.0) -> None:
    """Ring the points of cells where async chunks executed nothing fresh (see the summary's note)."""
    bad = rows["n_degenerate"].fillna(0).to_numpy() > 0
    if bad.any():
        y = np.asarray(y, dtype=np.float64)[bad] * scale
        ax.scatter(rows["latency_s"].to_numpy()[bad], y, s=160, facecolors="none", edgecolors="red", zorder=5)


def _colours(pooled: pd.DataFrame) -> dict[str, str]:
    cycle = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    labels = sorted({label for label, _, _ in _series(pooled)})
    return {p: cycle[i % len(cycle)] for i, p in enumerate(labels)}


def _ci_line(ax, x, mean, lo, hi, *, colour: str, mode: str, label: str, scale: float = 1.0,
             style: str | None = None) -> None:  # fmt: skip
    mean, lo, hi = (np.asarray(v, dtype=np.float64) * scale for v in (mean, lo, hi))
    line = style or MODE_STYLE.get(mode, "-")
    ax.plot(x, mean, line, marker=MODE_MARKER.get(mode, "o"), color=colour, label=label)
    ax.fill_between(x, lo, hi, color=colour, alpha=0.15, linewidth=0)


def _metric_line(ax, rows: pd.DataFrame, metric: str, *, colour: str, mode: str, label: str, scale: float = 1.0):
    """A metric's mean vs latency with its 95 % band; a point with fewer than agg.MIN_N_INTERVAL values has no
    band (aggregate gives it no interval): its values are drawn as dots and its n written beside it."""
    x = rows["latency_s"].to_numpy(dtype=np.float64)
    _ci_line(ax, x, rows[f"{metric}_mean"], rows[f"{metric}_ci_lo"], rows[f"{metric}_ci_hi"],
             colour=colour, mode=mode, label=label, scale=scale)  # fmt: skip
    if f"{metric}_values" not in rows:
        return
    for xi, n, values, mean in zip(x, rows[f"{metric}_n"], rows[f"{metric}_values"], rows[f"{metric}_mean"],
                                   strict=True):  # fmt: skip
        if not isinstance(values, str) or not values or not 0 < n < agg.MIN_N_INTERVAL:
            continue
        ys = np.asarray(json.loads(values), dtype=np.float64) * scale
        ax.scatter(np.full(len(ys), xi), ys, s=10, color=colour, alpha=0.6, zorder=4, linewidths=0)
        ax.annotate(f"n={int(n)}", (xi, mean * scale), xytext=(4, 4), textcoords="offset points", fontsize=6,
                    color=colour)  # fmt: skip


#: How a figure says which points have no interval.
SMALL_N_NOTE = f"no band below n={agg.MIN_N_INTERVAL}: dots are the values"


def _latency_ticks(pooled: pd.DataFrame) -> tuple[list[float], list[str]]:
    """Applied constant latencies (s) and their labels with N, the ticks each inference occupies."""
    values = sorted(pooled.loc[_constant(pooled), "latency_s"].astype(float).unique())
    return values, [f"{v:g}\nN={round(v / CONTROL_DT_S)}" for v in values]


def _constant(pooled: pd.DataFrame) -> pd.Series:
    dist = pooled.get("latency_dist", pd.Series("constant", index=pooled.index))
    return dist.isna() | dist.isin(["constant", ""])


def _distribution_ticks(pooled: pd.DataFrame) -> tuple[list[float], list[str]]:
    """Expected applied latencies (s) of the distribution cells that no constant cell has, with E[N]: drawn as
    minor ticks below the constant ones (a distribution's mean sits between the whole-tick latencies)."""
    constant = set(pooled.loc[_constant(pooled), "latency_s"].astype(float))
    values = sorted(set(pooled.loc[~_constant(pooled), "latency_s"].astype(float)) - constant)
    return values, [f"{v:g}\nE[N]={v / CONTROL_DT_S:.3g}" for v in values]


def _latency_axis(ax, pooled: pd.DataFrame) -> None:
    ax.set_xlabel(f"applied latency Δt_sim = N × {CONTROL_DT_S:g} s (grey: distribution means)", fontsize=9)
    ax.set_xticks(*_latency_ticks(pooled))
    dist_values, dist_labels = _distribution_ticks(pooled)
    if dist_values:
        ax.set_xticks(dist_values, dist_labels, minor=True)
        ax.tick_params(axis="x", which="minor", pad=26, labelsize=8, colors="dimgray")
    else:
        ax.set_xlabel(f"applied latency Δt_sim = N × {CONTROL_DT_S:g} s")
    ax.grid(alpha=0.3)


def _legends_below(fig, legend_axes, *, ncol: int = 1, title: str = "policy", footnote: str = "") -> None:
    """Lay ``fig`` out with each of ``legend_axes``' legends under it (the figure grows to make room) and an
    optional footnote at the bottom: a legend inside a panel hides its data."""
    rows = max(math.ceil(len(ax.get_legend_handles_labels()[1]) / ncol) for ax in legend_axes)
    legend_in, footnote_in = 0.35 + 0.16 * rows, 0.25 if footnote else 0.0
    width_in, height_in = fig.get_size_inches()
    fig.set_size_inches(width_in, height_in + legend_in + footnote_in)
    bottom = (legend_in + footnote_in) / (height_in + legend_in + footnote_in)
    fig.tight_layout(rect=(0, bottom, 1, 1))
    for ax in legend_axes:  # one legend: centred under the figure; one per panel: under its panel
        pos = ax.get_position()
        x = 0.5 if len(legend_axes) == 1 else pos.x0 + pos.width / 2
        fig.legend(*ax.get_legend_handles_labels(), title=title, fontsize=7, title_fontsize=8, ncol=ncol,
                   loc="upper center", bbox_to_anchor=(x, bottom))  # fmt: skip
    if footnote:
        fig.text(0.01, 0.01, footnote, fontsize=7, ha="left", va="bottom")


def _rate_note(pooled: pd.DataFrame) -> str:
    return "; ".join(_samplings(pooled))


def fig_success(pooled: pd.DataFrame) -> plt.Figure:
    """Fig. 4: one panel per protocol, one line per policy, shaded 95 % Wilson interval."""
    modes = [m for m in ("sync", "async") if m in set(pooled["mode"])] + sorted(set(pooled["mode"]) - {"sync", "async"})
    colours = _colours(pooled)
    decided = pooled.get("budget_decided", pd.Series(dtype=bool)).fillna(False).astype(bool).any()
    fig, axes = plt.subplots(1, len(modes), figsize=(5.5 * len(modes), 4.4), squeeze=False, sharey=True)
    budgets = set(pooled.get("budget_counts", pd.Series(dtype=object)).dropna())
    both = {"all", "action"} <= budgets
    for ax, mode in zip(axes[0], modes, strict=True):
        for policy, m, rows in _series(pooled):
            if m != mode:
                continue
            budget = rows["budget_counts"].iloc[0] if "budget_counts" in rows else "all"
            base = rows["series_policy"].iloc[0] if "series_policy" in rows else policy
            colour = colours.get(base, colours[policy])
            label = f"{base} · {BUDGET_LABEL.get(budget, budget)}" if both else policy
            style = ACTION_BUDGET_STYLE if budget == "action" else None
            _ci_line(ax, rows["latency_s"], rows["success_rate"], rows["success_ci_lo"], rows["success_ci_hi"],
                     colour=colour, mode=mode, label=label, scale=100.0, style=style)  # fmt: skip
            _degenerate_points(ax, rows, rows["success_rate"], 100.0)
            _budget_decided_points(ax, rows, colour, mode)
            _distribution_labels(ax, rows, colour)
        ax.set_title(f"{mode} execution")
        ax.set_ylim(-2, 102)
        ax.margins(x=0.12)
        _latency_axis(ax, pooled)
    axes[0][0].set_ylabel("success rate (%) [95% CI]")
    fig.suptitle(FIGURES["fig4_success"])
    _legends_below(fig, axes[0], footnote=BUDGET_FOOTNOTE if decided else "")
    return fig


def _budget_decided_points(ax, rows: pd.DataFrame, colour: str, mode: str) -> None:
    """Hollow markers on the cells where the budget, not the policy, decided the timeouts."""
    decided = rows.get("budget_decided", pd.Series(False, index=rows.index)).fillna(False).astype(bool).to_numpy()
    if decided.any():
        ax.scatter(rows["latency_s"].to_numpy()[decided], 100.0 * rows["success_rate"].to_numpy()[decided],
                   s=90, marker=MODE_MARKER.get(mode, "o"), facecolors="white", edgecolors=colour, linewidths=1.8,
                   zorder=6)  # fmt: skip


def _distribution_labels(ax, rows: pd.DataFrame, colour: str) -> None:
    """Name a distribution cell's point by its distribution and realised mean (agg.cell_latency_label)."""
    for _, r in rows.iterrows():
        dist = r.get("latency_dist")
        if isinstance(dist, str) and dist and dist != "constant":
            text = r.get("latency_label") or agg.cell_latency_label(r)
            y = 100.0 * r["success_rate"]
            ax.annotate(text.replace(" (", "\n("), (r["latency_s"], y), xytext=(-6, -16 if y > 50 else 8),
                        textcoords="offset points", fontsize=6, color=colour, ha="right")  # fmt: skip


def fig_trajectory(pooled: pd.DataFrame) -> plt.Figure:
    """Fig. 5: mean jerk, P90 jerk, the paper's EE-Osc and the detrended EE-Osc vs latency, one line per (policy,
    protocol), over successful episodes at the sampling named in the title. The two EE-Osc panels share their
    y axis: the paper's spreads the window's positions about their mean, so travel in the last 0.5 s counts;
    the detrended one about the window's straight line, so only back-and-forth does."""
    panels = (
        ("jerk_mean", "mean jerk (m/s³)", None),
        ("jerk_p90", "P90 jerk (m/s³)", None),
        ("ee_osc", "EE-Osc, paper A.3 (mm)", "about the window's mean: travel counts"),
        ("ee_osc_detrended", "EE-Osc detrended (mm)", "about the window's straight line: back-and-forth only"),
    )
    colours = _colours(pooled)
    fig, axes = plt.subplots(1, len(panels), figsize=(5.0 * len(panels), 4.3), squeeze=False)
    for ax, (metric, label, title) in zip(axes[0], panels, strict=True):
        scale = 1000.0 if metric.startswith("ee_osc") else 1.0
        for policy, mode, rows in _series(pooled):
            _metric_line(ax, rows, metric, colour=colours[policy], mode=mode, label=f"{policy} · {mode}", scale=scale)
        ax.set_ylabel(f"{label} [95% CI]")
        if title:
            ax.set_title(title, fontsize=9)
        _latency_axis(ax, pooled)
    low = min(ax.get_ylim()[0] for ax in axes[0][2:])
    high = max(ax.get_ylim()[1] for ax in axes[0][2:])
    for ax in axes[0][2:]:
        ax.set_ylim(low, high)  # the same scale: the detrended value is the part of the paper's that is not travel
    fig.suptitle(f"{FIGURES['fig5_trajectory']} (successful episodes; {_rate_note(pooled)}; {SMALL_N_NOTE})")
    _legends_below(fig, axes[0][:1], ncol=2, title="policy · protocol")
    return fig


def _stacked_bars(ax, pooled: pd.DataFrame, parts, total_metric: str) -> None:
    """Per latency, one stacked bar per (policy, protocol); whisker: 95 % CI of ``total_metric``."""
    series = _series(pooled)
    latencies = sorted(pooled["latency_s"].astype(float).unique())
    width = 0.8 / max(1, len(series))
    for i, (policy, mode, rows) in enumerate(series):
        by_lat = rows.set_index(rows["latency_s"].astype(float))
        x = np.arange(len(latencies)) - 0.4 + width * (i + 0.5)
        bottom = np.zeros(len(latencies))
        for col, label, colour in parts:
            name = col.replace("_j", "_per_step_j") + "_mean"
            h = np.nan_to_num(np.array([by_lat[name].get(lat, np.nan) for lat in latencies], dtype=np.float64))
            ax.bar(x, h, width * 0.92, bottom=bottom, color=colour, edgecolor="white",
                   hatch="//" if mode == "sync" else None, label=label if i == 0 else None)  # fmt: skip
            bottom += h
        lo = np.array([by_lat[f"{total_metric}_ci_lo"].get(lat, np.nan) for lat in latencies])
        hi = np.array([by_lat[f"{total_metric}_ci_hi"].get(lat, np.nan) for lat in latencies])
        ax.errorbar(x, bottom, yerr=[np.clip(bottom - lo, 0, None), np.clip(hi - bottom, 0, None)], fmt="none",
                    ecolor="black", capsize=3)  # fmt: skip
        for xi in x:
            ax.annotate(f"{policy}\n{mode}", (xi, 0), xytext=(0, -26), textcoords="offset points", ha="center",
                        fontsize=6, annotation_clip=False)  # fmt: skip
    ax.set_xticks(np.arange(len(latencies)), [f"{lat:g} s (N={round(lat / CONTROL_DT_S)})" for lat in latencies])
    ax.tick_params(axis="x", pad=30)
    ax.set_xlabel("injected latency Δt_sim (bars: policy · protocol; hatched: sync)")
    ax.set_ylim(0, ax.get_ylim()[1] * 1.18)  # room for the legend above the bars
    ax.legend(loc="upper center", ncol=len(parts), fontsize=8)
    ax.grid(axis="y", alpha=0.3)


def fig_energy_decomposition(pooled: pd.DataFrame) -> plt.Figure:
    """Fig. 6: per-step energy as stacked bars per latency and (policy, protocol): (a) mechanical +
    electrical loss + overhead, (b) the actuator part alone (the constant overhead hides it in (a))."""
    n_bars = len(_series(pooled)) * pooled["latency_s"].nunique()
    fig, axes = plt.subplots(1, 2, figsize=(max(10.0, 1.1 * n_bars), 4.8), squeeze=False)
    _stacked_bars(axes[0][0], pooled, ENERGY_PARTS, "energy_per_step_j")
    axes[0][0].set_ylabel("energy per control step (J) [95% CI of total]")
    axes[0][0].set_title("(a) mechanical + electrical loss + overhead")
    _stacked_bars(axes[0][1], pooled, ENERGY_PARTS[:2], "energy_actuator_per_step_j")
    axes[0][1].set_ylabel("energy per control step (J) [95% CI of sum]")
    axes[0][1].set_title("(b) actuators: mechanical + electrical loss")
    fig.suptitle(f"{FIGURES['fig6_energy_decomposition']} (successful episodes; {_rate_note(pooled)})")
    fig.tight_layout()
    return fig


def fig_energy(pooled: pd.DataFrame) -> plt.Figure:
    """Fig. 7: (a) per-step energy, (b) total episode energy vs latency."""
    panels = (("energy_per_step_j", "(a) energy per control step (J)"), ("energy_total_j", "(b) total energy (J)"))
    colours = _colours(pooled)
    fig, axes = plt.subplots(1, 2, figsize=(11.0, 4.0), squeeze=False)
    for ax, (metric, label) in zip(axes[0], panels, strict=True):
        for policy, mode, rows in _series(pooled):
            _metric_line(ax, rows, metric, colour=colours[policy], mode=mode, label=f"{policy} · {mode}")
        ax.set_ylabel(f"{label} [95% CI]")
        _latency_axis(ax, pooled)
    fig.suptitle(f"{FIGURES['fig7_energy']} (successful episodes; {_rate_note(pooled)}; {SMALL_N_NOTE})")
    _legends_below(fig, axes[0][:1], ncol=2, title="policy · protocol")
    return fig


#: Panels of Fig. 9: (agg.TIME_TO_SUCCESS_AXES key, x label).
TIME_TO_SUCCESS_PANELS = (
    ("sim_s", "sim time (s)"),
    ("action_ticks", "action ticks (ticks whose command came from a chunk)"),
)


def fig_time_to_success(episodes: pd.DataFrame, pooled: pd.DataFrame) -> plt.Figure:
    """Fig. 9: Kaplan-Meier fraction succeeded by t, one row per (policy variant, protocol), one curve per latency
    cell (and budget), in sim seconds and in action ticks; a failure is censored at its end (tick marks). A
    slower cell's curve rises later, a failing cell's stops lower: the two are different things."""
    eps = episodes.copy()
    # One row per variant and protocol: its constant latencies, distributions and both budgets together.
    eps["series_policy"] = agg.base_labels(eps, ("budget_counts", "latency_dist"))
    # One sampling per episode: a bag scored at two rates is one episode here (its outcome does not depend on it).
    samplings = [agg.sampling_label(r) for _, r in eps.iterrows()]
    eps = eps[[label == min(samplings) for label in samplings]] if samplings else eps
    groups = [(p, m) for (p, m), _ in eps.groupby(["series_policy", "mode"], sort=True)]
    both = {"all", "action"} <= set(eps["budget_counts"].dropna())
    labels = {  # the cell's own label: a distribution's realised mean differs between cells
        (r["policy"], r["mode"], r["latency_s"], r["latency_dist"]): r.get("latency_label") or agg.cell_latency_label(r)
        for _, r in pooled.iterrows()
    }
    fig, axes = plt.subplots(max(1, len(groups)), 2, figsize=(15.0, 3.6 * max(1, len(groups))), squeeze=False)
    for (policy, mode), row_axes in zip(groups, axes, strict=False):
        rows = eps[(eps["series_policy"] == policy) & (eps["mode"] == mode)]
        cells = sorted({(float(r.latency_s), str(r.latency_dist)) for r in rows.itertuples()})
        cmap = plt.get_cmap("plasma")  # ordered by latency; its light end is left out (invisible on white)
        colours = {cell: cmap(0.8 * i / max(1, len(cells) - 1)) for i, cell in enumerate(cells)}
        for (axis, xlabel), ax in zip(TIME_TO_SUCCESS_PANELS, row_axes, strict=True):
            rows = rows.assign(_budget_order=(rows["budget_counts"] != "all").astype(int))
            cell_keys = ["_budget_order", "latency_s", "latency_dist", "policy", "budget_counts"]
            for (_, latency, dist, variant, budget), cell_rows in rows.groupby(cell_keys, sort=True):
                times, events = agg.time_to_success(cell_rows, axis)
                if not len(times):
                    continue
                t, survival = agg.kaplan_meier(times, events)
                xs, ys = np.append(t, times.max()), 100.0 * (1.0 - np.append(survival, survival[-1]))
                colour = colours[(float(latency), str(dist))]
                label = labels.get((variant, mode, latency, dist)) or f"{latency:g} s"
                if both:
                    label += f" · {'paper' if budget == 'all' else budget} budget"
                style = ACTION_BUDGET_STYLE if budget == "action" else "-"
                ax.step(xs, ys, where="post", color=colour, linestyle=style, label=f"{label} (n={len(times)})")
                censored = times[~events]
                at = survival[np.searchsorted(t, censored, side="right") - 1]
                ax.plot(censored, 100.0 * (1.0 - at), "|", color=colour, markersize=9, markeredgewidth=1.5)
            ax.set_xlabel(xlabel)
            ax.set_ylim(-2, 102)
            ax.grid(alpha=0.3)
        row_axes[0].set_ylabel("succeeded by t (%)")
        row_axes[0].set_title(f"{policy} · {mode}", loc="left", fontsize=9)
        title = "latency" + (" · budget (paper: holds count; dotted: action)" if both else "")
        row_axes[1].legend(fontsize=7, title=f"{title}\nfailures: | at their end", title_fontsize=7, loc="upper left",
                           bbox_to_anchor=(1.02, 1.0))  # fmt: skip
    fig.suptitle(FIGURES["fig9_time_to_success"])
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.4 / fig.get_figheight()))  # the title keeps 0.4 in above the panels
    return fig


def make_figures(pooled: pd.DataFrame, episodes: pd.DataFrame | None = None) -> dict[str, plt.Figure]:
    """Figs. 4-7 from the pooled cells; Fig. 9 (time to success) needs the episodes."""
    figures = {
        "fig4_success": fig_success(pooled),
        "fig5_trajectory": fig_trajectory(pooled),
        "fig6_energy_decomposition": fig_energy_decomposition(pooled),
        "fig7_energy": fig_energy(pooled),
    }
    if episodes is not None:
        figures["fig9_time_to_success"] = fig_time_to_success(episodes, pooled)
    return figures


# -- pages -----------------------------------------------------------------------------------


def provenance(episodes: pd.DataFrame, results_dir: Path) -> dict[str, str]:
    """What produced these numbers: versions, commits, seeds, transports, spec."""
    out: dict[str, str] = {}
    versions: dict[str, set] = {}
    for raw in episodes.get("versions", pd.Series(dtype=object)).dropna():
        try:
            v = json.loads(raw) if isinstance(raw, str) else raw
        except ValueError:
            continue
        for k, val in (v or {}).items():
            versions.setdefault(k, set()).add(str(val))
    for k in sorted(versions):
        out[k] = ", ".join(sorted(versions[k]))
    for col, label in (("seed", "seeds"), ("init", "init states"), ("transport", "transports"),
                       ("suite", "suites"), ("task", "tasks")):  # fmt: skip
        if col in episodes:
            vals = sorted({v for v in episodes[col].dropna()}, key=lambda v: (str(type(v)), v))
            out[label] = ", ".join(str(v) for v in vals)
    spec = Path(results_dir) / "sweep.yaml"
    if spec.exists():
        out["sweep spec"] = str(spec.name)
    out["episodes"] = str(len(episodes))
    manifest = sweep_manifest(results_dir)
    if manifest is not None:
        done = set(episodes["key"].dropna()) if "key" in episodes else set()
        out["episodes of the spec not finished"] = str(len(manifest - done))
    return out


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
        row["budget"] = agg.budget_note(r)
        row["note"] = f"⚠ degenerate in {int(r['n_degenerate'])} episodes" if r.get("n_degenerate") else ""
        rows.append(row)
    return pd.DataFrame(rows)


#: (header, metric, decimals, scale) of the paired table: cell minus zero latency over pairs succeeding in both.
PAIRED_COLUMNS = (
    ("Δ time s", "completion_time_s", 2, 1.0),
    ("Δ action ticks", "action_ticks", 0, 1.0),
    ("Δ jerk m/s³", "jerk_mean", 2, 1.0),
    ("Δ EE-Osc mm", "ee_osc", 1, 1000.0),
    ("Δ EE-Osc detrended mm", "ee_osc_detrended", 1, 1000.0),
    ("Δ energy J", "energy_total_j", 0, 1.0),
    ("Δ J/step", "energy_per_step_j", 2, 1.0),
)


def paired_table(paired: pd.DataFrame) -> pd.DataFrame:
    """One row per latency > 0 cell: its successes against the zero-latency cell's and the paired changes."""
    rows = []
    for _, r in paired.iterrows():
        row = {"policy": r["policy"], "mode": r["mode"], "latency": r.get("latency_label") or agg.cell_latency_label(r),
               "sampling": agg.sampling_label(r),
               "success vs 0 s": f"{_count(r, 'cell_n_success')}/{_outcomes(r)} vs {r['zero_n_success']}/{r['zero_n']}",
               "pairs": int(r["n_pairs"])}  # fmt: skip
        for header, metric, decimals, scale in PAIRED_COLUMNS:
            row[header] = agg.ci_text(r, f"{metric}_diff", decimals, scale, signed=True)
        rows.append(row)
    return pd.DataFrame(rows)


def _count(r, key: str) -> str:
    value = r.get(key)
    return "?" if value is None or pd.isna(value) else str(int(value))


def _outcomes(r) -> str:
    n = [r.get("cell_n_success"), r.get("n_failure")]
    return "?" if any(v is None or pd.isna(v) for v in n) else str(int(n[0] + n[1]))


def paired_sentences(paired: pd.DataFrame) -> list[str]:
    """The report's findings, one sentence per latency > 0 cell: success against latency 0, what decided its
    timeouts, and the paired changes (never a comparison of success-only means over different task mixes)."""
    lines = []
    for _, r in paired.iterrows():
        latency = r.get("latency_label") or agg.cell_latency_label(r)
        text = f"**{r['policy']} · {r['mode']}, {latency}** against 0 s: "
        if not r["zero_n"]:
            lines.append(text + "no zero-latency cell of this variant and protocol to compare with.")
            continue
        text += f"success {_count(r, 'cell_n_success')}/{_outcomes(r)} against {r['zero_n_success']}/{r['zero_n']}"
        note = agg.budget_note(r)
        text += f" ({note})" if note and note != "action budget" else ""
        if not r["n_pairs"]:
            lines.append(text + "; no (task, init) pair succeeds in both, so there is no paired change.")
            continue
        changes = [
            f"{name}{f' ({unit})' if unit else ''} {agg.ci_text(r, f'{metric}_diff', decimals, scale, signed=True)}"
            for metric, name, decimals, scale, unit in PAIRED_SENTENCE
            if r.get(f"{metric}_diff_n")
        ]
        one = r["n_pairs"] == 1
        pairs = f"{int(r['n_pairs'])} pair{'' if one else 's'} that succeed{'s' if one else ''}"
        lines.append(f"{text}; over the {pairs} in both: {', '.join(changes)}.")
    return lines


EPISODE_COLUMNS = ("policy", "mode", "latency_s", "suite", "task", "init", "seed", "status", "completion_steps",
                   "action_ticks", "hold_ticks", "budget_limited", "jerk_mean", "ee_osc", "ee_osc_detrended",
                   "energy_total_j", "error_reason")  # fmt: skip


def episode_table(episodes: pd.DataFrame) -> pd.DataFrame:
    cols = [c for c in EPISODE_COLUMNS if c in episodes]
    return episodes.sort_values([c for c in ("policy", "mode", "latency_s", "suite", "task", "init", "seed")
                                 if c in episodes])[[*cols, "bag", *media.table_columns(episodes)]]  # fmt: skip


def _fmt(v) -> str:
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "–"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def _link(bag, prefix: str) -> str:
    return f"{prefix}{bag}/" if isinstance(bag, str) and bag else ""


def write_markdown(path: Path, summary: pd.DataFrame, per_task_md: str, prov: dict, episodes: pd.DataFrame,
                   prefix: str, paired: pd.DataFrame | None = None) -> None:  # fmt: skip
    lines = ["# LIBERO-LQ sweep report", ""]
    lines += [INTRO, ""] + [f"- {note}" for note in NOTES] + [""]
    if paired is not None and not paired.empty:
        lines += ["## Latency effects (paired against 0 s)", ""] + [f"- {s}" for s in paired_sentences(paired)] + [""]
    for name, title in FIGURES.items():
        lines += [f"## {title}", "", f"![{title}]({name}.png)", ""]
    lines += ["## Summary", "", summary.to_markdown(index=False), ""]
    if paired is not None and not paired.empty:
        lines += ["## Paired changes against 0 s", "", paired_table(paired).to_markdown(index=False), ""]
    lines += ["## Per task", "", per_task_md, ""]
    lines += ["## Provenance", "", "| | |", "|---|---|"] + [f"| {k} | {v} |" for k, v in prov.items()] + [""]
    lines += media.videos_md(episodes, FIGURE_KEYS)
    lines += ["## Episodes", ""]
    table = episode_table(episodes)
    header = [c for c in table.columns if c != "bag" and c not in media.MEDIA_COLUMNS]
    links = media.link_headers(table)
    lines += ["| " + " | ".join([*header, "bag", *links]) + " |", "|" + "---|" * (len(header) + 1 + len(links))]
    for _, r in table.iterrows():
        bag = r["bag"]
        cell = f"[bag]({_link(bag, prefix)})" if isinstance(bag, str) and bag else "–"
        cells = [*(_fmt(r[c]).replace("|", "/") for c in header), cell, *media.md_cells(r)]
        lines.append("| " + " | ".join(cells) + " |")
    path.write_text("\n".join(lines) + "\n")


INTRO = (
    "Pooled over tasks and init states per (policy, protocol, applied Δt_sim = N × 0.05 s, sampling); mean [95% CI]. "
    "Success: Wilson interval over episodes with an outcome (errors counted apart). Completion time, trajectory "
    "quality and energy: over successful episodes (succ.), seeded bootstrap of the mean; time (KM) is the "
    "Kaplan-Meier restricted mean up to the step budget over every episode with an outcome. The protocols differ in "
    "their replan horizon, not only in blocking: sync executes replan_steps actions of each chunk, async the H - N "
    "fresh ones (actions/chunk: measured). ⚠ / red rings: degenerate cells, where async chunks were no longer than N "
    "and no fresh action ran. Sampling: the rate of the trajectory metrics and how energy was integrated "
    "(docs/guide/scoring.md)."
)
#: The report's reading notes (after INTRO): how to read what the figures and tables attribute.
NOTES = (
    f"Few values: a metric over fewer than {agg.MIN_N_INTERVAL} episodes (or pairs) gets no bootstrap interval, "
    "which would undercover there (one value gives [v, v]); tables print the mean, n and the values, "
    "as MEAN (n=1) or MEAN (n=3: V1, V2, V3), and figures draw the values as dots without a band.",
    "Paired changes: success-only means of two latencies average different task mixes whenever their success "
    "differs, so the findings compare each latency > 0 cell with the zero-latency cell of the same variant and "
    "protocol over the (task, init state, seed) pairs that succeed in both: the change per pair, its mean and its "
    "bootstrap interval over pairs.",
    "Budgets: under the paper budget (holds count) every tick, held or not, counts against the suite's step budget; "
    "under the action budget only ticks whose command came from a chunk do (hard stop at 4x the budget). Fig. 4 draws "
    "both when a sweep ran both. A timeout under the paper budget is budget-limited when the same episode under the "
    "action budget succeeded or, without that run, when it executed fewer action ticks than the same task and init "
    "state needed to succeed at 0 s; a cell is budget-decided (◇, hollow marker) when at least half of its timeouts "
    "are budget-limited: there latency made the policy slower, the budget turned slower into failed.",
    "Fig. 9 separates slower from failing: the fraction succeeded by t, in sim seconds and in action ticks, with "
    "failures censored at their end; a slower cell rises later, a failing cell levels off lower.",
    "Latency labels: a distribution cell is named by its distribution and the mean Δt_sim its chunks actually got "
    "(realised mean, pooled over the cell's chunks); a constant cell by Δt_sim and N.",
    "EE-Osc: the paper's (A.3) is the spread of the last 10 positions (0.5 s) about their mean, so an arm still "
    "travelling at the end scores high; the detrended EE-Osc is the spread about the window's straight line, the "
    "back-and-forth alone. Fig. 5 shows both on one scale; a paper EE-Osc falling with latency while the detrended "
    "one stays flat means the arm arrives slower, not steadier.",
    "Async best case: in lockstep with no request slack the next chunk is requested N actions before the buffer "
    "empties and lands exactly as it does (constant latency, N ticks): no tick holds. Any jitter (a latency "
    "distribution, the real-time clock) makes the chunk land late, and every late tick is an underrun hold; a request "
    "slack of K actions requests K actions earlier and trades those holds for K stale actions.",
)
_CSS = """body{font-family:sans-serif;max-width:1200px;margin:2em auto;padding:0 1em}
table{border-collapse:collapse;font-size:12px}td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}
img{max-width:100%}.error{color:#b00}"""


def _bold_html(markdown: str) -> str:
    """Escaped HTML of a sentence whose only markup is markdown **bold**."""
    return re.sub(r"[*][*](.+?)[*][*]", r"<b>\1</b>", html.escape(markdown))


def write_html(path: Path, summary: pd.DataFrame, per_task: pd.DataFrame, prov: dict, episodes: pd.DataFrame,
               prefix: str, paired: pd.DataFrame | None = None) -> None:  # fmt: skip
    e = html.escape
    parts = ["<!doctype html><html><head><meta charset='utf-8'><title>LIBERO-LQ sweep report</title>",
             f"<style>{_CSS}</style></head><body><h1>LIBERO-LQ sweep report</h1>",
             f"<p>{html.escape(INTRO)}</p>", "<ul>", *(f"<li>{e(n)}</li>" for n in NOTES), "</ul>"]  # fmt: skip
    has_paired = paired is not None and not paired.empty
    if has_paired:
        parts.append("<h2>Latency effects (paired against 0 s)</h2><ul>")
        parts += [f"<li>{_bold_html(sentence)}</li>" for sentence in paired_sentences(paired)]
        parts.append("</ul>")
    for name, title in FIGURES.items():
        parts.append(f"<h2>{e(title)}</h2><img src='{name}.png' alt='{e(title)}'>")
    parts.append("<h2>Summary</h2>" + summary.to_html(index=False, na_rep="–"))
    if has_paired:
        parts.append("<h2>Paired changes against 0 s</h2>" + paired_table(paired).to_html(index=False, na_rep="–"))
    parts.append("<h2>Per task</h2>" + per_task.to_html(index=False, na_rep="–", float_format=lambda v: f"{v:.4g}"))
    parts.append("<h2>Provenance</h2><table>")
    parts += [f"<tr><th>{e(k)}</th><td style='text-align:left'>{e(v)}</td></tr>" for k, v in prov.items()]
    parts.append("</table>" + media.videos_html(episodes, FIGURE_KEYS) + "<h2>Episodes</h2><table><tr>")
    table = episode_table(episodes)
    header = [c for c in table.columns if c != "bag" and c not in media.MEDIA_COLUMNS]
    parts += [f"<th>{e(c)}</th>" for c in [*header, "bag", *media.link_headers(table)]]
    parts.append("</tr>")
    for _, r in table.iterrows():
        cls = " class='error'" if r.get("status") == "error" else ""
        cells = "".join(f"<td>{e(_fmt(r[c]))}</td>" for c in header)
        bag = r["bag"]
        link = (
            f"<a href='{e(_link(bag, prefix))}'>{e(str(bag).rsplit('/', 1)[-1])}</a>" if isinstance(bag, str) else "–"
        )
        parts.append(f"<tr{cls}>{cells}<td style='text-align:left'>{link}</td>{media.html_cells(r)}</tr>")
    parts.append("</table></body></html>")
    path.write_text("\n".join(parts))


@dataclass
class Report:
    out_dir: Path
    files: dict[str, Path]
    episodes: pd.DataFrame
    pooled: pd.DataFrame
    figures: dict[str, plt.Figure]
    #: Per-episode figures and replay videos that could not be made, and replays that differ from their bag.
    media_warnings: list[str] | None = None
    #: Paired changes of every latency > 0 cell against its zero-latency cell (paired_aggregates).
    paired: pd.DataFrame | None = None


def build_report(results_dir: Path, out_dir: Path | None = None, *, n_boot: int = 2000, seed: int = 0,
                 keep_figures: bool = False, all_episodes: bool = False, videos: int = 0,
                 progress: media.Progress | None = None) -> Report:  # fmt: skip
    """Write figures, tables, report.html and report.md for ``results_dir`` into ``out_dir``
    (default ``results_dir/report``). ``keep_figures`` leaves the matplotlib figures open (tests);
    ``all_episodes``: see load_episodes. Every episode gets a figure; ``videos``: replay videos per
    (policy, protocol, Δt_sim) cell (lq_ros/report/episode_media.py); ``progress(stage, done, total)`` follows both."""
    results_dir = Path(results_dir)
    out_dir = Path(out_dir) if out_dir else results_dir / "report"
    out_dir.mkdir(parents=True, exist_ok=True)
    episodes = load_episodes(results_dir, all_episodes=all_episodes)
    pooled = figure_aggregates(episodes, n_boot=n_boot, seed=seed)
    per_task = agg.aggregate(episodes, n_boot=n_boot, seed=seed)
    files = agg.write_tables(episodes, per_task, out_dir)
    pooled_csv = out_dir / "aggregates_pooled.csv"
    pooled.to_csv(pooled_csv, index=False)
    files["aggregates_pooled.csv"] = pooled_csv
    paired = paired_aggregates(episodes, pooled, n_boot=n_boot, seed=seed)
    paired_csv = out_dir / "paired_vs_zero_latency.csv"
    paired.to_csv(paired_csv, index=False)
    files[paired_csv.name] = paired_csv
    figures = make_figures(pooled, episodes) | report_async.make_boundary_figures(episodes, n_boot=n_boot, seed=seed)
    for name, fig in figures.items():
        path = out_dir / f"{name}.png"
        fig.savefig(path, dpi=110)
        files[path.name] = path
        if not keep_figures:
            plt.close(fig)
    episodes, media_warnings = media.add_episode_media(episodes, results_dir, out_dir, videos=videos,
                                                       cell_keys=FIGURE_KEYS, progress=progress)  # fmt: skip
    prov = provenance(episodes, results_dir)
    prefix = os.path.relpath(results_dir, out_dir).rstrip("/") + "/"
    summary = summary_table(pooled)
    files["report.md"] = out_dir / "report.md"
    write_markdown(files["report.md"], summary, agg.markdown_table(per_task), prov, episodes, prefix, paired)
    files["report.html"] = out_dir / "report.html"
    write_html(files["report.html"], summary, _per_task_view(per_task), prov, episodes, prefix, paired)
    return Report(out_dir, files, episodes, pooled, figures if keep_figures else {}, media_warnings, paired)


def _per_task_view(per_task: pd.DataFrame) -> pd.DataFrame:
    cols = [*agg.GROUP_KEYS, "n", "n_error"]
    view = per_task[cols].copy()
    for header, metric, decimals, scale in SUMMARY_COLUMNS:
        view[header] = [agg.ci_text(r, metric, decimals, scale) for _, r in per_task.iterrows()]
    return view
