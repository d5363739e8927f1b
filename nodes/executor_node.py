"""Executor node: the sync hold / async buffer protocol at the control rate (lockstep on /clock).

Per tick (see lq_ros.core.executor_protocol): apply the chunk due now (waiting for it if needed), maybe request
an observation (once /clock says the sim is at that tick, and wait until the sim has captured it, so the
observation is of this tick), then publish the one command for the tick. Ticks that need neither are
commanded ahead, without waiting for the sim. The loop is lq_ros.core.executor_protocol.TickDriver (every
transport's); this node's handlers say when to wait. Malformed chunks are rejected with a CHUNK_REJECTED event
and never published as commands (lq_ros.transport.ros.endpoints.ExecutorLink, shared with the real-time executor).

Only the policy node's chunks are heard (lq_ros.transport.ros.senders), and of those only the chunk of the
outstanding request is held (one at most, the first to arrive): a chunk for any other request id is dropped
with a WARNING event. A callback that raises ends the episode as an error (an ERROR event); the node lives on.

Managed node: activate builds a fresh protocol core from the episode's parameters (mode, latency,
merge... may change between episodes); deactivate stops it.
"""

from __future__ import annotations

import sys
import time

from lq_ros.core.executor_protocol import ExecutorCore, TickDriver
from lq_ros.core.run_config import RunConfig
from lq_ros.core.suite_constants import sim_time_of_tick, tick_of_sim_time
from lq_ros.transport.ros.endpoints import ExecutorLink
from lq_ros.transport.ros.rclpy_helpers import EpisodeNode, run_managed
from lq_ros.wire import messages as m
from lq_ros.wire.node_names import NODE_NAMES

#: WARNING events one episode publishes at most (dropped chunks); later ones are only logged.
MAX_WARNING_EVENTS = 100


class ExecutorNode(EpisodeNode):
    def __init__(self) -> None:
        super().__init__(NODE_NAMES["executor"])
        # Wall-clock seconds to wait for a due chunk before ending the episode as an error.
        self.declare_parameter("chunk_timeout_s", 60.0)
        self.finished = False

    def activate(self, cfg: RunConfig) -> None:
        """A fresh protocol core and fresh endpoints per episode (the protocol may change between episodes)."""
        self.core = ExecutorCore(cfg.executor_config())
        self.chunk_timeout_s = self.get_parameter("chunk_timeout_s").value
        self.finished = False
        self.tick_limit = cfg.tick_limit  # no command is sent for a tick the episode cannot reach
        self.driver = TickDriver(self.core, self)  # driver.tick: the tick whose command comes next
        self.sim_tick = -1  # the last tick the sim announced on /clock (its state is of that tick)
        self.pending_request = None  # a Request of driver.tick, sent once the sim has reached that tick
        self.awaiting_observation: int | None = None  # request id whose observation is not yet captured
        self.outstanding: int | None = None  # the request id whose chunk is awaited (one inference in flight)
        self.chunk = None  # its ActionChunk, once arrived: the only chunk ever held
        self.warnings_published = 0
        self.waiting_since: float | None = None

        self.link = ExecutorLink(
            self.core, self.episode_publisher, self.get_logger(), stamp=lambda: (self.tick_ns, self.driver.tick)
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
    @property
    def tick_ns(self) -> int:
        """Sim time of ``driver.tick``, ns: the stamp of its command, request and events (as in process)."""
        return m.to_ns(sim_time_of_tick(self.driver.tick))

    def on_clock(self, msg) -> None:
        if self.finished:
            return
        self.sim_tick = tick_of_sim_time(m.stamp_ns(msg) / 1e9)
        self.send_pending_request()
        self.driver.drive()

    def on_chunk(self, msg) -> None:
        """Hold the chunk of the outstanding request; any other (a stale, duplicate or foreign request id) is
        dropped with a WARNING event, so nothing accumulates and no later chunk replaces the policy's."""
        rid = msg.request_id
        if self.finished:
            return
        if rid != self.outstanding:
            expected = f"request {self.outstanding}" if self.outstanding is not None else "no request"
            self.warn(f"dropped a chunk for request {rid}: {expected} is outstanding", {"request_id": rid})
            return
        if self.chunk is not None:
            self.warn(f"dropped a second chunk for request {rid}: the first to arrive is applied", {"request_id": rid})
            return
        self.chunk = msg
        self.driver.drive()

    def on_observation(self, msg) -> None:
        if msg.request_id == self.awaiting_observation:
            self.awaiting_observation = None
            self.driver.drive()

    def on_event(self, event) -> None:
        if event.kind in m.EventKind.TERMINAL:
            self.finished = True

    # -- the tick: lq_ros.core.executor_protocol.TickDriver's handlers -------------------------------------
    # A tick's command depends on a new observation only at a request tick and on a new chunk only at its due
    # tick; every other command (buffered actions, holds) is known already. So the commands run ahead of the sim
    # up to the next tick that needs either, and the sim steps through them without a round trip per tick. A
    # request is sent once the sim has reached its tick (/clock), and the tick's command only once the sim has
    # captured that observation, so the observation is of that tick, exactly as in process.
    def ready(self) -> bool:
        return (
            not self.finished
            and self.sim_tick >= 0
            and self.awaiting_observation is None
            and self.pending_request is None
            and self.driver.tick < self.tick_limit  # the episode ends there at the latest (the sim's budget rule)
        )

    def request(self, request) -> bool:
        self.pending_request = request
        self.send_pending_request()
        return False  # until the sim has captured the observation (on_observation drives on)

    def send_pending_request(self) -> None:
        """Send the pending request once the sim is at its tick (else on_clock calls again)."""
        request = self.pending_request
        if request is None or self.finished or self.sim_tick < self.driver.tick:
            return
        self.pending_request = None
        self.awaiting_observation = self.outstanding = request.request_id
        self.chunk = None
        self.link.request_observation(self.tick_ns, request)

    def chunk_due(self, due) -> bool:
        return self.deliver(due)  # False until it has arrived: on_chunk drives on

    def failed(self, reason: str) -> None:
        self.end_with_error(reason)

    def command(self, step) -> bool:
        self.link.command(self.tick_ns, step)
        return True

    def deliver(self, due) -> bool:
        """Apply the chunk due at this tick; False while it has not arrived."""
        msg = self.chunk if due.request_id == self.outstanding else None
        if msg is None:
            self.waiting_since = self.waiting_since or time.monotonic()
            return False
        self.chunk = self.outstanding = None
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

    def warn(self, reason: str, detail: dict | None = None) -> None:
        """A WARNING event (recorded in the bag), at most MAX_WARNING_EVENTS per episode; the rest are logged."""
        self.warnings_published += 1
        if self.warnings_published > MAX_WARNING_EVENTS:
            self.get_logger().warning(reason)
            return
        if self.warnings_published == MAX_WARNING_EVENTS:
            reason += f" (warning {MAX_WARNING_EVENTS}: further ones of this episode are logged only)"
        self.get_logger().warning(reason)
        self.link.event(m.EventKind.WARNING, reason, {"node": "executor", **(detail or {})})

    def on_callback_error(self, reason: str) -> None:
        """A callback failed: the tick state machine is in an unknown state, so the episode ends as an error
        (recorded), and the node lives on for the next one."""
        if self.active and not self.finished:
            self.end_with_error(f"executor: {reason}")


def main() -> None:
    sys.exit(run_managed(ExecutorNode))


if __name__ == "__main__":
    main()
