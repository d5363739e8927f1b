"""The figures' drawing rules (lq_ros/report/plot_rules.py) on constructed episodes: no figure pools suites, a
cell whose arm never moved is masked, no panel is empty, no line joins means of fewer than 5 values, Fig. 9 has
Greenwood bands, budget marks by kind, titles clear of the panels."""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
import pytest
from matplotlib.collections import PathCollection

from lq_ros.report import async_figures as af
from lq_ros.report import figures as fg
from lq_ros.report import plot_rules as pr
from lq_ros.report import sweep_report as rp
from lq_ros.scoring import aggregate as agg


def _row(suite: str, *, mode: str = "async", latency: float = 0.0, init: int = 0, status: str = "success",
         jerk: float = 10.0, action: int = 100, **kw) -> dict:  # fmt: skip
    return {
        "policy": "scripted", "mode": mode, "latency_s": latency, "suite": suite, "task": 0, "init": init, "seed": 7,
        "status": status, "success": status == "success", "completion_steps": 100, "completion_time_s": 5.0,
        "action_ticks": action, "step_budget": 140, "trajectory_rate_hz": 20.0, "energy_sampling": "substep",
        "jerk_mean": jerk, "jerk_p90": 2 * jerk, "ee_osc": 0.02, "ee_osc_detrended": 0.005, "energy_total_j": 500.0,
        "energy_per_step_j": 5.0, "switch_executed_step_mean": jerk / 100, "switch_executed_step_max": jerk / 50,
        "chunk_switch_jerk_ratio": 1.2, "merge": "replace",
    } | kw  # fmt: skip


def _frame(rows: list[dict]) -> pd.DataFrame:
    return rp.add_energy_parts_per_step(agg.episodes_frame(rows))


def _figures(episodes: pd.DataFrame) -> dict[str, plt.Figure]:
    pooled = rp.figure_aggregates(episodes, n_boot=50)
    return fg.make_figures(pooled, episodes) | af.make_boundary_figures(episodes, n_boot=50)


@pytest.fixture
def close_all():
    yield
    plt.close("all")


def _note(fig) -> str:
    """The figure's footnote as one line (the layout wraps it to the figure's width)."""
    return " ".join(fig.texts[-1].get_text().split())


def _legend_labels(fig) -> list[str]:
    return [t.get_text() for legend in fig.legends for t in legend.get_texts()] + [
        t.get_text() for ax in fig.axes if ax.get_legend() for t in ax.get_legend().get_texts()
    ]


def _points(ax) -> np.ndarray:
    """Every finite (x, y) drawn as a line vertex or a scatter point (in data coordinates)."""
    out = [line.get_xydata() for line in ax.get_lines()]
    out += [c.get_offsets() for c in _scatters(ax) if c.get_offset_transform() == ax.transData]
    xy = np.concatenate([np.asarray(a, dtype=float).reshape(-1, 2) for a in out]) if out else np.empty((0, 2))
    return xy[np.isfinite(xy).all(axis=1)]


def _scatters(ax) -> list:
    """The scatter collections of ``ax`` (a band is a PolyCollection, whose offsets are a dummy (0, 0))."""
    return [c for c in ax.collections if isinstance(c, PathCollection) and len(c.get_offsets())]


def _joined_segments(ax) -> int:
    """Line segments with two finite ends (what a reader takes for a trend)."""
    total = 0
    for line in ax.get_lines():
        y = np.asarray(line.get_ydata(), dtype=float)
        total += int((np.isfinite(y[1:]) & np.isfinite(y[:-1])).sum()) if len(y) > 1 else 0
    return total


def _two_suites() -> pd.DataFrame:
    """The same policy on two suites, labelled apart (as if loaded from two sweeps), so the variant label does not
    name the suite: Spatial's jerk is 10, Object's 30 (pooled they would show 20). Six inits per cell."""
    spatial = [_row("libero_spatial", latency=lat, init=i, jerk=10.0) for lat in (0.0, 0.1) for i in range(6)]
    obj = [_row("libero_object", latency=lat, init=i, jerk=30.0) for lat in (0.0, 0.1) for i in range(6)]
    return pd.concat([_frame(spatial), _frame(obj)], ignore_index=True)


