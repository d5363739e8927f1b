"""The report's figures (Figs. 4-7 and 9; Fig. 8 is lq_ros/report/async_figures.py) drawn from the pooled cells
of lq_ros/report/sweep_report.py, with 95 % CIs."""

from __future__ import annotations

import json

import matplotlib

matplotlib.use("Agg")  # files only, never a display

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from lq_ros.core.suite_constants import CONTROL_DT_S  # noqa: E402
from lq_ros.report import async_figures as report_async  # noqa: E402
from lq_ros.report import plot_rules as pr  # noqa: E402
from lq_ros.report import suite_grid as sg  # noqa: E402
from lq_ros.scoring import aggregate as agg  # noqa: E402
from lq_ros.scoring.labels import base_labels  # noqa: E402
from lq_ros.scoring.survival import kaplan_meier_band as survival_band  # noqa: E402

#: Figures pool tasks and init states, never suites: one point per (policy, protocol, suite, latency) at one
#: sampling of the trajectory and energy metrics (rates never pool: jerk at 20 Hz and at 500 Hz differ ~4x).
FIGURE_KEYS = ("policy", "mode", "latency_s", "latency_dist", "suite", "trajectory_rate_hz", "energy_sampling")
#: One line of a figure.
SERIES_KEYS = ("policy", "mode", "suite", "trajectory_rate_hz", "energy_sampling")
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
#: Footnotes of the budget marks of Fig. 4, per ``budget_mark`` (the pooled cells' column).
BUDGET_FOOTNOTE = {
    "decided": "hollow marker: budget-decided cell, its action-budget twin succeeded where the paper budget timed out "
    "(holds spent the paper budget; see the report's notes)",
    "proxy": "dotted ring: budget-limited by the action-tick proxy only (no action-budget twin was run; lq eval "
    "--budget-counts both runs them): weaker evidence",
}
#: How a figure says which points have no interval (and are not joined).
SMALL_N_NOTE = pr.SMALL_N_NOTE


def _series(pooled: pd.DataFrame) -> list[tuple[str, str, pd.DataFrame]]:
    """(policy label, mode, rows sorted by latency) for every series present: one per suite (the label names it
    when the figure holds several) and sampling (named too when the report mixes samplings)."""
    mixed = len(_samplings(pooled)) > 1
    suites = _suites(pooled)
    out = []
    for key, rows in pooled.groupby(list(SERIES_KEYS), sort=True, dropna=False):
        policy, mode, suite = str(key[0]), str(key[1]), key[2]
        label = _with_suite(policy, suite, suites)
        label = f"{label} ({agg.sampling_label(rows.iloc[0])})" if mixed else label
        out.append((label, mode, rows.sort_values("latency_s")))
    return out


def _suites(frame: pd.DataFrame) -> set[str]:
    return {str(s) for s in frame["suite"].dropna()} if "suite" in frame else set()


def _with_suite(label: str, suite, suites: set[str]) -> str:
    """``label`` naming ``suite`` when the figure holds several suites (variant labels may name it already)."""
    if len(suites) < 2 or not isinstance(suite, str) or label.endswith(f" · {suite}"):
        return label
    return f"{label} · {suite}"


def _samplings(pooled: pd.DataFrame) -> list[str]:
    return sorted({agg.sampling_label(r) for _, r in pooled.iterrows()})


def _ci_line(ax, x, mean, lo, hi, *, colour: str, mode: str, label: str, scale: float = 1.0,
             style: str | None = None) -> None:  # fmt: skip
    """A rate's line (success: Wilson intervals hold at any n, so every point is joined)."""
    pr.mean_line(ax, x, mean, lo, hi, colour=colour, linestyle=style or MODE_STYLE.get(mode, "-"),
                 marker=MODE_MARKER.get(mode, "o"), label=label, scale=scale)  # fmt: skip


