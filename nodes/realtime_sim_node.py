"""Real-time sim node (``--clock realtime``): the LIBERO env stepped on a wall-clock timer at 20 Hz.

The lockstep sim (sim_node.py) steps tick m when the command for tick m arrives. This one steps tick m
at ``tick0 + m * 50 ms + SIM_STEP_OFFSET_S`` whatever has arrived (lq_ros/transport/ros/wall_clock.py): the command
for tick m if the executor delivered it in time, else the stop hold (zero arm delta, the last applied
gripper command), and that tick is counted as a missed command. State is published right after each
step, stamped with the next tick's scheduled wall time; there is no /clock. Observation requests are
answered at once with the current state, whatever tick it is (the observation carries its own tick).
A tick whose step started late or ran past the period is an overrun. Both counts are published on
/lq/realtime_stats when the episode ends. Episode events are as in lockstep, stamped in wall time.
"""

from __future__ import annotations

import json
import sys
import time
import traceback

import numpy as np
from rclpy.node import Node
from std_msgs.msg import String

from lq_ros.core.executor_protocol import Source
from lq_ros.core.run_config import versions
from lq_ros.core.suite_constants import DUMMY_ACTION
from lq_ros.sim.libero_env import LiberoEnv
from lq_ros.transport.ros.endpoints import publish_observation
from lq_ros.transport.ros.rclpy_helpers import LOSSLESS_QOS, declare_run_config, publisher, raw_subscription, run
from lq_ros.transport.ros.wall_clock import SIM_STEP_OFFSET_S, START_DELAY_S, OverrunCounter, TickClock, tick_state_msgs
from lq_ros.wire import messages as m
from lq_ros.wire.node_names import NODE_NAMES

STATS_TOPIC = "/lq/realtime_stats"


