"""Drawing rules every report figure follows, so no figure says more than its episodes show.

- A line joins two means only when both rest on at least ``MIN_JOIN_N`` values; a mean of fewer is drawn
  hollow and alone (with its values as dots, see lq_ros/report/figures.py), never as part of a trend.
- A cell whose every episode held the whole time (no action of any chunk ran: the arm never moved) has no
  trajectory, boundary or energy value worth drawing: its jerk would be 0 m/s³, the smoothest point of the
  figure. Such a cell is masked: a × in its line's colour at the panel's foot at its latency, no point.
- A cell with degenerate-protocol episodes (lq_ros/scoring/bag_scorer.py) is ringed red.
- A panel with no value to draw is left out, and the figure's footnote says which and why.
"""

from __future__ import annotations

import math
import textwrap

import matplotlib

matplotlib.use("Agg")  # files only, never a display

import matplotlib.transforms as mtransforms  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from lq_ros.scoring.intervals import MIN_N_INTERVAL  # noqa: E402

#: Fewest values a mean needs to be joined to its neighbours (the same as for an interval).
MIN_JOIN_N = MIN_N_INTERVAL
SMALL_N_NOTE = f"hollow, unjoined point: mean of fewer than {MIN_JOIN_N} values (no band; dots are the values)"
IDLE_NOTE = "× at the foot: every episode of the cell held throughout (no fresh action ran), its value is not drawn"
DEGENERATE_NOTE = "red ring: cell with degenerate-protocol episodes (see the summary)"
#: Where a masked cell's × sits, as a fraction of the panel's height.
MASK_Y = 0.03


def never_moved(episodes: pd.DataFrame) -> pd.Series:
    """True for the episodes whose arm never executed an action of a chunk (every tick held: action ticks 0),
    e.g. async with chunks no longer than N. Unknown counts are False (the episode is drawn as it is)."""
    out = pd.Series(False, index=episodes.index)
    for column in ("action_ticks", "fresh_actions_executed"):
        if column in episodes:
            out |= pd.to_numeric(episodes[column], errors="coerce").eq(0)
    return out


def idle_cells(rows: pd.DataFrame) -> np.ndarray:
    """Cells (rows of pooled aggregates with ``n_idle``) where every episode with an outcome never moved."""
    idle = pd.to_numeric(rows.get("n_idle", pd.Series(0, index=rows.index)), errors="coerce").fillna(0)
    outcomes = rows["n_success"].fillna(0) + rows["n_failure"].fillna(0)
    return ((idle > 0) & (idle >= outcomes)).to_numpy()


def mean_line(ax, x, mean, lo, hi, n=None, *, colour, linestyle="-", marker="o", label=None, masked=None,
              scale: float = 1.0) -> None:  # fmt: skip
    """Means vs ``x`` with their band. With ``n`` (values per point) a segment joins two points only when both
    have n >= MIN_JOIN_N, and a point below that is hollow; ``masked`` points are left out (mark_masked)."""
    x = np.asarray(x, dtype=np.float64)
    mean, lo, hi = (np.asarray(v, dtype=np.float64) * scale for v in (mean, lo, hi))
    hide = np.zeros(len(x), bool) if masked is None else np.asarray(masked, bool)
    mean = np.where(hide, np.nan, mean)
    lo, hi = np.where(hide, np.nan, lo), np.where(hide, np.nan, hi)
    few = np.zeros(len(x), bool) if n is None else np.nan_to_num(np.asarray(n, dtype=np.float64)) < MIN_JOIN_N
    joined = np.where(few, np.nan, mean)
    ax.plot(x, joined, linestyle=linestyle, marker=marker, color=colour, label=label)
    ax.fill_between(x, lo, hi, color=colour, alpha=0.15, linewidth=0)
    alone = few & np.isfinite(mean)
    if alone.any():
        ax.scatter(x[alone], mean[alone], s=40, marker=marker, facecolors="none", edgecolors=colour, linewidths=1.3,
                   zorder=5)  # fmt: skip


