"""``lq_ros.run_episode``: one real in-process episode with a policy object (examples/my_policy.py), as a notebook
runs it; and its refusals, one line each, before anything runs."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

import lq_ros
from lq_ros.recording.episode_bag import read_run_metadata
from tests.transport.test_inprocess import ee_positions

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


@pytest.fixture()
def my_policy_module(monkeypatch):
    monkeypatch.syspath_prepend(str(EXAMPLES))
    import my_policy

    yield my_policy
    sys.modules.pop("my_policy", None)


@pytest.mark.sim
def test_an_episode_with_a_policy_object_runs_and_returns_its_scored_row(tmp_path, my_policy_module, capsys):
    policy = my_policy_module.MyPolicy(lift_m=0.05, chunk_size=6)
    row = lq_ros.run_episode(policy, task=0, init=3, mode="async", latency_s=0.1, max_steps=12, out=tmp_path)
    assert row["status"] == "failure" and row["success"] is False and row["completion_steps"] == 12  # budget spent
    bag = Path(row["bag"])
    assert bag.parent == tmp_path and "my_policy.MyPolicy_async_100ms" in bag.name
    assert "[info]" not in capsys.readouterr().out  # LIBERO's start-up lines went to stderr
    meta = read_run_metadata(bag)
    assert meta["config"]["policy"] == "my_policy:MyPolicy"
    assert meta["policy_params"] == {"lift_m": 0.05, "chunk_size": 6}
    z = ee_positions(bag)[:, 2]
    assert z[-1] - z[0] > 0.01  # the template lifts the hand, as it says
    # Again into the same folder: replaced (a notebook reruns a cell), with the same policy object.
    again = lq_ros.run_episode(policy, task=0, init=3, mode="async", latency_s=0.1, max_steps=12, out=tmp_path)
    assert again["bag"] == row["bag"] and again["completion_steps"] == 12
    with pytest.raises(ValueError, match="already exists"):
        lq_ros.run_episode(policy, task=0, init=3, mode="async", latency_s=0.1, max_steps=12, out=tmp_path,
                           overwrite=False)  # fmt: skip


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"suite": "libero_spatail"}, "did you mean 'libero_spatial'?"),
        ({"task": 10}, "libero_spatial has tasks 0..9"),
        ({"init": 50}, "init states 0..49"),
        ({"mode": "asynch"}, "mode: 'asynch' is not one of sync, async (did you mean 'async'?)"),
        ({"merge": "rtx"}, "merge: 'rtx' is not one of replace"),
        ({"replan_step": 5}, "unknown option(s) ['replan_step']; valid:"),
        ({"clock": "realtime"}, "need the ROS stack"),
        ({"latency_s": 0.075}, "not a whole number of 0.05 s"),
    ],
)
def test_bad_arguments_are_one_line_before_anything_runs(tmp_path, kwargs, message, my_policy_module):
    with pytest.raises(ValueError) as refused:
        lq_ros.run_episode(my_policy_module.MyPolicy(), out=tmp_path, **kwargs)
    assert message in str(refused.value) and "\n" not in str(refused.value)
    assert not any(tmp_path.iterdir())


def test_a_policy_by_name_takes_policy_args_and_a_policy_object_does_not(tmp_path, my_policy_module):
    with pytest.raises(ValueError, match="takes no argument 'chunk'"):
        lq_ros.run_episode("sine", policy_args={"chunk": 4}, out=tmp_path)
    with pytest.raises(ValueError, match="a policy object has its own arguments"):
        lq_ros.run_episode(my_policy_module.MyPolicy(), policy_args={"lift_m": 0.1}, out=tmp_path)
    with pytest.raises(ValueError, match="Policy object or a policy name, got int"):
        lq_ros.run_episode(3, out=tmp_path)


@pytest.mark.sim
def test_a_policy_by_name_runs_too(tmp_path):
    row = lq_ros.run_episode("sine", policy_args={"chunk_size": 4}, max_steps=6, out=tmp_path)
    assert row["status"] == "failure" and row["completion_steps"] == 6 and "_sine_sync_0ms_" in row["bag"]
