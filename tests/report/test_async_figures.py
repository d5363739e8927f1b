"""Fig. 8 (lq_ros/report/async_figures.py) from a synthetic episode table: one line per merge strategy and
latency kind."""

import matplotlib.pyplot as plt
import numpy as np

from lq_ros.report.async_figures import PANELS, boundary_aggregates, fig_chunk_boundary
from lq_ros.scoring.aggregate import episodes_frame


def _row(merge, latency, dist, status, jump, init):
    return {
        "policy": "flow", "mode": "async", "merge": merge, "latency_s": latency, "latency_dist": dist,
        "suite": "libero_spatial", "task": 0, "init": init, "seed": 7, "status": status,
        "success": status == "success", "completion_steps": 100, "completion_time_s": 5.0, "jerk_mean": 10.0,
        "switch_executed_step_mean": jump, "switch_executed_step_max": 2 * jump, "chunk_disagreement_mean": 3 * jump,
        "chunk_switch_jump_mean": 5.0, "chunk_switch_jerk_ratio": 1.0 + jump,
        "traj_length": 1.0, "versions": "{}", "transport": "inprocess",
    }  # fmt: skip


def test_one_line_per_merge_strategy_and_latency_kind():
    rows = []
    for merge, jump in (("replace", 0.9), ("weighted_average", 0.6), ("rtc", 0.3)):
        for latency, uniform in ((0.1, "uniform:0.025:0.125"), (0.2, "uniform:0.125:0.225")):
            for init in range(5):  # five values a cell: joined (lq_ros/report/plot_rules.py)
                rows.append(_row(merge, latency, "constant", "success" if init else "failure", jump, init))
                rows.append(_row(merge, latency, uniform, "success", jump + 0.05, init))
    rows.append({**_row("replace", 0.2, "constant", "success", 0.1, 9), "mode": "sync"})  # not in Fig. 8
    frame = episodes_frame(rows)
    pooled = boundary_aggregates(frame, n_boot=100)
    assert set(pooled["merge"]) == {"replace", "weighted_average", "rtc"} and set(pooled["base"]) == {"flow"}
    assert set(pooled["latency_kind"]) == {"constant", "uniform"} and len(pooled) == 3 * 2 * 2
    fig = fig_chunk_boundary(frame, n_boot=100)
    axes = fig.axes
    assert len(axes) == len(PANELS)
    lines = [line for line in axes[1].get_lines() if len(line.get_xdata())]
    assert len(lines) == 6  # 3 strategies x {constant, uniform}
    labels = sorted(line.get_label() for line in lines)
    assert labels[0] == "replace" and "rtc (uniform latency)" in labels
    rtc = next(line for line in lines if line.get_label() == "rtc")
    assert np.allclose(rtc.get_ydata(), 0.3)  # the executed step, over every episode with an outcome
    panel = {metric: ax for ax, (metric, _, _) in zip(axes, PANELS, strict=True)}
    assert "chunk_switch_jump_mean" not in panel  # the jump against the old plan is not the executed quantity
    assert panel["switch_executed_step_mean"] is axes[1]
    for metric, factor in (("switch_executed_step_max", 2), ("chunk_disagreement_mean", 3)):
        line = next(line for line in panel[metric].get_lines() if line.get_label() == "rtc")
        assert np.allclose(line.get_ydata(), factor * 0.3)
    success = next(line for line in axes[0].get_lines() if line.get_label() == "rtc")
    assert np.allclose(success.get_ydata(), 100 * 4 / 5)
    plt.close(fig)
    empty = fig_chunk_boundary(frame[frame["mode"] == "sync"], n_boot=10)
    assert "no async episodes" in empty.axes[0].texts[0].get_text()
    plt.close(empty)
