"""Recorder of real-time episodes (wall-clock sim or a robot): a bag, then the unchanged scorer.

Like the lockstep metrics node it writes every episode topic as received (serialized CDR, header stamps
as log times; lq_ros.recording.episode_bag's crash-safe writer) and scores the bag when the episode is over. Besides:

- a robot's own topics (``robot_topics_json``: [{name, type}], e.g. its 500 Hz joint states, 100 Hz EE
  pose, the bridge's targets, the /clock of a robot on sim time) are recorded under their own names,
  subscribed reliable + volatile as a robot driver publishes them, logged at their stamps (the robot's
  clock); messages without a header or time are logged at their receive (wall) time;
- the real-time stats the nodes publish on /lq/realtime_stats (overrun ticks, missed commands) are
  recorded and copied into the run metadata (``realtime``), with ``clock: realtime`` and the robot's
  interface, so the bag says it is not bit-reproducible;
- the score uses ``ee_topic``/``joint_topic`` and the ``trajectory_rate``/``energy_rate`` given (a robot's
  topics have their own rates: ``native``), i.e. ``lq score BAG --ee-topic ... --rate native``.

The robot keeps publishing after the episode: the bag is closed once the episode topics have been quiet
for ``quiet_period_s`` after the terminal event and the executor's stats have arrived (or 2 s passed).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from lq_ros.core.run_config import versions
from lq_ros.recording.episode_bag import EpisodeBagWriter, episode_topics, log_time_ns, run_metadata
from lq_ros.recording.episode_folder import SCORE_FILE
from lq_ros.scoring.bag_scorer import score_bag, to_json
from lq_ros.transport.ros.rclpy_helpers import LOSSLESS_QOS, declare_run_config, json_param, msg_class, run
from lq_ros.wire import messages as m
from lq_ros.wire.node_names import NODE_NAMES

STATS = m.Topic("/lq/realtime_stats", "std_msgs/msg/String")
ROBOT_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST, depth=10000, reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)  # fmt: skip
#: Types whose first field is a std_msgs/Header or a Time (log time = its stamp); others: receive time.
_HEADER_TYPES = {"sensor_msgs/msg/JointState", "geometry_msgs/msg/PoseStamped", "sensor_msgs/msg/Image",
                 "rosgraph_msgs/msg/Clock"}  # fmt: skip


class RealtimeRecorderNode(Node):
    def __init__(self) -> None:
        super().__init__(NODE_NAMES["metrics"])
        self.cfg = declare_run_config(self)
        for name, default in (("bag_path", ""), ("cameras", [""]), ("camera_size_px", 224), ("quiet_period_s", 0.3),
                              ("ee_topic", m.EE_POSE.name), ("joint_topic", m.JOINT_STATES.name),
                              ("trajectory_rate", "auto"), ("energy_rate", "auto")):  # fmt: skip
            self.declare_parameter(name, default)
        self.policy_params = json_param(self, "policy_params_json")
        self.robot_topics = [m.Topic(t["name"], t["type"]) for t in json.loads(self._p("robot_topics_json", "[]"))]
        self.robot_info = json.loads(self._p("robot_json", "null"))
        self.cameras = tuple(c for c in self.get_parameter("cameras").value if c)
        self.bag_path = Path(self.get_parameter("bag_path").value)
        self.quiet_period_s = self.get_parameter("quiet_period_s").value
        own = [t for t in episode_topics(self.cfg, self.cameras) if t.name != m.CLOCK.name] + [STATS]
        self.topics = own + self.robot_topics
        self.versions = versions()
        self.stats: dict[str, dict] = {}
        self.started_detail: dict = {}
        self.writer = EpisodeBagWriter(self.bag_path, self.topics)
        self.writer.set_run_metadata(self._metadata())
        for topic in own:
            self.create_subscription(
                msg_class(topic.msgtype), topic.name, self._recorder(topic), LOSSLESS_QOS, raw=True
            )
        for topic in self.robot_topics:
            self.create_subscription(msg_class(topic.msgtype), topic.name, self._recorder(topic), ROBOT_QOS, raw=True)
        self.robot_names = {t.name for t in self.robot_topics}
        self.last_message = time.monotonic()
        self.terminal_at: float | None = None
        self.finished = False
        self.exit_code = 0
        self.create_timer(0.1, self.finish_when_quiet)

    def _p(self, name: str, default: str) -> str:
        self.declare_parameter(name, default)
        return self.get_parameter(name).value

    def _recorder(self, topic: m.Topic):
        header = topic.msgtype in _HEADER_TYPES or topic.msgtype.startswith("lq_msgs/")

        def record(data: bytes) -> None:
            if self.finished:
                return
            self.writer.write(topic, log_time_ns(topic, data) if header else time.time_ns(), data)
            if topic.name in self.robot_names:
                return
            self.last_message = time.monotonic()
            if topic.name == m.EPISODE_EVENTS.name:
                event = m.deserialize(data, topic.msgtype)
                if event.kind == m.EventKind.STARTED:
                    self.started_detail = json.loads(event.detail_json)
                elif event.kind in m.EventKind.TERMINAL and self.terminal_at is None:
                    self.terminal_at = time.monotonic()
            elif topic.name == STATS.name:
                stats = json.loads(m.deserialize(data, topic.msgtype).data)
                self.stats[stats.get("node", "?")] = stats

        return record

    def _metadata(self) -> dict:
        env_versions = dict(self.started_detail.get("versions") or self.versions)
        env_versions["rclpy"] = self.versions["rclpy"]
        size = self.get_parameter("camera_size_px").value if self.cameras else None
        meta = run_metadata(self.cfg, self.policy_params, "ros", env_versions, size)
        meta.update(clock="realtime", robot=self.robot_info, realtime=self.stats)
        return meta

    def finish_when_quiet(self) -> None:
        if self.terminal_at is None or self.finished:
            return
        quiet = time.monotonic() - self.last_message > self.quiet_period_s
        if quiet and ("executor" in self.stats or time.monotonic() - self.terminal_at > 2.0):
            self.finish()

    def finish(self) -> None:
        self.finished = True
        self.writer.set_run_metadata(self._metadata())
        self.writer.close()
        kwargs = {
            "ee_topic": self.get_parameter("ee_topic").value,
            "joint_topic": self.get_parameter("joint_topic").value,
            "rate": self.get_parameter("trajectory_rate").value,
            "energy_rate": self.get_parameter("energy_rate").value,
        }
        row = score_bag(self.bag_path, **kwargs)
        (self.bag_path / SCORE_FILE).write_text(to_json(row) + "\n")
        self.get_logger().info(f"episode {row['status']}; bag {self.bag_path}")

    def close(self) -> None:
        if not self.finished:
            t_ns = time.time_ns()
            data = m.event_msg(t_ns, m.EventKind.STOPPED, 0, "recording stopped before the episode ended")
            self.writer.write(m.EPISODE_EVENTS, t_ns, data)
            self.finish()


def main() -> None:
    sys.exit(run(RealtimeRecorderNode))


if __name__ == "__main__":
    main()
