"""Executor node: the sync hold / async buffer protocol at the control rate, on either clock.

Per tick (see lq_ros.core.executor_protocol): apply the chunk due now, maybe request an observation, then
publish the one command for the tick. The loop is lq_ros.core.executor_protocol.TickDriver (every transport's);
what waiting means is the run's ``clock`` (read at every activation), one handler class each:

- ``lockstep`` (:class:`LockstepTicks`): a due chunk is waited for; an observation is requested as soon as the
  tick that needs it is known (the sim answers on reaching that tick), and the tick's command waits until the sim
  has queued the request (its echo) or captured the observation, so the observation is of this tick. Every other
  command is sent ahead, without waiting for the sim.
- ``realtime`` (:class:`WallClockTicks`, lq_ros/transport/ros/wall_clock.py): tick m starts at ``tick0 + m *
  50 ms`` (``tick0_wall_ns`` from the STARTED event) and waits for nothing: an observation request goes out
  without waiting for the observation, a due chunk that is already here is applied, and one that has not arrived
  ``COMMAND_DEADLINE_S`` into the tick is declared late (``ExecutorCore.late``): the tick holds or runs on the
  buffer, and the chunk applies at the first tick after it arrives, its stale rows dropped. Ticks whose command
  went out more than one period after the tick's scheduled start are overruns; the counts go out on
  /lq/realtime_stats when the episode ends.

Anchored relative actions (lq_ros/core/relative_actions.py) need the state of the tick each row executes: lockstep asks
the sim for it (/lq/anchor_state_request, answered on /lq/anchor_state on reaching the tick) and sends the command
once it has come; the wall clock has no such state, and such an episode ends as an error (the core's NO_STATE).

Malformed chunks are rejected with a CHUNK_REJECTED event and never published as commands
(lq_ros.transport.ros.endpoints.ExecutorLink). Only the policy node's chunks are heard (lq_ros.transport.ros.senders).
Lockstep holds only the chunk of the outstanding request (one at most, the first to arrive): a chunk for any
other request id is dropped with a WARNING event. A callback that raises ends the episode as an error (an
ERROR event); the node lives on.

Managed node: activate builds a fresh protocol core from the episode's parameters (mode, latency, merge,
clock... may change between episodes); deactivate stops it.
"""

from __future__ import annotations

import json
import time

from std_msgs.msg import String

from lq_ros.core.control import ControlStart
from lq_ros.core.executor_protocol import ExecutorCore, TickDriver
from lq_ros.core.relative_actions import anchor_state
from lq_ros.core.run_config import RunConfig
from lq_ros.core.suite_constants import sim_time_of_tick
from lq_ros.transport.ros.endpoints import ExecutorLink
from lq_ros.transport.ros.rclpy_helpers import EpisodeNode, run_managed
from lq_ros.transport.ros.wall_clock import COMMAND_DEADLINE_S, OverrunCounter, TickClock, stats_json
from lq_ros.wire import messages as m
from lq_ros.wire.node_names import NODE_NAMES

#: WARNING events one episode publishes at most (dropped chunks); later ones are only logged.
MAX_WARNING_EVENTS = 100


class ExecutorNode(EpisodeNode):
    def __init__(self) -> None:
        super().__init__(NODE_NAMES["executor"])
        # Wall-clock seconds to wait for a requested chunk before ending the episode as an error.
        self.declare_parameter("chunk_timeout_s", 60.0)
        self.finished = False

    def activate(self, cfg: RunConfig) -> None:
        """A fresh protocol core, endpoints and clock per episode (the protocol may change between episodes)."""
        self.core = ExecutorCore(cfg.executor_config())
        self.chunk_timeout_s = self.get_parameter("chunk_timeout_s").value
        self.finished = False
        self.control_started = False
        self.warnings_published = 0
        self.ticks = (WallClockTicks if cfg.clock == "realtime" else LockstepTicks)(self, cfg)
        self.driver = TickDriver(self.core, self.ticks)  # driver.tick: the tick whose command comes next
        self.link = ExecutorLink(self.core, self.episode_publisher, self.get_logger(), stamp=self.ticks.stamp)
        self.ticks.subscribe()

    def deactivate(self) -> None:
        self.finished = True
        self.ticks.stop()

    def on_event(self, event) -> None:
        if event.kind == m.EventKind.STARTED and not (self.finished or self.control_started):
            self.control_started = True
            # The episode's control mode and start command come from the sim (lq_ros.core.control), before tick 0.
            try:
                self.core.start(ControlStart.from_detail(json.loads(event.detail_json)))
            except (ValueError, RuntimeError) as exc:
                return self.end_with_error(f"cannot start the episode: {exc}")
        self.ticks.on_event(event)
        if event.kind in m.EventKind.TERMINAL and not self.finished:
            self.finish()

    def end_with_error(self, reason: str) -> None:
        self.link.error(reason)
        self.finish()

    def finish(self) -> None:
        self.finished = True
        self.ticks.stop()
        self.seal_episode()

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


