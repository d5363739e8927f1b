"""Sim node: owns the LIBERO env and applies exactly one command per control tick (lockstep).

Publishes /clock, /joint_states (effort = arm torque), /ee_pose, /lq/energy_integrals every tick
(and per physics substep on /joint_states_physics, /ee_pose_physics when enabled), the observation
and camera images only when asked (/lq/observation_request), and episode events. Tick m is stepped only once the command
for tick m has arrived, so sim time never depends on wall-clock timing.

Managed node (lq_ros.transport.ros.rclpy_helpers.EpisodeNode): configure creates the task's env (hard reset); activate
resets it to the episode's init state and seed (soft: same MjSim, bit-identical to a rebuild) and
starts the episode once every peer is connected; deactivate stops stepping.
"""

from __future__ import annotations

import sys
import traceback

from lq_ros.core.executor_protocol import Source
from lq_ros.core.run_config import RunConfig, versions
from lq_ros.core.suite_constants import sim_time_of_tick
from lq_ros.sim.libero_env import LiberoEnv
from lq_ros.transport.ros.endpoints import publish_observation
from lq_ros.transport.ros.rclpy_helpers import EpisodeNode, run_managed
from lq_ros.wire import messages as m
from lq_ros.wire.node_names import NODE_NAMES


class SimNode(EpisodeNode):
    CONFIGURE_FIELDS = ("suite", "task", "cameras", "camera_size_px", "physics_rate")

    def __init__(self) -> None:
        super().__init__(NODE_NAMES["sim"])
        # What the policy needs rendered (the launcher asks the policy).
        self.declare_parameter("cameras", [""])
        self.declare_parameter("camera_size_px", self.cfg.camera_size_for(None))
        # Subscribers each topic needs before the episode starts (so no node misses tick 0).
        self.declare_parameter("min_subscribers", 1)
        self.declare_parameter("min_clock_subscribers", 3)
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
        self.state = self.env.reset(cfg.init, cfg.seed)  # the hard reset (MjSim built) belongs to configure

    def activate(self, cfg: RunConfig) -> None:
        self.init_index, self.seed, self.run_cfg = cfg.init, cfg.seed, cfg
        self.action_ticks = 0  # ticks whose command came from a chunk (budget_counts action)
        self.queued: dict = {}  # tick -> ActionCommand received ahead of its tick
        self.min_subscribers = self.get_parameter("min_subscribers").value
        self.min_clock_subscribers = self.get_parameter("min_clock_subscribers").value
        self.finished = False
        self.started = False
        self.state = self.env.reset(self.init_index, self.seed)  # soft after the first (lq_ros.sim.libero_env)
        self.pubs = {
            t.name: self.episode_publisher(t)
            for t in (m.CLOCK, m.JOINT_STATES, m.EE_POSE, m.ENERGY_INTEGRALS, m.OBSERVATION, m.EPISODE_EVENTS)
            + ((m.JOINT_STATES_PHYSICS, m.EE_POSE_PHYSICS) if self.physics_rate else ())
            + tuple(m.camera_topic(c) for c in self.env.camera_names)
        }
        self.command_sub = self.episode_subscription(m.COMMAND, self.on_command)
        self.request_sub = self.episode_subscription(m.OBSERVATION_REQUEST, self.on_request)
        self.episode_subscription(m.EPISODE_EVENTS, self.on_event)
        self.start_timer = self.episode_timer(0.05, self.start_when_ready)

    def deactivate(self) -> None:
        self.finished = True

    def cleanup(self) -> None:
        if self.env is not None:
            self.env.close()
            self.env = None

    # -- episode start ----------------------------------------------------------------------
    def start_when_ready(self) -> None:
        """Publish STARTED and tick 0 once every peer is connected."""
        clock_ok = self.pubs[m.CLOCK.name].get_subscription_count() >= self.min_clock_subscribers
        subs_ok = all(pub.get_subscription_count() >= self.min_subscribers for pub in self.pubs.values())
        peers_ok = self.command_sub.get_publisher_count() > 0 and self.request_sub.get_publisher_count() > 0
        if not (clock_ok and subs_ok and peers_ok):
            return
        self.start_timer.cancel()
        self.started = True
        detail = m.started_detail(self.env.task, self.init_index, self.seed, self.versions)
        self.event(m.EventKind.STARTED, 0, "", detail)
        self.publish_state()

    # -- callbacks --------------------------------------------------------------------------
    def on_request(self, req) -> None:
        if self.finished or not self._expect_tick(req.tick, "observation request"):
            return
        try:
            obs = self.env.observe(with_images=True)
        except Exception as exc:  # noqa: BLE001 - any env failure ends the episode as an error
            return self.fail(f"observation failed: {exc}", traceback.format_exc())
        publish_observation(self.pubs, obs, req.request_id)

    def on_command(self, cmd) -> None:
        """Queue the command of a tick at or after the current one; step through every queued tick in order.

        The executor may send the commands of several ticks ahead (those that need neither a new observation
        nor a new chunk), so the sim steps through them without waiting for a round trip per tick.
        """
        if self.finished:
            return
        late = cmd.tick < self.state.tick or cmd.tick in self.queued
        if not self.started or late or cmd.tick >= self.run_cfg.tick_limit:  # (the limit bounds the queue)
            self.get_logger().error(f"command for tick {cmd.tick} ignored: the sim is at tick {self.state.tick}")
            return
        self.queued[cmd.tick] = cmd
        while not self.finished and self.state.tick in self.queued:
            self.step(self.queued.pop(self.state.tick))

    def step(self, cmd) -> None:
        try:
            self.state = self.env.step(cmd.action)
        except Exception as exc:  # noqa: BLE001
            return self.fail(f"env.step failed at tick {cmd.tick}: {exc}", traceback.format_exc())
        self.action_ticks += cmd.source == Source.CHUNK
        spent = None if self.state.success else self.run_cfg.budget_spent(self.state.tick, self.action_ticks)
        self.publish_state(clock=not (self.state.success or spent))
        if self.state.success:
            self.end(m.EventKind.SUCCESS, "")
        elif spent:
            self.end(m.EventKind.TIMEOUT, spent)

    def on_event(self, event) -> None:
        # Another node (executor, policy) ended the episode: stop stepping.
        if event.kind in m.EventKind.TERMINAL and not self.finished:
            self.get_logger().info(f"episode ended by a peer: {m.EventKind.NAMES[event.kind]} {event.reason}")
            self.finished = True

    # -- helpers ----------------------------------------------------------------------------
    def _expect_tick(self, tick: int, what: str) -> bool:
        if self.started and tick == self.state.tick:
            return True
        self.get_logger().error(f"{what} for tick {tick} ignored: the sim is at tick {self.state.tick}")
        return False

    def publish_state(self, clock: bool = True) -> None:
        for topic, _t, data in m.tick_state_msgs(self.state, self.physics_rate, clock):
            self.pubs[topic.name].publish(data)

    def event(self, kind: int, tick: int, reason: str = "", detail: dict | None = None) -> None:
        t_ns = m.to_ns(sim_time_of_tick(tick))
        self.pubs[m.EPISODE_EVENTS.name].publish(m.event_msg(t_ns, kind, tick, reason, detail))

    def end(self, kind: int, reason: str, detail: dict | None = None) -> None:
        self.event(kind, self.state.tick, reason, detail)
        self.finished = True

    def fail(self, reason: str, trace: str) -> None:
        self.get_logger().error(reason)
        self.end(m.EventKind.ERROR, reason, {"traceback": trace, "node": "sim"})


def main() -> None:
    sys.exit(run_managed(SimNode))


if __name__ == "__main__":
    main()
