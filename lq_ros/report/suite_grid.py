"""The small-multiples layout of the report's line figures (Figs. 4, 5 and 7): a row of panels per suite, never two
suites in one panel (suites differ in difficulty and in their metrics' scale, so one panel would pool or crowd
them). A series keeps its colour in every panel (the panel, not the legend, names the suite), and a panel with
nothing to draw says why instead of staying blank. Fig. 8 lays out its blocks the same way
(lq_ros/report/async_figures.py); Fig. 9 has a row per series, each of one suite."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")  # files only, never a display

import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402

#: The separator of a label's parts (a variant label names its suite after it when a figure holds several).
SEPARATOR = " · "
#: Grey of a panel's "nothing to draw" text.
EMPTY_COLOUR = "#777777"


def suites_of(frame: pd.DataFrame) -> list[str | None]:
    """The suites of ``frame``'s rows, sorted: a row of panels each; [None] when it names none."""
    suites = sorted({str(s) for s in frame["suite"].dropna()}) if "suite" in frame else []
    return suites or [None]


def without_suite(label: str, suites: list[str | None]) -> str:
    """``label`` without the `` · <suite>`` a figure of several suites gives it (its panel names the suite)."""
    for suite in suites:
        if suite:
            label = label.replace(f"{SEPARATOR}{suite}", "")
    return label


def panel_title(suite: str | None, text: str, several: bool, sep: str = SEPARATOR) -> str:
    """A panel's title: ``<suite><sep><text>`` in a figure of several suites, else ``text`` (``sep`` "\n" puts a
    long ``text`` on a line of its own)."""
    if not several or suite is None:
        return text
    return f"{suite}{sep}{text}" if text else suite


def grid(n_suites: int, n_cols: int, panel_in: tuple[float, float], sharey: bool | str = False):
    """(figure, axes[row][col]): a row per suite, ``n_cols`` panels of ``panel_in`` (width, height) inches each."""
    width_in, height_in = panel_in
    return plt.subplots(n_suites, n_cols, figsize=(width_in * n_cols, height_in * n_suites), squeeze=False,
                        sharey=sharey)  # fmt: skip


def colours(labels) -> dict[str, str]:
    """A colour per label (sorted, from the style's cycle), the same in every panel."""
    cycle = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    return {label: cycle[i % len(cycle)] for i, label in enumerate(sorted(set(labels)))}


def say_empty(ax, text: str) -> None:
    """Say in the middle of ``ax`` why it has nothing drawn (a blank panel reads as a drawing error)."""
    ax.text(0.5, 0.5, text, transform=ax.transAxes, ha="center", va="center", color=EMPTY_COLOUR, fontsize=9)


def one_legend(target, axes) -> None:
    """Give ``target`` an (invisible) entry for every labelled line of ``axes`` it lacks, so the figure's one legend
    names every series of every panel."""
    have = set(target.get_legend_handles_labels()[1])
    for ax in axes:
        for line in ax.get_lines():
            label = line.get_label()
            if label.startswith("_") or label in have:
                continue
            have.add(label)
            target.plot([], [], color=line.get_color(), linestyle=line.get_linestyle(), marker=line.get_marker(),
                        label=label)  # fmt: skip
