"""benchmarks/eval_learned.py --merge --by-weights: runs pool by checkpoint bytes, never by name alone."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def ev():
    spec = importlib.util.spec_from_file_location("eval_learned", ROOT / "benchmarks" / "eval_learned.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _row(spec: str, task: int, init: int, status: str = "success", md5: str | None = "a" * 32) -> dict:
    row = {"suite": "libero_spatial", "policy": spec, "task": task, "init": init, "status": status, "ticks": 120,
           "replan_steps": 8, "weights": "oft_c8_libero_spatial.json", "wall_s": 1.0}  # fmt: skip
    if md5:
        row["weights_md5"] = md5
    return row


def _latency(spec: str) -> dict:
    return {"suite": "libero_spatial", "policy": spec, "task": 0, "infer_s": [0.001, 0.002]}


def test_same_bytes_pool_into_one_column(ev, capsys):
    copy = "oft:weights=/elsewhere/oft_c8_libero_spatial.json"
    rows = [_row(copy, 0, 0), _row(copy, 0, 1, "failure"), _latency(copy), _row("oft", 0, 2), _latency("oft")]
    out, labels, spec_of = ev.by_weights(rows)
    assert labels == ["oft_c8"] and spec_of == {("libero_spatial", "oft_c8"): copy}
    assert [r["policy"] for r in out] == ["oft_c8"] * 5 and out[0]["spec"] == copy
    summary = ev.report(out, labels, isolated=False)["libero_spatial"]["oft_c8"]
    assert (summary["success"], summary["episodes"], summary["per_task"]) == (2, 3, {0: [2, 3]})
    assert summary["infer_calls"] == 4
    assert "oft_c8: weights md5 " + "a" * 32 in capsys.readouterr().out


def test_different_bytes_or_a_repeated_episode_are_refused(ev):
    with pytest.raises(SystemExit, match="oft_c8"):
        ev.by_weights([_row("oft", 0, 0), _row("oft:weights=/x/oft_c8_libero_spatial.json", 0, 1, md5="b" * 32)])
    with pytest.raises(SystemExit, match="twice"):
        ev.by_weights([_row("oft", 0, 0), _row("oft:weights=/x/oft_c8_libero_spatial.json", 0, 0)])


def test_a_run_without_recorded_digest_is_checked_against_the_file_it_names(ev, tmp_path):
    """Old runs did not record the MD5: the spec's weights file (here a copy of the shipped one) is hashed."""
    shipped = ROOT / "lq_ros" / "policies" / "weights" / "oft_c8_libero_spatial.json"
    meta = json.loads(shipped.read_text())
    (tmp_path / shipped.name).write_text(shipped.read_text())
    (tmp_path / meta["weights_file"]).write_bytes(shipped.with_name(meta["weights_file"]).read_bytes())
    real = ev.weights_digest(shipped)
    copy = f"oft:weights={tmp_path / shipped.name}"
    out, _, _ = ev.by_weights([_row(copy, 0, 0, md5=None), _row("oft", 0, 1, md5=real)])
    assert {r["policy"] for r in out} == {"oft_c8"}
    (tmp_path / meta["weights_file"]).write_bytes(b"other bytes")
    with pytest.raises(SystemExit, match="not recorded"):
        ev.by_weights([_row("oft", 0, 1, md5=real), _row(copy, 0, 0, md5=None)])


def _lat_row(spec: str, mode: str, latency: float, init: int, status: str, md5: str = "a" * 32) -> dict:
    return {"suite": "libero_object", "policy": spec, "mode": mode, "latency_s": latency, "task": 0, "init": init,
            "status": status, "ticks": 100, "replan_steps": 5, "weights": "w.json", "weights_md5": md5}  # fmt: skip


def test_latency_table_cells_and_merge_refusals(ev, capsys):
    rows = [_lat_row("flow", "async", 0.1, i, "success" if i < 3 else "failure") for i in range(4)]
    rows += [
        _lat_row("flow", "sync", 0.0, 0, "error: boom"),
        _lat_row("flow:variant=delay", "async", 0.1, 0, "success"),
    ]
    summary = ev.latency_report(ev.check_latency_rows(rows))["libero_object"]
    assert summary["flow"]["async"]["0.1"] == [3, 4] and summary["flow"]["sync"]["0"] == [0, 1]
    out = capsys.readouterr().out
    assert "3/4 = 75% [30-95 | n/a]" in out and "errors: 1" in out and "flow:variant=delay" in out
    assert f"flow: w.json (md5 {'a' * 32})" in out
    with pytest.raises(SystemExit, match="twice"):
        ev.check_latency_rows(rows + rows[:1])
    with pytest.raises(SystemExit, match="different weight files"):
        ev.check_latency_rows(rows + [_lat_row("flow", "async", 0.1, 9, "success", md5="b" * 32)])


def test_each_budget_gets_its_own_table_and_the_same_episode_under_both_is_not_a_repeat(ev, capsys):
    paper = [_lat_row("flow", "sync", 0.2, i, "failure") for i in range(2)]  # rows without the key: the paper's
    action = [{**_lat_row("flow", "sync", 0.2, i, "success"), "budget_counts": "action"} for i in range(2)]
    summary = ev.latency_report(ev.check_latency_rows(paper + action))["libero_object"]
    assert summary["flow"]["sync"]["0.2"] == [0, 2]
    assert summary["flow budget=action"]["sync"]["0.2"] == [2, 2]
    out = capsys.readouterr().out
    assert "paper budget (holds count)" in out and "action budget (holds do not count)" in out
    with pytest.raises(SystemExit, match="twice"):
        ev.check_latency_rows(paper + action + action[:1])


def test_a_totals_intervals_from_a_tables_per_task_counts(ev):
    """--from-counts gives what a run's table prints for the same per-task counts: Wilson over the episodes, and the
    task-clustered interval (wider when the tasks differ, as 10/10 against 0/10 do)."""
    per_task = (10, 0, 5, 10, 0, 5, 10, 0, 5, 5)
    rows = [{"task": t, "status": "success" if i < k else "failure"} for t, k in enumerate(per_task) for i in range(10)]
    low, high = ev.task_clustered(rows)
    assert (
        ev.total_from_counts([f"{k}/10" for k in per_task]) == f"50/100 = 50% [40-60 | {ev.interval_text(low, high)}]"
    )
    assert low < 0.40 and high > 0.60  # clustered: wider than Wilson's
    assert ev.total_from_counts(["5/10", "5/10"]).endswith("| n/a]")  # too few tasks for a clustered interval
    for bad in ("11/10", "3", "a/10", "1/0", "-1/10"):
        with pytest.raises(ValueError, match="is not k/n"):
            ev.total_from_counts(["5/10", bad])
