"""lq_ros/transport/ros/senders.py: the node a message's publisher belongs to, as the ROS graph names it."""

from __future__ import annotations

import pytest

from lq_ros.transport.ros.senders import UNNAMED, graph_node_name


def test_a_node_is_named_with_its_namespace():
    assert graph_node_name("lq_sim", "/") == "/lq_sim"
    assert graph_node_name("lq_sim", "/robot1") == "/robot1/lq_sim"


def test_an_endpoint_without_a_node_is_named_empty():
    assert graph_node_name("", "/") == ""


@pytest.mark.parametrize(("name", "namespace"), [(UNNAMED[0], UNNAMED[1]), (UNNAMED[0], "/"), ("lq_sim", UNNAMED[1])])
def test_rmws_placeholders_are_not_a_name_yet(name, namespace):
    """Until the publisher's participant has sent its node list, the graph lists the endpoint under placeholders:
    taken for a name, the sim's first events were ignored as a stranger's and the episode never ended."""
    assert graph_node_name(name, namespace) is None