def _metric_line(ax, rows: pd.DataFrame, metric: str, *, colour: str, mode: str, label: str,
                 scale: float = 1.0) -> set[str]:  # fmt: skip
    """A metric's mean vs latency with its 95 % band, by the rules of lq_ros/report/plot_rules.py: a point with
    fewer than MIN_JOIN_N values is hollow, unjoined and bandless, its values drawn as dots and its n beside it;
    a cell whose arm never moved is masked. Returns the notes that apply (plot_rules' *_NOTE)."""
    x = rows["latency_s"].to_numpy(dtype=np.float64)
    idle = pr.idle_cells(rows)
    n = rows.get(f"{metric}_n")
    pr.mean_line(ax, x, rows[f"{metric}_mean"], rows[f"{metric}_ci_lo"], rows[f"{metric}_ci_hi"], n, colour=colour,
                 linestyle=MODE_STYLE.get(mode, "-"), marker=MODE_MARKER.get(mode, "o"), label=label, masked=idle,
                 scale=scale)  # fmt: skip
    pr.mark_masked(ax, x[idle], colour)
    mean = np.where(idle, np.nan, rows[f"{metric}_mean"].to_numpy(dtype=np.float64))
    notes = {pr.IDLE_NOTE} if idle.any() else set()
    if pr.ring_degenerate(ax, rows, mean, scale):
        notes.add(pr.DEGENERATE_NOTE)
    if n is None:
        return notes
    few = np.isfinite(mean) & (np.nan_to_num(n.to_numpy(dtype=np.float64)) < pr.MIN_JOIN_N)
    if few.any():
        notes.add(pr.SMALL_N_NOTE)
    values_of = rows[f"{metric}_values"] if f"{metric}_values" in rows else pd.Series("", index=rows.index)
    for xi, ni, values, m in zip(x, n, values_of, mean, strict=True):
        if not np.isfinite(m) or not ni > 0:
            continue
        # Every point's n: the means of two latencies average different episodes (the successes of each), so
        # the reader sees how many each rests on (the paired changes against 0 s are in the paired table).
        ax.annotate(f"n={int(ni)}", (xi, m * scale), xytext=(4, 4), textcoords="offset points", fontsize=6,
                    color=colour)  # fmt: skip
        if isinstance(values, str) and values and ni < agg.MIN_N_INTERVAL:
            ys = np.asarray(json.loads(values), dtype=np.float64) * scale
            ax.scatter(np.full(len(ys), xi), ys, s=10, color=colour, alpha=0.6, zorder=4, linewidths=0)
    return notes


#: Footnote of the success-only means of Figs. 5 and 7: a line joins means of different episode sets.
EPISODE_SET_NOTE = (
    "n: the successful episodes behind each mean; a line joins means of different episode sets (the successes of each "
    "latency), so a change along it mixes the latency's effect with which episodes succeed: the paired changes "
    "against 0 s (paired_vs_zero_latency.csv) compare the same episodes"
)


def _notes(found: set[str], *extra: str) -> str:
    """The footnote of the notes found, in a fixed order, then ``extra``."""
    return pr.footnote(*(n for n in (pr.SMALL_N_NOTE, pr.IDLE_NOTE, pr.DEGENERATE_NOTE) if n in found), *extra)


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


def _rate_note(pooled: pd.DataFrame) -> str:
    return "; ".join(_samplings(pooled))


def _budget_marks(rows: pd.DataFrame) -> np.ndarray:
    """Each cell's budget mark: ``budget_mark`` ("decided", "proxy" or "") where the pooled cells carry it, else
    "decided" from ``budget_decided``. Never on a cell with degenerate episodes (its timeouts say nothing of the
    budget: the arm barely ran)."""
    if "budget_mark" in rows:
        marks = rows["budget_mark"].fillna("").astype(str).to_numpy()
    else:
        decided = rows.get("budget_decided", pd.Series(False, index=rows.index)).fillna(False).astype(bool)
        marks = np.where(decided.to_numpy(), "decided", "")
    degenerate = rows.get("n_degenerate", pd.Series(0, index=rows.index)).fillna(0).to_numpy() > 0
    return np.where(degenerate, "", marks)


