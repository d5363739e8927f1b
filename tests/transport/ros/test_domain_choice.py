"""lq run's ROS domain: --domain-id, else an exported ROS_DOMAIN_ID, else a free one; bad values in one line."""

from __future__ import annotations

import pytest

from lq_ros.transport.ros.domain_choice import choose_domain


def test_the_flag_wins_then_the_exported_id_then_a_free_one():
    assert choose_domain(42, {"ROS_DOMAIN_ID": "153"}) == (42, "--domain-id")
    assert choose_domain(None, {"ROS_DOMAIN_ID": " 153 "}) == (153, "ROS_DOMAIN_ID")
    assert choose_domain(None, {"ROS_DOMAIN_ID": ""}) == (None, "a free one")
    assert choose_domain(None, {}) == (None, "a free one")


@pytest.mark.parametrize(
    "flag, environ, message",
    [
        (None, {"ROS_DOMAIN_ID": "abc"}, "ROS_DOMAIN_ID='abc' is not a ROS domain id: expected a whole number 0..232"),
        (None, {"ROS_DOMAIN_ID": "300"}, "ROS_DOMAIN_ID 300 is not a ROS domain id: expected 0..232"),
        (-1, {}, "--domain-id -1 is not a ROS domain id: expected 0..232"),
    ],
)
def test_a_bad_id_is_one_line(flag, environ, message):
    with pytest.raises(ValueError) as refused:
        choose_domain(flag, environ)
    assert str(refused.value).startswith(message) and "\n" not in str(refused.value)
