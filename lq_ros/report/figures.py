"""The report's figures (Figs. 4-7 and 9; Fig. 8 is lq_ros/report/async_figures.py) drawn from the pooled cells
of lq_ros/report/sweep_report.py, with 95 % CIs."""

from __future__ import annotations

import json
import math

import matplotlib

matplotlib.use("Agg")  # files only, never a display

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from lq_ros.core.suite_constants import CONTROL_DT_S  # noqa: E402
from lq_ros.report import async_figures as report_async  # noqa: E402
from lq_ros.scoring import aggregate as agg  # noqa: E402

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
