"""``lq eval --budget-counts``: the action-budget twins the report's budget attribution asks for."""

from __future__ import annotations

from lq_ros.cli.eval import BUDGET_CHOICES, eval_spec
from lq_ros.run.sweep.spec import expand_spec
from tests.test_cli_errors import assert_refused, lq


def _spec(budget: str):
    raw = eval_spec("sine", {}, "libero_spatial", "0-1", "0-2", [0.0, 0.2], ["sync", "async"], "replace", 5, [7], 0, 0,
                    "inprocess", "twins", budget_counts=BUDGET_CHOICES[budget])  # fmt: skip
    return raw, expand_spec(raw)


def test_both_runs_every_episode_under_each_budget():
    raw, spec = _spec("both")
    assert raw["budget_counts"] == ["all", "action"]
    cells = {}
    for c in spec.configs:
        cells.setdefault((c.task, c.init, c.seed, c.mode, c.latency_s), set()).add(c.budget_counts)
    assert len(cells) == 2 * 3 * 2 * 2 and all(b == {"all", "action"} for b in cells.values())
    raw, spec = _spec("action")
    assert {c.budget_counts for c in spec.configs} == {"action"}
    raw, spec = _spec("all")
    assert "budget_counts" not in raw and {c.budget_counts for c in spec.configs} == {"all"}  # the spec as before


def test_a_wrong_budget_is_one_line():
    assert_refused(lq("eval", "--policy", "sine", "--out", "/nonexistent/x", "--budget-counts", "actoin"),
                   "--budget-counts 'actoin': expected all, action or both", "did you mean 'action'?")  # fmt: skip
