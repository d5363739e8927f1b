"""lq_ros/sim/fast_tick.py without a simulator: the LQ_FAST_TICK setting, the consecutive-index slice."""

from __future__ import annotations

import numpy as np
import pytest

from lq_ros.sim import fast_tick


def test_the_fast_tick_is_on_unless_turned_off():
    assert fast_tick.enabled({}) is True
    assert fast_tick.enabled({"LQ_FAST_TICK": " On "}) is True
    assert fast_tick.enabled({"LQ_FAST_TICK": "off"}) is False


def test_another_value_is_refused_naming_the_valid_ones():
    with pytest.raises(ValueError, match=r"LQ_FAST_TICK='0': expected on or off"):
        fast_tick.enabled({"LQ_FAST_TICK": "0"})


def test_a_consecutive_index_becomes_a_slice_selecting_the_same_elements():
    values = np.arange(20.0) * 1.5
    index = np.array([9, 10, 11, 12, 13, 14, 15])
    chosen = fast_tick.consecutive_slice(index)
    assert chosen == slice(9, 16)
    np.testing.assert_array_equal(values[chosen], values[index])
    assert np.shares_memory(values[chosen], values)  # a view: read at each substep without indexing


def test_a_gap_a_repeat_a_reversal_or_nothing_gives_no_slice():
    for index in ([1, 2, 4], [3, 3, 4], [5, 4, 3], []):
        assert fast_tick.consecutive_slice(np.array(index, dtype=np.intp)) is None
