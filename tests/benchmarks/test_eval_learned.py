"""benchmarks/eval_learned.py's success tables: beside each total's Wilson interval, its task-clustered interval."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

from lq_ros.scoring.intervals import clustered_success_ci, wilson_interval

_PATH = Path(__file__).resolve().parents[2] / "benchmarks" / "eval_learned.py"
_SPEC = importlib.util.spec_from_file_location("eval_learned", _PATH)
eval_learned = importlib.util.module_from_spec(_SPEC)
sys.modules.setdefault("eval_learned", eval_learned)
_SPEC.loader.exec_module(eval_learned)

#: Successes of 10 init states per task: strongly clustered (one task never succeeds, three always do).
PER_TASK = (0, 10, 10, 10, 5, 6, 7, 2, 9, 1)


def rows(per_task=PER_TASK, **extra) -> list[dict]:
    return [
        {"suite": "libero_spatial", "policy": "flow", "task": task, "init": init, "ticks": 100, "replan_steps": 5,
         "status": "success" if init < ok else "timeout", "weights": "flow.json", "weights_md5": "0",
         "infer_s": [0.01], **extra}
        for task, ok in enumerate(per_task)
        for init in range(10)
    ]  # fmt: skip


def test_the_total_carries_its_task_clustered_interval(capsys):
    summary = eval_learned.report(rows(), ["flow"], isolated=False)["libero_spatial"]["flow"]
    clustered = clustered_success_ci([[1.0] * ok + [0.0] * (10 - ok) for ok in PER_TASK])
    wilson = wilson_interval(sum(PER_TASK), 100)
    assert summary["task_clustered95"] == pytest.approx(clustered)
    assert summary["wilson95"] == pytest.approx(wilson)
    # Clustered outcomes: the interval that resamples tasks is the wider one, on both sides.
    assert clustered[0] < wilson[0] - 0.05 and clustered[1] > wilson[1] + 0.05
    printed = capsys.readouterr().out
    assert f"[{100 * clustered[0]:.0f}-{100 * clustered[1]:.0f}]" in printed
    assert "task-clustered 95% interval, % (10 tasks)" in printed


def test_too_few_tasks_give_no_clustered_interval(capsys):
    summary = eval_learned.report(rows(PER_TASK[:3]), ["flow"], isolated=False)["libero_spatial"]["flow"]
    assert all(x != x for x in summary["task_clustered95"])  # NaN: three tasks are too few to resample
    assert "[n/a]" in capsys.readouterr().out


def test_latency_cells_carry_both_intervals(capsys):
    eval_learned.latency_report(rows(latency_s=0.2, mode="async"))
    clustered = clustered_success_ci([[1.0] * ok + [0.0] * (10 - ok) for ok in PER_TASK])
    wilson = wilson_interval(sum(PER_TASK), 100)
    percent = [f"{100 * low:.0f}-{100 * high:.0f}" for low, high in (wilson, clustered)]
    assert f"60/100 = 60% [{percent[0]} | {percent[1]}]" in capsys.readouterr().out
