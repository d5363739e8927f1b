"""lq_ros.report.prose: the sentences on paired comparisons say what the paired tests found and no more."""

from __future__ import annotations

import pandas as pd

from lq_ros.core.wording import counted
from lq_ros.report import prose
from lq_ros.scoring.paired_tests import paired_policies


def _cell(latency: float, tasks: int, inits: int, p_fails: set, q_fails: set) -> list[dict]:
    """Arms p and q (sync, LIBERO-Spatial) on ``tasks`` x ``inits`` shared episodes; the sets hold (task, init) pairs
    that fail."""
    rows = []
    for policy, fails in (("p", p_fails), ("q", q_fails)):
        for t in range(tasks):
            for i in range(inits):
                rows.append({"policy": policy, "mode": "sync", "suite": "libero_spatial", "latency_s": latency,
                             "task": t, "init": i, "seed": 7, "status": "failure" if (t, i) in fails else "success",
                             "completion_time_s": 5.0, "tick_limit": 220, "step_budget": 220})  # fmt: skip
    return rows


def comparisons() -> pd.DataFrame:
    rows = _cell(0.1, 6, 2, set(), {(t, i) for t in range(6) for i in range(2)})  # q fails all 12: across tasks
    rows += _cell(0.2, 6, 10, set(), {(t, i) for t in (0, 1) for i in range(10)})  # q fails two whole tasks
    rows += _cell(0.3, 6, 1, set(), {(0, 0), (1, 0), (2, 0)})  # three discordant pairs: untestable
    rows += _cell(0.4, 6, 10, {(5, 8), (5, 9)}, {(t, 0) for t in range(6)})  # 6 against 2: tested, not called
    return paired_policies(pd.DataFrame(rows), n_boot=500)


def test_comparison_sentences_call_only_adjusted_hits_and_qualify_clustered_ones():
    table = comparisons().set_index("latency_s")
    assert list(table["testable"]) == [True, True, False, True]
    assert list(table["called"]) == [True, True, False, False]
    lines = prose.comparison_sentences(table.reset_index())
    assert len(lines) == 5
    undeclared, across, clustered, tested, untestable = lines
    assert undeclared.startswith("No primary comparison was declared") and "exploratory" in undeclared
    assert across.startswith("Exploratory: **p · sync** succeeds more often than **q · sync** (libero_spatial, 0.1 s")
    assert "12 succeed only with A and 0 only with B" in across and "(these tasks, other init states)" in across
    # 6 tasks all one way: the task-level test's floor 2/64 = 0.031 < 0.05, but Holm over two exploratory
    # comparisons doubles it; the sentence names the population each p-value speaks for.
    assert "task-level sign-flip p = 0.031" in across
    # Two whole tasks carry the difference: McNemar calls it, the task-level test does not, and the sentence says
    # the difference holds for these tasks only.
    assert "shown on these tasks, not for other tasks of the suite" in clustered
    assert tested.startswith("1 of the 4 paired comparisons shows no difference at a family-wise 5% level")
    assert "no difference detected, which is not the same as equal" in tested
    assert untestable.startswith("1 comparison has fewer than 6 discordant pairs")


def test_no_sentence_compares_separate_intervals():
    lines = prose.comparison_sentences(comparisons())
    assert not any("overlap" in line for line in lines)
    assert all("McNemar" in line or "discordant" in line or "family-wise" in line for line in lines[1:])


def test_the_notes_state_the_simulated_coverage_not_a_blanket_95_percent():
    """The notes said every interval "holds its 95% coverage at these sizes"; at 5-10 tasks the simulation measures
    less in some cells, and the notes quote its range (intervals.CLUSTER_COVERAGE, benchmarks/interval_coverage.py)."""
    from lq_ros.report.prose import NOTES

    intervals = NOTES[0]
    assert "holds its 95% coverage" not in intervals and "resampled" not in intervals
    assert "cover 91.5-99.7% (success), 92.3-100.0% (paired differences)" in intervals
    assert "benchmarks/interval_coverage.py" in intervals and "Tango" in intervals


def test_counts_of_one_are_singular():
    """'over 6 shared episodes of 1 task', never '1 tasks'; one comparison is 'the 1 paired comparison'."""
    one_task = paired_policies(pd.DataFrame(_cell(0.1, 1, 6, set(), {(0, i) for i in range(6)})), n_boot=200)
    _, called = prose.comparison_sentences(one_task)
    assert "over 6 shared episodes of 1 task;" in called and "and 1 task cannot give less than 1" in called
    alone = paired_policies(pd.DataFrame(_cell(0.4, 6, 10, {(5, 8), (5, 9)}, {(t, 0) for t in range(6)})), n_boot=200)
    assert prose.comparison_sentences(alone)[1].startswith("1 of the 1 paired comparison shows no difference")
    assert [counted(n, "pair") for n in (0, 1, 2)] == ["0 pairs", "1 pair", "2 pairs"]
    assert [counted(n, "succeeds", "succeed") for n in (1, 3)] == ["1 succeeds", "3 succeed"]
