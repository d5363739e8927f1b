"""Test helper: follow a run's sim time from outside. ``python -m tests.clock_probe OUT`` (ROS_DOMAIN_ID set).

Writes the latest /clock stamp (ns) to OUT whenever one arrives, atomically, until stopped. It keeps only the newest
/clock sample (depth 1): with every sample queued (the recorder's lossless QoS) a probe on a loaded machine fell
seconds of sim time behind the run, and its readings bounded nothing.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from lq_ros.transport.ros.rclpy_helpers import msg_class
from lq_ros.wire import messages as m


def main() -> None:
    out = Path(sys.argv[1])
    tmp = out.with_name(out.name + ".tmp")
    latest = [0]

    def on_clock(data: bytes) -> None:
        t_ns = m.leading_stamp_ns(data)
        if t_ns > latest[0]:
            latest[0] = t_ns
            tmp.write_text(str(t_ns))
            os.replace(tmp, out)

    rclpy.init()
    node = rclpy.create_node("lq_test_clock_probe")
    newest_only = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.VOLATILE)  # fmt: skip
    node.create_subscription(msg_class(m.CLOCK.msgtype), m.CLOCK.name, on_clock, newest_only, raw=True)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
