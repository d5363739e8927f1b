"""Every CSV the report writes has the columns its code declares: a small synthetic sweep store (no simulator) run
through lq report. The bad case: a string replace of ``_p`` that wrote ``jerk_p_adjusted90_diff_p_adjusted``."""

from __future__ import annotations

import json

import pandas as pd
import pytest
import yaml

from lq_ros.report import sweep_report as rp
from lq_ros.scoring import paired_tests as pt

TASKS, INITS = range(5), range(2)


def _row(policy: str, latency: float, task: int, init: int) -> dict:
    """q fails task 4 at 0.2 s; everything else succeeds, slower with latency (q slower than p)."""
    fails = policy == "q" and latency > 0 and task == 4
    steps = 100 + int(200 * latency) + 5 * task + init + (7 if policy == "q" else 0)
    return {
        "policy": policy, "mode": "sync", "latency_s": latency, "suite": "libero_spatial", "task": task, "init": init,
        "seed": 7, "status": "failure" if fails else "success", "success": not fails, "completion_steps": steps,
        "completion_time_s": steps * 0.05, "action_ticks": 100 + task, "step_budget": 220, "tick_limit": 220,
        "trajectory_rate_hz": 20.0, "energy_sampling": "substep", "jerk_mean": 10.0 + latency + task / 10,
        "jerk_p90": 20.0 + task, "ee_osc": 0.002, "ee_osc_detrended": 0.001, "traj_length": 1.0,
        "energy_mech_j": 50.0 + task, "energy_elec_j": 20.0 + init, "energy_overhead_j": 4.25 * steps,
        "energy_total_j": 70.0 + task + init + 4.25 * steps, "energy_per_step_j": (70.0 + 4.25 * steps) / steps,
        "n_degenerate": 0,
    }  # fmt: skip


@pytest.fixture(scope="module")
def report(tmp_path_factory) -> rp.Report:
    out = tmp_path_factory.mktemp("columns")
    (out / "results").mkdir()
    for policy in ("p", "q"):
        for latency in (0.0, 0.2):
            for task in TASKS:
                for init in INITS:
                    row = _row(policy, latency, task, init)
                    key = f"{policy}-{latency}-{task}-{init}"
                    record = {"key": key, "status": row["status"], "row": row, "attempts": [], "bag": None}
                    (out / "results" / f"{key}.json").write_text(json.dumps(record))
    spec = {"name": "columns", "policies": ["p", "q"], "analysis": {"primary": [{"a": "p", "b": "q"}],
                                                                    "equivalence_margin": 0.2}}  # fmt: skip
    (out / "sweep.yaml").write_text(yaml.safe_dump(spec))
    return rp.build_report(out, n_boot=200)


def _headers(report: rp.Report) -> dict[str, list[str]]:
    return {name: list(pd.read_csv(path, nrows=0).columns) for name, path in report.files.items()
            if name.endswith(".csv")}  # fmt: skip


def test_every_csv_header_is_declared_and_unmangled(report):
    headers = _headers(report)
    assert {"paired_vs_zero_latency.csv", "paired_policies.csv"} <= set(headers)
    for name, columns in headers.items():
        assert len(columns) == len(set(columns)), f"{name}: a column twice"
        mangled = [c for c in columns if "p_adjusted" in c and not c.endswith("p_adjusted")]
        assert not mangled, f"{name}: {mangled}"
    assert headers["paired_policies.csv"] == list(pt.COMPARISON_COLUMNS)
    metrics = (*pt.PAIRED_METRICS, pt.RMST_METRIC)
    declared = {f"{m}_diff_{s}" for m in metrics for s in pt.DIFF_SUFFIXES}
    declared |= {f"{m}_{side}_mean" for m in metrics for side in ("zero", "cell")}
    per_metric = [c for c in headers["paired_vs_zero_latency.csv"] if any(c.startswith(m) for m in metrics)]
    assert per_metric and set(per_metric) <= declared, sorted(set(per_metric) - declared)
    adjusted = {c for c in per_metric if c.endswith("_p_adjusted")}
    assert adjusted == {f"{m}_diff_p_adjusted" for m in pt.TESTED_METRICS}  # totals untested
    assert {"jerk_p90_diff_p_adjusted", "energy_actuator_j_diff_p_adjusted", "time_to_success_s_diff_p_adjusted"} <= (
        adjusted
    )


def test_the_declared_primary_is_the_holm_family_and_the_report_says_which_population(report):
    table = pd.read_csv(report.files["paired_policies.csv"])
    primary = table[table["primary"]]
    assert len(primary) == 2 and set(primary["latency_s"]) == {0.0, 0.2}  # p against q at each latency
    assert set(table.loc[~table["primary"], "family"]) <= {"exploratory"}
    assert table["cluster_p"].notna().all() and (table["equivalence_margin"] == 0.2).all()
    text = report.files["report.md"].read_text()
    assert "declared primary" in text and "other tasks of the suite" in text
    assert "energy net of the constant 85 W overhead" in text
    # Five tasks: a change against 0 s called over pairs cannot be carried to other tasks (2/2^5 = 0.0625).
    assert "time to success (s) +2.00 (n=10, all equal) (task-level p 0.062: these tasks only)" in text
