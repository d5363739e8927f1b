"""Metrics node: records the episode topics to a rosbag2 MCAP bag, then scores it offline.

Messages are written exactly as received (serialized CDR) with their header stamps as log times (sim time in
lockstep). The bag is crash-safe (lq_ros.recording.episode_bag): killed with SIGKILL, it keeps all but the last
0.5 s of sim time, and its metadata.yaml (with the run metadata) exists from the start. Once a terminal event
(success, timeout, error) has arrived and, from every node that publishes episode topics, its message counts
(/lq/published_counts, sent when the episode ends for that node) with that many messages received on every
recorded topic, the bag is closed, scored with lq_ros.scoring.bag_scorer and the score written next to it
(score.json). A node whose counts do not come (it died) is waited for ``COUNTS_WAIT_S``, then the bag is closed once
the topics have been quiet for ``quiet_period_s``, with a WARNING event naming what was missing.
Stopped early (deactivated, Ctrl-C), it records a STOPPED event so the episode scores as an error, not
a failure.

Episode events are recorded only from the sim and executor nodes, chunks only from the policy node
(lq_ros.transport.ros.senders): a message another participant of the domain publishes there (a forged SUCCESS)
is recorded as a WARNING event instead, never as the outcome. A message that cannot be recorded (e.g. a chunk
whose latency is no whole number of ticks) is dropped with a WARNING event; no callback ends the node.

Real-time runs (``clock: realtime``, read at every activation; a wall-clock sim or a robot through the bridge)
record besides:

- a robot's own topics (``robot_topics_json``: [{name, type}], e.g. its 500 Hz joint states, 100 Hz EE pose,
  the bridge's targets, the /clock of a robot on sim time) under their own names, subscribed reliable + volatile
  as a robot driver publishes them, logged at their stamps (the robot's clock); messages without a header or
  time are logged at their receive (wall) time; each robot topic, once its first message has arrived, is named
  on /lq/recorder_hears (the bridge starts the episode only when the robot's state topics are there);
- the nodes' counts on /lq/realtime_stats (overrun ticks, missed commands), also copied into the run metadata
  (``realtime``), with ``clock: realtime`` and the robot's interface, so the bag says it is not bit-reproducible;
- commands as they arrive (a robot applies each when it arrives; the wall-clock sim steps on time whatever came).

The score then uses ``ee_topic``/``joint_topic`` and the ``trajectory_rate``/``energy_rate`` given (a robot's
topics have their own rates: ``native``), i.e. ``lq score BAG --ee-topic ... --rate native``. A robot keeps
publishing after the episode: its topics are recorded until the bag closes, and never keep it open, with one
promise: a robot on sim time has its /clock recorded up to the end event's stamp (the bridge stamps the end with
a /clock the recorder may receive after the event; the bag stays open for it up to ``CLOCK_COVER_WAIT_S``, and a
/clock that never gets there is a WARNING event).

Managed node: activate opens the episode's bag (``bag_path``); once the bag is closed and scored the
node deactivates itself, which tells the lifecycle manager the episode is over.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import time
import traceback
from collections import Counter
from pathlib import Path

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from lq_ros.core.run_config import RunConfig, versions
from lq_ros.core.suite_constants import sim_time_of_tick, tick_of_sim_time
from lq_ros.recording.episode_bag import EpisodeBagWriter, episode_topics, log_time_ns, run_metadata
from lq_ros.recording.episode_folder import SCORE_FILE
from lq_ros.robot.robot_config import SIM_RECORDER_PARAMETERS
from lq_ros.scoring.bag_scorer import score_bag, to_json
from lq_ros.transport.ros.rclpy_helpers import LOSSLESS_QOS, EpisodeNode, msg_class, publisher, run_managed
from lq_ros.transport.ros.senders import EXPECTED_SENDERS, SenderSubscription, expected_sender, sender_text
from lq_ros.wire import messages as m
from lq_ros.wire.node_names import NODE_NAMES

#: WARNING events the recorder writes per episode at most (rogue or unusable messages); then one count.
MAX_WARNING_EVENTS = 100
#: Topics whose messages the recorder reads (episode events: outcome; commands: the last tick; real-time counts).
_DECODED = (m.EPISODE_EVENTS.name, m.COMMAND.name, m.REALTIME_STATS.name)
#: Lockstep: topics sent ahead of the sim, each message recorded once the sim has stepped its tick (a chunk's: the
#: tick it is due).
_SENT_AHEAD = (m.COMMAND.name, m.OBSERVATION_REQUEST.name, m.ACTION_CHUNK.name)
#: A robot's own topics: what a robot driver typically offers (reliable, volatile), deep enough for 500 Hz.
ROBOT_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST, depth=10000, reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)  # fmt: skip
#: Types whose first field is a std_msgs/Header or a Time (log time = its stamp); others: receive time.
_STAMPED_TYPES = {"sensor_msgs/msg/JointState", "geometry_msgs/msg/PoseStamped", m.IMAGE_MSGTYPE,
                  "rosgraph_msgs/msg/Clock", m.TASK_OBJECT_POSES.msgtype}  # fmt: skip
#: Wall seconds after the terminal event the recorder waits at most for every node's message counts.
COUNTS_WAIT_S = 2.0
#: Wall seconds after the terminal event the recorder waits at most for a robot's /clock to reach the event's stamp.
CLOCK_COVER_WAIT_S = 1.0
#: The type of a robot's /clock (a robot on sim time).
CLOCK_MSGTYPE = "rosgraph_msgs/msg/Clock"
#: The nodes whose message counts the recorder takes (the sim or, against a robot, the bridge steps the episode).
ANNOUNCING_NODES = tuple(NODE_NAMES[role] for role in ("sim", "bridge", "policy", "executor"))


class MetricsNode(EpisodeNode):
    PUBLISHES_EPISODE = False  # it records the others' counts

    def __init__(self) -> None:
        super().__init__(NODE_NAMES["metrics"])
        self.declare_parameter("bag_path", "")
        self.declare_parameter("cameras", [""])
        self.declare_parameter("camera_size_px", self.cfg.camera_size_for(None))
        # Wall seconds without messages before the bag is closed when a node's message counts did not come.
        self.declare_parameter("quiet_period_s", 0.3)
        self.declare_parameter("policy_params_json", "{}")
        # Real time against a robot (the launcher sets them from the robot's YAML): what to record and score.
        for name, value in SIM_RECORDER_PARAMETERS.items():
            self.declare_parameter(name, value)
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
        self.realtime = cfg.clock == "realtime"
        self.topics = episode_topics(cfg, cameras)
        robot_topics: list[m.Topic] = []
        if self.realtime:  # no /clock: the counts instead, and the robot's own topics
            self.topics = [t for t in self.topics if t.name != m.CLOCK.name] + [m.REALTIME_STATS]
            robot_topics = [
                m.Topic(t["name"], t["type"]) for t in json.loads(self.get_parameter("robot_topics_json").value)
            ]
        self.robot_info = json.loads(self.get_parameter("robot_json").value)
        self.stepping_node: str | None = None  # the node that started the episode: the sim, or the bridge
        self.announced: dict[str, dict[str, int]] = {}  # node -> topic -> messages it published
        self.received: Counter[str] = Counter()  # topic -> messages received from the stack's nodes
        self.closing = False
        self.stats: dict[str, dict] = {}  # real time: node -> its counts
        self.terminal_at: float | None = None
        self.end_stamp_ns: int | None = None  # the terminal event's stamp
        self.robot_clock = any(t.msgtype == CLOCK_MSGTYPE for t in robot_topics)  # a robot on sim time
        self.last_clock_ns = -1  # its latest /clock recorded
        self.started_detail: dict = {}
        self.last_message = time.monotonic()
        self.terminal_seen = False
        self.last_tick = 0  # the last tick whose command was recorded
        self.sim_tick = 0  # the last tick whose state the sim published
        self.end_tick: int | None = None  # commands of this tick and later were never applied (terminal event)
        # (tick, topic, log ns, bytes) of commands, requests and chunks sent ahead, not yet known to take effect
        self.held: list[tuple[int, m.Topic, int, bytes]] = []
        self.warnings_written = 0
        self.warnings_suppressed = 0
        self.writer = EpisodeBagWriter(self.bag_path, self.topics + robot_topics)
        self.finished = False
        self.writer.set_run_metadata(self._run_metadata(self.versions))
        for topic in self.topics:
            record = self._recorder(topic)
            if topic.name in EXPECTED_SENDERS:  # only its stack nodes: others' are recorded as warnings
                sub = SenderSubscription(self, msg_class(topic.msgtype), topic.name, LOSSLESS_QOS, record)
            else:
                sub = self.create_subscription(msg_class(topic.msgtype), topic.name, record, LOSSLESS_QOS, raw=True)
            self._episode_entities.append(sub)
        self.robot_heard: set[str] = set()  # robot topics with a message received this episode
        if robot_topics:
            self.heard_pub = publisher(self, m.RECORDER_HEARS)
            self._episode_entities.append(self.heard_pub)
        for topic in robot_topics:
            sub = self.create_subscription(msg_class(topic.msgtype), topic.name, self._robot_recorder(topic), ROBOT_QOS,
                                           raw=True)  # fmt: skip
            self._episode_entities.append(sub)
        counts_sub = self.create_subscription(
            String, m.PUBLISHED_COUNTS.name, lambda msg: self.guarded("message counts", self.on_counts, msg),
            LOSSLESS_QOS,
        )  # fmt: skip
        self._episode_entities.append(counts_sub)
        self.episode_timer(0.1, self.finish_when_quiet)

    def deactivate(self) -> None:
        if not self.finished and not self.received and not getattr(self, "robot_heard", None):
            # Deactivated before any node published (another node refused to activate): no episode took place, so
            # no bag is left (an empty one would score as a stopped episode, an error of a run that never started).
            self.finished = True
            self.writer.close()
            shutil.rmtree(self.bag_path, ignore_errors=True)
            self.get_logger().info(f"no episode started: bag {self.bag_path} not kept")
            return
        if not self.finished:
            # Stopped before the episode ended: say so in the bag, so it scores as an error.
            t_ns = time.time_ns() if self.realtime else m.to_ns(sim_time_of_tick(self.last_tick))
            data = m.event_msg(t_ns, m.EventKind.STOPPED, self.last_tick, "recording stopped before the episode ended")
            self.writer.write(m.EPISODE_EVENTS, t_ns, data)
            self.finish()

    def _recorder(self, topic: m.Topic):
        checked = topic.name in EXPECTED_SENDERS

        def record(data: bytes, sender: str | None = None) -> None:
            if self.finished:
                return
            if checked and not expected_sender(self, topic.name, sender):
                self.on_rogue_message(topic, sender, data)
                return
            self.received[topic.name] += 1
            try:
                write(data, sender)
            finally:
                self.close_when_complete()  # (this may be the episode's last message, whatever became of it)

        def write(data: bytes, sender: str | None) -> None:
            try:
                log_ns = self._log_time_ns(topic, data)
                message = m.deserialize(data, topic.msgtype) if topic.name in _DECODED else None
            except Exception as exc:  # noqa: BLE001 - e.g. a chunk whose latency is no whole number of ticks
                self.get_logger().error(f"unusable message on {topic.name}: {exc}\n{traceback.format_exc()}")
                source = sender_text(sender) if checked else "its publisher"
                self.record_warning(
                    f"recorder: dropped a message on {topic.name} from {source} ({len(data)} bytes): "
                    f"{type(exc).__name__}: {exc}",
                    {"topic": topic.name},
                )
                return
            try:
                self.last_message = time.monotonic()
                if topic.name in _SENT_AHEAD and not self.realtime:
                    self.hold_until_applied(topic, tick_of_sim_time(log_ns / 1e9), log_ns, data)
                    return
                self.writer.write(topic, log_ns, data)
                if topic.name == m.EPISODE_EVENTS.name:
                    if message.kind == m.EventKind.STARTED and sender:
                        self.stepping_node = sender.rsplit("/", 1)[-1]
                    self.on_event(message)
                elif topic.name == m.COMMAND.name:  # (real time: recorded as it arrives)
                    self.last_tick = max(self.last_tick, message.tick)
                elif topic.name == m.REALTIME_STATS.name:
                    stats = json.loads(message.data)
                    self.stats[stats.get("node", "?")] = stats
                elif topic.name == m.JOINT_STATES.name and not self.realtime:
                    self.sim_reached(tick_of_sim_time(log_ns / 1e9))
            except Exception as exc:  # noqa: BLE001 - never out of the spin loop: the recorder must live
                self.get_logger().error(f"recording {topic.name} failed: {exc}\n{traceback.format_exc()}")
                self.record_warning(f"recorder: a message on {topic.name} failed: {type(exc).__name__}: {exc}")

        return record

    def _log_time_ns(self, topic: m.Topic, data: bytes) -> int:
        """Its stamp (lq_ros.recording.episode_bag.log_time_ns); a real-time message without one: receive time."""
        if self.realtime and not (topic.msgtype in _STAMPED_TYPES or topic.msgtype.startswith("lq_msgs/")):
            return time.time_ns()
        return log_time_ns(topic, data)

    def _robot_recorder(self, topic: m.Topic):
        """A robot's own topic: recorded at its stamps (or receive time); it never keeps the bag open."""

        def record(data: bytes) -> None:
            if self.finished:
                return
            if topic.name not in self.robot_heard:
                self.robot_heard.add(topic.name)
                self.heard_pub.publish(String(data=json.dumps({"topics": sorted(self.robot_heard)})))
            try:
                log_ns = self._log_time_ns(topic, data)
                self.writer.write(topic, log_ns, data)
            except Exception as exc:  # noqa: BLE001 - never out of the spin loop
                self.get_logger().error(f"recording {topic.name} failed: {exc}")
                self.record_warning(f"recorder: a message on {topic.name} failed: {type(exc).__name__}: {exc}")
                return
            if topic.msgtype == CLOCK_MSGTYPE:
                self.last_clock_ns = max(self.last_clock_ns, log_ns)
                self.close_when_complete()  # (the end's stamp may be covered now)

        return record

    def on_rogue_message(self, topic: m.Topic, sender: str | None, data: bytes) -> None:
        """Not recorded on its topic (it is not the episode's), but as a WARNING event saying what came from whom."""
        what = ""
        if topic.name == m.EPISODE_EVENTS.name:
            with contextlib.suppress(Exception):
                event = m.deserialize(data, topic.msgtype)
                what = f" ({m.EventKind.NAMES.get(event.kind, event.kind)} event, tick {event.tick})"
        elif topic.name == m.ACTION_CHUNK.name:
            with contextlib.suppress(Exception):
                what = f" (chunk for request {m.deserialize(data, topic.msgtype).request_id})"
        self.get_logger().warning(f"ignored a message on {topic.name} from {sender_text(sender)}{what}")
        self.record_warning(
            f"recorder: ignored a message on {topic.name} from {sender_text(sender)}{what}: only "
            f"{', '.join(EXPECTED_SENDERS[topic.name])} publish there",
            {"topic": topic.name, "sender": sender or ""},
        )

    def on_callback_error(self, reason: str) -> None:
        self.record_warning(f"recorder: {reason}")

    def record_warning(self, reason: str, detail: dict | None = None) -> None:
        """A WARNING event in the bag (at the last commanded tick), at most MAX_WARNING_EVENTS per episode."""
        if self.finished:
            return
        if self.warnings_written >= MAX_WARNING_EVENTS:
            self.warnings_suppressed += 1
            return
        self.warnings_written += 1
        t_ns = m.to_ns(sim_time_of_tick(self.last_tick))
        data = m.event_msg(t_ns, m.EventKind.WARNING, self.last_tick, reason, {"node": "recorder", **(detail or {})})
        try:
            self.writer.write(m.EPISODE_EVENTS, t_ns, data)
        except Exception as exc:  # noqa: BLE001
            self.get_logger().error(f"cannot record the warning {reason!r}: {exc}")

    # -- lockstep: what was sent ahead is recorded once its tick is stepped -----------------------------------
    def hold_until_applied(self, topic: m.Topic, tick: int, log_ns: int, data: bytes) -> None:
        """Record a command, observation request or chunk of ``tick`` (a chunk's: its due tick) once the sim has
        stepped that tick (its state of tick + 1 arrived).

        The executor sends commands and requests, and the policy its chunks, ahead of the sim; the episode may end
        (success, budget) before the sim reaches their tick. Those never took effect, and the bag records what
        happened, as the in-process transport does."""
        if self.end_tick is not None and tick >= self.end_tick:
            return
        if tick < self.sim_tick:
            self.write_held(tick, topic, log_ns, data)
        else:
            self.held.append((tick, topic, log_ns, data))

    def sim_reached(self, tick: int) -> None:
        """The sim's state of ``tick`` arrived: every tick before it was stepped."""
        self.sim_tick = max(self.sim_tick, tick)
        self.flush_held(self.sim_tick)

    def flush_held(self, before_tick: int) -> None:
        """Write what is held for ticks before ``before_tick`` (in the order it arrived); keep the rest."""
        keep = []
        for item in self.held:
            if item[0] < before_tick:
                self.write_held(*item)
            else:
                keep.append(item)
        self.held = keep

    def write_held(self, tick: int, topic: m.Topic, log_ns: int, data: bytes) -> None:
        self.writer.write(topic, log_ns, data)
        if topic.name == m.COMMAND.name:
            self.last_tick = max(self.last_tick, tick)

    def on_event(self, event) -> None:
        if event.kind == m.EventKind.STARTED:
            self.started_detail = json.loads(event.detail_json)
            self.writer.set_run_metadata(self._run_metadata(self._env_versions()))
        elif event.kind in m.EventKind.TERMINAL:
            self.terminal_seen = True
            self.terminal_at = self.terminal_at or time.monotonic()
            if self.end_stamp_ns is None:
                self.end_stamp_ns = m.stamp_ns(event)
            if self.realtime:
                return
            # SUCCESS and TIMEOUT at tick T come after the sim stepped T - 1: what was sent for T on never took
            # effect. An ERROR at T (e.g. the step of T failed) keeps that of T, as the in-process runner does.
            stepped = event.kind in (m.EventKind.SUCCESS, m.EventKind.TIMEOUT)
            self.end_tick = event.tick if stepped else event.tick + 1
            self.flush_held(self.end_tick)
            self.held = []

    # -- closing the bag -----------------------------------------------------------------------------------
    def on_counts(self, msg) -> None:
        """A node's message counts for the episode (it publishes nothing more of it)."""
        try:
            announced = json.loads(msg.data)
            node, counts = announced["node"], {str(k): int(v) for k, v in announced["counts"].items()}
        except (ValueError, KeyError, TypeError, AttributeError) as exc:
            self.record_warning(f"recorder: unusable message counts {msg.data[:200]!r}: {exc}")
            return
        if node in ANNOUNCING_NODES and node not in self.announced:
            self.announced[node] = counts
            self.close_when_complete()

    @property
    def counted_nodes(self) -> tuple[str, ...]:
        """The nodes whose message counts close the bag: policy, executor and the node that started the episode."""
        stepping = (self.stepping_node,) if self.stepping_node else ()
        return (NODE_NAMES["policy"], NODE_NAMES["executor"], *stepping)

    def missing(self) -> list[str]:
        """What the bag still lacks: nodes whose counts have not come, topics with fewer messages than counted."""
        lacking = [] if self.stepping_node else ["the STARTED event"]
        lacking += [f"{node}'s message counts" for node in self.counted_nodes if node not in self.announced]
        expected: Counter[str] = Counter()
        for counts in self.announced.values():
            expected.update(counts)
        lacking += [
            f"{t.name}: {self.received[t.name]} of {expected[t.name]} messages"
            for t in self.topics
            if self.received[t.name] < expected[t.name]
        ]
        return lacking

    def close_when_complete(self) -> None:
        """Once the episode has ended and every message of it has arrived, close the bag (in a timer callback:
        deactivating destroys the subscription this may be called from)."""
        if self.terminal_seen and not self.finished and not self.closing and not self.missing():
            if not self.clock_covered():
                return  # (the timer asks again)
            self.closing = True
            self.get_logger().info(f"every message of the episode arrived; counts: {json.dumps(self.announced)}")
            self.episode_timer(0.0, self.close_bag)

    def clock_covered(self) -> bool:
        """A robot on sim time: its recorded /clock reaches the end event's stamp, or CLOCK_COVER_WAIT_S has passed
        since the end (then a WARNING event says where the /clock stopped)."""
        if not self.robot_clock or self.end_stamp_ns is None or self.last_clock_ns >= self.end_stamp_ns:
            return True
        if time.monotonic() - self.terminal_at < CLOCK_COVER_WAIT_S:
            return False
        self.record_warning(
            f"recorder: the robot's /clock was recorded up to {self.last_clock_ns / 1e9:.3f} s, before the end "
            f"event's {self.end_stamp_ns / 1e9:.3f} s ({CLOCK_COVER_WAIT_S:g} s waited)"
        )
        self.robot_clock = False  # said once
        return True

    def finish_when_quiet(self) -> None:
        """A node's counts or messages did not come (it died): close once waited for and quiet, saying what lacks."""
        self.close_when_complete()  # (complete, but waiting for a robot's /clock to cover the end)
        if not self.terminal_seen or self.finished or self.closing:
            return
        now = time.monotonic()
        if now - self.terminal_at > COUNTS_WAIT_S and now - self.last_message > self.quiet_period_s:
            lacking = self.missing()
            if lacking:
                self.record_warning(f"recorder: closed the bag {COUNTS_WAIT_S:g} s after the episode's end without "
                                    f"{'; '.join(lacking)}")  # fmt: skip
            self.closing = True
            self.close_bag()

    def close_bag(self) -> None:
        if self.finished:
            return
        try:
            self.finish()
        finally:
            # The episode is recorded: leave the active state (the manager waits for this transition).
            self.trigger_deactivate()

    def _env_versions(self) -> dict:
        """The simulator's versions (from its STARTED event), with this node's rclpy."""
        env_versions = dict(self.started_detail.get("versions") or self.versions)
        env_versions["rclpy"] = self.versions["rclpy"]
        return env_versions

    def _run_metadata(self, env_versions: dict) -> dict:
        camera_size_px = self.get_parameter("camera_size_px").value if self.cameras else None
        meta = run_metadata(self.cfg, self.policy_params, "ros", env_versions, camera_size_px)
        if self.realtime:
            meta.update(clock="realtime", robot=self.robot_info, realtime=self.stats)
        return meta

    def finish(self) -> None:
        if self.warnings_suppressed:
            self.warnings_written = 0
            self.record_warning(f"recorder: {self.warnings_suppressed} more warnings of this episode not recorded")
        if self.end_tick is not None:  # what took effect but arrived after the sim's last state
            self.flush_held(self.end_tick)
        self.finished = True
        self.writer.set_run_metadata(self._run_metadata(self._env_versions()))
        self.writer.close()
        scoring = {
            "ee_topic": self.get_parameter("ee_topic").value,
            "joint_topic": self.get_parameter("joint_topic").value,
            "rate": self.get_parameter("trajectory_rate").value,
            "energy_rate": self.get_parameter("energy_rate").value,
        }
        try:
            row = score_bag(self.bag_path, **scoring)
        except Exception as exc:  # noqa: BLE001 - the bag is closed and kept; the launcher scores it again
            self.get_logger().error(f"scoring {self.bag_path} failed: {exc}\n{traceback.format_exc()}")
            return
        (self.bag_path / SCORE_FILE).write_text(to_json(row) + "\n")
        self.get_logger().info(f"episode {row['status']}; bag {self.bag_path}")


def main() -> None:
    run_managed(MetricsNode)


if __name__ == "__main__":
    main()
