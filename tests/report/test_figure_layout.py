"""Figs. 4-9 read at a glance: Fig. 4 a panel per (suite, protocol), Figs. 5 and 7 a row of panels per suite (a
suite with nothing to draw says why), Fig. 6 legible at 1600 px wide whatever the number of series, Fig. 8 a colour
per series, Fig. 9 a suite's rows together."""

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


@pytest.mark.parametrize("name, metrics", [("fig5_trajectory", fg.TRAJECTORY_PANELS),
                                           ("fig7_energy", fg.ENERGY_PANELS)])  # fmt: skip
def test_figs5_and_7_are_a_row_of_panels_per_suite_legible_at_1600_px(episodes, pooled, name, metrics):
    fig = fg.make_figures(pooled, episodes)[name]
    assert fig.get_size_inches()[0] * DPI <= 1600
    axes = np.array(fig.axes).reshape(len(SUITES), len(metrics))
    for row, suite in zip(axes, sorted(SUITES), strict=True):  # rows in the suites' order, a panel per metric
        for ax, (_, label, _, _) in zip(row, metrics, strict=True):
            assert ax.get_title().split("\n")[0] == suite and ax.get_ylabel().startswith(label)
            drawn = [line for line in ax.get_lines() if len(line.get_xdata())]
            assert len(drawn) == 4  # its suite's two policies x two protocols, no other suite's
    colours = {}
    for ax in fig.axes:  # a policy keeps its colour in every panel; the protocol is the line style
        for line in ax.get_lines():
            if len(line.get_xdata()):
                colours.setdefault(line.get_label(), set()).add(to_hex(line.get_color()))
    assert set(colours) == {f"{p} · {m}" for p in ("scripted", "sine") for m in ("sync", "async")}
    assert all(len(c) == 1 for c in colours.values())
    assert colours["scripted · sync"] == colours["scripted · async"] != colours["sine · sync"]
    for column in axes.T:  # one scale down a column: the suites compare at a glance
        assert len({ax.get_ylim() for ax in column}) == 1


def test_a_suite_without_successes_says_why_its_panels_are_empty(episodes):
    failed = episodes.assign(status=np.where(episodes["suite"] == "libero_object", "failure", episodes["status"]))
    failed["success"] = failed["status"] == "success"
    pooled = rp.figure_aggregates(failed, n_boot=50)
    for fig in (fg.fig_trajectory(pooled), fg.fig_energy(pooled)):
        for ax in fig.axes:
            says = [t.get_text() for t in ax.texts if t.get_text() == fg.NO_SUCCESS_TEXT]
            empty = not [line for line in ax.get_lines() if np.isfinite(np.asarray(line.get_ydata(), float)).any()]
            assert empty == ax.get_title().startswith("libero_object") == bool(says), ax.get_title()


def test_fig9_keeps_a_suites_rows_together_each_titled_by_its_suite(episodes, pooled):
    fig = fg.fig_time_to_success(episodes, pooled)
    titles = [ax.get_title(loc="left") for ax in fig.axes if ax.get_title(loc="left")]
    assert [t.split(" · ")[0] for t in titles] == [s for s in sorted(SUITES) for _ in range(4)]  # 2 policies x 2 modes
    assert fig.get_size_inches()[0] * DPI <= 1600
