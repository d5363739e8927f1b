"""The RTC check both LeRobot 0.6 test files run on a flow-matching policy (SmolVLA, pi0, pi0.5)."""

from __future__ import annotations

import numpy as np

from lq_ros.core.merge import ActionPrefix
from lq_ros.core.types import TaskInfo
from tests.standin_servers import standin_observation


def check_rtc_follows_the_prefix(policy, task: TaskInfo, chunk: int, steps: int) -> None:
    """The executor's prefix and delay reach LeRobot's RTC processor: the guided chunk's first d rows follow the
    prefix; the unguided chunk from the same observation and noise does not; the hard schedule guides only the
    first d rows; a request without a prefix after RTC ran gets select_action's ``steps`` rows again. Leaves
    ``policy`` open (its owner closes it)."""
    obs = standin_observation(64, 3)
    prefix = np.tile([0.4, -0.3, 0.2, 0.1, -0.1, 0.3, -1.0], (8, 1))
    delay = 3
    policy.check_merge("rtc")
    policy.reset(task, 5)
    unguided = policy.infer(obs, prefix=ActionPrefix(np.zeros((0, 7)), delay=0))  # no rows: nothing guides
    policy.reset(task, 5)
    guided = policy.infer(obs, prefix=ActionPrefix(prefix, delay=delay))
    policy.reset(task, 5)
    hard = policy.infer(obs, prefix=ActionPrefix(prefix, delay=delay, schedule="hard"))
    policy.reset(task, 5)
    plain = policy.infer(obs)  # no prefix after RTC ran: select_action's queue, RTC off again
    assert unguided.shape == guided.shape == hard.shape == (chunk, 7)
    far = np.abs(unguided[:delay] - prefix[:delay]).mean()
    near = np.abs(guided[:delay] - prefix[:delay]).mean()
    assert near < 0.05 < 0.2 < far, (near, far)
    assert np.abs(hard[:delay] - prefix[:delay]).mean() < 0.05
    assert not np.allclose(guided[delay:], hard[delay:])  # exp guides rows d..7 too, hard only the first d
    np.testing.assert_allclose(plain, unguided[:steps], atol=1e-5)