def test_no_figure_pools_suites(close_all):
    episodes = _two_suites()
    assert set(episodes["policy"]) == {"scripted"}  # the label alone would pool them
    figures = _figures(episodes)
    panels = [ax.get_title() for ax in figures["fig4_success"].axes if ax.get_title()]  # Fig. 4: a panel per suite
    assert sorted(panels) == ["libero_object · async execution", "libero_spatial · async execution"]
    panels = [ax.get_title(loc="left") for ax in figures[af.NAME].axes if "success" in ax.get_ylabel()]
    assert sorted(panels) == ["libero_object", "libero_spatial"]  # Fig. 8: a block of panels per suite
    for name in ("fig5_trajectory", "fig7_energy"):  # a row of panels per suite, each panel naming its suite
        suites = [ax.get_title().split("\n")[0] for ax in figures[name].axes]
        assert sorted(set(suites)) == ["libero_object", "libero_spatial"], (name, suites)
        assert suites.count("libero_object") == suites.count("libero_spatial"), (name, suites)
    jerk_5 = {ax.get_title(): set(np.round(_points(ax)[:, 1], 6)) for ax in figures["fig5_trajectory"].axes
              if "mean jerk" in ax.get_ylabel()}  # fmt: skip
    assert jerk_5 == {"libero_object": {30.0}, "libero_spatial": {10.0}}  # one suite a panel, never their mean 20
    jerk_8 = [ax for ax in figures[af.NAME].axes if "mean jerk" in ax.get_ylabel()]
    values = sorted((set(np.round(_points(ax)[:, 1], 6)) for ax in jerk_8), key=sorted)
    assert values == [{10.0}, {30.0}]  # one suite a panel
    titles = [ax.get_title(loc="left") for ax in figures["fig9_time_to_success"].axes if ax.get_title(loc="left")]
    assert titles == ["libero_object · scripted · async", "libero_spatial · scripted · async"]


def _with_idle_cell() -> pd.DataFrame:
    """Async 0 s and 0.2 s move; at 0.4 s every episode held throughout (0 action ticks) and scored jerk 0. Two
    cells succeed there so the success-only figures have a value to mask too."""
    rows = [_row("libero_spatial", latency=lat, init=i) for lat in (0.0, 0.2) for i in range(6)]
    rows += [_row("libero_spatial", latency=0.4, init=i, jerk=0.0, action=0, degenerate_protocol=True,
                  status="success" if i < 2 else "failure") for i in range(6)]  # fmt: skip
    return _frame(rows)


def test_a_cell_that_never_moved_is_masked_not_drawn_smooth(close_all):
    episodes = _with_idle_cell()
    assert pr.never_moved(episodes).sum() == 6
    figures = _figures(episodes)
    quality = [*figures["fig5_trajectory"].axes[:2], *figures["fig7_energy"].axes]
    quality += [ax for ax in figures[af.NAME].axes if ax.get_visible() and "success" not in ax.get_ylabel()]
    for ax in quality:
        xy = _points(ax)
        assert 0.4 not in set(np.round(xy[:, 0], 6)), ax.get_ylabel()  # no value at 0.4 s: masked
        foot = [c for c in _scatters(ax) if c.get_offset_transform() != ax.transData]
        assert [tuple(np.round(c.get_offsets()[0], 3)) for c in foot] == [(0.4, pr.MASK_Y)], ax.get_ylabel()
    for name in ("fig5_trajectory", "fig7_energy", af.NAME):
        assert pr.IDLE_NOTE in _note(figures[name]), name
    # Its success is a real outcome (the arm did not move, so it failed): drawn, and ringed.
    success = figures["fig4_success"].axes[0]
    assert (0.4, pytest.approx(100 / 3)) in [tuple(p) for p in _points(success)]


def test_no_empty_panel_and_the_footnote_says_why(close_all):
    episodes = _two_suites()  # no chunk ever overlapped the old plan: chunk disagreement has no value
    fig = af.fig_chunk_boundary(episodes, n_boot=50)
    labels = [ax.get_ylabel() for ax in fig.axes if ax.get_visible()]  # (a block of panels per suite: two)
    assert len(labels) == 2 * (len(af.PANELS) - 1) and not any("disagreement" in label for label in labels)
    for ax in fig.axes:
        if ax.get_visible():
            assert len(_points(ax)), ax.get_ylabel()
    assert "not drawn: chunk disagreement on overlap (action units) (no chunk overlapped" in _note(fig)
    # With the metric present, the panel is back.
    with_overlap = episodes.assign(chunk_disagreement_mean=0.3)
    fig = af.fig_chunk_boundary(with_overlap, n_boot=50)
    assert sum(ax.get_visible() for ax in fig.axes) == 2 * len(af.PANELS)


