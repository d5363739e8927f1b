"""The report attributes its effects: budget-decided cells, both budgets, time-to-success curves, the detrended
EE-Osc, few-value cells and paired changes; on constructed rows (closed form) and on real in-process episodes."""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pytest

from lq_ros.report import figures as fg
from lq_ros.report import prose, tables
from lq_ros.report import sweep_report as rp
from lq_ros.scoring import aggregate as agg
from lq_ros.scoring.attribution import decomposition_table
from lq_ros.scoring.paired_tests import BH_ADJUSTMENT


def _row(status: str, *, mode: str = "sync", latency: float = 0.0, steps: int = 100, action: int = 100, **kw):
    return {
        "policy": "scripted", "mode": mode, "latency_s": latency, "suite": "libero_spatial", "task": 0,
        "init": kw.pop("init", 0), "seed": 7, "status": status, "success": status == "success",
        "completion_steps": steps, "completion_time_s": steps * 0.05, "action_ticks": action, "step_budget": 140,
        "trajectory_rate_hz": 20.0, "energy_sampling": "substep", "jerk_mean": 10.0, "ee_osc": 0.02,
        "ee_osc_detrended": 0.005, "energy_total_j": 500.0, "energy_per_step_j": 5.0, "n_degenerate": 0,
    } | kw  # fmt: skip


def _episodes():
    """Sync: 0 s succeeds (100 action ticks, inits 0-2); at 0.2 s (inits 0-5) the paper budget times out after 70
    action ticks and the action budget succeeds at 180 ticks. Async: 0.2 s times out after 130 action ticks (a
    policy failure)."""
    rows = []
    for mode in ("sync", "async"):
        rows += [_row("success", mode=mode, steps=100 + i, action=100 + i, init=i) for i in range(3)]
    # Six timeouts: a budget mark needs at least five (lq_ros/scoring/budget.py).
    rows += [_row("failure", latency=0.2, steps=140, action=70, init=i) for i in range(6)]
    rows += [_row("success", latency=0.2, steps=180, action=100, init=i, budget_counts="action") for i in range(6)]
    rows += [_row("failure", mode="async", latency=0.2, steps=140, action=130, init=i) for i in range(3)]
    rows += [_row("success", steps=100 + i, action=100 + i, init=i, budget_counts="action") for i in range(3)]
    return rp.add_energy_parts_per_step(agg.episodes_frame(rows))


@pytest.fixture(scope="module")
def synthetic():
    episodes = _episodes()
    pooled = rp.figure_aggregates(episodes, n_boot=100)
    figures = fg.make_figures(pooled, episodes)
    yield episodes, pooled, figures
    for fig in figures.values():
        plt.close(fig)


def _hollow_points(ax) -> list[tuple[float, float]]:
    """Offsets of the scatter points drawn with a white face (budget-decided markers)."""
    out = []
    for coll in ax.collections:
        faces = coll.get_facecolors()
        if len(faces) and np.allclose(faces[:, :3], 1.0):
            out += [tuple(map(float, xy)) for xy in coll.get_offsets()]
    return out


def test_fig4_marks_the_budget_decided_cell_and_draws_both_budgets(synthetic):
    _, pooled, figures = synthetic
    fig = figures["fig4_success"]
    sync_ax, async_ax = fig.axes[:2]
    assert _hollow_points(sync_ax) == [(0.2, 0.0)]  # the paper budget's 0 % at 0.2 s: holds spent the budget
    assert _hollow_points(async_ax) == []  # 130 action ticks > the 100 needed: the policy failed
    labels = [text.get_text() for legend in fig.legends for text in legend.get_texts()]
    assert "scripted · paper budget (holds count)" in labels and "scripted · action budget" in labels
    styles = {line.get_label(): line.get_linestyle() for line in sync_ax.get_lines()}
    assert styles["scripted · action budget"] == ":" and styles["scripted · paper budget (holds count)"] == "--"
    action = [line for line in sync_ax.get_lines() if line.get_label() == "scripted · action budget"][0]
    assert action.get_xydata().tolist() == [[0.0, 100.0], [0.2, 100.0]]
    assert any("hollow marker: budget-decided" in t.get_text() for t in fig.texts)
    cell = pooled[(pooled["mode"] == "sync") & (pooled["latency_s"] == 0.2) & (pooled["budget_counts"] == "all")]
    assert cell["budget_decided"].tolist() == [True] and cell["action_budget_success_rate"].tolist() == [1.0]


