"""Two run folders in one report: a policy in both is a variant per run, compared on the episodes both ran."""

from __future__ import annotations

import json

import pandas as pd
import pytest

from lq_ros.report import runs
from lq_ros.report.sweep_report import build_report
from lq_ros.run.sweep import ResultStore
from tests.report.test_figure_rules import _row


def write_run(folder, successes: int) -> None:
    """A sweep folder of 'sine' episodes, sync at 0 s: tasks 0-5, inits 0-1; the first ``successes`` succeed."""
    store = ResultStore(folder)
    store.create()
    for i, (task, init) in enumerate((t, n) for t in range(6) for n in range(2)):
        row = _row("libero_spatial", mode="sync", task=task, init=init, policy="sine",
                   status="success" if i < successes else "failure")  # fmt: skip
        key = f"{folder.name}{i:03d}"
        store.write({"key": key, "status": row["status"], "bag": None, "row": row, "attempts": []})


def test_a_policy_in_two_runs_is_compared_pair_by_pair(tmp_path):
    write_run(tmp_path / "before", successes=12)
    write_run(tmp_path / "after", successes=3)
    report = build_report([tmp_path / "before", tmp_path / "after"], tmp_path / "compare", n_boot=100)
    assert set(report.episodes["policy"]) == {"sine · before", "sine · after"}  # never pooled into one cell
    assert set(report.episodes["run"]) == {"before", "after"}
    compared = pd.read_csv(tmp_path / "compare" / "paired_policies.csv")
    [row] = compared.to_dict("records")
    assert {row["arm_a"], row["arm_b"]} == {"sine · before", "sine · after"} and row["n_pairs"] == 12
    assert (tmp_path / "compare" / "report.html").exists()


def test_run_names_and_refusals(tmp_path):
    assert runs.run_names([tmp_path / "a" / "x", tmp_path / "b" / "y"]) == ["x", "y"]
    assert runs.run_names([tmp_path / "a" / "x", tmp_path / "b" / "x"]) == ["a/x", "b/x"]
    write_run(tmp_path / "one", successes=1)
    with pytest.raises(ValueError, match="named twice"):
        runs.load_runs([tmp_path / "one", tmp_path / "one"], lambda d: pd.DataFrame())
    with pytest.raises(ValueError, match="--out"):
        build_report([tmp_path / "one", tmp_path / "one"])
    assert json.loads((tmp_path / "one" / "results" / "one000.json").read_text())["row"]["policy"] == "sine"
