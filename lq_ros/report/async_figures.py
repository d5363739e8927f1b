"""The report's chunk-boundary figure: success and chunk-boundary quality vs latency, one line per merge
strategy (async episodes; lq_ros/scoring/chunk_boundary.py defines the metrics, lq_ros/core/merge.py the
strategies)."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from lq_ros.core.merge import Merge  # noqa: E402
from lq_ros.core.suite_constants import CONTROL_DT_S  # noqa: E402
from lq_ros.report import plot_rules as pr  # noqa: E402
from lq_ros.scoring import aggregate as agg  # noqa: E402
from lq_ros.scoring.labels import _variant_label  # noqa: E402

NAME = "fig8_chunk_boundary"
TITLE = "Fig. 8 - success and chunk-boundary quality vs latency, per merge strategy (async)"
#: (metric, y label, scale): success is the Wilson rate; the boundary metrics are means over every episode with
#: an outcome (the ``_all`` columns): the strategies' success rates differ, and conditioning a protocol
#: property on success would compare different episodes (the success-only means are in the tables).
PANELS = (
    ("success_rate", "success rate (%) [95% CI]", 100.0),
    # The executed command step ‖c_t - c_{t-1}‖ at every handover (switches and overlap ends): the same quantity
    # for every strategy (not the jump against the old plan, which a blend shrinks by definition).
    ("switch_executed_step_mean", "executed step at handovers, mean (action units) [95% CI]", 1.0),
    ("switch_executed_step_max", "executed step at handovers, max (action units) [95% CI]", 1.0),
    # Before merging: how far the new chunk's rows are from the old plan where they overlap (null: no overlap).
    ("chunk_disagreement_mean", "chunk disagreement on overlap (action units) [95% CI]", 1.0),
    ("chunk_switch_jerk_ratio", "jerk near switches / elsewhere [95% CI]", 1.0),
    # Null when switches come every 5 ticks or less (docs/design/async.md); the episode's mean jerk always exists.
    ("jerk_mean", "mean jerk, 20 Hz (m/s³) [95% CI]", 1.0),
)
POPULATION = "_all"
#: Panels per row of the figure (at most; fewer when panels are left out).
COLUMNS = 3
#: Line style per latency kind (constant and the distributions).
KIND_STYLE = {"constant": "-", "uniform": "--", "normal": "-.", "lognormal": ":", "trace": (0, (1, 1))}
#: One line: a suite never pools with another.
SERIES = ("suite", "base", "merge", "latency_kind")
#: Why a boundary panel can have nothing to draw (the footnote names the panel and this).
EMPTY_REASON = {
    "chunk_disagreement_mean": "no chunk overlapped the old plan (no overlapping merge ran, or N > H/2)",
    "chunk_switch_jerk_ratio": "switches every 5 ticks or less leave no jerk away from them",
}


def boundary_aggregates(episodes: pd.DataFrame, *, n_boot: int = 2000, seed: int = 0) -> pd.DataFrame:
    """aggregate() of the async episodes per (suite, policy variant without its merge, merge, latency kind,
    Δt_sim). Success is over every episode with an outcome; the boundary metrics over the episodes whose arm moved
    (an episode that held throughout has no boundary and a jerk of 0): ``n_idle`` counts the others."""
    eps = episodes[episodes.get("mode", pd.Series(dtype=object)) == "async"].copy()
    if eps.empty:
        return pd.DataFrame()
    eps["merge"] = eps["merge"].fillna(Merge.REPLACE.value) if "merge" in eps else Merge.REPLACE.value
    dist = eps["latency_dist"] if "latency_dist" in eps else pd.Series("constant", index=eps.index)
    eps["latency_kind"] = dist.fillna("constant").astype(str).str.split(":").str[0]
    eps["suite"] = eps["suite"].fillna("").astype(str) if "suite" in eps else ""
    unlabelled = eps.copy()
    if "policy_name" in unlabelled:
        unlabelled["policy"] = unlabelled["policy_name"]
    eps["base"] = unlabelled.apply(lambda r: _variant_label(r, ("merge", "latency_dist")), axis=1)
    by = [*SERIES, "latency_s"]
    cells = agg.aggregate(eps, by=by, n_boot=n_boot, seed=seed)
    idle = pr.never_moved(eps) & eps["status"].isin(["success", "failure"])
    counts = eps.assign(_idle=idle).groupby(by, sort=True)["_idle"].sum().rename("n_idle").reset_index()
    cells = cells.merge(counts, on=by, how="left")
    if idle.any():  # the boundary metrics again, without the episodes that never moved
        moving = agg.aggregate(eps[~idle], by=by, n_boot=n_boot, seed=seed) if (~idle).any() else pd.DataFrame()
        metric_cols = [c for c in cells.columns if c.startswith(tuple(m for m, _, _ in PANELS[1:]))]
        cells = cells.drop(columns=metric_cols)
        if moving.empty:
            cells = cells.assign(**{c: np.nan for c in metric_cols})
        else:
            cells = cells.merge(moving[[*by, *[c for c in metric_cols if c in moving]]], on=by, how="left")
    return cells


def series_colours(keys: list[tuple], order: dict[str, int]) -> dict[tuple, str]:
    """A colour per line (suite, base, merge, latency kind): by merge strategy when the lines differ only in it
    (and in latency kind: the line style tells those apart), else one colour per (suite, base, merge), so no
    two series share a colour and a style."""
    cycle = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    if len({(k[0], k[1]) for k in keys}) == 1:
        return {k: cycle[order.get(k[2], len(order)) % len(cycle)] for k in keys}
    groups = sorted({k[:3] for k in keys}, key=lambda g: (g[0], str(g[1]), order.get(g[2], 99)))
    index = {g: i for i, g in enumerate(groups)}
    return {k: cycle[index[k[:3]] % len(cycle)] for k in keys}


def _panel_values(rows: pd.DataFrame, metric: str, scale: float):
    """(mean, lo, hi, n) of a panel's metric in ``rows`` (n None for the success rate: always joined)."""
    if metric == "success_rate":
        return rows["success_rate"], rows["success_ci_lo"], rows["success_ci_hi"], None
    col = f"{metric}{POPULATION}"
    return rows[f"{col}_mean"], rows[f"{col}_ci_lo"], rows[f"{col}_ci_hi"], rows[f"{col}_n"]