class RealtimeSimNode(Node):
    def __init__(self) -> None:
        super().__init__(NODE_NAMES["sim"])
        cfg = declare_run_config(self)
        self.declare_parameter("cameras", [""])
        self.declare_parameter("camera_size_px", cfg.camera_size_for(None))
        self.declare_parameter("min_subscribers", 1)
        # Extra wall seconds per step: stands in for a slower machine (tests of the overrun counting).
        self.declare_parameter("step_delay_s", 0.0)
        self.step_delay_s = self.get_parameter("step_delay_s").value
        cameras = tuple(c for c in self.get_parameter("cameras").value if c)
        self.min_subscribers = self.get_parameter("min_subscribers").value
        self.cfg = cfg
        self.pubs = {
            t.name: publisher(self, t)
            for t in (m.JOINT_STATES, m.EE_POSE, m.ENERGY_INTEGRALS, m.OBSERVATION, m.EPISODE_EVENTS)
            + tuple(m.camera_topic(c) for c in cameras)
        }
        self.stats_pub = self.create_publisher(String, STATS_TOPIC, LOSSLESS_QOS)
        self.command_sub = raw_subscription(self, m.COMMAND, self.on_command)
        self.request_sub = raw_subscription(self, m.OBSERVATION_REQUEST, self.on_request)
        raw_subscription(self, m.EPISODE_EVENTS, self.on_event)
        self.env = LiberoEnv(
            cfg.suite, cfg.task, camera_names=cameras, camera_size=self.get_parameter("camera_size_px").value
        )
        self.state = self.env.reset(cfg.init, cfg.seed)
        self.commands: dict[int, tuple[np.ndarray, int]] = {}  # tick -> (action, source), as they arrive
        self.action_ticks = 0  # ticks whose command came from a chunk (budget_counts action)
        self.last_action = np.asarray(DUMMY_ACTION, dtype=np.float64)
        self.clock: TickClock | None = None
        self.finished = False
        self.missed: list[int] = []  # ticks stepped with the hold because their command was late
        self.overruns = OverrunCounter()
        self.versions = versions()
        self.start_timer = self.create_timer(0.05, self.start_when_ready)
        self.create_timer(0.002, self.poll)

    def start_when_ready(self) -> None:
        subs_ok = all(pub.get_subscription_count() >= self.min_subscribers for pub in self.pubs.values())
        peers_ok = self.command_sub.get_publisher_count() > 0 and self.request_sub.get_publisher_count() > 0
        # Events: this node, the policy, the executor and the recorder must all hear STARTED at once.
        if not (subs_ok and peers_ok and self.pubs[m.EPISODE_EVENTS.name].get_subscription_count() >= 4):
            return
        self.start_timer.cancel()
        # Tick 0 a little later, so that every node has STARTED (and its clock) before the first tick.
        self.clock = TickClock(time.time_ns() + round(START_DELAY_S * 1e9))
        detail = m.started_detail(self.env.task, self.cfg.init, self.cfg.seed, self.versions)
        detail.update(tick0_wall_ns=self.clock.tick0_ns, clock="realtime")
        self.event(m.EventKind.STARTED, 0, "", detail)
        self.publish_state()

    def on_command(self, cmd) -> None:
        if self.clock is not None and not self.finished and cmd.tick >= self.state.tick:
            self.commands[cmd.tick] = (np.asarray(cmd.action, dtype=np.float64), cmd.source)

    def on_request(self, req) -> None:
        if self.finished or self.clock is None:
            return
        try:
            obs = self.env.observe(with_images=True)
        except Exception as exc:  # noqa: BLE001
            return self.fail(f"observation failed: {exc}", traceback.format_exc())
        obs.sim_time_s = self.clock.tick_ns(obs.tick) / 1e9  # the tick's scheduled wall time
        publish_observation(self.pubs, obs, req.request_id)

    def on_event(self, event) -> None:
        if event.kind in m.EventKind.TERMINAL and not self.finished:
            self.finished = True
            self.publish_stats()

    def poll(self) -> None:
        if self.finished or self.clock is None:
            return
        tick = self.state.tick
        scheduled = self.clock.tick_ns(tick) + round(SIM_STEP_OFFSET_S * 1e9)
        start = time.time_ns()
        if start < scheduled:
            return
        self.drain_commands()
        action, source = self.commands.pop(tick, (None, None))
        if action is None:
            self.missed.append(tick)
            action = np.zeros(7)
            action[-1] = self.last_action[-1]
        self.action_ticks += source == Source.CHUNK
        self.last_action = action
        try:
            self.state = self.env.step(action)
            if self.step_delay_s:
                time.sleep(self.step_delay_s)
        except Exception as exc:  # noqa: BLE001
            return self.fail(f"env.step failed at tick {tick}: {exc}", traceback.format_exc())
        self.publish_state()
        self.overruns.record(tick, start - scheduled, time.time_ns() - start)
        spent = self.cfg.budget_spent(self.state.tick, self.action_ticks)
        if self.state.success:
            self.end(m.EventKind.SUCCESS, "")
        elif spent:
            self.end(m.EventKind.TIMEOUT, spent)

    def drain_commands(self) -> None:
        """Take every command that has arrived before stepping.

        rclpy's executor runs ready timers before subscriptions and takes one message per subscription per
        wait. A sim that has fallen behind has this timer always ready, so it would step each tick just
        before the tick's command is taken, and miss every command (seen: 220 of 220).
        """
        sub = self.command_sub
        while True:
            with sub.handle:
                taken = sub.handle.take_message(sub.msg_type, sub.raw)
            if taken is None:
                return
            self.on_command(m.deserialize(taken[0], m.COMMAND.msgtype))

    def publish_state(self) -> None:
        for topic, _t, data in tick_state_msgs(self.state, self.clock):
            self.pubs[topic.name].publish(data)

    def event(self, kind: int, tick: int, reason: str = "", detail: dict | None = None) -> None:
        self.pubs[m.EPISODE_EVENTS.name].publish(m.event_msg(self.clock.tick_ns(tick), kind, tick, reason, detail))

    def end(self, kind: int, reason: str) -> None:
        self.event(kind, self.state.tick, reason)
        self.finished = True
        self.publish_stats()

    def fail(self, reason: str, trace: str) -> None:
        self.get_logger().error(reason)
        self.event(m.EventKind.ERROR, self.state.tick, reason, {"traceback": trace, "node": "sim"})
        self.finished = True
        self.publish_stats()

    def publish_stats(self) -> None:
        stats = dict(self.overruns.summary(), node="sim", missed_commands=len(self.missed),
                     missed_command_ticks=self.missed[:200])  # fmt: skip
        self.stats_pub.publish(String(data=json.dumps(stats, sort_keys=True)))
        self.get_logger().info(f"real-time sim: {stats}")

    def close(self) -> None:
        self.env.close()


def main() -> None:
    sys.exit(run(RealtimeSimNode, stay_alive=True))


if __name__ == "__main__":
    main()
