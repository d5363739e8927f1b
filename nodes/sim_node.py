"""Sim node: owns the LIBERO env and applies exactly one command per control tick, on either clock.

Publishes /joint_states (effort = arm torque), /ee_pose, /lq/energy_integrals every tick, the observation and
camera images only when asked (/lq/observation_request), and episode events. The clock mode is the run's
``clock`` parameter, read at every activation (lq_ros/transport/ros/wall_clock.py):

- ``lockstep``: tick m is stepped only once the command for tick m has arrived, so sim time never depends on
  wall-clock timing; /clock is published every tick (and per physics substep /joint_states_physics,
  /ee_pose_physics when enabled). An observation request is of the current tick or a later one: the executor
  sends it as soon as it knows the tick needs one. One for the current tick is answered at once; one for a later
  tick is queued, echoed on /lq/observation_request_queued, and answered on reaching that tick, before it is
  stepped. The executor sends that tick's command only once it has the echo or the observation, so the sim
  never steps a requested tick before it has the request. Requests that arrived meanwhile are taken before every
  step, so the echo goes out while the sim steps the ticks before, not once it has stopped at the requested one.
- ``realtime``: tick m is stepped at ``tick0 + m * 50 ms + SIM_STEP_OFFSET_S`` of wall time whatever has
  arrived: the command for tick m if the executor delivered it in time, else the stop hold (zero arm delta,
  the last applied gripper command; absolute control: the last command), and that tick is counted as a missed
  command. State is stamped with the
  ticks' scheduled wall times; there is no /clock. An observation request is answered at once with the current
  state, unless the sim runs late and has not stepped to the request's tick yet: then on reaching it (the
  observation carries its own tick). A tick whose step started late or ran
  past the period is an overrun; both counts go out on /lq/realtime_stats when the episode ends.

Lockstep, anchored relative actions: a request on /lq/anchor_state_request for a tick is answered on /lq/anchor_state
with that tick's observation without images (now, or on reaching the tick, before stepping it).

Managed node (lq_ros.transport.ros.rclpy_helpers.EpisodeNode): configure creates the task's env (hard reset);
activate resets it to the episode's init state and seed (soft: same MjSim, bit-identical to a rebuild) and
starts the episode once every peer is connected; deactivate stops stepping.
"""

from __future__ import annotations

import dataclasses
import time
import traceback

import numpy as np
from std_msgs.msg import String

from lq_ros.core.control import ControlMode, hold_action, parse_control_mode
from lq_ros.core.executor_protocol import Source
from lq_ros.core.observation_history import ObservationHistory
from lq_ros.core.run_config import RunConfig, versions
from lq_ros.core.suite_constants import sim_time_of_tick
from lq_ros.sim.libero_env import LiberoEnv, import_simulator_in_background
from lq_ros.transport.ros.endpoints import publish_observation
from lq_ros.transport.ros.rclpy_helpers import (
    START_CHECK_PERIOD_S,
    EpisodeNode,
    reliable_subscribers,
    run_managed,
    take_pending,
)
from lq_ros.transport.ros.wall_clock import (
    SIM_STEP_OFFSET_S,
    START_DELAY_S,
    OverrunCounter,
    TickClock,
    stats_json,
    tick_state_msgs,
)
from lq_ros.wire import messages as m
from lq_ros.wire.node_names import NODE_NAMES