def test_fig9_time_to_success_steps_at_the_known_times(synthetic):
    _, _, figures = synthetic
    fig = figures["fig9_time_to_success"]
    titles = [ax.get_title(loc="left") for ax in fig.axes]
    assert titles[::2] == ["scripted · async", "scripted · sync"]
    sync_s, sync_ticks = fig.axes[2:4]
    curves = {line.get_label(): line for line in sync_s.get_lines() if line.get_label().startswith(("0", "0.2"))}
    zero = curves["0 s (N=0) · paper budget (n=3)"]
    # Successes at 100, 101, 102 ticks = 5.00, 5.05, 5.10 s: one step of a third each, then held to the last time.
    assert zero.get_xdata() == pytest.approx([0.0, 5.0, 5.05, 5.1, 5.1])
    assert zero.get_ydata() == pytest.approx([0.0, 100 / 3, 200 / 3, 100.0, 100.0])
    failed = curves["0.2 s (N=4) · paper budget (n=6)"]
    assert failed.get_xdata() == pytest.approx([0.0, 7.0]) and failed.get_ydata() == pytest.approx([0.0, 0.0])
    slower = curves["0.2 s (N=4) · action budget (n=6)"]  # the same cell succeeds later under the action budget
    assert slower.get_xdata()[-1] == pytest.approx(9.0) and slower.get_ydata()[-1] == pytest.approx(100.0)
    ticks = {line.get_label(): line for line in sync_ticks.get_lines()}
    assert ticks["0.2 s (N=4) · paper budget (n=6)"].get_xdata()[-1] == pytest.approx(70.0)  # censored at 70


def test_fig5_draws_the_detrended_ee_osc_beside_the_papers(synthetic):
    _, _, figures = synthetic
    axes = figures["fig5_trajectory"].axes
    assert "paper A.3" in axes[2].get_ylabel() and "detrended" in axes[3].get_ylabel()
    assert "travel counts" in axes[2].get_title() and "back-and-forth only" in axes[3].get_title()
    # Three values a cell: hollow, unjoined means (lq_ros/report/plot_rules.py).
    paper, detrended = (np.array([xy[1] for c in ax.collections if c.get_sizes().size and c.get_sizes()[0] == 40
                                  for xy in c.get_offsets()]) for ax in axes[2:])  # fmt: skip
    assert set(np.round(paper[np.isfinite(paper)], 6)) == {20.0}  # mm; no successes at 0.2 s: no point
    assert set(np.round(detrended[np.isfinite(detrended)], 6)) == {5.0}


def test_tables_and_sentences(synthetic):
    episodes, pooled, _ = synthetic
    summary = tables.summary_table(pooled).set_index(["policy", "mode", "latency"])
    row = summary.loc[("scripted", "sync", "0.2 s (N=4)")]
    assert (
        row["budget"]
        == "◇ budget-decided by the action-budget twins: 6/6 timeouts succeed under the action budget (100% [61, 100]);"
        " action budget: 100 % of 6"
    )
    zero = summary.loc[("scripted", "sync", "0 s (N=0)")]
    assert zero["time s (succ.)"] == "5.05 (n=3: 5.00, 5.05, 5.10)"  # three values: listed, no interval
    paired = rp.paired_aggregates(episodes, pooled, n_boot=100)
    assert set(paired["p_adjustment"]) == {BH_ADJUSTMENT}  # paired_vs_zero_latency.csv names its correction
    sentences = prose.paired_sentences(paired)
    failed = [s for s in sentences if s.startswith("**scripted · sync, 0.2 s")][0]
    note = "◇ budget-decided by the action-budget twins: 6/6 timeouts succeed under the action budget (100% [61, 100])"
    assert f"success 0/6 against 3/3 ({note}" in failed and "no (task, init, seed) pair succeeds" in failed
    # The policy label is escaped for markdown (its brackets are not a link).
    slower = [s for s in sentences if s.startswith(r"**scripted \[budget_counts=action\] · sync, 0.2 s")][0]
    # Action budget: 180 against 100, 101, 102 ticks per pair = +4.00, +3.95, +3.90 s.
    # Three pairs: no interval, no test, so no change is called (the values are listed).
    assert (
        "over the 3 pairs that succeed in both, no change shown; not shown to change: completion time (s) +3.95"
        " (n=3: +4.00, +3.95, +3.90)"
    ) in slower


# -- real bags -------------------------------------------------------------------------------------------------

#: A budget below what the held sync episode needs: sync 0.2 s times out under it, succeeds under the action budget.
MAX_STEPS = 140


@pytest.fixture(scope="module")
def real_report(tmp_path_factory, spatial_env):
    """Five real in-process episodes of LIBERO-Spatial task 0, init 0, 140-tick budget: sync and async at 0 s,
    sync 0.2 s under both budgets, async 0.2 s under the paper budget."""
    from lq_ros.core.run_config import RunConfig
    from lq_ros.transport.inprocess import run_inprocess

    out = tmp_path_factory.mktemp("attribution")
    outcomes = {}
    for mode, latency, budget in (("sync", 0.0, "all"), ("sync", 0.2, "all"), ("sync", 0.2, "action"),
                                  ("async", 0.0, "all"), ("async", 0.2, "all")):  # fmt: skip
        cfg = RunConfig(mode=mode, latency_s=latency, max_steps=MAX_STEPS, budget_counts=budget)
        outcomes[(mode, latency, budget)] = run_inprocess(cfg, out / "bags", env=spatial_env).status
    report = rp.build_report(out / "bags", out / "report", n_boot=200, keep_figures=True)
    yield outcomes, report
    for fig in report.figures.values():
        plt.close(fig)


