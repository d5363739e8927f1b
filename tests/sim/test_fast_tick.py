"""lq_ros/sim/fast_tick.py without a simulator: the LQ_FAST_TICK setting."""

from __future__ import annotations

import pytest

from lq_ros.sim import fast_tick


def test_the_fast_tick_is_on_unless_turned_off():
    assert fast_tick.enabled({}) is True
    assert fast_tick.enabled({"LQ_FAST_TICK": " On "}) is True
    assert fast_tick.enabled({"LQ_FAST_TICK": "off"}) is False


def test_another_value_is_refused_naming_the_valid_ones():
    with pytest.raises(ValueError, match=r"LQ_FAST_TICK='0': expected on or off"):
        fast_tick.enabled({"LQ_FAST_TICK": "0"})
