"""Run one episode and score it: the outcome decides the row's status (no simulator needed here)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from lq_ros.core.bounded_file import RESULTS_FILE_MAX_BYTES, FileRefused
from lq_ros.core.run_config import RunConfig
from lq_ros.recording.episode_folder import SCORE_FILE
from lq_ros.run import episode
from lq_ros.run.episode import run_episode, scored_row, settle
from lq_ros.transport.outcome import EpisodeOutcome
from lq_ros.transport.ros import stack as launcher


def test_settle_makes_a_run_error_an_error_row_with_its_reason():
    row = {"status": "success", "success": True}
    settle(row, EpisodeOutcome("error", 12, "policy node exited with code 1", Path("bag")))
    assert row == {"status": "error", "success": None, "error_reason": "policy node exited with code 1"}
    row = {"status": "error", "success": None, "error_reason": "the bag's own reason"}
    settle(row, EpisodeOutcome("error", 12, "other", Path("bag")))
    assert row["error_reason"] == "the bag's own reason"
    row = {"status": "failure", "success": False}
    assert settle(row, EpisodeOutcome("failure", 30, "timeout", Path("bag"))) == {"status": "failure", "success": False}


def test_no_bag_at_all_scores_as_an_error_naming_the_episode(tmp_path):
    assert scored_row(tmp_path / "ep") == {"episode": "ep", "status": "error", "success": None}


def _fifo(path: Path) -> None:
    os.mkfifo(path)


def _link(path: Path) -> None:
    (path.parent / "elsewhere.json").write_text('{"status": "success", "success": true}')
    path.symlink_to(path.parent / "elsewhere.json")


def _huge(path: Path) -> None:
    path.write_text('{"status": "success", "pad": "' + "x" * RESULTS_FILE_MAX_BYTES + '"}')


def _list(path: Path) -> None:
    path.write_text("[1, 2]")


@pytest.mark.parametrize(
    "make, problem",
    [
        (_fifo, "not a regular file"),
        (_link, "a link, not a regular file"),
        (_huge, "bytes; at most"),
        (_list, "not a JSON object"),
    ],  # fmt: skip
)
def test_a_score_file_that_is_no_small_regular_json_file_is_refused_in_one_line(tmp_path, no_hang, make, problem):
    bag = tmp_path / "ep"
    bag.mkdir()
    make(bag / SCORE_FILE)
    with pytest.raises(FileRefused) as refused:
        scored_row(bag)  # a FIFO would block a plain read: this returns at once
    message = str(refused.value)
    assert message.startswith(f"score file {bag / SCORE_FILE}: ") and problem in message and "\n" not in message


def test_a_refused_score_file_makes_the_ros_episode_an_error_naming_it(monkeypatch, tmp_path, no_hang):
    cfg = RunConfig(policy="sine")
    bag = tmp_path / cfg.episode_name()
    bag.mkdir()
    os.mkfifo(bag / SCORE_FILE)
    monkeypatch.setattr(launcher, "launch_nodes", lambda cfg, out, **_: (Path(out) / cfg.episode_name(), ""))
    outcome, row = run_episode(cfg, tmp_path, "ros")
    assert outcome.status == row["status"] == "error" and row["success"] is None
    assert row["error_reason"].startswith(f"score file {bag / SCORE_FILE}: not a regular file")


@pytest.mark.parametrize(
    "launch_error, scored, status, reason",
    [
        ("", {"status": "failure", "success": False, "completion_steps": 30}, "failure", ""),
        ("sim node exited with code 1", {"status": "failure", "success": False}, "error", "sim node exited with code"),
        # No terminal event in the bag: the scorer says "unknown", the run is an error.
        ("", {"status": "unknown", "success": None, "error_reason": "no terminal event"}, "error", "no terminal event"),
    ],
)
def test_ros_outcome_from_the_launch_and_the_score(monkeypatch, tmp_path, launch_error, scored, status, reason):
    monkeypatch.setattr(launcher, "launch_nodes", lambda cfg, out, **_: (Path(out) / cfg.episode_name(), launch_error))
    monkeypatch.setattr(episode, "scored_row", lambda bag: dict(scored))
    outcome, row = run_episode(RunConfig(policy="sine"), tmp_path, "ros")
    assert outcome.status == row["status"] == status
    assert outcome.reason.startswith(reason) and outcome.ticks == scored.get("completion_steps", 0)
    assert row["success"] is (None if status == "error" else False)


def test_unknown_transport_is_refused(tmp_path):
    with pytest.raises(ValueError, match="transport"):
        run_episode(RunConfig(policy="sine"), tmp_path, "zmq")
