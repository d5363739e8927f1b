"""Small rclpy helpers shared by the node programs (imported only by nodes, never by the cores)."""

from __future__ import annotations

import importlib
import json
from collections.abc import Callable

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from lq_ros import messages as m
from lq_ros.config import RunConfig

#: Every LIBERO-LQ topic: nothing may be lost (reliable, deep history) and a subscriber that
#: matches a little late still receives what was published before (transient local).
LOSSLESS_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=10000,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)


def msg_class(msgtype: str):
    """rclpy message class of a ROS 2 type name such as 'sensor_msgs/msg/JointState'."""
    pkg, _, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


def publisher(node: Node, topic: m.Topic):
    return node.create_publisher(msg_class(topic.msgtype), topic.name, LOSSLESS_QOS)


def raw_subscription(node: Node, topic: m.Topic, callback: Callable[[object], None]):
    """Subscribe to serialized bytes and hand the callback the message decoded by the shared codec."""

    def on_raw(data: bytes) -> None:
        callback(m.deserialize(data, topic.msgtype))

    return node.create_subscription(msg_class(topic.msgtype), topic.name, on_raw, LOSSLESS_QOS, raw=True)


def declare_run_config(node: Node) -> RunConfig:
    """Declare every RunConfig field as a parameter (RunConfig's default, same name) and return the run.

    The launcher writes them once for all nodes (``/**`` in the params file), so no node repeats a
    default or builds its own protocol configuration.
    """
    defaults = RunConfig().ros_parameters()
    for name, default in defaults.items():
        node.declare_parameter(name, default)
    return RunConfig.from_ros_parameters({name: node.get_parameter(name).value for name in defaults})


def json_param(node: Node, name: str, default: dict | None = None) -> dict:
    node.declare_parameter(name, json.dumps(default or {}))
    return json.loads(node.get_parameter(name).value)


def run(node_factory: Callable[[], Node], stay_alive: bool = False) -> int:
    """ros2/examples-style main: spin until Ctrl-C or external shutdown; returns the exit code.

    Unless ``stay_alive``, it also returns once the node sets ``finished``.
    """
    code = 0
    try:
        rclpy.init()
        node = node_factory()
        try:
            while rclpy.ok() and (stay_alive or not getattr(node, "finished", False)):
                rclpy.spin_once(node, timeout_sec=0.1)
            code = getattr(node, "exit_code", 0)
        finally:
            close = getattr(node, "close", None)
            if close is not None:
                close()
            node.destroy_node()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        rclpy.try_shutdown()
    return code