def mark_masked(ax, x, colour="red") -> None:
    """A × at the panel's foot at each latency in ``x`` (a masked cell)."""
    x = np.asarray(x, dtype=np.float64)
    if len(x):
        foot = mtransforms.blended_transform_factory(ax.transData, ax.transAxes)
        ax.scatter(x, np.full(len(x), MASK_Y), marker="x", s=45, color=colour, transform=foot, zorder=6,
                   clip_on=False)  # fmt: skip


def ring_degenerate(ax, rows: pd.DataFrame, y, scale: float = 1.0) -> bool:
    """Ring the points of cells with degenerate-protocol episodes; True when any was ringed."""
    bad = rows.get("n_degenerate", pd.Series(0, index=rows.index)).fillna(0).to_numpy() > 0
    y = np.asarray(y, dtype=np.float64) * scale
    bad &= np.isfinite(y)
    if bad.any():
        ax.scatter(rows["latency_s"].to_numpy(dtype=np.float64)[bad], y[bad], s=160, facecolors="none",
                   edgecolors="red", zorder=5)  # fmt: skip
    return bool(bad.any())


#: A value axis spans at least this fraction of the largest magnitude it shows, so that differences far below
#: the values' own size (e.g. 0.0006 J on 4 J per step) are not drawn as if they were large.
MIN_RELATIVE_SPAN = 0.1


def no_zoom_into_noise(ax, min_relative_span: float = MIN_RELATIVE_SPAN) -> None:
    """Widen ``ax``'s y range about its centre to at least ``min_relative_span`` of its largest magnitude."""
    low, high = ax.get_ylim()
    need = min_relative_span * max(abs(low), abs(high))
    if high - low < need:
        centre = (low + high) / 2
        ax.set_ylim(centre - need / 2, centre + need / 2)


def has_data(values) -> bool:
    return bool(np.isfinite(np.asarray(values, dtype=np.float64)).any())


def footnote(*notes: str) -> str:
    """The notes that apply, one a line."""
    return "\n".join(n for n in notes if n)


def layout(fig, legend_axes=(), *, title: str, legend_title: str = "policy", ncol: int = 1, note: str = "") -> None:
    """Lay ``fig`` out: ``title`` in a band of its own above the panels (never over a panel's title or label),
    each of ``legend_axes``' legends under it (the figure grows to make room: a legend inside a panel hides its
    data) and ``note`` (one line per note) at the bottom."""
    width_in = fig.get_size_inches()[0]
    # Wrapped to the figure's width (about 15 characters an inch at 7 pt), so no note runs off the image.
    note = "\n".join(textwrap.fill(line, max(40, int(15 * width_in))) for line in note.split("\n")) if note else ""
    counts = [len(ax.get_legend_handles_labels()[1]) for ax in legend_axes]
    rows = max((math.ceil(c / ncol) for c in counts if c), default=0)
    legend_in = 0.35 + 0.16 * rows if rows else 0.0
    note_in = 0.08 + 0.13 * (note.count("\n") + 1) if note else 0.0
    title_in = 0.12 + 0.22 * (title.count("\n") + 1)
    width_in, height_in = fig.get_size_inches()
    total = height_in + legend_in + note_in + title_in
    fig.set_size_inches(width_in, total)
    bottom, top = (legend_in + note_in) / total, 1 - title_in / total
    fig.suptitle(title, y=1 - 0.1 / total, va="top")
    fig.tight_layout(rect=(0, bottom, 1, top))
    for ax, count in zip(legend_axes, counts, strict=True):  # one legend: centred; one per panel: under its panel
        if not count:
            continue
        pos = ax.get_position()
        x = 0.5 if len(legend_axes) == 1 else pos.x0 + pos.width / 2
        fig.legend(*ax.get_legend_handles_labels(), title=legend_title, fontsize=7, title_fontsize=8, ncol=ncol,
                   loc="upper center", bbox_to_anchor=(x, bottom))  # fmt: skip
    if note:
        fig.text(0.01, 0.06 / total, note, fontsize=7, ha="left", va="bottom")
