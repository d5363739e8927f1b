"""rosbag2 (MCAP storage) episode bags for both transports: topics, run metadata, writer, sim-time log times.

The writer is crash-safe: a recorder killed with SIGKILL at any moment leaves a bag the scorer reads up
to the last 0.5 s of sim time (marked partial). The ``.mcap`` is written with the ``mcap`` library
(profile ``ros2``, schemas ``ros2msg``, messages ``cdr``, zstd chunks with CRCs); a chunk is written out
(to the OS, which keeps it after a SIGKILL) whenever it spans :data:`FLUSH_SIM_NS` of sim time, after
every episode event and when it reaches :data:`CHUNK_BYTES`. ``metadata.yaml`` exists from the moment
the bag is opened (provisional: every topic, the run metadata, no counts) and is completed at close;
:func:`reindex` rebuilds it from the ``.mcap`` of a bag whose recorder died (``lq reindex``).
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from lq_ros.core.redact import redact_args, redact_config
from lq_ros.core.suite_constants import CONTROL_DT_S, latency_ticks
from lq_ros.wire import messages as m

if TYPE_CHECKING:  # the scorer imports this module: keep it free of the run configuration's imports
    from lq_ros.core.run_config import RunConfig
    from lq_ros.recording.mcap_reader import TopicBudget

#: The largest metadata.yaml read, bytes (an episode's is a few kB).
MAX_METADATA_BYTES = 1 << 20
#: Key of the run metadata (JSON) in metadata.yaml's custom_data.
RUN_METADATA_KEY = "lq_run"
#: Key of the bag's state in metadata.yaml's custom_data: recording (provisional), closed, or reindexed.
BAG_STATE_KEY = "lq_bag"
#: A chunk is written out once it spans this much sim time (the most a SIGKILLed recorder loses).
FLUSH_SIM_NS = 500_000_000
#: ... or once it holds this many uncompressed bytes.
CHUNK_BYTES = 1 << 20
#: rosbag2 metadata format version written (the one rosbags and Jazzy's rosbag2 read).
ROSBAG2_VERSION = 9
ROS_DISTRO = "jazzy"


def episode_topics(cfg: RunConfig, camera_names: tuple[str, ...]) -> list[m.Topic]:
    """Every topic an episode of ``cfg`` records (the same list for both transports)."""
    topics = [*m.CORE_TOPICS, *m.TASK_TOPICS]
    if cfg.physics_rate:
        topics += [m.JOINT_STATES_PHYSICS, m.EE_POSE_PHYSICS]
    topics += [m.camera_topic(c) for c in camera_names]
    return topics


def run_metadata(
    cfg: RunConfig, policy_params: dict, transport: str, env_versions: dict, camera_size_px: int | None
) -> dict:
    """The run metadata stored in a bag (``set_run_metadata``): configuration, policy, transport, versions.

    ``camera_size_px``: the render size actually used (None: no camera rendered).
    """
    return {
        "config": redact_config(cfg.to_dict()),  # no secrets in results (lq_ros/core/redact.py)
        "config_key": cfg.key(),
        "camera_size_px": camera_size_px,
        "policy_params": redact_args(policy_params),
        "transport": transport,
        "lockstep": cfg.clock == "lockstep",
        # Real-time runs depend on wall-clock timing (lq_ros/transport/ros/wall_clock.py): never bit-identical
        # on a rerun.
        "bit_reproducible": cfg.clock == "lockstep",
        "latency_ticks": cfg.latency_ticks,
        "versions": env_versions,
    }


def log_time_ns(topic: m.Topic, data: bytes) -> int:
    """Sim time at which a serialized message takes effect, used as its bag log time.

    Using sim time (not receive time) makes a lockstep bag independent of scheduling. A chunk is
    logged at the tick it is applied (observation time + N ticks), the rest at their header stamp.
    Every LIBERO-LQ message starts with its stamp, so only chunks need decoding (not per tick).
    """
    if topic.msgtype == m.ACTION_CHUNK.msgtype:
        msg = m.deserialize(data, topic.msgtype)
        return m.stamp_ns(msg) + m.to_ns(latency_ticks(msg.injected_latency_s) * CONTROL_DT_S)
    return m.leading_stamp_ns(data)


# -- metadata.yaml ------------------------------------------------------------------------------------------


@dataclass
class _TopicStats:
    topic: m.Topic
    type_hash: str = ""
    count: int = 0


@dataclass
class _FileStats:
    """What metadata.yaml says about one .mcap file: per-topic counts and the log-time span."""

    name: str
    topics: dict[str, _TopicStats] = field(default_factory=dict)
    start_ns: int | None = None
    end_ns: int | None = None

    def add(self, topic: str, t_ns: int) -> None:
        self.topics[topic].count += 1
        self.start_ns = t_ns if self.start_ns is None else min(self.start_ns, t_ns)
        self.end_ns = t_ns if self.end_ns is None else max(self.end_ns, t_ns)

    @property
    def count(self) -> int:
        return sum(s.count for s in self.topics.values())


def _metadata_document(files: list[_FileStats], custom_data: dict[str, str]) -> dict:
    """rosbag2 metadata.yaml (version 9) as rosbags and rosbag2 read it."""
    start = min((f.start_ns for f in files if f.start_ns is not None), default=0)
    end = max((f.end_ns for f in files if f.end_ns is not None), default=start)
    topics: dict[str, _TopicStats] = {}
    for f in files:
        for name, stats in f.topics.items():
            merged = topics.setdefault(name, _TopicStats(stats.topic, stats.type_hash))
            merged.count += stats.count
    return {
        "rosbag2_bagfile_information": {
            "version": ROSBAG2_VERSION,
            "storage_identifier": "mcap",
            "relative_file_paths": [f.name for f in files],
            "duration": {"nanoseconds": end - start},
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": sum(f.count for f in files),
            "topics_with_message_count": [
                {
                    "topic_metadata": {
                        "name": s.topic.name,
                        "type": s.topic.msgtype,
                        "serialization_format": "cdr",
                        "offered_qos_profiles": [],
                        "type_description_hash": s.type_hash,
                    },
                    "message_count": s.count,
                }
                for s in topics.values()
            ],
            "compression_format": "",
            "compression_mode": "",
            "files": [
                {
                    "path": f.name,
                    "starting_time": {"nanoseconds_since_epoch": f.start_ns or 0},
                    "duration": {"nanoseconds": (f.end_ns or 0) - (f.start_ns or 0)},
                    "message_count": f.count,
                }
                for f in files
            ],
            "custom_data": dict(custom_data) or None,
            "ros_distro": ROS_DISTRO,
        }
    }


def _write_metadata(bag: Path, document: dict) -> None:
    """Replace metadata.yaml atomically (write + rename): a kill leaves the old or the new file, whole; never
    written through a link (``lq reindex`` writes into bag folders that may come from anyone)."""
    import yaml

    from lq_ros.core.safe_write import write_text

    dumper = getattr(yaml, "CSafeDumper", yaml.SafeDumper)
    text = yaml.dump(document, Dumper=dumper, sort_keys=False, default_flow_style=False, width=120)
    write_text(bag / "metadata.yaml", text)


# -- the writer ---------------------------------------------------------------------------------------------


#: Topics written to chunks of their own (lane name): 25x the control data, which the default scoring skips.
_PHYSICS_LANE_TOPICS = frozenset({m.JOINT_STATES_PHYSICS.name, m.EE_POSE_PHYSICS.name})
_IMAGE_TYPES = frozenset({"sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"})


def _chunk_lane(topic: m.Topic) -> str | None:
    if topic.name in _PHYSICS_LANE_TOPICS:
        return "physics"
    if topic.msgtype in _IMAGE_TYPES:
        return "images"
    return None


class EpisodeBagWriter:
    """Writes one episode to ``path`` (a new rosbag2 folder: metadata.yaml + .mcap), crash-safe.

    ``flush_sim_ns``: a chunk is written out once its messages span this much sim time (log time).
    """

    def __init__(
        self, path: Path, topics: Iterable[m.Topic], *, flush_sim_ns: int = FLUSH_SIM_NS, chunk_bytes: int = CHUNK_BYTES
    ) -> None:
        from mcap.writer import CompressionType, Writer

        self.path = Path(path)
        if self.path.exists():
            raise FileExistsError(f"bag folder {self.path} already exists; choose a new output name")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.path.mkdir()
        self.flush_sim_ns = flush_sim_ns
        self._stats = _FileStats(f"{self.path.name}.mcap")
        self._file = open(self.path / self._stats.name, "xb")  # noqa: SIM115 - closed in close()
        self._writer = Writer(
            self._file, chunk_size=chunk_bytes, compression=CompressionType.ZSTD, enable_crcs=True,
            enable_data_crcs=True,
        )  # fmt: skip
        self._writer.start(profile="ros2", library=_library())
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._custom: dict[str, str] = {BAG_STATE_KEY: "recording"}
        self._chunk_start_ns: int | None = None  # log-time watermark when the pending chunk got its first message
        # Bulky lanes (physics-rate topics, images) wait here and go to chunks of their own at each flush,
        # so a reader that wants only the control-rate topics skips their chunks undecompressed.
        self._lanes: dict[str, list[tuple[int, int, bytes]]] = {}
        self._watermark_ns = 0
        self.messages_written = 0
        self.closed = False
        for topic in topics:
            self.add_topic(topic, provisional=False)
        self._writer.flush()  # the header is on disk from the start: never a 0-byte file
        self._write_provisional()

    def add_topic(self, topic: m.Topic, provisional: bool = True) -> None:
        if topic.name in self._channels:
            return
        store = m.typestore()
        if topic.msgtype not in self._schemas:
            text, _ = store.generate_msgdef(topic.msgtype, ros_version=2)
            self._schemas[topic.msgtype] = self._writer.register_schema(
                name=topic.msgtype, encoding="ros2msg", data=text.encode()
            )
        self._channels[topic.name] = self._writer.register_channel(
            topic=topic.name, message_encoding="cdr", schema_id=self._schemas[topic.msgtype],
            metadata={"offered_qos_profiles": "[]"},
        )  # fmt: skip
        self._stats.topics[topic.name] = _TopicStats(topic, store.hash_rihs01(topic.msgtype))
        if provisional:
            self._write_provisional()

    def write(self, topic: m.Topic, log_ns: int, data: bytes) -> None:
        lane = _chunk_lane(topic)
        if lane is None:
            self._writer.add_message(self._channels[topic.name], log_time=log_ns, data=data, publish_time=log_ns)
        else:
            self._lanes.setdefault(lane, []).append((self._channels[topic.name], log_ns, data))
        self._stats.add(topic.name, log_ns)
        self.messages_written += 1
        self._watermark_ns = max(self._watermark_ns, log_ns)
        if self._chunk_start_ns is None:
            self._chunk_start_ns = self._watermark_ns
        if topic.name == m.EPISODE_EVENTS.name or self._watermark_ns - self._chunk_start_ns >= self.flush_sim_ns:
            self.flush()

    def flush(self) -> None:
        """Write the pending chunks out (to the OS: they survive a SIGKILL of this process)."""
        self._writer.flush()
        for lane in sorted(self._lanes):
            for channel_id, log_ns, data in self._lanes.pop(lane):
                self._writer.add_message(channel_id, log_time=log_ns, data=data, publish_time=log_ns)
            self._writer.flush()
        self._chunk_start_ns = None

    def set_run_metadata(self, metadata: dict) -> None:
        self._custom[RUN_METADATA_KEY] = json.dumps(metadata, sort_keys=True, default=str)
        if not self.closed:
            self._write_provisional()

    def _write_provisional(self) -> None:
        _write_metadata(self.path, _metadata_document([self._provisional_stats()], self._custom))

    def _provisional_stats(self) -> _FileStats:
        """Every topic, no counts: what is on disk is unknown until close (lq reindex counts it)."""
        stats = _FileStats(self._stats.name)
        stats.topics = {k: _TopicStats(s.topic, s.type_hash) for k, s in self._stats.topics.items()}
        return stats

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        self._custom[BAG_STATE_KEY] = "closed"
        document = _metadata_document([self._stats], self._custom)
        import yaml

        # Like rosbag2, the MCAP also carries the bag's metadata (for tools that read only the .mcap).
        self.flush()
        info = yaml.safe_dump(document["rosbag2_bagfile_information"], sort_keys=False)
        self._writer.add_metadata("rosbag2", {"serialized_metadata": info})
        self._writer.finish()
        self._file.close()
        _write_metadata(self.path, document)


def _library() -> str:
    from importlib import metadata

    def version(dist: str) -> str:
        try:
            return metadata.version(dist)
        except metadata.PackageNotFoundError:
            return "?"

    return f"lq_ros {version('lq_ros')}; mcap {version('mcap')}"


def read_run_metadata(path: Path) -> dict:
    """Run metadata stored by EpisodeBagWriter ({} for bags from other tools).

    Raises ValueError naming metadata.yaml when it is not a regular file (a directory, a FIFO: never
    opened), not a rosbag2 metadata file, or its run metadata is not a JSON object; OSError when unreadable.
    """
    raw = _custom_data(path).get(RUN_METADATA_KEY)
    if not raw:
        return {}
    where = Path(path) / "metadata.yaml"
    try:
        metadata = json.loads(raw)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{where}: custom_data {RUN_METADATA_KEY} is not JSON ({exc})") from None
    if not isinstance(metadata, dict):
        raise ValueError(f"{where}: custom_data {RUN_METADATA_KEY} is not a JSON object")
    return metadata


def _custom_data(path: Path) -> dict:
    import yaml

    from lq_ros.recording.mcap_reader import McapDamage, open_regular

    meta_file = Path(path) / "metadata.yaml"
    try:
        with open_regular(meta_file) as f:
            text = f.read(MAX_METADATA_BYTES + 1)  # bounded: a sparse 512 MiB file is not read whole
    except McapDamage as exc:  # a directory or a FIFO named metadata.yaml
        raise ValueError(str(exc).replace("not a bag file", "not a metadata file")) from None
    if len(text) > MAX_METADATA_BYTES:
        raise ValueError(f"{meta_file}: more than {MAX_METADATA_BYTES} bytes, not an episode's metadata file")
    loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)  # libyaml: ~10x faster, matters when scoring many bags
    try:
        document = yaml.load(text, Loader=loader)  # safe: a !!python tag is refused, never constructed
    except yaml.YAMLError as exc:
        raise ValueError(f"{meta_file}: not valid YAML ({' '.join(str(exc).split())})") from None
    info = document.get("rosbag2_bagfile_information") if isinstance(document, dict) else None
    if not isinstance(info, dict):
        raise ValueError(f"{meta_file}: not a rosbag2 metadata file (no rosbag2_bagfile_information mapping)")
    custom = info.get("custom_data") or {}
    if not isinstance(custom, dict):
        raise ValueError(f"{meta_file}: custom_data is not a mapping")
    return dict(custom)


# -- reindex: metadata.yaml rebuilt from the .mcap ----------------------------------------------------------


class BagRefused(ValueError):
    """A bag folder that cannot be reindexed as it is; the message names the file and the problem."""


@dataclass
class ReindexResult:
    bag: Path
    messages: int
    damage: list[str]
    #: False when a .mcap ended without its end records (a recorder that died).
    complete: bool


@dataclass
class McapScan:
    """Every readable message of one .mcap, in file order, and what was wrong with the file."""

    stats: _FileStats
    damage: list[str]
    complete: bool
    #: (topic, log time ns, CDR bytes), when asked for
    messages: list[tuple[str, int, bytes]] | None = None


def reindex(bag: Path, budget: TopicBudget | None = None) -> ReindexResult:
    """Rebuild ``bag/metadata.yaml`` from its ``.mcap`` files (like ``ros2 bag reindex``).

    Counts every readable message; a truncated file or a corrupt chunk is named in ``damage`` and what
    follows a truncation is not counted. The run metadata of an existing metadata.yaml is kept. The
    ``.mcap`` is not modified: the scorer still sees (and reports) its damage. ``budget``: the records the
    files of the bag may walk in all (``lq reindex`` passes lq_ros.scoring.read_budget.reindex_budget); beyond
    it the rest is damage, named. Raises FileNotFoundError
    for a folder without a .mcap and BagRefused for one holding something other than regular files
    (a FIFO would block the read forever; a metadata.yaml directory cannot be replaced).
    """
    from lq_ros.recording.mcap_reader import McapDamage, open_regular

    bag = Path(bag)
    if not bag.is_dir():
        raise BagRefused(f"{bag}: not a bag folder (a rosbag2 bag is a folder holding .mcap files)")
    files = sorted(bag.glob("*.mcap"))
    if not files:
        raise FileNotFoundError(f"{bag}: no .mcap file (not a rosbag2 MCAP bag folder)")
    meta_file = bag / "metadata.yaml"
    for file in [*files, meta_file] if meta_file.exists() else files:
        try:
            open_regular(file).close()
        except (McapDamage, OSError) as exc:
            raise BagRefused(str(exc) if isinstance(exc, McapDamage) else f"{file}: cannot read ({exc})") from None
    custom: dict[str, str] = {}
    if meta_file.exists():
        try:
            custom = _custom_data(bag)
        except (ValueError, OSError):  # an unreadable metadata.yaml is what reindex replaces
            custom = {}
    scans = [scan_mcap(file, budget=budget) for file in files]
    damage = [f"{file.name}: {d}" for file, scan in zip(files, scans) for d in scan.damage]
    complete = all(scan.complete for scan in scans)
    custom[BAG_STATE_KEY] = "reindexed" + (f" (damaged: {'; '.join(damage)})" if damage else "")
    _write_metadata(bag, _metadata_document([scan.stats for scan in scans], custom))
    return ReindexResult(bag, sum(scan.stats.count for scan in scans), damage, complete)


def scan_mcap(path: Path, keep_messages: bool = False, budget: TopicBudget | None = None) -> McapScan:
    """Walk one .mcap to its end or its damage: topics, counts, log-time span (and the messages).

    Streams the file with the scorer's reader (one chunk in memory at a time, every record walked);
    topics are listed in the order their channels are defined. A file that cannot be read from the start
    (not MCAP, not a regular file) is damage too. ``budget``: the records it may walk (shared by a bag's files).
    """
    from lq_ros.recording.mcap_reader import McapDamage, StreamingMcapReader

    path = Path(path)
    scan = McapScan(_FileStats(path.name), [], False, [] if keep_messages else None)
    reader = StreamingMcapReader(path, None, budget=budget)
    counts: dict[str, list[int]] = {}  # topic -> [count, first log time, last log time]
    try:
        for channel, log_ns, payload in reader.messages():
            seen = counts.get(channel.topic)
            if seen is None:
                counts[channel.topic] = [1, log_ns, log_ns]
            else:
                seen[0] += 1
                seen[1], seen[2] = min(seen[1], log_ns), max(seen[2], log_ns)
            if scan.messages is not None:
                scan.messages.append((channel.topic, log_ns, bytes(payload)))
    except McapDamage as exc:
        reader.damage.append(str(exc).removeprefix(f"{path}: "))
    except OSError as exc:
        reader.damage.append(f"cannot read: {exc}")
    store = m.typestore()
    for channel in reader.channels.values():
        if channel.topic in scan.stats.topics:
            continue
        known = channel.msgtype in store.types
        type_hash = store.hash_rihs01(channel.msgtype) if known else ""
        scan.stats.topics[channel.topic] = stats = _TopicStats(m.Topic(channel.topic, channel.msgtype), type_hash)
        count, first, last = counts.get(channel.topic, (0, None, None))
        stats.count = count
        if count:
            scan.stats.start_ns = first if scan.stats.start_ns is None else min(scan.stats.start_ns, first)
            scan.stats.end_ns = last if scan.stats.end_ns is None else max(scan.stats.end_ns, last)
    scan.damage, scan.complete = reader.damage, reader.complete
    return scan