class _Ticks:
    """What both clocks' handlers share: applying an arrived chunk, and ending on a failure."""

    node: ExecutorNode

    def apply(self, request_id: int, msg) -> bool:
        """Apply the chunk of ``request_id`` (a malformed one is rejected; a policy error ends the episode)."""
        error = self.node.link.apply_chunk(request_id, msg)
        if error:
            self.node.end_with_error(error)
        return True

    def failed(self, reason: str) -> None:
        self.node.end_with_error(reason)


class LockstepTicks(_Ticks):
    """TickDriver's handlers on sim time: a due chunk and a requested observation are waited for, nothing else
    (lq_ros.core.executor_protocol.TickHandlers). The sim's STARTED event starts the ticks.

    A tick's command depends on a new observation only at a request tick and on a new chunk only at its due
    tick; every other command (buffered actions, holds) is known already. So the commands run ahead of the sim
    up to the next tick that needs either, and the sim steps through them without a round trip per tick. A
    request goes out as soon as the driver reaches its tick, and the tick's command once the sim has either
    queued the request (it echoes it on /lq/observation_request_queued and answers it on reaching the tick,
    before stepping it) or captured the observation: the observation is of that tick, exactly as in process,
    whatever order DDS delivers the two topics in. The echo usually comes back while the sim still steps the
    ticks before, so a request tick waits for nothing. The policy publishes a chunk as soon as it is inferred
    (lq_ros.transport.ros.endpoints.ChunkServer) and it is held here until its due tick.
    """

    def __init__(self, node: ExecutorNode, cfg: RunConfig) -> None:
        self.node = node
        self.tick_limit = cfg.tick_limit  # no command is sent for a tick the episode cannot reach
        self.started = False  # the sim has started the episode (STARTED)
        self.awaiting_observation: int | None = None  # request id the sim has neither queued nor answered yet
        self.outstanding: int | None = None  # the request id whose chunk is awaited (one inference in flight)
        self.chunk = None  # its ActionChunk, once arrived: the only chunk ever held
        self.waiting_since: float | None = None
        self.awaiting_state: int | None = None  # the tick whose anchor state was asked of the sim
        self.state_asked_at = 0.0  # monotonic time of the last ask (asked again each second until it comes)
        self.state_since = 0.0  # monotonic time of the first ask for that tick

    def subscribe(self) -> None:
        node = self.node
        node.episode_subscription(m.ACTION_CHUNK, self.on_chunk)
        node.episode_subscription(m.OBSERVATION, self.on_observation)
        node.episode_subscription(m.OBSERVATION_REQUEST_QUEUED, self.on_request_queued)
        node.episode_subscription(m.ANCHOR_STATE, self.on_anchor_state)
        self.anchor_request_pub = node.episode_publisher(m.ANCHOR_STATE_REQUEST)
        node.episode_subscription(m.EPISODE_EVENTS, node.on_event)
        node.episode_timer(1.0, self.check_chunk_timeout)

    @property
    def tick_ns(self) -> int:
        """Sim time of ``driver.tick``, ns: the stamp of its command, request and events (as in process)."""
        return m.to_ns(sim_time_of_tick(self.node.driver.tick))

    def stamp(self) -> tuple[int, int]:
        return self.tick_ns, self.node.driver.tick

    def stop(self) -> None:
        self.waiting_since = None

    # -- callbacks --------------------------------------------------------------------------------------
    def on_chunk(self, msg) -> None:
        """Hold the chunk of the outstanding request; any other (a stale, duplicate or foreign request id) is
        dropped with a WARNING event, so nothing accumulates and no later chunk replaces the policy's."""
        rid = msg.request_id
        if self.node.finished:
            return
        if rid != self.outstanding:
            expected = f"request {self.outstanding}" if self.outstanding is not None else "no request"
            self.node.warn(f"dropped a chunk for request {rid}: {expected} is outstanding", {"request_id": rid})
            return
        if self.chunk is not None:
            self.node.warn(
                f"dropped a second chunk for request {rid}: the first to arrive is applied", {"request_id": rid}
            )
            return
        self.chunk = msg
        self.node.driver.drive()

    def on_observation(self, msg) -> None:
        if msg.request_id == self.awaiting_observation:
            self.awaiting_observation = None
            self.node.driver.drive()

    def on_request_queued(self, msg) -> None:
        """The sim holds the awaited request: it will capture the observation before it steps that tick."""
        if msg.request_id == self.awaiting_observation and msg.tick == self.node.driver.tick:
            self.awaiting_observation = None
            self.node.driver.drive()

    def on_anchor_state(self, msg) -> None:
        """The sim's observation of the tick whose command resolves anchored relative actions."""
        if msg.tick != self.awaiting_state or self.node.finished:
            return  # (an answer to a repeated ask)
        self.awaiting_state = None
        state = anchor_state(msg.eef_pos, msg.eef_quat, msg.gripper_qpos)
        self.node.core.observe_state(msg.tick, state)
        self.node.driver.drive()

    def on_event(self, event) -> None:
        if event.kind == m.EventKind.STARTED and not self.node.finished:
            self.started = True
            self.node.driver.drive()

    # -- TickHandlers -------------------------------------------------------------------------------------
    def ready(self) -> bool:
        return (
            not self.node.finished
            and self.started
            and self.awaiting_observation is None
            and self.awaiting_state is None
            and self.node.driver.tick < self.tick_limit  # the episode ends there at the latest (the sim's budget rule)
        )

    def request(self, request) -> bool:
        self.awaiting_observation = self.outstanding = request.request_id
        self.chunk = None
        self.node.link.request_observation(self.tick_ns, request)
        return False  # until the sim has queued the request or captured the observation (their callbacks drive on)

    def chunk_due(self, due) -> bool:
        """Apply the chunk due at this tick; False while it has not arrived (on_chunk drives on)."""
        msg = self.chunk if due.request_id == self.outstanding else None
        if msg is None:
            self.waiting_since = self.waiting_since or time.monotonic()
            return False
        self.chunk = self.outstanding = None
        self.waiting_since = None
        return self.apply(due.request_id, msg)

    def state_needed(self, tick: int) -> bool:
        """This tick's command resolves anchored relative actions: ask the sim for the tick's state (it answers on
        reaching the tick, before stepping it); False until it comes (on_anchor_state drives on)."""
        self.awaiting_state = tick
        self.state_since = self.state_asked_at = time.monotonic()
        self.anchor_request_pub.publish(m.anchor_state_request_msg(self.tick_ns, tick))
        return False

    def command(self, step) -> bool:
        self.node.link.command(self.tick_ns, step)
        return True

    def check_chunk_timeout(self) -> None:
        timeout_s = self.node.chunk_timeout_s
        if self.waiting_since is not None and time.monotonic() - self.waiting_since > timeout_s:
            self.node.end_with_error(f"no chunk from the policy within {timeout_s} s (wall clock)")
        tick, now = self.awaiting_state, time.monotonic()
        if tick is not None and not self.node.finished:
            if now - self.state_since > timeout_s:
                self.node.end_with_error(f"no state of tick {tick} from the sim within {timeout_s} s (wall clock)")
            elif now - self.state_asked_at >= 1.0:  # a request sent before the sim's subscription matched is lost
                self.state_asked_at = now
                self.anchor_request_pub.publish(m.anchor_state_request_msg(self.tick_ns, tick))


