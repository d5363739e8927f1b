"""lq_ros.run.sweep.record_check: a results record or manifest is used only if every field it is read by is sound."""

from __future__ import annotations

import json
import os

import pytest

from lq_ros.core.bounded_file import FileRefused
from lq_ros.run.sweep.record_check import read_manifest, record_problem


def good_record(**changes) -> dict:
    row = {"episode": "e", "policy": "sine", "mode": "sync", "suite": "libero_spatial", "task": 0, "init": 0,
           "seed": 7, "latency_s": 0.0, "status": "failure", "success": False}  # fmt: skip
    record = {"key": "k1", "status": "failure", "bag": "bags/e", "row": row,
              "attempts": [{"attempt": 1, "status": "failure", "log": "logs/k1.a1.log", "wall_s": 3.5}]}  # fmt: skip
    record.update(changes)
    return record


def test_a_sound_record_passes():
    assert record_problem(good_record(), "k1") is None
    assert record_problem(good_record(bag=None, attempts=[]), "k1") is None


@pytest.mark.parametrize(
    ("changes", "problem"),
    [
        ({"key": "k2"}, "key 'k2' is not the file's name"),
        ({"bag": "../../elsewhere"}, "bag '../../elsewhere' is not a path inside the sweep folder"),
        ({"bag": "/etc"}, "bag '/etc' is not a path inside the sweep folder"),
        ({"attempts": {"attempt": 1}}, "attempts is a dict, not a list"),
        ({"attempts": [1]}, "attempts[0] is an int, not an object"),
        ({"attempts": [{"attempt": 0, "status": "error"}]}, "attempts[0].attempt 0 is not a whole number >= 1"),
        ({"attempts": [{"attempt": 1, "status": "error", "wall_s": -4}]}, "attempts[0].wall_s -4 is not a time >= 0"),
        ({"attempts": [{"attempt": 1, "status": "error", "log": "/tmp/x"}]}, "attempts[0].log '/tmp/x' is not a path"),
        ({"row": "success"}, "row: the row is a str, not an object of fields"),
    ],
)
def test_a_wrong_field_of_a_record_is_named(changes, problem):
    assert record_problem(good_record(**changes), "k1").startswith(problem)


@pytest.mark.parametrize(
    "content",
    ['{"episodes": 3}', '["k1"]', '{"episodes": [1, 2]}', '{"name": "x"}', "{"],
)
def test_a_broken_manifest_is_refused_by_name(tmp_path, content):
    (tmp_path / "manifest.json").write_text(content)
    with pytest.raises(FileRefused, match=r"^manifest .*manifest\.json: "):
        read_manifest(tmp_path / "manifest.json")


def test_a_manifest_fifo_is_refused_without_blocking(tmp_path):
    os.mkfifo(tmp_path / "manifest.json")
    with pytest.raises(FileRefused, match="not a regular file"):
        read_manifest(tmp_path / "manifest.json")


def test_the_manifest_the_orchestrator_writes_is_read(tmp_path):
    (tmp_path / "manifest.json").write_text(json.dumps({"name": "s", "episodes": {"k1": {"policy": "sine"}, "k2": {}}}))
    assert read_manifest(tmp_path / "manifest.json") == {"k1", "k2"}
