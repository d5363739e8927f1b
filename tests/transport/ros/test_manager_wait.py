"""nodes/manager_node.py's wait for a managed node's service: false while nobody serves it, true once a node does
(rclpy's own ``Client.wait_for_service`` looks every 0.25 s; the manager's looks every few milliseconds)."""

from __future__ import annotations

import subprocess
import sys

from lq_ros.transport.ros.stack import child_environment, reserved_domain

#: In a process of its own (a ROS domain of its own): the wait without a server, then with one.
PROBE = """
import rclpy
from lifecycle_msgs.srv import GetState
from lq_ros_nodes.manager_node import wait_for_service

rclpy.init()
caller = rclpy.create_node("lq_wait_probe_caller")
client = caller.create_client(GetState, "/lq_wait_probe/get_state")
print("without a server:", wait_for_service(client, 0.2))
server = rclpy.create_node("lq_wait_probe")
server.create_service(GetState, "/lq_wait_probe/get_state", lambda request, response: response)
print("with a server:", wait_for_service(client, 60.0))
rclpy.shutdown()
"""


def test_the_wait_is_false_without_a_server_and_true_once_one_serves(tmp_path):
    with reserved_domain() as domain:
        env = child_environment(domain.id, tmp_path / "ros_logs")
        proc = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.splitlines() == ["without a server: False", "with a server: True"], proc.stdout
