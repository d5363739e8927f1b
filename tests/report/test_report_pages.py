"""report.md opens with a summary that reads in one screen, whatever the sweep's size."""

from __future__ import annotations

import pandas as pd

from lq_ros.report import sweep_report as rp


def test_the_summary_is_at_most_sixty_lines_and_points_to_the_rest():
    summary = pd.DataFrame({"policy": ["p"] * 200, "mode": ["sync"] * 200, "latency": [f"{i}" for i in range(200)],
                            "n": [10] * 200, "success %": ["50 [30, 70]"] * 200})  # fmt: skip
    comparisons = pd.DataFrame({"called": [True, False, False]})
    lines = rp.summary_markdown(summary, None, comparisons, ["at 0.4 s the extra failures are mostly missed grasps."])
    assert lines[0] == "## Summary" and len(lines) <= rp.SUMMARY_LINES
    text = "\n".join(lines)
    assert f"(the first {rp.SUMMARY_ROWS} of 200 cells; all: aggregates_pooled.csv and report.html)" in text
    assert "Paired comparisons: 1 of 3 called a difference" in text and "missed grasps" in text
    assert "| n " in text or "|   n |" in text  # each row says its n
