"""The validation's slow policy: the inner policy's chunk, after a controlled wall time."""

import time

import numpy as np
import pytest

from lq_ros.core.types import Observation, TaskInfo
from lq_ros.policies import make_policy

TASK = TaskInfo("libero_spatial", 0, "t", "do it", [], 220, 50)


def _obs() -> Observation:
    return Observation(0, 0.5, np.zeros(3), np.array([0, 0, 0, 1.0]), np.zeros(2), np.zeros(7), np.zeros(7))


def test_infer_takes_the_wall_time_and_returns_the_inner_chunk() -> None:
    slow = make_policy("lq_ros.policies.sleepy:SleepyPolicy", sleep_s=0.05, inner="sine")
    fast = make_policy("sine")
    slow.reset(TASK, 7)
    fast.reset(TASK, 7)
    started = time.perf_counter()
    chunk = slow.infer(_obs())
    assert time.perf_counter() - started >= 0.05
    assert np.array_equal(chunk, fast.infer(_obs()))
    assert slow.params() == {"sleep_s": 0.05, "inner": "sine"}
    assert make_policy("lq_ros.policies.sleepy:SleepyPolicy").needs_object_poses  # the scripted expert's


def test_negative_sleep_refused() -> None:
    with pytest.raises(ValueError, match="sleep_s"):
        make_policy("lq_ros.policies.sleepy:SleepyPolicy", sleep_s=-1)
