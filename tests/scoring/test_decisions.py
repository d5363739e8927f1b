"""lq_ros.scoring.decisions: the task-level sign-flip test, the declared analysis plan, equivalence."""

import math

import numpy as np
import pytest

from lq_ros.scoring.decisions import (
    AnalysisPlan,
    PlanError,
    Primary,
    cluster_means,
    cluster_p,
    equivalent,
    min_cluster_p,
    parse_analysis,
    sign_flip_p,
)


def test_sign_flip_p_on_five_tasks_by_hand():
    # Task means 1, 2, 3, 4, -1: |sum| = 9 of a total magnitude 11. Flipping a subset of magnitude F gives
    # |11 - 2F| >= 9 iff F <= 1 ({}, {1}, {-1}: 3 subsets) or F >= 10 (their 3 complements): 6 of 32.
    assert sign_flip_p([1, 2, 3, 4, -1]) == pytest.approx(6 / 32)
    assert sign_flip_p([0.1, 0.2, 0.3, 0.4, -0.1]) == pytest.approx(6 / 32)  # ties survive floating point
    assert sign_flip_p([1, 1, 1, 1, 1]) == pytest.approx(2 / 32) == min_cluster_p(5)
    assert sign_flip_p([0, 0, 0]) == 1.0 and math.isnan(sign_flip_p([]))


def test_sign_flip_p_is_exact_to_16_tasks_and_drawn_beyond():
    rng = np.random.default_rng(3)
    d16 = rng.normal(0.3, 1.0, 16)
    signs = np.array([[1 - 2 * ((k >> j) & 1) for j in range(16)] for k in range(2**16)])
    assert sign_flip_p(d16) == pytest.approx(np.mean(np.abs(signs @ d16) >= abs(d16.sum()) - 1e-9))
    d40 = np.full(40, 1.0)
    assert sign_flip_p(d40) == pytest.approx(1 / 100_001)  # no random pattern of 40 reaches all-one-sign


def test_cluster_p_uses_the_task_not_the_episode():
    """120 pairs in 10 tasks: 12 pairs per task, every task's mean the same sign in 6 tasks and the other in 4. As 120
    independent pairs (a one-sample test) this is decisive; with the task as the unit it is not."""
    tasks = np.repeat(np.arange(10), 12)
    per_task = np.array([0.5, 0.5, 0.5, 0.5, 0.5, 0.5, -0.25, -0.25, -0.25, -0.25])
    values = per_task[tasks]
    assert cluster_means(values, tasks) == pytest.approx(per_task)
    assert cluster_p(values, tasks) > 0.05


def test_equivalence_is_a_tost_at_the_margin():
    assert equivalent(-0.03, 0.04, 0.05) is True
    assert equivalent(-0.12, 0.13, 0.05) is False  # "+2 [-12, +13]": no difference detected, not equality
    assert equivalent(-0.03, 0.04, None) is None and equivalent(math.nan, 0.1, 0.05) is None


def test_parse_analysis_declares_primaries_and_refuses_self_comparisons():
    plan = parse_analysis(
        {"primary": [{"a": "flow [variant=delay]", "b": "flow", "mode": "async", "latency_s": 0.2}],
         "equivalence_margin": 0.1}, policy_names=["flow"])  # fmt: skip
    assert plan == AnalysisPlan((Primary("flow [variant=delay]", "flow", "async", "async", (0.2,)),), 0.1)
    row = {"suite": "libero_object", "latency_s": 0.2, "budget_counts": "all", "arm_a": "flow · libero_object",
           "mode_a": "async", "arm_b": "flow [variant=delay] · libero_object", "mode_b": "async"}  # fmt: skip
    assert plan.is_primary(row)  # either order, suite suffix dropped
    assert not plan.is_primary(row | {"latency_s": 0.1})
    assert parse_analysis(None) == AnalysisPlan()
    refusals = {
        "compares 'flow' with itself": {"primary": [{"a": "flow", "b": "flow", "mode": "async"}]},
        "names no policy of the spec": {"primary": [{"a": "oft", "b": "flow"}]},
        "equivalence_margin: expected": {"equivalence_margin": 10},
        "expected a mapping with keys": {"primary": [], "margin": 0.1},
        "mode: expected sync or async": {"primary": [{"a": "flow", "b": "flow [x=1]", "mode": "both"}]},
    }
    for message, raw in refusals.items():
        with pytest.raises(PlanError, match=message):
            parse_analysis(raw, policy_names=["flow"])
    # One arm in two modes is a comparison (sync against async).
    assert parse_analysis({"primary": [{"a": "flow", "b": "flow", "mode_a": "sync", "mode_b": "async"}]}).primary