def test_no_line_joins_means_of_fewer_than_five_values(close_all):
    # 0 s and 0.1 s: six values each; 0.2 s: three; 0.3 s: six.
    rows = [_row("libero_spatial", latency=lat, init=i) for lat in (0.0, 0.1, 0.3) for i in range(6)]
    rows += [_row("libero_spatial", latency=0.2, init=i, jerk=20.0) for i in range(3)]
    figures = _figures(_frame(rows))
    for ax in (figures["fig5_trajectory"].axes[0], figures["fig7_energy"].axes[0]):
        (line,) = [line for line in ax.get_lines() if np.isfinite(line.get_ydata()).any()]
        y = np.asarray(line.get_ydata(), dtype=float)
        assert np.isfinite(y).tolist() == [True, True, False, True]  # 0.2 s is out of the line
        assert _joined_segments(ax) == 1  # 0 -> 0.1 only: 0.1 -> 0.2 -> 0.3 would pass through n = 3
        hollow = [c for c in _scatters(ax) if len(c.get_facecolors()) == 0 and c.get_offset_transform() == ax.transData]
        assert [tuple(np.round(c.get_offsets()[0], 6)) for c in hollow if c.get_sizes()[0] == 40][0][0] == 0.2
    assert pr.SMALL_N_NOTE in _note(figures["fig5_trajectory"])
    jerk_8 = [ax for ax in figures[af.NAME].axes if "mean jerk" in ax.get_ylabel()][0]
    assert _joined_segments(jerk_8) == 1


def test_fig9_draws_greenwood_bands(close_all):
    rows = [_row("libero_spatial", init=i, completion_time_s=5.0 + i) for i in range(4)]
    rows += [_row("libero_spatial", init=4 + i, status="failure", completion_time_s=7.0) for i in range(2)]
    episodes = _frame(rows)
    fig = fg.fig_time_to_success(episodes, rp.figure_aggregates(episodes, n_boot=50))
    ax = fig.axes[0]
    (band,) = [c for c in ax.collections if c.get_paths() and len(c.get_paths()[0].vertices) > 2]
    ys = band.get_paths()[0].vertices[:, 1]
    # The band spans the Greenwood interval of the curve: after the first success at 5 s (S = 5/6, n = 6):
    from lq_ros.scoring.survival import kaplan_meier_band

    times, events = agg.time_to_success(episodes, "sim_s")
    _, s, lo, hi = kaplan_meier_band(times, events)
    assert s[1] == pytest.approx(5 / 6)
    for bound in (100 * (1 - hi[1]), 100 * (1 - lo[1])):
        assert np.isclose(ys, bound).any(), bound
    assert "Greenwood" in _note(fig)


def _budget_pooled(mark: str, degenerate: int = 0) -> pd.DataFrame:
    rows = [_row("libero_spatial", mode="sync", init=i) for i in range(3)]
    rows += [_row("libero_spatial", mode="sync", latency=0.2, init=i, status="failure") for i in range(3)]
    pooled = rp.figure_aggregates(_frame(rows), n_boot=50)
    late = pooled["latency_s"] == 0.2
    pooled["budget_mark"] = np.where(late, mark, "")
    pooled.loc[late, "n_degenerate"] = degenerate
    return pooled


@pytest.mark.parametrize("mark", ["decided", "proxy"])
def test_budget_marks_by_kind(close_all, mark):
    fig = fg.fig_success(_budget_pooled(mark))
    ax = fig.axes[0]
    white = [c for c in _scatters(ax) if len(c.get_facecolors()) and np.allclose(c.get_facecolors()[:, :3], 1.0)]
    dotted = [c for c in _scatters(ax) if c.get_linestyle()[0][1] is not None]
    if mark == "decided":
        assert [tuple(c.get_offsets()[0]) for c in white] == [(0.2, 0.0)] and not dotted
    else:  # weaker and drawn differently: a dotted ring, no filled marker
        assert [tuple(c.get_offsets()[0]) for c in dotted] == [(0.2, 0.0)] and not white
    assert fg.BUDGET_FOOTNOTE[mark] in _note(fig)


