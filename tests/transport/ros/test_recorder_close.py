"""The recorder (nodes/metrics_node.py) closes the bag on the nodes' announced message counts, and says so when
they do not add up: a real metrics node process, driven through its lifecycle services, fed by publishers that
take the stack nodes' names from this test process."""

from __future__ import annotations

import contextlib
import json
import subprocess
import sys
import time

import numpy as np
import pytest

from lq_ros.core.executor_protocol import Command, Source
from lq_ros.recording.bag_compare import bag_messages
from lq_ros.transport.processes import die_with_parent
from lq_ros.transport.ros.stack import NODE_MODULE, child_environment, reserved_domain
from lq_ros.wire import messages as m
from tests.transport.ros.test_lifecycle import LifecycleClient

pytestmark = [pytest.mark.slow, pytest.mark.ros]


class StandInNodes:
    """Publishers of episode events, commands and message counts, in nodes named as the stack's nodes."""

    def __init__(self, domain_id: int) -> None:
        import rclpy
        import rclpy.executors
        from std_msgs.msg import String

        from lq_ros.transport.ros.rclpy_helpers import LOSSLESS_QOS, msg_class

        self.rclpy, self.String = rclpy, String
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.nodes = {
            name: rclpy.create_node(name, context=self.context) for name in ("lq_sim", "lq_executor", "lq_policy")
        }
        self.events = self.nodes["lq_sim"].create_publisher(
            msg_class(m.EPISODE_EVENTS.msgtype), m.EPISODE_EVENTS.name, LOSSLESS_QOS
        )
        self.commands = self.nodes["lq_executor"].create_publisher(
            msg_class(m.COMMAND.msgtype), m.COMMAND.name, LOSSLESS_QOS
        )
        self.counts = {
            name: node.create_publisher(String, m.PUBLISHED_COUNTS.name, LOSSLESS_QOS)
            for name, node in self.nodes.items()
        }
        self.executor = rclpy.executors.SingleThreadedExecutor(context=self.context)
        for node in self.nodes.values():
            self.executor.add_node(node)

    def spin(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.02)

    def wait_matched(self) -> None:
        end = time.monotonic() + 30
        while (
            self.events.get_subscription_count() == 0
            or self.commands.get_subscription_count() == 0
            or any(p.get_subscription_count() == 0 for p in self.counts.values())
        ):
            assert time.monotonic() < end, "the recorder never subscribed"
            self.spin(0.05)
        self.spin(0.5)  # (the recorder learns the senders' node names from the graph)

    def announce(self, node: str, counts: dict[str, int]) -> None:
        self.counts[node].publish(self.String(data=json.dumps({"node": node, "counts": counts})))

    def close(self) -> None:
        self.executor.shutdown()
        for node in self.nodes.values():
            node.destroy_node()
        self.rclpy.try_shutdown(context=self.context)


@contextlib.contextmanager
def recorder_process(tmp_path, *parameters: str):
    """A metrics node process (``-p name:=value`` for each of ``parameters``), its lifecycle client and the stand-in
    nodes, on a domain of their own; shut down (or killed) and closed afterwards."""
    with reserved_domain() as domain:
        env = child_environment(domain.id, tmp_path / "ros_logs")
        args = [a for p in parameters for a in ("-p", p)]
        with open(tmp_path / "metrics.log", "wb") as log:
            proc = subprocess.Popen(
                [sys.executable, "-m", NODE_MODULE.format("metrics"), "--ros-args", *args], env=env, stdout=log,
                stderr=subprocess.STDOUT, preexec_fn=die_with_parent, pass_fds=(domain.lock_fd,),
            )  # fmt: skip
        client = LifecycleClient(domain.id, "lq_metrics")
        stand_ins = StandInNodes(domain.id)
        try:
            yield proc, client, stand_ins
            assert client.set_state("shutdown") and proc.wait(timeout=30) == 0
        finally:
            stand_ins.close()
            client.close()
            if proc.poll() is None:
                proc.kill()
                proc.wait()


def run_recorder(tmp_path, announce) -> tuple[list[tuple[int, bytes]], str, float]:
    """Activate a recorder, publish STARTED and SUCCESS events from "lq_sim", then ``announce(stand_ins)``; wait
    until the recorder deactivates itself. Returns the bag's events, its log and the wall seconds from SUCCESS to
    inactive."""
    bag = tmp_path / "bag"
    with recorder_process(tmp_path, f"bag_path:={bag}", "max_steps:=10") as (_, client, stand_ins):
        assert client.set_state("configure") and client.set_state("activate")
        stand_ins.wait_matched()
        stand_ins.events.publish(m.event_msg(0, m.EventKind.STARTED, 0, "", {"versions": {}}))
        stand_ins.events.publish(m.event_msg(0, m.EventKind.SUCCESS, 0, ""))
        sent = time.monotonic()
        announce(stand_ins)
        while client.state() == "active":
            assert time.monotonic() - sent < 30, "the recorder never closed the bag"
            stand_ins.spin(0.05)
        closed_after_s = time.monotonic() - sent
    return bag_messages(bag)[m.EPISODE_EVENTS.name], (tmp_path / "metrics.log").read_text(), closed_after_s