class WallClockTicks(_Ticks):
    """TickDriver's handlers on the wall clock: nothing waits but a due chunk, and that only until
    COMMAND_DEADLINE_S into its tick (lq_ros/transport/ros/wall_clock.py)."""

    def __init__(self, node: ExecutorNode, cfg: RunConfig) -> None:
        self.node = node
        self.clock: TickClock | None = None
        self.deciding = False  # the wall clock has reached driver.tick and its command is not out yet
        self.tick_start_ns = 0
        self.waiting_due = False
        self.chunks: dict[int, object] = {}  # request id -> decoded ActionChunk
        self.requested_at: dict[int, float] = {}  # request id -> monotonic time of the request
        self.overruns = OverrunCounter()
        self.late_chunks = 0
        self.stats_published = False

    def subscribe(self) -> None:
        node = self.node
        self.stats_pub = node.episode_publisher(m.REALTIME_STATS)
        node.episode_subscription(m.ACTION_CHUNK, self.on_chunk)
        node.episode_subscription(m.EPISODE_EVENTS, node.on_event)
        node.episode_timer(0.002, self.poll)  # 2 ms: tick starts and deadlines are met to a few ms

    def stamp(self) -> tuple[int, int]:
        """(scheduled wall time, tick) of the tick being decided (or the next one) for an event."""
        tick = self.node.driver.tick
        return (self.clock.tick_ns(tick) if self.clock else 0), tick

    def stop(self) -> None:
        """The episode is over: publish what it counted (once)."""
        if self.stats_published:
            return
        self.stats_published = True
        stats = dict(self.overruns.summary(), late_chunks=self.late_chunks, node="executor")
        self.stats_pub.publish(String(data=stats_json(stats)))
        self.node.get_logger().info(f"real-time executor: {stats}")

    # -- callbacks --------------------------------------------------------------------------------------
    def on_event(self, event) -> None:
        if event.kind == m.EventKind.STARTED and self.clock is None:
            self.clock = TickClock(json.loads(event.detail_json)["tick0_wall_ns"])

    def on_chunk(self, msg) -> None:
        self.chunks[msg.request_id] = msg
        self.requested_at.pop(msg.request_id, None)
        if self.deciding and self.waiting_due:
            self.node.driver.drive()

    def poll(self) -> None:
        node = self.node
        if node.finished or self.clock is None:
            return
        now = time.time_ns()
        tick = node.driver.tick
        if not self.deciding and now >= self.clock.tick_ns(tick):
            self.deciding, self.tick_start_ns = True, now
            node.driver.drive()
        elif self.deciding and self.waiting_due and now >= self.clock.tick_ns(tick) + COMMAND_DEADLINE_S * 1e9:
            node.core.late(tick)
            self.late_chunks += 1
            self.waiting_due = False
            node.driver.drive()
        stuck = [rid for rid, t in self.requested_at.items() if time.monotonic() - t > node.chunk_timeout_s]
        if stuck and not node.finished:
            node.end_with_error(f"no chunk from the policy within {node.chunk_timeout_s} s (wall clock)")

    # -- TickHandlers -------------------------------------------------------------------------------------
    def ready(self) -> bool:
        return not self.node.finished and self.deciding

    def request(self, request) -> bool:
        self.node.link.request_observation(self.clock.tick_ns(request.tick), request)  # its observation is not awaited
        self.requested_at[request.request_id] = time.monotonic()
        return True

    def chunk_due(self, due) -> bool:
        msg = self.chunks.pop(due.request_id, None)
        if msg is None:
            self.waiting_due = True  # until it arrives or the deadline passes (poll)
            return False
        self.waiting_due = False
        if msg.observation_tick != due.tick:
            # An overloaded sim answered with a later tick's observation: the rows start there, as the bag says.
            try:
                self.node.core.observed_at(due.request_id, msg.observation_tick)
            except ValueError as exc:
                self.node.end_with_error(str(exc))
                return True
        return self.apply(due.request_id, msg)

    def command(self, step) -> bool:
        scheduled = self.clock.tick_ns(step.tick)
        self.node.link.command(scheduled, step)
        self.overruns.record(step.tick, self.tick_start_ns - scheduled, time.time_ns() - self.tick_start_ns)
        self.deciding = False
        return False  # one tick per period: poll starts the next when the wall clock reaches it


def main() -> None:
    run_managed(ExecutorNode)


if __name__ == "__main__":
    main()