@pytest.mark.slow
@pytest.mark.sim
def test_real_bags_attribute_the_sync_timeout_to_the_budget_and_the_async_one_to_the_policy(real_report):
    outcomes, report = real_report
    assert outcomes == {("sync", 0.0, "all"): "success", ("sync", 0.2, "all"): "failure",
                        ("sync", 0.2, "action"): "success", ("async", 0.0, "all"): "success",
                        ("async", 0.2, "all"): "failure"}  # fmt: skip
    eps = report.episodes.set_index(["mode", "latency_s", "budget_counts"])
    assert eps.loc[("sync", 0.2, "all"), "budget_limited"] is True  # its action-budget twin succeeded
    assert eps.loc[("sync", 0.2, "all"), "budget_basis"] == "action-budget run"
    sync_zero = eps.loc[("sync", 0.0, "all"), "action_ticks"]
    assert eps.loc[("sync", 0.2, "all"), "action_ticks"] < sync_zero  # holds spent the budget
    assert eps.loc[("async", 0.2, "all"), "budget_limited"] is False
    assert eps.loc[("async", 0.2, "all"), "action_ticks"] >= eps.loc[("async", 0.0, "all"), "action_ticks"]
    pooled = report.pooled.set_index(["mode", "latency_s", "budget_counts"])
    # One timeout, rescued: the episode is budget-limited, but one episode is too few to mark the cell.
    assert not bool(pooled.loc[("sync", 0.2, "all"), "budget_decided"])
    assert not bool(pooled.loc[("async", 0.2, "all"), "budget_decided"])
    sync_ax, async_ax = report.figures["fig4_success"].axes[:2]
    assert _hollow_points(sync_ax) == [] and _hollow_points(async_ax) == []
    md = Path(report.files["report.md"]).read_text()
    assert (
        "1/1 timeouts succeed under the action budget (100% [21, 100]): too few timeouts to attribute (a mark needs 5)"
        "; action budget: 100 % of 1"
    ) in md
    # The action budget has no 0 s cell of its own: the paper budget's stands in (no tick holds at 0 s).
    slower = eps.loc[("sync", 0.2, "action"), "completion_time_s"] - eps.loc[("sync", 0.0, "all"), "completion_time_s"]
    assert slower > 0
    assert (
        r"**scripted \[max_steps=140, budget_counts=action\] · sync, 0.2 s (N=4)** against 0 s: success 1/1 against "
        "1/1; over the 1 pair (a failure at the horizon)"
    ) in md
    assert (
        "over the 1 pair that succeeds in both, no change shown; not shown to change: completion time (s) "
        f"{slower:+.2f} (n=1)"
    ) in md
    assert "fig9_time_to_success.png" in md and report.files["fig9_time_to_success.png"].stat().st_size > 10_000


def test_the_report_decomposes_the_cells_run_under_both_budgets(synthetic):
    """Sync 0.2 s ran under both budgets (3 pairs: 0 s success, paper budget timeout, action budget success): drop
    100 points, all of it the budget's. Async ran under the paper budget only: no row (the paired table has its
    drop)."""
    episodes, _, _ = synthetic
    rows = rp.budget_decomposition(episodes, n_boot=100)
    assert rows[["mode", "latency_s", "n_pairs"]].values.tolist() == [["sync", 0.2, 3]]
    row = rows.iloc[0]
    assert (row["drop_total"], row["drop_budget"], row["drop_rest"]) == (1.0, 1.0, 0.0)
    view = decomposition_table(rows)
    assert view[["drop (pp)", "budget (pp)", "rest (pp)"]].values.tolist() == [["+100", "+100", "+0"]]  # one task


@pytest.mark.slow
@pytest.mark.sim
def test_real_bags_report_the_same_decomposition_as_the_benchmark(real_report):
    """benchmarks/attribution_table.py and the report's section print one table from the same bags."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
    from attribution_table import table

    _, report = real_report
    md = Path(report.files["report.md"]).read_text()
    bags = report.files["report.md"].parent.parent / "bags"
    benchmark = table(bags)
    assert f"## {rp.ATTRIBUTION_TITLE}" in md and benchmark in md
    assert "+100 |" in benchmark and report.files["attribution.csv"].exists()  # drop and budget, one task
