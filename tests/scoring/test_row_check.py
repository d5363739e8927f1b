"""lq_ros.scoring.row_check: a row read back from a folder is pooled only if every field it is read by is sound."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from lq_ros.scoring.row_check import row_problem


def good_row(**changes) -> dict:
    row = {
        "episode": "scripted_sync_0.1s_t0_i0_s7", "policy": "scripted", "mode": "sync", "suite": "libero_spatial",
        "task": 0, "init": 0, "seed": 7, "latency_s": 0.1, "latency_dist": "constant", "status": "success",
        "success": True, "completion_time_s": 2.5, "completion_steps": 50, "jerk_mean": 1.2, "sparc": -1.5,
        "ldlj": -7.0, "energy_total_j": 300.0, "traj_length": 0.4, "versions": '{"mujoco": "2.3.7"}',
        "error_reason": None, "policy_args": "{}", "replan_steps": 5, "traj_efficiency": math.nan,
        "warnings": ["1 chunk rejected"], "null_reasons": {"sparc": "too short"},
    }  # fmt: skip
    row.update(changes)
    return row


def test_a_sound_row_passes_with_nulls_and_negative_smoothness():
    assert row_problem(good_row()) is None
    assert row_problem(good_row(status="failure", success=False, completion_time_s=None)) is None
    assert row_problem(good_row(status="error", success=None, error_reason="node died")) is None
    assert row_problem(good_row(status="unknown", success=None, init=None, seed=None)) is None


def test_a_table_row_of_numpy_scalars_is_read_as_its_values():
    frame = pd.DataFrame([good_row(), good_row(task=1, success=True)])
    assert frame["task"].dtype == np.int64 and frame["success"].dtype == bool
    assert [row_problem(r) for r in frame.to_dict("records")] == [None, None]


@pytest.mark.parametrize(
    ("row", "problem"),
    [
        ([good_row()], "the row is a list, not an object of fields"),
        (good_row(task="3"), "task '3' is not a whole number >= 0"),
        (good_row(task=-1), "task -1 is not a whole number >= 0"),
        (good_row(task=True), "task True is not a whole number >= 0"),
        (good_row(init=1.5), "init 1.5 is not a whole number >= 0"),
        (good_row(completion_time_s=-2.0), "completion_time_s -2.0 is negative"),
        (good_row(latency_s=-0.1), "latency_s -0.1 is negative"),
        (good_row(jerk_mean="1.2"), "jerk_mean '1.2' is not a number"),
        (good_row(energy_total_j=math.inf), "energy_total_j is inf"),
        (good_row(status="error", success=True), "status error with success True"),
        (good_row(status="success", success=None), "status success with success None"),
        (good_row(status="failure", success=True), "status failure with success True"),
        (good_row(status="done"), "status 'done'; expected one of success, failure, error, unknown"),
        (good_row(policy=["scripted"]), "policy ['scripted'] is not a name"),
        (good_row(replan_steps=[5]), "replan_steps is a list, not one value"),
        (good_row(replan_steps=math.inf), "replan_steps is inf"),
        (good_row(policy_args="chunk=8"), "policy_args is text that is not JSON"),
        (good_row(policy_args="[8]"), "policy_args is a list, not dict"),
        (good_row(versions=["2.3.7"]), "versions is a list, not dict"),
        (good_row(warnings='{"a": 1}'), "warnings is a dict, not list"),
    ],
)
def test_a_wrong_or_contradictory_field_is_named(row, problem):
    assert row_problem(row) == problem


def test_a_row_without_a_run_configuration_says_what_is_missing_and_why():
    row = {"episode": "b", "status": "error", "success": None, "error_reason": "b: no metadata.yaml\n(a plain MCAP)"}
    assert row_problem(row) == (
        "no run configuration (policy, mode, suite, task, latency_s missing) (b: no metadata.yaml (a plain MCAP))"
    )
    assert row_problem(good_row(latency_s=math.nan)) == "no run configuration (latency_s missing)"
