"""rosbag2 (MCAP storage) episode bags for both transports: topics, run metadata, writer, sim-time log times."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

from lq_ros import messages as m
from lq_ros.suites import CONTROL_DT_S, latency_ticks

if TYPE_CHECKING:  # the scorer imports this module: keep it free of the run configuration's imports
    from lq_ros.config import RunConfig

#: Key of the run metadata (JSON) in metadata.yaml's custom_data.
RUN_METADATA_KEY = "lq_run"


def episode_topics(cfg: RunConfig, camera_names: tuple[str, ...]) -> list[m.Topic]:
    """Every topic an episode of ``cfg`` records (the same list for both transports)."""
    topics = list(m.CORE_TOPICS)
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
        "config": cfg.to_dict(),
        "config_key": cfg.key(),
        "camera_size_px": camera_size_px,
        "policy_params": policy_params,
        "transport": transport,
        "lockstep": True,
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


class EpisodeBagWriter:
    """Writes one episode to ``path`` (a new rosbag2 folder: metadata.yaml + .mcap)."""

    def __init__(self, path: Path, topics: list[m.Topic]) -> None:
        from rosbags.rosbag2 import StoragePlugin, Writer

        self.path = Path(path)
        if self.path.exists():
            raise FileExistsError(f"bag folder {self.path} already exists; choose a new output name")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._writer = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        self._writer.open()
        self._connections = {}
        for topic in topics:
            self.add_topic(topic)
        self.messages_written = 0

    def add_topic(self, topic: m.Topic) -> None:
        if topic.name not in self._connections:
            self._connections[topic.name] = self._writer.add_connection(
                topic.name, topic.msgtype, typestore=m.typestore()
            )

    def write(self, topic: m.Topic, log_ns: int, data: bytes) -> None:
        self._writer.write(self._connections[topic.name], log_ns, data)
        self.messages_written += 1

    def set_run_metadata(self, metadata: dict) -> None:
        self._writer.set_custom_data(RUN_METADATA_KEY, json.dumps(metadata, sort_keys=True, default=str))

    def close(self) -> None:
        self._writer.close()


def read_run_metadata(path: Path) -> dict:
    """Run metadata stored by EpisodeBagWriter ({} for bags from other tools)."""
    import yaml

    meta_file = Path(path) / "metadata.yaml"
    loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)  # libyaml: ~10x faster, matters when scoring many bags
    info = yaml.load(meta_file.read_text(), Loader=loader)["rosbag2_bagfile_information"]
    raw = (info.get("custom_data") or {}).get(RUN_METADATA_KEY)
    return json.loads(raw) if raw else {}
