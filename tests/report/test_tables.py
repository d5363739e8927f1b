"""lq_ros.report.tables: the comparison table shows the Holm family as it is; the paired table stars only the changes
whose adjusted p is below 0.05."""

from __future__ import annotations

import pandas as pd

from lq_ros.report import tables
from tests.report.test_prose import comparisons


def test_comparison_table_shows_no_adjusted_p_outside_the_holm_family():
    table = tables.comparison_table(comparisons()).set_index("latency")
    assert table.loc["0.3 s (N=6)", "Holm p"] == "– (too few discordant)"
    assert table.loc["0.1 s (N=2)", "A only / B only"] == "12 / 0"
    assert table.loc["0.1 s (N=2)", "success A − B (points)"].startswith("+100 [")
    assert float(table.loc["0.4 s (N=8)", "Holm p"]) > 0.05


def test_paired_table_stars_adjusted_hits_only():
    base = {"policy": "p", "mode": "sync", "latency_label": "0.2 s (N=4)", "zero_n_success": 9, "zero_n": 10,
            "cell_n_success": 8, "n_failure": 2, "n_pairs": 8, "n_pairs_all": 10, "time_to_success_s_diff_n": 8,
            "time_to_success_s_diff_mean": 1.0, "time_to_success_s_diff_ci_lo": 0.5,
            "time_to_success_s_diff_ci_hi": 1.5, "time_to_success_s_diff_p": 0.001}  # fmt: skip
    rows = pd.DataFrame([base | {"time_to_success_s_diff_p_adjusted": 0.004},
                         base | {"policy": "q", "time_to_success_s_diff_p_adjusted": 0.07}])  # fmt: skip
    table = tables.paired_table(rows).set_index("policy")
    assert table.loc["p", "Δ time to success s (all pairs)"] == "+1.00 [+0.50, +1.50] *"
    assert table.loc["q", "Δ time to success s (all pairs)"] == "+1.00 [+0.50, +1.50]"
    assert table.loc["p", "pairs (all / both succeed)"] == "10 / 8"