#: Fig. 4's band notes: which 95 % interval a line's band is (lq_ros/scoring/intervals.py).
CLUSTER_BAND_NOTE = "band: task-clustered 95% interval (the task as the unit: speaks for other tasks of the suite)"
WILSON_BAND_NOTE = (
    f"hatched band: Wilson 95% interval over episodes, for a line with a cell of fewer than {agg.MIN_N_INTERVAL} "
    "tasks (no task-clustered interval): it speaks for these tasks only"
)


def _success_band(rows: pd.DataFrame) -> tuple[pd.Series, pd.Series, str]:
    """A line's band: the task-clustered interval when every cell of the line has one, else the Wilson interval
    over episodes (one kind per line, so a band never changes meaning along it). Returns (lo, hi, note)."""
    lo, hi = rows.get("success_cluster_ci_lo"), rows.get("success_cluster_ci_hi")
    rated = rows["success_rate"].notna()
    if lo is not None and hi is not None and bool(np.isfinite(lo[rated].to_numpy(dtype=np.float64)).all()):
        return lo, hi, CLUSTER_BAND_NOTE
    return rows["success_ci_lo"], rows["success_ci_hi"], WILSON_BAND_NOTE


def fig_success(pooled: pd.DataFrame) -> plt.Figure:
    """Fig. 4: small multiples, one panel per (suite, protocol): a row per suite, a column per protocol, never two
    suites in one panel; one line per policy (its colour the same in every panel), shaded 95 % band (task-clustered
    where every cell of the line has one, else Wilson, hatched and footnoted: _success_band); budget marks (hollow:
    decided by the action-budget twin; dotted ring: the proxy alone) and red rings on degenerate cells."""
    modes = [m for m in ("sync", "async") if m in set(pooled["mode"])] + sorted(set(pooled["mode"]) - {"sync", "async"})
    suites = sg.suites_of(pooled)
    several = len(suites) > 1
    budgets = set(pooled.get("budget_counts", pd.Series(dtype=object)).dropna())
    both = {"all", "action"} <= budgets
    lines = []  # (suite, mode, base label, legend label, budget, rows)
    for policy, mode, rows in _series(pooled):
        suite = rows["suite"].iloc[0] if "suite" in rows else None
        budget = rows["budget_counts"].iloc[0] if "budget_counts" in rows else "all"
        base = str(rows["series_policy"].iloc[0] if "series_policy" in rows else policy)
        # A figure of one suite names it in the label; of several, the panel names it.
        base = sg.without_suite(base, suites) if several else _with_suite(base, suite, set(suites) - {None})
        label = f"{base} · {BUDGET_LABEL.get(budget, budget)}" if both else base
        lines.append((suite if several else None, mode, base, label, budget, rows))
    colours = sg.colours(line[2] for line in lines)
    fig, axes = sg.grid(len(suites), len(modes), (5.5, 4.0), sharey=True)
    found: set[str] = set()
    for r, suite in enumerate(suites):
        for c, mode in enumerate(modes):
            ax = axes[r][c]
            drawn = 0
            for line_suite, m, base, label, budget, rows in lines:
                if m != mode or (several and line_suite != suite):
                    continue
                drawn += 1
                colour = colours[base]
                style = ACTION_BUDGET_STYLE if budget == "action" else None
                lo, hi, band = _success_band(rows)
                _ci_line(ax, rows["latency_s"], rows["success_rate"], lo, hi, colour=colour, mode=mode, label=label,
                         scale=100.0, style=style)  # fmt: skip
                if band == WILSON_BAND_NOTE:  # hatched over its fill: not the interval the other lines' bands are
                    ax.fill_between(rows["latency_s"], 100.0 * lo, 100.0 * hi, facecolor="none", edgecolor=colour,
                                    hatch="///", linewidth=0, alpha=0.45)  # fmt: skip
                found.add(band)
                if pr.ring_degenerate(ax, rows, rows["success_rate"], 100.0):
                    found.add(pr.DEGENERATE_NOTE)
                found |= _budget_mark_points(ax, rows, colour, mode)
                _distribution_labels(ax, rows, colour)
            ax.set_title(sg.panel_title(suite, f"{mode} execution", several), fontsize=10)
            if not drawn:  # a cell of the grid this run has no episodes for: say so rather than leave it blank
                sg.say_empty(ax, f"no {mode} episodes\nof this suite in this run")
            ax.set_ylim(-2, 102)
            ax.margins(x=0.12)
            _latency_axis(ax, pooled)
            if c == 0:
                ax.set_ylabel("success rate (%) [95% CI]")
    sg.one_legend(axes[0][0], [ax for row in axes for ax in row])
    notes = [n for n in (CLUSTER_BAND_NOTE, WILSON_BAND_NOTE) if n in found]
    notes += [BUDGET_FOOTNOTE[k] for k in ("decided", "proxy") if BUDGET_FOOTNOTE[k] in found]
    pr.layout(fig, [axes[0][0]], title=FIGURES["fig4_success"], note=pr.footnote(*notes, _notes(found)),
              ncol=min(3, max(1, len(axes[0][0].get_legend_handles_labels()[1]))))  # fmt: skip
    return fig


