"""The console's lines beyond a row: rejected chunks (count and first reason), where a crash's traceback is."""

from __future__ import annotations

from pathlib import Path

import pytest

from lq_ros.core.run_config import RunConfig
from lq_ros.run.episode import run_episode, settle
from lq_ros.run.episode_notes import crash_log, warnings_of
from lq_ros.transport.outcome import EpisodeOutcome


def test_no_rejections_no_warning():
    assert warnings_of({"chunks_rejected": 0}, None) == [] and warnings_of({}, None) == []
    assert warnings_of({"chunks_rejected": 2}, None) == ["2 chunks rejected, the robot held instead"]


def test_an_error_row_names_the_log_holding_the_traceback(tmp_path):
    bag = tmp_path / "ep"
    (bag / "logs").mkdir(parents=True)
    (bag / "logs" / "sim.log").write_text("all fine\n")
    (bag / "logs" / "policy.log").write_text("inference failed: boom\nTraceback (most recent call last):\n  ...\n")
    assert crash_log(bag) == bag / "logs" / "policy.log"
    row = settle({"status": "error"}, EpisodeOutcome("error", 3, "policy error: boom", bag))
    assert row["error_reason"] == f"policy error: boom (traceback: {bag / 'logs' / 'policy.log'})"
    assert crash_log(tmp_path / "none") is None


@pytest.mark.sim
def test_inprocess_nan_chunk_warns_and_a_crash_keeps_its_traceback(tmp_path):
    nan = RunConfig(policy="faulty", policy_args={"fault": "nan", "at_requests": [2]}, max_steps=20, replan_steps=4)
    outcome, row = run_episode(nan, tmp_path, "inprocess")
    assert row["status"] == "failure"
    [line] = warnings_of(row, outcome.bag_path)
    assert line.startswith("1 chunk rejected, the robot held instead (first: ") and "non-finite" in line
    crash = RunConfig(policy="faulty", policy_args={"fault": "raise", "at_requests": [1]}, max_steps=20)
    outcome, row = run_episode(crash, tmp_path, "inprocess")
    log = Path(outcome.bag_path) / "logs" / "episode.log"
    assert row["status"] == "error" and row["error_reason"].endswith(f"(traceback: {log})")
    text = log.read_text()
    assert "Traceback (most recent call last)" in text and "injected failure on request 1" in text
