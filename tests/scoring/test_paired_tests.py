"""lq_ros.scoring.paired_tests: exact McNemar, Holm and Benjamini-Hochberg, paired comparisons of arms."""

import math

import numpy as np
import pandas as pd
import pytest

from lq_ros.scoring.paired_tests import benjamini_hochberg, compare_pairs, holm, mcnemar_exact_p, paired_policies


def test_mcnemar_exact_p():
    assert mcnemar_exact_p(0, 0) == 1.0
    assert mcnemar_exact_p(5, 5) == pytest.approx(1.0)
    # 6 discordant pairs all one way: 2 * 0.5**6.
    assert mcnemar_exact_p(6, 0) == pytest.approx(2 * 0.5**6)
    assert mcnemar_exact_p(0, 6) == mcnemar_exact_p(6, 0)
    assert mcnemar_exact_p(9, 1) == pytest.approx(2 * (1 + 10) / 2**10)
    with pytest.raises(ValueError):
        mcnemar_exact_p(-1, 2)


def test_holm_and_benjamini_hochberg():
    p = [0.01, 0.04, 0.03, math.nan, 0.5]
    np.testing.assert_allclose(holm(p), [0.04, 0.09, 0.09, math.nan, 0.5])
    np.testing.assert_allclose(benjamini_hochberg(p), [0.04, 0.04 * 4 / 3, 0.04 * 4 / 3, math.nan, 0.5])
    np.testing.assert_allclose(holm([0.9, 0.8]), [1.0, 1.0])


def arm(statuses: list[str], times: list[float] | None = None, tasks: list[int] | None = None) -> pd.DataFrame:
    n = len(statuses)
    return pd.DataFrame({
        "task": tasks or [i // 5 for i in range(n)], "init": [i % 5 for i in range(n)], "seed": 7,
        "status": statuses, "completion_time_s": times or [5.0 if s == "success" else 11.0 for s in statuses],
        "tick_limit": 220, "step_budget": 220,
    })  # fmt: skip


def test_compare_pairs_counts_discordant_pairs_and_leaves_errors_out():
    a = arm(["success"] * 8 + ["failure", "error"])
    b = arm(["failure"] * 4 + ["success"] * 4 + ["success", "success"])
    out = compare_pairs(a, b, n_boot=500)
    assert out["n_pairs"] == 9  # the error's pair is left out
    assert (out["both"], out["a_only"], out["b_only"], out["neither"]) == (4, 4, 1, 0)
    assert out["diff"] == pytest.approx(3 / 9)
    assert out["mcnemar_p"] == pytest.approx(mcnemar_exact_p(4, 1))
    assert out["diff_ci_lo"] <= out["diff"] <= out["diff_ci_hi"]
    # Time to success over every pair, failures at the horizon (220 ticks = 11 s): A 8 x 5 s + 1 x 11 s.
    assert out["rmst_a_s"] == pytest.approx((8 * 5 + 11) / 9)
    assert out["rmst_b_s"] == pytest.approx((4 * 11 + 5 * 5) / 9)


def test_paired_policies_compares_policies_within_a_protocol_and_protocols_within_a_policy():
    rows = []
    for policy, mode, statuses in (("p", "sync", ["success"] * 10), ("p", "async", ["failure"] * 10),
                                   ("q", "sync", ["success"] * 5 + ["failure"] * 5)):  # fmt: skip
        frame = arm(statuses)
        frame["policy"], frame["mode"], frame["suite"], frame["latency_s"] = policy, mode, "libero_spatial", 0.2
        rows.append(frame)
    table = paired_policies(pd.concat(rows, ignore_index=True), n_boot=200)
    kinds = sorted(zip(table.comparison, table.arm_a, table.mode_a, table.arm_b, table.mode_b, strict=True))
    assert kinds == [("policy", "p", "sync", "q", "sync"), ("protocol", "p", "sync", "p", "async")]
    protocol = table[table.comparison == "protocol"].iloc[0]
    assert (protocol.a_only, protocol.b_only, protocol["diff"]) == (10, 0, 1.0)
    assert protocol.p_adjusted == pytest.approx(min(1.0, 2 * mcnemar_exact_p(10, 0)))
    assert bool(protocol.called)
    policy = table[table.comparison == "policy"].iloc[0]
    assert policy.a_only == 5 and not policy.called
