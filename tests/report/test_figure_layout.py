"""Figs. 4, 6 and 8 read at a glance: Fig. 4 a panel per (suite, protocol), Fig. 6 legible at 1600 px wide
whatever the number of series, Fig. 8 a colour per series."""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np
import pytest
from matplotlib.colors import to_hex

from lq_ros.report import async_figures as af
from lq_ros.report import figures as fg
from lq_ros.report import sweep_report as rp
from tests.report.test_figure_rules import _frame, _row

DPI = 110  # what lq report saves at
SUITES = ("libero_spatial", "libero_object")


@pytest.fixture(scope="module")
def episodes():
    """Two suites x two policies x two protocols x three latencies, six inits a cell."""
    rng = np.random.default_rng(0)
    rows = [
        _row(suite, mode=mode, latency=lat, init=i, policy=policy, energy_mech_j=100.0, energy_elec_j=50.0,
             energy_overhead_j=300.0, status="success" if rng.random() > lat else "failure")
        for suite in SUITES for policy in ("scripted", "sine") for mode in ("sync", "async")
        for lat in (0.0, 0.1, 0.2) for i in range(6)
    ]  # fmt: skip
    return _frame(rows)


@pytest.fixture(scope="module")
def pooled(episodes):
    return rp.figure_aggregates(episodes, n_boot=50)


@pytest.fixture(autouse=True)
def close_all():
    yield
    plt.close("all")


def test_fig4_is_a_panel_per_suite_and_protocol(pooled):
    fig = fg.fig_success(pooled)
    panels = {ax.get_title(): ax for ax in fig.axes if ax.get_title()}
    assert set(panels) == {f"{s} · {m} execution" for s in SUITES for m in ("sync", "async")}
    for title, ax in panels.items():
        drawn = [line for line in ax.get_lines() if len(line.get_xdata())]
        assert len(drawn) == 2, title  # the two policies of its suite and protocol, no other suite's
    colours = {}
    for ax in panels.values():  # a policy keeps its colour in every panel
        for line in ax.get_lines():
            if len(line.get_xdata()):
                colours.setdefault(line.get_label(), set()).add(to_hex(line.get_color()))
    assert set(colours) == {"scripted", "sine"} and all(len(c) == 1 for c in colours.values())


def test_fig6_is_legible_at_1600_px_wide(pooled):
    fig = fg.fig_energy_decomposition(pooled)
    width_px, height_px = fig.get_size_inches() * DPI
    assert width_px <= 1600  # 8 series x 3 latencies drew a bar each side by side, 2900 px wide, 6 pt labels
    rows = len(fg._series(pooled))
    assert len([ax for ax in fig.axes if ax.get_visible()]) == 2 * rows
    assert height_px / rows < 300  # a row per series, not a page each


def test_fig8_is_a_block_of_panels_per_suite_and_gives_each_series_its_own_colour(episodes):
    fig = af.fig_chunk_boundary(episodes, n_boot=50)
    success = [ax for ax in fig.axes if ax.get_visible() and "success" in ax.get_ylabel()]
    assert sorted(ax.get_title(loc="left") for ax in success) == sorted(SUITES)  # never two suites in one panel
    for ax in success:
        lines = [line for line in ax.get_lines() if len(line.get_xdata())]
        assert len(lines) == 2  # async: the two policies of its suite, both with merge replace
        assert len({to_hex(line.get_color()) for line in lines}) == 2  # (one colour per merge: both the same)