def _budget_mark_points(ax, rows: pd.DataFrame, colour: str, mode: str) -> set[str]:
    """Budget marks on the cells where the budget, not the policy, decided the timeouts: a hollow marker when the
    action-budget twin shows it, a dotted ring when only the proxy does. Returns the footnotes that apply."""
    marks = _budget_marks(rows)
    x, y = rows["latency_s"].to_numpy(dtype=np.float64), 100.0 * rows["success_rate"].to_numpy(dtype=np.float64)
    notes = set()
    decided, proxy = marks == "decided", marks == "proxy"
    if decided.any():
        ax.scatter(x[decided], y[decided], s=90, marker=MODE_MARKER.get(mode, "o"), facecolors="white",
                   edgecolors=colour, linewidths=1.8, zorder=6)  # fmt: skip
        notes.add(BUDGET_FOOTNOTE["decided"])
    if proxy.any():
        ax.scatter(x[proxy], y[proxy], s=260, marker="o", facecolors="none", edgecolors=colour, linewidths=1.0,
                   linestyles=":", zorder=6)  # fmt: skip
        notes.add(BUDGET_FOOTNOTE["proxy"])
    return notes


def _distribution_labels(ax, rows: pd.DataFrame, colour: str) -> None:
    """Name a distribution cell's point by its distribution and realised mean (agg.cell_latency_label)."""
    for _, r in rows.iterrows():
        dist = r.get("latency_dist")
        if isinstance(dist, str) and dist and dist != "constant":
            text = r.get("latency_label") or agg.cell_latency_label(r)
            y = 100.0 * r["success_rate"]
            ax.annotate(text.replace(" (", "\n("), (r["latency_s"], y), xytext=(-6, -16 if y > 50 else 8),
                        textcoords="offset points", fontsize=6, color=colour, ha="right")  # fmt: skip


#: Panels of Fig. 5: (metric, y label, the panel's own note or None, scale to the label's unit).
TRAJECTORY_PANELS = (
    ("jerk_mean", "mean jerk (m/s³)", None, 1.0),
    ("jerk_p90", "P90 jerk (m/s³)", None, 1.0),
    ("ee_osc", "EE-Osc, paper A.3 (mm)", "about the window's mean: travel counts", 1000.0),
    ("ee_osc_detrended", "EE-Osc detrended (mm)", "about the window's straight line: back-and-forth only", 1000.0),
)
#: Panels of Fig. 7, as TRAJECTORY_PANELS.
ENERGY_PANELS = (
    ("energy_per_step_j", "(a) energy per control step (J)", None, 1.0),
    ("energy_total_j", "(b) total energy (J)", None, 1.0),
)
#: A panel of Figs. 5 and 7 with no mean to draw (no successful episode of the suite has the metric).
NO_SUCCESS_TEXT = "no successful episode\nof this suite has a value"


