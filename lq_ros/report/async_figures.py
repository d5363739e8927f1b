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
from lq_ros.scoring import aggregate as agg  # noqa: E402

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
#: Panels per row of the figure.
COLUMNS = 3
#: Line style per latency kind (constant and the distributions).
KIND_STYLE = {"constant": "-", "uniform": "--", "normal": "-.", "lognormal": ":", "trace": (0, (1, 1))}
SERIES = ("base", "merge", "latency_kind")


def boundary_aggregates(episodes: pd.DataFrame, *, n_boot: int = 2000, seed: int = 0) -> pd.DataFrame:
    """aggregate() of the async episodes per (policy variant without its merge, merge, latency kind, Δt_sim)."""
    eps = episodes[episodes.get("mode", pd.Series(dtype=object)) == "async"].copy()
    if eps.empty:
        return pd.DataFrame()
    eps["merge"] = eps["merge"].fillna(Merge.REPLACE.value) if "merge" in eps else Merge.REPLACE.value
    dist = eps["latency_dist"] if "latency_dist" in eps else pd.Series("constant", index=eps.index)
    eps["latency_kind"] = dist.fillna("constant").astype(str).str.split(":").str[0]
    unlabelled = eps.copy()
    if "policy_name" in unlabelled:
        unlabelled["policy"] = unlabelled["policy_name"]
    eps["base"] = unlabelled.apply(lambda r: agg._variant_label(r, ("merge", "latency_dist")), axis=1)
    return agg.aggregate(eps, by=[*SERIES, "latency_s"], n_boot=n_boot, seed=seed)


def fig_chunk_boundary(episodes: pd.DataFrame, *, n_boot: int = 2000, seed: int = 0) -> plt.Figure:
    pooled = boundary_aggregates(episodes, n_boot=n_boot, seed=seed)
    n_cols = COLUMNS
    n_rows = -(-len(PANELS) // n_cols)
    fig, grid = plt.subplots(n_rows, n_cols, figsize=(4.6 * n_cols, 4.3 * n_rows), squeeze=False)
    axes = list(grid.flat)
    for ax in axes[len(PANELS) :]:
        ax.set_visible(False)
    axes = axes[: len(PANELS)]
    if pooled.empty:
        for ax in axes:
            ax.text(0.5, 0.5, "no async episodes", ha="center", va="center", transform=ax.transAxes)
        fig.suptitle(TITLE)
        return fig
    order = {m.value: i for i, m in enumerate(Merge)}
    cycle = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    colour = {m: cycle[order.get(m, len(order)) % len(cycle)] for m in pooled["merge"].unique()}
    bases = sorted(pooled["base"].astype(str).unique())
    markers = dict(zip(bases, "osD^v<>p*h", strict=False))
    latencies = sorted(pooled["latency_s"].astype(float).unique())
    for ax, (metric, label, scale) in zip(axes, PANELS, strict=True):
        keys = sorted(pooled.groupby(list(SERIES)).groups, key=lambda k: (str(k[0]), order.get(k[1], 99), str(k[2])))
        for base, merge, kind in keys:
            rows = pooled[(pooled["base"] == base) & (pooled["merge"] == merge) & (pooled["latency_kind"] == kind)]
            rows = rows.sort_values("latency_s")
            if metric == "success_rate":
                mean, lo, hi = rows["success_rate"], rows["success_ci_lo"], rows["success_ci_hi"]
            else:
                col = f"{metric}{POPULATION}"
                mean, lo, hi = rows[f"{col}_mean"], rows[f"{col}_ci_lo"], rows[f"{col}_ci_hi"]
            mean, lo, hi = (np.asarray(v, dtype=np.float64) * scale for v in (mean, lo, hi))
            name = merge if len(bases) == 1 else f"{base} · {merge}"
            name += "" if kind == "constant" else f" ({kind} latency)"
            x = rows["latency_s"].astype(float).to_numpy()
            style = KIND_STYLE.get(kind, "--")
            ax.plot(x, mean, linestyle=style, marker=markers.get(str(base), "o"), color=colour[merge], label=name)
            ax.fill_between(x, lo, hi, color=colour[merge], alpha=0.12, linewidth=0)
        if metric == "chunk_switch_jerk_ratio":
            ax.axhline(1.0, color="grey", linewidth=0.8, linestyle=":")
        if metric == "success_rate":
            ax.set_ylim(-2, 102)
        ax.set_ylabel(label)
        ax.set_xlabel(f"applied latency Δt_sim (mean of a distribution) = N × {CONTROL_DT_S:g} s")
        ax.set_xticks(latencies, [f"{v:g}\nN={v / CONTROL_DT_S:.3g}" for v in latencies])
        ax.grid(alpha=0.3)
    axes[0].legend(title="merge strategy", fontsize=7)
    fig.suptitle(f"{TITLE}; boundary metrics over all episodes with an outcome")
    fig.tight_layout()
    return fig


def make_boundary_figures(episodes: pd.DataFrame, *, n_boot: int = 2000, seed: int = 0) -> dict[str, plt.Figure]:
    return {NAME: fig_chunk_boundary(episodes, n_boot=n_boot, seed=seed)}
