"""Metrics node: records the episode topics to a rosbag2 MCAP bag, then scores it offline.

Messages are written exactly as received (serialized CDR) with their sim-time log stamps. The bag is
crash-safe (lq_ros.recording.episode_bag): killed with SIGKILL, it keeps all but the last 0.5 s of sim time, and its
metadata.yaml (with the run metadata) exists from the start. Once a
terminal event (success, timeout, error) has arrived and the topics have been quiet for a moment,
the bag is closed, scored with lq_ros.scoring.bag_scorer and the score written next to it (score.json).
Stopped early (deactivated, Ctrl-C), it records a STOPPED event so the episode scores as an error, not
a failure.

Managed node: activate opens the episode's bag (``bag_path``); once the bag is closed and scored the
node deactivates itself, which tells the lifecycle manager the episode is over.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from lq_ros.core.run_config import RunConfig, versions
from lq_ros.core.suite_constants import sim_time_of_tick
from lq_ros.recording.episode_bag import EpisodeBagWriter, episode_topics, log_time_ns, run_metadata
from lq_ros.scoring.bag_scorer import score_bag, to_json
from lq_ros.transport.ros.rclpy_helpers import LOSSLESS_QOS, EpisodeNode, msg_class, run_managed
from lq_ros.wire import messages as m

SCORE_FILE = "score.json"


class MetricsNode(EpisodeNode):
    def __init__(self) -> None:
        super().__init__("lq_metrics")
        self.declare_parameter("bag_path", "")
        self.declare_parameter("cameras", [""])
        self.declare_parameter("camera_size_px", self.cfg.camera_size_for(None))
        # Wall seconds without messages, after the terminal event, before the bag is closed.
        self.declare_parameter("quiet_period_s", 0.3)
        self.declare_parameter("policy_params_json", "{}")
        self.versions = versions()
        self.finished = True

    def activate(self, cfg: RunConfig) -> None:
        bag_path = self.get_parameter("bag_path").value
        if not bag_path:
            raise ValueError("parameter bag_path is empty: set the episode's bag folder before activating")
        self.bag_path = Path(bag_path)
        self.policy_params = json.loads(self.get_parameter("policy_params_json").value)
        self.quiet_period_s = self.get_parameter("quiet_period_s").value
        self.cameras = cameras = tuple(c for c in self.get_parameter("cameras").value if c)
        self.topics = episode_topics(cfg, cameras)
        self.started_detail: dict = {}
        self.last_message = time.monotonic()
        self.terminal_seen = False
        self.last_tick = 0
        self.writer = EpisodeBagWriter(self.bag_path, self.topics)
        self.finished = False
        self.writer.set_run_metadata(self._run_metadata(self.versions))
        for topic in self.topics:
            sub = self.create_subscription(
                msg_class(topic.msgtype), topic.name, self._recorder(topic), LOSSLESS_QOS, raw=True
            )
            self._episode_entities.append(sub)
        self.episode_timer(0.1, self.finish_when_quiet)

    def deactivate(self) -> None:
        if not self.finished:
            # Stopped before the episode ended: say so in the bag, so it scores as an error.
            t_ns = m.to_ns(sim_time_of_tick(self.last_tick))
            data = m.event_msg(t_ns, m.EventKind.STOPPED, self.last_tick, "recording stopped before the episode ended")
            self.writer.write(m.EPISODE_EVENTS, t_ns, data)
            self.finish()

    def _recorder(self, topic: m.Topic):
        def record(data: bytes) -> None:
            if self.finished:
                return
            self.writer.write(topic, log_time_ns(topic, data), data)
            self.last_message = time.monotonic()
            if topic.name == m.EPISODE_EVENTS.name:
                self.on_event(m.deserialize(data, topic.msgtype))
            elif topic.name == m.COMMAND.name:
                self.last_tick = m.deserialize(data, topic.msgtype).tick

        return record

    def on_event(self, event) -> None:
        if event.kind == m.EventKind.STARTED:
            self.started_detail = json.loads(event.detail_json)
            self.writer.set_run_metadata(self._run_metadata(self._env_versions()))
        elif event.kind in m.EventKind.TERMINAL:
            self.terminal_seen = True

    def finish_when_quiet(self) -> None:
        if self.terminal_seen and not self.finished and time.monotonic() - self.last_message > self.quiet_period_s:
            self.finish()
            # The episode is recorded: leave the active state (the manager waits for this transition).
            self.trigger_deactivate()

    def _env_versions(self) -> dict:
        """The simulator's versions (from its STARTED event), with this node's rclpy."""
        env_versions = dict(self.started_detail.get("versions") or self.versions)
        env_versions["rclpy"] = self.versions["rclpy"]
        return env_versions

    def _run_metadata(self, env_versions: dict) -> dict:
        camera_size_px = self.get_parameter("camera_size_px").value if self.cameras else None
        return run_metadata(self.cfg, self.policy_params, "ros", env_versions, camera_size_px)

    def finish(self) -> None:
        self.finished = True
        self.writer.set_run_metadata(self._run_metadata(self._env_versions()))
        self.writer.close()
        row = score_bag(self.bag_path)
        (self.bag_path / SCORE_FILE).write_text(to_json(row) + "\n")
        self.get_logger().info(f"episode {row['status']}; bag {self.bag_path}")


def main() -> None:
    sys.exit(run_managed(MetricsNode))


if __name__ == "__main__":
    main()