def _metric_grid(pooled: pd.DataFrame, panels, *, title: str, panel_in: tuple[float, float],
                 same_scale: tuple[int, ...] = ()) -> plt.Figure:  # fmt: skip
    """Small multiples of success-only means vs latency (Figs. 5 and 7): a row per suite (lq_ros/report/suite_grid.py),
    a panel per metric, one line per (policy variant, protocol, sampling) in the colour of its variant in every
    row; a metric keeps one y scale down its column, and the ``same_scale`` columns share one scale."""
    suites = sg.suites_of(pooled)
    several = len(suites) > 1
    lines = [(rows["suite"].iloc[0] if several else None, sg.without_suite(label, suites), mode, rows)
             for label, mode, rows in _series(pooled)]  # fmt: skip
    colours = sg.colours(base for _, base, _, _ in lines)
    fig, axes = sg.grid(len(suites), len(panels), panel_in, sharey="col")
    found: set[str] = set()
    for suite, row_axes in zip(suites, axes, strict=True):
        for ax, (metric, label, note, scale) in zip(row_axes, panels, strict=True):
            drawn = False
            for line_suite, base, mode, rows in lines:
                if several and line_suite != suite:
                    continue
                found |= _metric_line(ax, rows, metric, colour=colours[base], mode=mode, label=f"{base} · {mode}",
                                      scale=scale)  # fmt: skip
                drawn |= pr.has_data(np.where(pr.idle_cells(rows), np.nan, rows[f"{metric}_mean"]))
            ax.set_ylabel(f"{label} [95% CI]", fontsize=9)
            ax.set_title(sg.panel_title(suite, note or "", several, sep="\n"), fontsize=9)
            _latency_axis(ax, pooled)
            if not drawn:
                sg.say_empty(ax, NO_SUCCESS_TEXT)
    if same_scale:  # (down a column the scale is shared already: one row's panels set it for all)
        low = min(axes[0][c].get_ylim()[0] for c in same_scale)
        high = max(axes[0][c].get_ylim()[1] for c in same_scale)
        for c in same_scale:
            axes[0][c].set_ylim(low, high)
    for c in range(len(panels)):
        pr.no_zoom_into_noise(axes[0][c])
    sg.one_legend(axes[0][0], [ax for row in axes for ax in row])
    n_labels = len(axes[0][0].get_legend_handles_labels()[1])
    pr.layout(fig, [axes[0][0]], title=f"{title} (successful episodes; {_rate_note(pooled)})",
              legend_title="policy · protocol", ncol=max(1, min(len(panels), n_labels)),
              note=_notes(found, EPISODE_SET_NOTE))  # fmt: skip
    return fig


def fig_trajectory(pooled: pd.DataFrame) -> plt.Figure:
    """Fig. 5: mean jerk, P90 jerk, the paper's EE-Osc and the detrended EE-Osc vs latency over successful episodes
    at the sampling named in the title, a row of panels per suite. The two EE-Osc columns share their y axis: the
    paper's spreads the window's positions about their mean, so travel in the last 0.5 s counts; the detrended one
    about the window's straight line, so only back-and-forth does."""
    return _metric_grid(pooled, TRAJECTORY_PANELS, title=FIGURES["fig5_trajectory"], panel_in=(3.6, 3.4),
                        same_scale=(2, 3))  # fmt: skip


