"""Real-time executor: the sync hold / async buffer protocol (lq_ros/core/executor_protocol.py) on a wall-clock timer.

The lockstep executor (executor_node.py) waits for each tick's /clock and for every due chunk; this one waits
for nothing (lq_ros/transport/ros/wall_clock.py). Tick m starts at ``tick0 + m * 50 ms`` (``tick0_wall_ns``
from the STARTED event); the core's answer for the tick is worked out at once: an observation request goes out
without waiting for the observation, a due chunk that is already here is applied, and one that has not
arrived ``COMMAND_DEADLINE_S`` into the tick is declared late (``ExecutorCore.late``): the tick holds or
runs on the buffer, and the chunk applies at the first tick after it arrives, its stale rows (the ticks
that really passed) dropped. Ticks whose command went out more than one period after the tick's
scheduled start are overruns; the count and the worst lateness are published on /lq/realtime_stats
(std_msgs/String, JSON) when the episode ends. Requests, chunk handling, commands and events are the
lockstep executor's (lq_ros.transport.ros.endpoints.ExecutorLink).
"""

from __future__ import annotations

import json
import sys
import time

from rclpy.node import Node
from std_msgs.msg import String

from lq_ros.core.executor_protocol import ExecutorCore, TickDriver
from lq_ros.transport.ros.endpoints import ExecutorLink
from lq_ros.transport.ros.rclpy_helpers import LOSSLESS_QOS, declare_run_config, publisher, raw_subscription, run
from lq_ros.transport.ros.wall_clock import COMMAND_DEADLINE_S, OverrunCounter, TickClock
from lq_ros.wire import messages as m
from lq_ros.wire.node_names import NODE_NAMES

STATS_TOPIC = "/lq/realtime_stats"


class RealtimeExecutorNode(Node):
    def __init__(self) -> None:
        super().__init__(NODE_NAMES["executor"])
        self.core = ExecutorCore(declare_run_config(self).executor_config())
        # Wall-clock seconds to wait for a requested chunk before ending the episode as an error.
        self.declare_parameter("chunk_timeout_s", 60.0)
        self.chunk_timeout_s = self.get_parameter("chunk_timeout_s").value
        self.link = ExecutorLink(self.core, lambda topic: publisher(self, topic), self.get_logger(), self.event_stamp)
        self.stats_pub = self.create_publisher(String, STATS_TOPIC, LOSSLESS_QOS)
        raw_subscription(self, m.ACTION_CHUNK, self.on_chunk)
        raw_subscription(self, m.EPISODE_EVENTS, self.on_event)
        self.create_timer(0.002, self.poll)  # 2 ms: tick starts and deadlines are met to a few ms

        self.clock: TickClock | None = None
        self.finished = False
        self.driver = TickDriver(self.core, self)  # driver.tick: the tick being decided, or the next one
        self.deciding = False  # the wall clock has reached driver.tick and its command is not out yet
        self.tick_start_ns = 0
        self.waiting_due = False
        self.chunks: dict[int, object] = {}  # request id -> decoded ActionChunk
        self.requested_at: dict[int, float] = {}  # request id -> monotonic time of the request
        self.overruns = OverrunCounter()
        self.late_chunks = 0

    # -- callbacks --------------------------------------------------------------------------------------
    def on_event(self, event) -> None:
        if event.kind == m.EventKind.STARTED and self.clock is None:
            self.clock = TickClock(json.loads(event.detail_json)["tick0_wall_ns"])
        elif event.kind in m.EventKind.TERMINAL and not self.finished:
            self.finish()

    def on_chunk(self, msg) -> None:
        self.chunks[msg.request_id] = msg
        self.requested_at.pop(msg.request_id, None)
        if self.deciding and self.waiting_due:
            self.driver.drive()

    def poll(self) -> None:
        if self.finished or self.clock is None:
            return
        now = time.time_ns()
        tick = self.driver.tick
        if not self.deciding and now >= self.clock.tick_ns(tick):
            self.deciding, self.tick_start_ns = True, now
            self.driver.drive()
        elif self.deciding and self.waiting_due and now >= self.clock.tick_ns(tick) + COMMAND_DEADLINE_S * 1e9:
            self.core.late(tick)
            self.late_chunks += 1
            self.waiting_due = False
            self.driver.drive()
        stuck = [rid for rid, t in self.requested_at.items() if time.monotonic() - t > self.chunk_timeout_s]
        if stuck and not self.finished:
            self.end_with_error(f"no chunk from the policy within {self.chunk_timeout_s} s (wall clock)")

    # -- the tick: lq_ros.core.executor_protocol.TickDriver's handlers; nothing waits but a due chunk ----------
    def ready(self) -> bool:
        return not self.finished and self.deciding

    def request(self, request) -> bool:
        self.link.request_observation(self.clock.tick_ns(request.tick), request)  # its observation is not awaited
        self.requested_at[request.request_id] = time.monotonic()
        return True

    def chunk_due(self, due) -> bool:
        msg = self.chunks.pop(due.request_id, None)
        if msg is None:
            self.waiting_due = True  # until it arrives or the deadline passes (poll)
            return False
        self.waiting_due = False
        error = self.link.apply_chunk(due.request_id, msg)
        if error:
            self.end_with_error(error)
        return True

    def failed(self, reason: str) -> None:
        self.end_with_error(reason)

    def command(self, step) -> bool:
        scheduled = self.clock.tick_ns(step.tick)
        self.link.command(scheduled, step)
        self.overruns.record(step.tick, self.tick_start_ns - scheduled, time.time_ns() - self.tick_start_ns)
        self.deciding = False
        return False  # one tick per period: poll starts the next when the wall clock reaches it

    def event_stamp(self) -> tuple[int, int]:
        """(scheduled wall time, tick) of the tick being decided (or the next one) for an event."""
        tick = self.driver.tick
        return (self.clock.tick_ns(tick) if self.clock else 0), tick

    def end_with_error(self, reason: str) -> None:
        self.link.error(reason)
        self.finish()

    def finish(self) -> None:
        self.finished = True
        stats = dict(self.overruns.summary(), late_chunks=self.late_chunks, node="executor")
        self.stats_pub.publish(String(data=json.dumps(stats, sort_keys=True)))
        self.get_logger().info(f"real-time executor: {stats}")


def main() -> None:
    sys.exit(run(RealtimeExecutorNode, stay_alive=True))


if __name__ == "__main__":
    main()