def test_no_budget_mark_on_a_degenerate_cell(close_all):
    fig = fg.fig_success(_budget_pooled("decided", degenerate=3))
    ax = fig.axes[0]
    assert not [c for c in _scatters(ax) if len(c.get_facecolors()) and np.allclose(c.get_facecolors()[:, :3], 1.0)]
    assert fg.BUDGET_FOOTNOTE["decided"] not in _note(fig)


def test_titles_clear_the_panels(close_all):
    figures = _figures(_with_idle_cell())
    for name, fig in figures.items():
        renderer = fig.canvas.get_renderer()
        title = fig._suptitle.get_window_extent(renderer)
        for ax in fig.axes:
            if ax.get_visible():
                assert ax.get_tightbbox(renderer).y1 <= title.y0 + 1, (name, ax.get_ylabel(), ax.get_title())


def _band_edges(ax) -> np.ndarray:
    bands = [c for c in ax.collections if c.get_paths() and len(c.get_paths()[0].vertices) > 2]
    return np.unique(np.round(np.concatenate([b.get_paths()[0].vertices[:, 1] for b in bands]), 6))


@pytest.mark.parametrize("tasks", [6, 3])
def test_fig4_band_is_task_clustered_when_every_cell_has_that_interval(close_all, tasks):
    # Success clusters by task (task 0 always fails): the clustered interval is wider than Wilson's.
    rows = [
        _row("libero_spatial", mode="sync", latency=lat, task=t, init=i, status="failure" if t == 0 else "success")
        for lat in (0.0, 0.2) for t in range(tasks) for i in range(4)
    ]  # fmt: skip
    pooled = rp.figure_aggregates(_frame(rows), n_boot=200)
    fig = fg.fig_success(pooled)
    edges = _band_edges(fig.axes[0])
    if tasks >= agg.MIN_N_INTERVAL:
        want = pooled[["success_cluster_ci_lo", "success_cluster_ci_hi"]]
        assert fg.CLUSTER_BAND_NOTE in _note(fig) and fg.WILSON_BAND_NOTE not in _note(fig)
        assert (pooled["success_cluster_ci_lo"] < pooled["success_ci_lo"]).all()  # the test can tell them apart
    else:  # too few tasks: Wilson, with dashed edges and its own note
        want = pooled[["success_ci_lo", "success_ci_hi"]]
        assert fg.WILSON_BAND_NOTE in _note(fig) and fg.CLUSTER_BAND_NOTE not in _note(fig)
        assert [c for c in fig.axes[0].collections if c.get_hatch() == "///"]
    for bound in 100 * want.to_numpy().ravel():
        assert np.isclose(edges, bound).any(), bound


def test_no_axis_zooms_into_noise(close_all):
    """A per-step energy of 4.2500-4.2506 J (the 85 W overhead dominates) is drawn on an axis at least a tenth of
    its size wide, not stretched so 0.0006 J fills the panel."""
    fig, ax = plt.subplots()
    ax.plot([0.0, 0.1, 0.2], [4.2500, 4.2503, 4.2506])
    assert ax.get_ylim()[1] - ax.get_ylim()[0] < 0.01  # matplotlib's own range: the noise fills the panel
    pr.no_zoom_into_noise(ax)
    low, high = ax.get_ylim()
    assert high - low >= 0.1 * 4.2506 * 0.999 and low < 4.2500 and high > 4.2506
    ax.set_ylim(0, 10)
    pr.no_zoom_into_noise(ax)  # a range that is already wide stays as it is
    assert ax.get_ylim() == (0, 10)


def test_fig4_says_why_a_panel_of_its_grid_is_empty(close_all):
    """Spatial run in both protocols, Object in async only: Object's sync panel says it has no episodes."""
    spatial = [_row("libero_spatial", mode=m, latency=lat, init=i) for m in ("sync", "async") for lat in (0.0, 0.1)
               for i in range(6)]  # fmt: skip
    obj = [_row("libero_object", latency=lat, init=i) for lat in (0.0, 0.1) for i in range(6)]
    episodes = pd.concat([_frame(spatial), _frame(obj)], ignore_index=True)
    fig = _figures(episodes)["fig4_success"]
    texts = {ax.get_title(): " ".join(t.get_text() for t in ax.texts) for ax in fig.axes if ax.get_title()}
    assert "no sync episodes" in texts["libero_object · sync execution"]
    assert "no " not in texts["libero_spatial · sync execution"]
