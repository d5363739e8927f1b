"""Executor node: the sync hold / async buffer protocol at the control rate (lockstep on /clock).

Each /clock message starts a control tick. Per tick (see lq_ros.core.executor_protocol): apply the chunk due now
(waiting for it if needed), maybe request an observation (and wait until the sim has captured it,
so the observation is of this tick), then publish the one command for the tick. Malformed chunks
are rejected with a CHUNK_REJECTED event and never published as commands (lq_ros.transport.ros.endpoints.ExecutorLink,
shared with the real-time executor).

Managed node: activate builds a fresh protocol core from the episode's parameters (mode, latency,
merge... may change between episodes); deactivate stops it.
"""

from __future__ import annotations

import sys
import time

from lq_ros.core.executor_protocol import ChunkDue, ExecutorCore, Failed, ObservationNeeded
from lq_ros.core.run_config import RunConfig
from lq_ros.core.suite_constants import tick_of_sim_time
from lq_ros.transport.ros.endpoints import ExecutorLink
from lq_ros.transport.ros.rclpy_helpers import EpisodeNode, run_managed
from lq_ros.wire import messages as m


class ExecutorNode(EpisodeNode):
    def __init__(self) -> None:
        super().__init__("lq_executor")
        # Wall-clock seconds to wait for a due chunk before ending the episode as an error.
        self.declare_parameter("chunk_timeout_s", 60.0)
        self.finished = False

    def activate(self, cfg: RunConfig) -> None:
        """A fresh protocol core and fresh endpoints per episode (the protocol may change between episodes)."""
        self.core = ExecutorCore(cfg.executor_config())
        self.chunk_timeout_s = self.get_parameter("chunk_timeout_s").value
        self.finished = False
        self.tick: int | None = None  # tick waiting for its command
        self.tick_ns = 0
        self.awaiting_observation: int | None = None  # request id whose observation is not yet captured
        self.chunks: dict[int, object] = {}  # request id -> decoded ActionChunk
        self.waiting_since: float | None = None

        self.link = ExecutorLink(
            self.core, self.episode_publisher, self.get_logger(), stamp=lambda: (self.tick_ns, self.tick or 0)
        )
        self.episode_subscription(m.CLOCK, self.on_clock)
        self.episode_subscription(m.ACTION_CHUNK, self.on_chunk)
        self.episode_subscription(m.OBSERVATION, self.on_observation)
        self.episode_subscription(m.EPISODE_EVENTS, self.on_event)
        self.episode_timer(1.0, self.check_chunk_timeout)

    def deactivate(self) -> None:
        self.finished = True
        self.waiting_since = None

    # -- callbacks --------------------------------------------------------------------------
    def on_clock(self, msg) -> None:
        if self.finished:
            return
        self.tick_ns = m.stamp_ns(msg)
        self.tick = tick_of_sim_time(self.tick_ns / 1e9)
        self.advance()

    def on_chunk(self, msg) -> None:
        self.chunks[msg.request_id] = msg
        self.advance()

    def on_observation(self, msg) -> None:
        if msg.request_id == self.awaiting_observation:
            self.awaiting_observation = None
            self.advance()

    def on_event(self, event) -> None:
        if event.kind in m.EventKind.TERMINAL:
            self.finished = True

    # -- the tick state machine -------------------------------------------------------------
    def advance(self) -> None:
        """Do as much of the current tick as the messages in hand allow (lq_ros.core.executor_protocol's loop)."""
        while not self.finished and self.tick is not None and self.awaiting_observation is None:
            step = self.core.advance(self.tick)
            if isinstance(step, ObservationNeeded):
                # Continue once the sim has captured the observation of this tick.
                self.awaiting_observation = step.request.request_id
                self.link.request_observation(self.tick_ns, step.request)
            elif isinstance(step, ChunkDue):
                if not self.deliver(step.request):
                    return  # not arrived yet: on_chunk calls advance again
            elif isinstance(step, Failed):
                self.end_with_error(step.reason)
            else:
                self.link.command(self.tick_ns, step)
                self.tick = None

    def deliver(self, due) -> bool:
        """Apply the chunk due at this tick; False while it has not arrived."""
        msg = self.chunks.pop(due.request_id, None)
        if msg is None:
            self.waiting_since = self.waiting_since or time.monotonic()
            return False
        self.waiting_since = None
        error = self.link.apply_chunk(due.request_id, msg)
        if error:
            self.end_with_error(error)
        return True

    def check_chunk_timeout(self) -> None:
        if self.waiting_since is not None and time.monotonic() - self.waiting_since > self.chunk_timeout_s:
            self.end_with_error(f"no chunk from the policy within {self.chunk_timeout_s} s (wall clock)")

    def end_with_error(self, reason: str) -> None:
        self.link.error(reason)
        self.finished = True
        self.waiting_since = None


def main() -> None:
    sys.exit(run_managed(ExecutorNode))


if __name__ == "__main__":
    main()
