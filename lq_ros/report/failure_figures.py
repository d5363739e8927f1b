"""Failure modes by latency (fig10_failure_modes.png): one panel per suite and policy (rows) and protocol
(columns); at each latency a bar stacks the cell's failure modes as fractions of its episodes, so the bar's
height is the cell's failure rate. Suites are never pooled. A cell of fewer than MIN_JOIN_N classified episodes
gets no bar (a hatched outline says so); n is printed above every bar. Episodes in which no fresh action ran
(``no_action_executed``: the protocol's failure, not the policy's) are stacked apart on top, hatched and outlined;
a mode not validated against an observer is starred in the legend."""

from __future__ import annotations

import textwrap

import matplotlib

matplotlib.use("Agg")  # files only, never a display

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from lq_ros.report.plot_rules import MIN_JOIN_N  # noqa: E402
from lq_ros.scoring import failure_modes  # noqa: E402

#: One colour per policy failure mode (tab10; grey for stalled).
MODE_COLOURS = {
    "undone": "#9467bd", "budget_out_progressing": "#2ca02c", "stalled": "#7f7f7f", "pushed_or_toppled": "#bcbd22",
    "wrong_object_disturbed": "#8c564b", "never_reached": "#1f77b4", "stopped_short": "#17becf",
    "grasp_missed": "#ff7f0e", "dropped_in_transit": "#d62728", "placed_off_target": "#e377c2",
}  # fmt: skip
#: The protocol's failure: white, hatched, outlined, above a gap.
NO_ACTION_STYLE = {"facecolor": "white", "hatch": "xxx", "edgecolor": "#444444", "linewidth": 0.6}
PROTOCOLS = ("sync", "async")


def fig_failure_modes(fractions: pd.DataFrame) -> plt.Figure | None:
    """The figure from failure_aggregate.mode_fractions per FIGURE_KEYS (constant latencies), or None without
    classified episodes."""
    if fractions.empty:
        return None
    frame = fractions
    if "latency_dist" in frame:
        frame = frame[frame["latency_dist"].fillna("constant").eq("constant")]
    if frame.empty:
        return None
    rows = sorted({(s, p) for s, p in zip(frame["suite"], frame["policy"], strict=True)}, key=str)
    protocols = [p for p in PROTOCOLS if p in set(frame["mode"])]
    latencies = sorted(frame["latency_s"].dropna().unique())
    fig, axes = plt.subplots(len(rows), len(protocols), figsize=(4.2 * len(protocols) + 2.6, 2.3 * len(rows) + 1.2),
                             squeeze=False, sharex=True, sharey=True)  # fmt: skip
    x = np.arange(len(latencies))
    small = found_degenerate = False
    for r, (suite, policy) in enumerate(rows):
        for c, protocol in enumerate(protocols):
            ax = axes[r, c]
            cells = frame[(frame["suite"] == suite) & (frame["policy"] == policy) & (frame["mode"] == protocol)]
            for i, latency in enumerate(latencies):
                cell = cells[cells["latency_s"] == latency]
                if cell.empty:
                    continue
                n = int(cell["n"].iloc[0])
                if n < MIN_JOIN_N:
                    ax.bar(i, 1.0, width=0.7, fill=False, hatch="//", edgecolor="#bbbbbb", linewidth=0.5)
                    ax.text(i, 1.02, f"n={n}", ha="center", va="bottom", fontsize=7)
                    small = True
                    continue
                bottom = 0.0
                by_mode = cell.set_index("failure_mode")["fraction"]
                for mode in failure_modes.FAILURE_MODES:
                    height = float(by_mode.get(mode, 0.0))
                    if height > 0:
                        ax.bar(i, height, bottom=bottom, width=0.7, color=MODE_COLOURS[mode], edgecolor="white",
                               linewidth=0.4)  # fmt: skip
                        bottom += height
                no_action = sum(float(by_mode.get(mode, 0.0)) for mode in failure_modes.PROTOCOL_MODES)
                if no_action > 0:  # apart: a gap, then hatched
                    ax.bar(i, no_action, bottom=bottom + 0.02, width=0.7, **NO_ACTION_STYLE)
                    bottom += no_action + 0.02
                degenerate = int(cell["n_degenerate"].iloc[0]) if "n_degenerate" in cell else 0
                ax.text(i, bottom + 0.02, f"n={n}" + (f"\n{degenerate} degenerate" if degenerate else ""),
                        ha="center", va="bottom", fontsize=7, color="tab:red" if degenerate else "black")  # fmt: skip
                found_degenerate |= bool(degenerate)
            ax.set_ylim(0, 1.3)
            ax.set_yticks([0, 0.2, 0.4, 0.6, 0.8, 1.0])
            ax.set_xticks(x, [f"{v:g}" for v in latencies])
            ax.grid(axis="y", alpha=0.3)
            if r == 0:
                ax.set_title(protocol, fontsize=10)
            if c == 0:
                ax.set_ylabel(f"{suite}\n{policy}\nfraction of episodes", fontsize=8)
            if r == len(rows) - 1:
                ax.set_xlabel("Δt_sim (s)")
    handles = [plt.Rectangle((0, 0), 1, 1, color=MODE_COLOURS[m]) for m in failure_modes.FAILURE_MODES]
    handles.append(plt.Rectangle((0, 0), 1, 1, **NO_ACTION_STYLE))
    labels = [m.replace("_", " ") + ("" if m in failure_modes.VALIDATED_MODES else " *")
              for m in failure_modes.FAILURE_MODES]  # fmt: skip
    labels.append("no action executed\n(the protocol's, apart)")
    fig.legend(handles, labels, loc="center right", fontsize=8, frameon=False, title="failure mode",
               title_fontsize=8)  # fmt: skip
    note = (
        "Bar height: the cell's failure rate; its parts: the failure modes (docs/guide/failure_modes.md). "
        "* not validated against an observer: the classifier's reading of the task state. Hatched, above a gap: "
        "no fresh action ran (the protocol starved the arm), not a policy failure."
    )
    if small:
        note += f" Hatched outline: fewer than {MIN_JOIN_N} classified episodes, no bar."
    if found_degenerate:
        note += " Red: episodes of a degenerate async protocol (chunks no longer than N: the arm never moves)."
    width = int(fig.get_figwidth() * 17)  # characters of 7 pt text per line across the figure
    fig.text(0.01, 0.005, textwrap.fill(note, width), fontsize=7, va="bottom")
    fig.suptitle("Failure modes by latency", fontsize=11)
    legend_in = 2.4  # the legend's column, in
    fig.tight_layout(rect=(0, 0.03 + 0.45 / fig.get_figheight(), 1 - legend_in / fig.get_figwidth(), 0.97))
    return fig