class SimNode(EpisodeNode):
    CONFIGURE_FIELDS = ("suite", "task", "cameras", "camera_size_px", "physics_rate")

    def __init__(self) -> None:
        super().__init__(NODE_NAMES["sim"])
        # What the policy needs rendered (the launcher asks the policy).
        self.declare_parameter("cameras", [""])
        self.declare_parameter("camera_size_px", self.cfg.camera_size_for(None))
        # Ticks of observations the policy conditions on (Policy.observation_history_ticks; the launcher asks it):
        # above 1 every tick's observation is captured and the ticks before a request go with its observation.
        self.declare_parameter("history_ticks", 1)
        # How the policy's arm actions are meant (Policy.control_mode; the launcher asks it): relative or absolute.
        self.declare_parameter("control_mode", "relative")
        # Subscribers each topic needs before the episode starts (so no node misses tick 0): any, and on the
        # episode events (every node must hear STARTED; real time: its tick0) and on /clock (lockstep) the peers
        # the launcher started (events: policy, executor, recorder + this node; /clock: the recorder).
        self.declare_parameter("min_subscribers", 1)
        self.declare_parameter("min_clock_subscribers", 1)
        self.declare_parameter("min_event_subscribers", 4)
        # Real time: extra wall seconds per step, standing in for a slower machine (tests of the overrun counting).
        self.declare_parameter("step_delay_s", 0.0)
        self.env: LiberoEnv | None = None
        self.finished = False
        self.started = False
        self.versions = versions()

    # -- lifecycle ---------------------------------------------------------------------------
    def configure(self, cfg: RunConfig) -> None:
        cameras = tuple(c for c in self.get_parameter("cameras").value if c)
        self.physics_rate = cfg.physics_rate
        self.get_logger().info(f"creating {cfg.suite} task {cfg.task} (cameras: {cameras or 'none'})")
        self.env = LiberoEnv(
            cfg.suite, cfg.task, camera_names=cameras, camera_size=self.get_parameter("camera_size_px").value,
            record_physics=self.physics_rate,
        )  # fmt: skip
        mode = self.control_mode()
        # the hard reset (MjSim built) belongs to configure
        self.state = self.env.reset(cfg.init, cfg.seed, control_mode=mode)
        self.reset_for = (cfg.init, cfg.seed, mode)  # what the env is reset to and not stepped since

    def control_mode(self) -> ControlMode:
        return parse_control_mode(self.get_parameter("control_mode").value, "sim parameter control_mode")

    def activate(self, cfg: RunConfig) -> None:
        self.init_index, self.seed, self.run_cfg = cfg.init, cfg.seed, cfg
        self.realtime = cfg.clock == "realtime"
        self.action_ticks = 0  # ticks whose command came from a chunk (budget_counts action)
        self.queued: dict = {}  # tick -> ActionCommand received ahead of its tick
        self.requests: dict = {}  # tick -> ObservationRequest received ahead of it (real time: the sim ran late)
        self.min_subscribers = self.get_parameter("min_subscribers").value
        self.min_clock_subscribers = self.get_parameter("min_clock_subscribers").value
        self.min_event_subscribers = self.get_parameter("min_event_subscribers").value
        self.finished = False
        self.started = False
        mode = self.control_mode()
        if self.reset_for != (cfg.init, cfg.seed, mode):  # (the first episode after configure starts from its reset)
            # soft after the first (lq_ros.sim.libero_env)
            self.state = self.env.reset(self.init_index, self.seed, control_mode=mode)
        self.reset_for = None
        self.history = ObservationHistory(self.get_parameter("history_ticks").value)
        self.history.capture(self.env.observe)  # tick 0
        state_topics = (m.JOINT_STATES, m.EE_POSE, m.ENERGY_INTEGRALS, *m.TASK_TOPICS, m.OBSERVATION, m.EPISODE_EVENTS)
        if self.history.active:
            state_topics += (m.OBSERVATION_HISTORY, m.OBSERVATION_HISTORY_IMAGES)
        if not self.realtime:
            state_topics = (m.CLOCK, *state_topics, m.OBSERVATION_REQUEST_QUEUED) + (
                (m.JOINT_STATES_PHYSICS, m.EE_POSE_PHYSICS) if self.physics_rate else ()
            )
        self.pubs = {
            t.name: self.episode_publisher(t)
            for t in state_topics + tuple(m.camera_topic(c) for c in self.env.camera_names)
        }
        self.command_sub = self.episode_subscription(m.COMMAND, self.on_command)
        self.anchor_ticks: set[int] = set()  # lockstep: ticks whose anchor state was asked for ahead of them
        if not self.realtime:
            self.anchor_pub = self.episode_publisher(m.ANCHOR_STATE)
            self.episode_subscription(m.ANCHOR_STATE_REQUEST, self.on_anchor_request)
        self.request_sub = self.episode_subscription(m.OBSERVATION_REQUEST, self.on_request)
        self.episode_subscription(m.EPISODE_EVENTS, self.on_event)
        if self.realtime:
            self.clock: TickClock | None = None
            self.last_action = np.asarray(self.env.control.start_action, dtype=np.float64)
            self.missed: list[int] = []  # ticks stepped with the hold because their command was late
            self.overruns = OverrunCounter()
            self.step_delay_s = self.get_parameter("step_delay_s").value
            self.stats_pub = self.episode_publisher(m.REALTIME_STATS)
            self.episode_timer(0.002, self.step_on_time)
        self.start_timer = self.episode_timer(START_CHECK_PERIOD_S, self.start_when_ready)

    def deactivate(self) -> None:
        self.finished = True

    def cleanup(self) -> None:
        if self.env is not None:
            self.env.close(collect=not self.exiting)  # (exiting: the process's last collection comes next)
            self.env = None

    # -- episode start ----------------------------------------------------------------------
    def start_when_ready(self) -> None:
        """Publish STARTED and tick 0 once every peer is connected (real time: tick 0 START_DELAY_S later)."""
        subs_ok = all(pub.get_subscription_count() >= self.min_subscribers for pub in self.pubs.values())
        peers_ok = self.command_sub.get_publisher_count() > 0 and self.request_sub.get_publisher_count() > 0
        peers_ok = peers_ok and self.pubs[m.EPISODE_EVENTS.name].get_subscription_count() >= self.min_event_subscribers
        if not self.realtime:  # (a node's use_sim_time time source subscribes best effort: not a peer of the episode)
            peers_ok = peers_ok and reliable_subscribers(self, m.CLOCK) >= self.min_clock_subscribers
        if not (subs_ok and peers_ok):
            return
        self.start_timer.cancel()
        self.started = True
        detail = m.started_detail(self.env.task, self.init_index, self.seed, self.versions, self.env.control)
        if self.realtime:
            self.clock = TickClock(time.time_ns() + round(START_DELAY_S * 1e9))
            detail.update(tick0_wall_ns=self.clock.tick0_ns, clock="realtime")
        self.event(m.EventKind.STARTED, 0, "", detail)
        self.publish_state()

    # -- callbacks --------------------------------------------------------------------------
    def on_request(self, req) -> None:
        if self.finished:
            return
        # Lockstep: asked ahead of its tick. Real time: the sim runs late (a step that took longer than the period)
        # and has not stepped to the request's tick yet; the policy must see that tick's state, so the answer waits
        # for it, as the executor and the scorer count the chunk's stale rows from the request's tick.
        if self.started and self.state.tick < req.tick < self.run_cfg.tick_limit:
            if req.tick in self.requests:
                self.get_logger().error(f"a second observation request for tick {req.tick} ignored")
            else:
                self.requests[req.tick] = req  # answered on reaching that tick (step)
                if not self.realtime:  # (the lockstep executor waits for the echo; the wall clock waits for nothing)
                    self.pubs[m.OBSERVATION_REQUEST_QUEUED.name].publish(
                        m.serialize(req, m.OBSERVATION_REQUEST.msgtype)
                    )
            return
        if self.realtime and req.tick >= self.run_cfg.tick_limit:
            return  # the wall clock ran past the episode's last tick while the sim catches up: no such state comes
        if not (self.realtime and self.started or self._expect_tick(req.tick, "observation request")):
            return
        self.observe(req)

    def on_anchor_request(self, req) -> None:
        """Lockstep: the executor needs the state of ``req.tick`` to resolve its command (anchored relative
        actions): answered now if the sim is at that tick, else on reaching it (before stepping it)."""
        if self.finished or not self.started:
            return
        if req.tick == self.state.tick:
            self.publish_anchor_state()
        elif self.state.tick < req.tick < self.run_cfg.tick_limit:
            self.anchor_ticks.add(req.tick)
        else:
            self.get_logger().error(f"no anchor state of tick {req.tick}: the sim is at tick {self.state.tick}")

    def publish_anchor_state(self) -> None:
        """The current tick's observation without images, for the executor to anchor the tick's command with."""
        try:
            obs = self.env.observe(with_images=False)
        except Exception as exc:  # noqa: BLE001 - any env failure ends the episode as an error
            return self.fail(f"observation failed: {exc}", traceback.format_exc())
        self.anchor_pub.publish(m.observation_msg(obs, 0))

    def observe(self, req) -> None:
        """Publish the observation of the current tick for ``req``."""
        try:
            obs = self.history.attach(self.env.observe(with_images=True))
        except Exception as exc:  # noqa: BLE001 - any env failure ends the episode as an error
            return self.fail(f"observation failed: {exc}", traceback.format_exc())
        if self.realtime:
            obs.sim_time_s = self.clock.tick_ns(obs.tick) / 1e9  # the tick's scheduled wall time
            obs.history = tuple(
                dataclasses.replace(past, sim_time_s=self.clock.tick_ns(past.tick) / 1e9) for past in obs.history
            )
        publish_observation(self.pubs, obs, req.request_id)

    def on_command(self, cmd) -> None:
        """Queue the command of a tick at or after the current one.

        Lockstep: step through every queued tick in order (the executor may send the commands of several ticks
        ahead, those that need neither a new observation nor a new chunk, so the sim steps through them
        without a round trip per tick). Real time: the wall clock steps them (:meth:`step_on_time`).
        """
        if self.finished:
            return
        if self.realtime:
            if self.started and cmd.tick >= self.state.tick:
                self.queued[cmd.tick] = cmd
            return
        late = cmd.tick < self.state.tick or cmd.tick in self.queued
        if not self.started or late or cmd.tick >= self.run_cfg.tick_limit:  # (the limit bounds the queue)
            self.get_logger().error(f"command for tick {cmd.tick} ignored: the sim is at tick {self.state.tick}")
            return
        self.queued[cmd.tick] = cmd
        while not self.finished and self.state.tick in self.queued:
            self.take_requests()
            cmd = self.queued.pop(self.state.tick)
            self.step(cmd.tick, cmd.action, cmd.source)

    def take_requests(self) -> None:
        """Lockstep: queue (and echo) the observation requests that arrived while the sim stepped, before the
        next step. Left to the executor's turn, a request sent with the commands of the ticks before its own
        would be taken only once those are stepped, and its tick would wait for the echo's round trip."""
        for req in take_pending(self.request_sub, m.OBSERVATION_REQUEST):
            self.on_request(req)

    def step_on_time(self) -> None:
        """Real time: step the current tick once its wall time (+ SIM_STEP_OFFSET_S) has come, with its command
        or, if that has not arrived, the stop hold (a missed command)."""
        if self.finished or self.clock is None:
            return
        tick = self.state.tick
        scheduled = self.clock.tick_ns(tick) + round(SIM_STEP_OFFSET_S * 1e9)
        start = time.time_ns()
        if start < scheduled:
            return
        self.drain_commands()
        cmd = self.queued.pop(tick, None)
        if cmd is None:
            self.missed.append(tick)
            # (no chunk's: not an action tick)
            action, source = hold_action(self.env.control.mode, self.last_action), Source.HOLD_INFERENCE
        else:
            action, source = np.asarray(cmd.action, dtype=np.float64), cmd.source
        self.last_action = action
        self.step(tick, action, source, started_ns=(start, scheduled))

    def drain_commands(self) -> None:
        """Take every command that has arrived before stepping (real time).

        rclpy's executor runs ready timers before subscriptions and takes one message per subscription per
        wait. A sim that has fallen behind has its step timer always ready, so it would step each tick just
        before the tick's command is taken, and miss every command (seen: 220 of 220).
        """
        for cmd in take_pending(self.command_sub, m.COMMAND):
            self.on_command(cmd)

    def step(self, tick: int, action, source: int, started_ns: tuple[int, int] | None = None) -> None:
        """Step ``tick``; end the episode on success or a spent budget. Real time: ``started_ns`` is (when the step
        started, when it was scheduled), wall ns, for the overrun count."""
        try:
            self.state = self.env.step(action)
            self.history.capture(self.env.observe)
            if started_ns is not None and self.step_delay_s:
                time.sleep(self.step_delay_s)
        except Exception as exc:  # noqa: BLE001
            return self.fail(f"env.step failed at tick {tick}: {exc}", traceback.format_exc())
        self.action_ticks += source == Source.CHUNK
        spent = None if self.state.success else self.run_cfg.budget_spent(self.state.tick, self.action_ticks)
        self.publish_state(clock=not (self.state.success or spent))
        if started_ns is not None:
            start, scheduled = started_ns
            self.overruns.record(tick, start - scheduled, time.time_ns() - start)
        if self.state.success:
            self.end(m.EventKind.SUCCESS, "")
        elif spent:
            self.end(m.EventKind.TIMEOUT, spent)
        elif self.state.tick in self.requests:  # asked ahead for this tick's observation (real time: the sim ran late)
            self.observe(self.requests.pop(self.state.tick))
        if not self.finished and self.state.tick in self.anchor_ticks:  # (lockstep only)
            self.anchor_ticks.discard(self.state.tick)
            self.publish_anchor_state()

    def on_event(self, event) -> None:
        # Another node (executor, policy) ended the episode: stop stepping.
        if event.kind in m.EventKind.TERMINAL and not self.finished:
            self.get_logger().info(f"episode ended by a peer: {m.EventKind.NAMES[event.kind]} {event.reason}")
            self.finished = True
            self.publish_stats()
            self.seal_episode()

    # -- helpers ----------------------------------------------------------------------------
    def _expect_tick(self, tick: int, what: str) -> bool:
        if self.started and tick == self.state.tick:
            return True
        self.get_logger().error(f"{what} for tick {tick} ignored: the sim is at tick {self.state.tick}")
        return False

    def publish_state(self, clock: bool = True) -> None:
        if self.realtime:
            msgs = tick_state_msgs(self.state, self.clock)
        else:
            msgs = m.tick_state_msgs(self.state, self.physics_rate, clock)
        for topic, _t, data in msgs:
            self.pubs[topic.name].publish(data)

    def event(self, kind: int, tick: int, reason: str = "", detail: dict | None = None) -> None:
        t_ns = self.clock.tick_ns(tick) if self.realtime else m.to_ns(sim_time_of_tick(tick))
        self.pubs[m.EPISODE_EVENTS.name].publish(m.event_msg(t_ns, kind, tick, reason, detail))

    def end(self, kind: int, reason: str, detail: dict | None = None) -> None:
        self.event(kind, self.state.tick, reason, detail)
        self.finished = True
        self.publish_stats()
        self.seal_episode()

    def fail(self, reason: str, trace: str) -> None:
        self.get_logger().error(reason)
        self.end(m.EventKind.ERROR, reason, {"traceback": trace, "node": "sim"})

    def publish_stats(self) -> None:
        """Real time: what this episode's stepping counted (the recorder keeps it in the bag's metadata)."""
        if not self.realtime:
            return
        stats = dict(self.overruns.summary(), node="sim", missed_commands=len(self.missed),
                     missed_command_ticks=self.missed[:200])  # fmt: skip
        self.stats_pub.publish(String(data=stats_json(stats)))
        self.get_logger().info(f"real-time sim: {stats}")


def main() -> None:
    import_simulator_in_background(then=m.typestore)  # while rclpy starts and the launcher discovers this node
    run_managed(SimNode)


if __name__ == "__main__":
    main()