def warnings(events: list[tuple[int, bytes]]) -> list[str]:
    decoded = [m.deserialize(data, m.EPISODE_EVENTS.msgtype) for _, data in events]
    return [e.reason for e in decoded if e.kind == m.EventKind.WARNING]


def test_the_bag_closes_as_soon_as_every_count_adds_up(tmp_path):
    def announce(stand_ins: StandInNodes) -> None:
        stand_ins.announce("lq_sim", {m.EPISODE_EVENTS.name: 2})
        stand_ins.announce("lq_executor", {})
        stand_ins.announce("lq_policy", {})

    events, log, _ = run_recorder(tmp_path, announce)
    assert warnings(events) == [] and "every message of the episode arrived" in log  # (not the fallback)


def test_the_last_message_to_arrive_may_be_a_command_sent_ahead_of_the_end(tmp_path):
    """A command the executor sent ahead for a tick the episode never reached: not recorded (never applied), but
    counted, and the bag closes on its arrival."""

    def announce(stand_ins: StandInNodes) -> None:
        stand_ins.announce("lq_sim", {m.EPISODE_EVENTS.name: 2})
        stand_ins.announce("lq_executor", {m.COMMAND.name: 1})
        stand_ins.announce("lq_policy", {})
        stand_ins.spin(0.5)  # (the counts are in; the command is not)
        stand_ins.commands.publish(m.command_msg(m.to_ns(0.05), Command(3, np.zeros(7), Source.CHUNK)))

    events, log, _ = run_recorder(tmp_path, announce)
    assert warnings(events) == [] and "every message of the episode arrived" in log


def test_a_missing_count_and_a_lost_message_are_named_in_the_bag(tmp_path):
    def announce(stand_ins: StandInNodes) -> None:
        stand_ins.announce("lq_sim", {m.EPISODE_EVENTS.name: 3})  # one more than the recorder will receive
        stand_ins.announce("lq_executor", {})  # and nothing from lq_policy, as if it had died

    events, log, closed_after_s = run_recorder(tmp_path, announce)
    (warning,) = warnings(events)
    assert "without lq_policy's message counts; /lq/episode_events: 2 of 3 messages" in warning, warning
    assert "every message of the episode arrived" not in log
    assert closed_after_s >= 2.0  # it waited for the counts before giving up on them


def test_the_recorder_says_when_it_receives_a_robot_topic(tmp_path):
    """The bridge starts a robot episode on /lq/recorder_hears, not on the recorder's subscription: the graph lists
    a subscription before the robot's publisher has matched it, and a volatile robot topic loses what it sent
    before (a CI run once recorded the EE pose from 0.2 s into the episode)."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState
    from std_msgs.msg import String

    from lq_ros.transport.ros.rclpy_helpers import LOSSLESS_QOS

    topic = "/test_robot/joint_states"
    robot_topics = json.dumps([{"name": topic, "type": "sensor_msgs/msg/JointState"}])
    parameters = (f"bag_path:={tmp_path}/b", "clock:=realtime", f"robot_topics_json:='{robot_topics}'")
    with recorder_process(tmp_path, *parameters) as (_, client, stand_ins):
        heard: list[list[str]] = []
        node = stand_ins.nodes["lq_sim"]

        def on_heard(msg) -> None:
            heard.append(json.loads(msg.data)["topics"])

        node.create_subscription(String, m.RECORDER_HEARS.name, on_heard, LOSSLESS_QOS)
        volatile = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
        joints = node.create_publisher(JointState, topic, volatile)
        assert client.set_state("configure") and client.set_state("activate")
        end = time.monotonic() + 30
        while joints.get_subscription_count() == 0:
            assert time.monotonic() < end, "the recorder never subscribed"
            stand_ins.spin(0.05)
        stand_ins.spin(1.0)
        assert heard == []  # subscribed, but nothing received yet
        msg = JointState()
        msg.header.stamp.sec = 1
        for _ in range(3):
            joints.publish(msg)
        end = time.monotonic() + 30
        while not heard:
            assert time.monotonic() < end, "the recorder never said it receives the robot's topic"
            stand_ins.spin(0.05)
        stand_ins.spin(0.5)
        assert heard == [[topic]]  # once, when the first message arrived