def _drawable(pooled: pd.DataFrame, metric: str) -> bool:
    """A panel has something to draw: a finite value in a cell that is not masked."""
    if metric == "success_rate":
        return pr.has_data(pooled["success_rate"])
    col = f"{metric}{POPULATION}_mean"
    return col in pooled and pr.has_data(pooled[col].to_numpy(dtype=np.float64)[~pr.idle_cells(pooled)])


def fig_chunk_boundary(episodes: pd.DataFrame, *, n_boot: int = 2000, seed: int = 0) -> plt.Figure:
    """Fig. 8: success and the boundary metrics vs latency, one line per (suite, variant, merge, latency kind).
    Panels with nothing to draw are left out and named in the footnote; masked and small-n cells follow
    lq_ros/report/plot_rules.py."""
    pooled = boundary_aggregates(episodes, n_boot=n_boot, seed=seed)
    if pooled.empty:
        fig, ax = plt.subplots(figsize=(6.0, 2.5))
        ax.set_axis_off()
        ax.text(0.5, 0.5, "no async episodes: nothing to draw", ha="center", va="center", transform=ax.transAxes)
        pr.layout(fig, title=TITLE)
        return fig
    panels = [p for p in PANELS if _drawable(pooled, p[0])]
    left_out = [p for p in PANELS if p not in panels]
    n_cols = min(COLUMNS, len(panels))
    n_rows = -(-len(panels) // n_cols)
    # Small multiples: the panels once per suite, one block of rows each (never two suites in one panel).
    suites = sorted(pooled["suite"].unique()) if pooled["suite"].nunique() > 1 else [None]
    fig, grid = plt.subplots(n_rows * len(suites), n_cols, figsize=(4.6 * n_cols, 4.0 * n_rows * len(suites)),
                             squeeze=False)  # fmt: skip
    blocks = []  # (suite or None, its panels' axes)
    for k, suite_k in enumerate(suites):
        block = list(grid[k * n_rows : (k + 1) * n_rows].flat)
        for ax in block[len(panels) :]:
            ax.set_visible(False)
        blocks.append((suite_k, block[: len(panels)]))
    axes = blocks[0][1]
    order = {m.value: i for i, m in enumerate(Merge)}
    lines = sorted({(str(s), str(b)) for s, b in zip(pooled["suite"], pooled["base"], strict=True)})
    markers = dict(zip(sorted({b for _, b in lines}), "osD^v<>p*h", strict=False))  # a variant's, in every suite
    several_bases = pooled["base"].nunique() > 1
    latencies = sorted(pooled["latency_s"].astype(float).unique())
    found: set[str] = set()
    keys = sorted(pooled.groupby(list(SERIES)).groups, key=lambda k: (k[0], str(k[1]), order.get(k[2], 99), k[3]))
    # A series keeps its colour in every suite's panels (the panel names the suite).
    colour = series_colours(sorted({("", *k[1:]) for k in keys}), order)
    for suite_k, (ax, (metric, label, scale)) in ((s, p) for s, block in blocks for p in zip(block, panels)):
        for suite, base, merge, kind in keys:
            if suite_k is not None and suite != suite_k:
                continue
            rows = pooled[(pooled["suite"] == suite) & (pooled["base"] == base) & (pooled["merge"] == merge)
                          & (pooled["latency_kind"] == kind)].sort_values("latency_s")  # fmt: skip
            mean, lo, hi, n = _panel_values(rows, metric, scale)
            x = rows["latency_s"].astype(float).to_numpy()
            masked = None if metric == "success_rate" else pr.idle_cells(rows)
            name = f"{base} · {merge}" if several_bases else merge
            name += "" if kind == "constant" else f" ({kind} latency)"
            pr.mean_line(ax, x, mean, lo, hi, n, colour=colour[("", base, merge, kind)],
                         linestyle=KIND_STYLE.get(kind, "--"),
                         marker=markers.get(str(base), "o"), label=name, masked=masked,
                         scale=scale)  # fmt: skip
            shown = np.asarray(mean, dtype=np.float64)
            if masked is not None and masked.any():
                pr.mark_masked(ax, x[masked], colour[("", base, merge, kind)])
                shown = np.where(masked, np.nan, shown)
                found.add(pr.IDLE_NOTE)
            if n is not None and (np.isfinite(shown) & (np.nan_to_num(n.to_numpy(dtype=float)) < pr.MIN_JOIN_N)).any():
                found.add(pr.SMALL_N_NOTE)
            if pr.ring_degenerate(ax, rows, shown, scale):
                found.add(pr.DEGENERATE_NOTE)
        if metric == "chunk_switch_jerk_ratio":
            ax.axhline(1.0, color="grey", linewidth=0.8, linestyle=":")
        if metric == "success_rate":
            ax.set_ylim(-2, 102)
        if suite_k is not None:
            ax.set_title(suite_k, fontsize=9, loc="left")
        ax.set_ylabel(label, fontsize=9)
        ax.set_xlabel(f"applied latency Δt_sim (mean of a distribution) = N × {CONTROL_DT_S:g} s", fontsize=8)
        ax.set_xticks(latencies, [f"{v:g}\nN={v / CONTROL_DT_S:.3g}" for v in latencies])
        ax.grid(alpha=0.3)
    notes = [f"not drawn: {label.split(' [')[0]} ({EMPTY_REASON.get(metric, 'no episode has a value')})"
             for metric, label, _ in left_out]  # fmt: skip
    notes.append("boundary metrics: means over every episode with an outcome whose arm moved; success over all")
    notes += [n for n in (pr.SMALL_N_NOTE, pr.IDLE_NOTE, pr.DEGENERATE_NOTE) if n in found]
    legend = "merge strategy" if len({b for _, b in lines}) == 1 else "policy · merge strategy"
    _one_legend(axes[0], [block[0] for _, block in blocks])
    pr.layout(fig, axes[:1], title=TITLE, legend_title=legend, ncol=min(3, len(keys)),
              note=pr.footnote(*notes))  # fmt: skip
    return fig


def _one_legend(target, axes) -> None:
    """Give ``target`` an (invisible) entry for every labelled line of ``axes`` it lacks: one legend for all suites."""
    have = set(target.get_legend_handles_labels()[1])
    for ax in axes:
        for line in ax.get_lines():
            if not line.get_label().startswith("_") and line.get_label() not in have:
                have.add(line.get_label())
                target.plot([], [], color=line.get_color(), linestyle=line.get_linestyle(), marker=line.get_marker(),
                            label=line.get_label())  # fmt: skip


def make_boundary_figures(episodes: pd.DataFrame, *, n_boot: int = 2000, seed: int = 0) -> dict[str, plt.Figure]:
    return {NAME: fig_chunk_boundary(episodes, n_boot=n_boot, seed=seed)}