def _stacked_bars(ax, rows: pd.DataFrame, latencies: list[float], parts, total_metric: str, mode: str) -> bool:
    """One series' stacked bar per latency; whisker: 95 % CI of ``total_metric``. A cell whose arm never moved gets
    no bar but a red × (plot_rules); returns whether any did."""
    by_lat = rows.set_index(rows["latency_s"].astype(float))
    idle_at = dict(zip(by_lat.index, pr.idle_cells(rows), strict=True))
    idle = np.array([bool(idle_at.get(lat, False)) for lat in latencies])
    x = np.arange(len(latencies), dtype=np.float64)
    bottom = np.zeros(len(latencies))
    for col, label, colour in parts:
        name = col.replace("_j", "_per_step_j") + "_mean"
        h = np.array([by_lat[name].get(lat, np.nan) if name in by_lat else np.nan for lat in latencies])
        h = np.nan_to_num(np.where(idle, np.nan, h.astype(np.float64)))
        ax.bar(x, h, 0.6, bottom=bottom, color=colour, edgecolor="white", hatch="//" if mode == "sync" else None,
               label=label)  # fmt: skip
        bottom += h
    lo = np.array([by_lat[f"{total_metric}_ci_lo"].get(lat, np.nan) for lat in latencies], dtype=np.float64)
    hi = np.array([by_lat[f"{total_metric}_ci_hi"].get(lat, np.nan) for lat in latencies], dtype=np.float64)
    lo, hi = np.where(idle, np.nan, lo), np.where(idle, np.nan, hi)
    ax.errorbar(x, bottom, yerr=[np.clip(bottom - lo, 0, None), np.clip(hi - bottom, 0, None)], fmt="none",
                ecolor="black", capsize=3)  # fmt: skip
    pr.mark_masked(ax, x[idle], "black")
    ax.set_xticks(x, [f"{lat:g} s (N={round(lat / CONTROL_DT_S)})" for lat in latencies], fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    return bool(idle.any())


#: Fig. 6's width, inches: legible at 1600 px whatever the number of series (a row per series, not a bar each).
FIG6_WIDTH_IN = 11.0


def fig_energy_decomposition(pooled: pd.DataFrame) -> plt.Figure:
    """Fig. 6: per-step energy as stacked bars per latency, small multiples: a row per (policy, protocol, suite),
    (a) mechanical + electrical loss + overhead, (b) the actuator part alone (the constant overhead hides it in
    (a)). Hatched bars: sync."""
    series = _series(pooled)
    latencies = sorted(pooled["latency_s"].astype(float).unique())
    fig, axes = plt.subplots(len(series), 2, figsize=(FIG6_WIDTH_IN, 2.1 * len(series) + 0.6), squeeze=False)
    idle = False
    for (policy, mode, rows), (left, right) in zip(series, axes, strict=True):
        idle |= _stacked_bars(left, rows, latencies, ENERGY_PARTS, "energy_per_step_j", mode)
        _stacked_bars(right, rows, latencies, ENERGY_PARTS[:2], "energy_actuator_per_step_j", mode)
        # The row's series on its left (a panel title per row would not fit beside the other panel's).
        left.set_ylabel("\n".join([*policy.split(" · "), mode, "J per control step"]), fontsize=8)
    axes[0][0].set_title("(a) mechanical + electrical loss + overhead", fontsize=10)
    axes[0][1].set_title("(b) actuators: mechanical + electrical loss", fontsize=10)
    for ax in axes[-1]:
        ax.set_xlabel("injected latency Δt_sim (whisker: 95% CI of the stack's total)", fontsize=8)
    title = f"{FIGURES['fig6_energy_decomposition']} (successful episodes; {_rate_note(pooled)})"
    pr.layout(fig, [axes[0][0]], title=title, legend_title="energy part (hatched: sync)", ncol=len(ENERGY_PARTS),
              note=pr.IDLE_NOTE if idle else "")  # fmt: skip
    return fig


def fig_energy(pooled: pd.DataFrame) -> plt.Figure:
    """Fig. 7: (a) per-step energy, (b) total episode energy vs latency, a row of panels per suite."""
    return _metric_grid(pooled, ENERGY_PANELS, title=FIGURES["fig7_energy"], panel_in=(5.5, 3.6))


#: Panels of Fig. 9: (agg.TIME_TO_SUCCESS_AXES key, x label).
TIME_TO_SUCCESS_PANELS = (
    ("sim_s", "sim time (s)"),
    ("action_ticks", "action ticks (ticks whose command came from a chunk)"),
)
#: Footnote of Fig. 9.
KM_NOTE = (
    "bands: pointwise 95% log-log Greenwood intervals of the fraction succeeded, before the first success the exact "
    "(Clopper-Pearson) bound (none where every episode at risk succeeded); ⚠ in a label: every episode of the cell "
    "held throughout (no fresh action ran)"
)


def fig_time_to_success(episodes: pd.DataFrame, pooled: pd.DataFrame) -> plt.Figure:
    """Fig. 9: Kaplan-Meier fraction succeeded by t with its Greenwood band (lq_ros/scoring/survival.py), one row
    per (policy variant, protocol, suite), one curve per latency cell (and budget), in sim seconds and in action
    ticks; a failure is censored at its end (tick marks). A slower cell's curve rises later, a failing cell's stops
    lower: the two are different things."""
    eps = episodes.copy()
    # One row per variant, protocol and suite: its constant latencies, distributions and both budgets together.
    eps["series_policy"] = base_labels(eps, ("budget_counts", "latency_dist"))
    suites = _suites(eps)
    if "suite" in eps:
        eps["series_policy"] = [_with_suite(str(p), s, suites) for p, s in zip(eps["series_policy"], eps["suite"],
                                                                               strict=True)]  # fmt: skip
    # One sampling per episode: a bag scored at two rates is one episode here (its outcome does not depend on it).
    samplings = [agg.sampling_label(r) for _, r in eps.iterrows()]
    eps = eps[[label == min(samplings) for label in samplings]] if samplings else eps
    several = len(suites) > 1
    order = ["suite", "series_policy", "mode"] if "suite" in eps else ["series_policy", "mode"]
    # A row per series, the rows of one suite together (each row holds one suite: its panel title names it).
    groups = [(k[-2], k[-1]) for k, _ in eps.groupby(order, sort=True, dropna=False)]
    both = {"all", "action"} <= set(eps["budget_counts"].dropna())
    labels = {  # the cell's own label: a distribution's realised mean differs between cells
        (r["policy"], r["mode"], r["latency_s"], r["latency_dist"]): r.get("latency_label") or agg.cell_latency_label(r)
        for _, r in pooled.iterrows()
    }
    idle = pr.never_moved(eps)
    fig, axes = plt.subplots(max(1, len(groups)), 2, figsize=(14.5, 3.6 * max(1, len(groups))), squeeze=False)
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
                t, survival, s_lo, s_hi = survival_band(times, events)
                xs, ys = np.append(t, times.max()), 100.0 * (1.0 - np.append(survival, survival[-1]))
                colour = colours[(float(latency), str(dist))]
                label = labels.get((variant, mode, latency, dist)) or f"{latency:g} s"
                if both:
                    label += f" · {'paper' if budget == 'all' else budget} budget"
                outcomes = cell_rows["status"].isin(["success", "failure"])
                if outcomes.any() and idle[cell_rows.index][outcomes].all():
                    label += " ⚠"
                style = ACTION_BUDGET_STYLE if budget == "action" else "-"
                ax.step(xs, ys, where="post", color=colour, linestyle=style, label=f"{label} (n={len(times)})")
                # 1 - S: the upper bound of the fraction succeeded is 1 - the lower bound of S.
                band_lo, band_hi = (100.0 * (1.0 - np.append(b, b[-1])) for b in (s_hi, s_lo))
                ax.fill_between(xs, band_lo, band_hi, step="post", color=colour, alpha=0.12, linewidth=0)
                censored = times[~events]
                at = survival[np.searchsorted(t, censored, side="right") - 1]
                ax.plot(censored, 100.0 * (1.0 - at), "|", color=colour, markersize=9, markeredgewidth=1.5)
            ax.set_xlabel(xlabel)
            ax.set_ylim(-2, 102)
            ax.grid(alpha=0.3)
            if not ax.get_lines():
                sg.say_empty(ax, "no episode of this series\nended in success or failure")
        row_axes[0].set_ylabel("succeeded by t (%) [95% band]")
        suite = rows["suite"].iloc[0] if several else None
        title = sg.panel_title(suite, f"{sg.without_suite(str(policy), sorted(suites))} · {mode}", several)
        row_axes[0].set_title(title, loc="left", fontsize=9)
        title = "latency" + (" · budget (paper: holds count; dotted: action)" if both else "")
        row_axes[1].legend(fontsize=7, title=f"{title}\nfailures: | at their end", title_fontsize=7, loc="upper left",
                           bbox_to_anchor=(1.02, 1.0))  # fmt: skip
    if not groups:
        sg.say_empty(axes[0][0], "no episode in this report")
    pr.layout(fig, title=FIGURES["fig9_time_to_success"], note=KM_NOTE)
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
