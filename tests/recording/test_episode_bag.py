"""The episode bag writer: readable by rosbags, the mcap library and the scorer; crash-safe by construction.

SIGKILL of a real recorder mid-episode is tested on the four-node stack in tests/transport/ros/test_faults.py; here
the writer alone: what is on disk at every moment, a writer process killed at random moments, the
provisional and the final metadata.yaml, CRCs, reindex.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from lq_ros.core.executor_protocol import Command
from lq_ros.recording.bag_compare import bag_messages
from lq_ros.recording.episode_bag import FLUSH_SIM_NS, EpisodeBagWriter, read_run_metadata, reindex, scan_mcap
from lq_ros.scoring.bag_scorer import score_bag
from lq_ros.wire import messages as m

REPO = Path(__file__).resolve().parents[2]
TICK_NS = 50_000_000
T0_NS = 500_000_000
RUN_META = {"config": {"policy": "synthetic", "mode": "sync", "latency_s": 0.0, "suite": "libero_spatial", "task": 0,
                       "init": 0, "seed": 7}, "versions": {"git_commit": "abc"}}  # fmt: skip


def tick_messages(tick: int) -> list[tuple[m.Topic, int, bytes]]:
    """One control tick of an episode, as the transports record it."""
    t = T0_NS + tick * TICK_NS
    pos = [0.1 + 0.001 * tick, 0.0, 1.0]
    out = [
        (m.JOINT_STATES, t, m.joint_state_msg(t, np.zeros(7), np.full(7, 0.1), np.full(7, 2.0))),
        (m.EE_POSE, t, m.ee_pose_msg(t, pos, [0, 0, 0, 1])),
        (m.COMMAND, t, m.command_msg(t, Command(tick=tick, action=np.zeros(7), source=0, request_id=1, chunk_index=0))),
        (m.CLOCK, t, m.clock_msg(t)),
    ]
    if tick == 0:
        out.insert(0, (m.EPISODE_EVENTS, t, m.event_msg(t, m.EventKind.STARTED, 0)))
    return out


def write_episode(path: Path, ticks: int, end: bool = True) -> list[tuple[m.Topic, int, bytes]]:
    writer = EpisodeBagWriter(path, list(m.CORE_TOPICS))
    writer.set_run_metadata(RUN_META)
    written = []
    for tick in range(ticks):
        for item in tick_messages(tick):
            writer.write(*item)
            written.append(item)
    if end:
        t = T0_NS + (ticks - 1) * TICK_NS
        item = (m.EPISODE_EVENTS, t, m.event_msg(t, m.EventKind.SUCCESS, ticks - 1))
        writer.write(*item)
        written.append(item)
        writer.close()
    return written


def by_topic(items) -> dict[str, list[tuple[int, bytes]]]:
    out: dict[str, list] = {}
    for topic, t, data in items:
        name = topic if isinstance(topic, str) else topic.name
        out.setdefault(name, []).append((t, bytes(data)))
    return {k: sorted(v) for k, v in out.items()}


def test_closed_bag_is_a_rosbag2_mcap_bag_every_reader_agrees_on(tmp_path):
    written = write_episode(tmp_path / "ep", 120)
    bag = tmp_path / "ep"
    # rosbags' AnyReader (metadata.yaml + the MCAP summary) and a plain walk of the file agree with what was written.
    assert bag_messages(bag) == by_topic(written)
    (mcap,) = bag.glob("*.mcap")
    scan = scan_mcap(mcap, keep_messages=True)
    assert scan.complete and not scan.damage and by_topic(scan.messages) == by_topic(written)
    # The mcap library: ros2 profile, ros2msg schemas, cdr messages, zstd chunks, each with its CRC.
    from mcap.reader import make_reader
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader

    with mcap.open("rb") as f:
        reader = make_reader(f)
        header, summary = reader.get_header(), reader.get_summary()
    assert header.profile == "ros2"
    assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
    assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
    assert summary.statistics.message_count == len(written)
    with mcap.open("rb") as f:
        chunks = [r for r in StreamReader(f, emit_chunks=True).records if isinstance(r, Chunk)]
    assert len(chunks) == summary.statistics.chunk_count >= 120 * TICK_NS // FLUSH_SIM_NS
    assert all(c.compression == "zstd" and c.uncompressed_crc != 0 for c in chunks)
    # metadata.yaml: complete counts, the run metadata, closed.
    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    counts = {t["topic_metadata"]["name"]: t["message_count"] for t in info["topics_with_message_count"]}
    assert counts[m.EE_POSE.name] == 120 and counts[m.EPISODE_EVENTS.name] == 2 and counts[m.OBSERVATION.name] == 0
    assert info["message_count"] == len(written) and info["custom_data"]["lq_bag"] == "closed"
    assert info["starting_time"]["nanoseconds_since_epoch"] == T0_NS
    assert info["duration"]["nanoseconds"] == 119 * TICK_NS
    assert read_run_metadata(bag) == RUN_META
    row = score_bag(bag)
    assert row["status"] == "success" and row["partial"] is False and row["completion_steps"] == 119


def test_at_every_moment_the_file_holds_all_but_the_last_half_second(tmp_path):
    """What a SIGKILL would leave, checked after every message: the OS has everything older than 0.5 s."""
    bag = tmp_path / "ep"
    writer = EpisodeBagWriter(bag, list(m.CORE_TOPICS))
    (mcap,) = bag.glob("*.mcap")
    assert mcap.stat().st_size > 0  # the header is on disk from the start
    latest = 0
    for tick in range(60):
        for topic, t, data in tick_messages(tick):
            writer.write(topic, t, data)
            latest = max(latest, t)
            on_disk = scan_mcap(mcap, keep_messages=True)
            assert not on_disk.complete
            kept = {(tp, lt) for tp, lt, _ in on_disk.messages}
            # Everything logged more than FLUSH_SIM_NS before the newest message is readable...
            older = {(tp.name, lt) for tick_ in range(tick + 1) for tp, lt, _ in tick_messages(tick_)
                     if lt <= latest - FLUSH_SIM_NS}  # fmt: skip
            assert older <= kept, (tick, topic.name)
            # ... and an episode event the moment it is written.
            if topic == m.EPISODE_EVENTS:
                assert (topic.name, t) in kept
    writer.close()


_KILLED_WRITER = """
import sys, time
from pathlib import Path
from tests.recording.test_episode_bag import RUN_META, tick_messages
from lq_ros.wire import messages as m
from lq_ros.recording.episode_bag import EpisodeBagWriter

writer = EpisodeBagWriter(Path(sys.argv[1]), list(m.CORE_TOPICS))
writer.set_run_metadata(RUN_META)
for tick in range(10_000):
    for item in tick_messages(tick):
        writer.write(*item)
    print(tick, flush=True)
    time.sleep(0.002)
"""


@pytest.mark.parametrize("kill_after_ticks", [3, 41, 157])
def test_writer_killed_with_sigkill_loses_at_most_half_a_second(tmp_path, kill_after_ticks):
    bag = tmp_path / "ep"
    proc = subprocess.Popen([sys.executable, "-c", _KILLED_WRITER, str(bag)], cwd=REPO, stdout=subprocess.PIPE,
                            text=True)  # fmt: skip
    last = -1
    while last < kill_after_ticks:
        last = int(proc.stdout.readline())
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    last = max([last, *(int(line) for line in proc.stdout.read().split())])  # ticks written before the kill
    proc.stdout.close()
    (mcap,) = bag.glob("*.mcap")
    scan = scan_mcap(mcap, keep_messages=True)
    poses = [t for topic, t, _ in scan.messages if topic == m.EE_POSE.name]
    newest = T0_NS + last * TICK_NS
    assert not scan.complete
    assert (max(poses) if poses else T0_NS - TICK_NS) >= newest - FLUSH_SIM_NS - TICK_NS
    # The readable part is exactly the start of the episode.
    expected = by_topic(item for tick in range(last + 1) for item in tick_messages(tick))
    for topic, items in by_topic(scan.messages).items():
        assert items == expected[topic][: len(items)]
    # The provisional metadata.yaml names every topic and carries the run metadata: the scorer reads it.
    assert read_run_metadata(bag) == RUN_META
    row = score_bag(bag)
    assert row["partial"] is True and row["status"] == "error" and row["policy"] == "synthetic"
    # lq reindex counts what is readable.
    result = reindex(bag)
    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert result.messages == info["message_count"] == len(scan.messages) and not result.complete
    assert read_run_metadata(bag) == RUN_META


def test_provisional_metadata_exists_from_the_open_and_is_completed_at_close(tmp_path):
    bag = tmp_path / "ep"
    writer = EpisodeBagWriter(bag, [m.EE_POSE, m.EPISODE_EVENTS])
    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["custom_data"] == {"lq_bag": "recording"} and info["message_count"] == 0
    names = [t["topic_metadata"]["name"] for t in info["topics_with_message_count"]]
    assert names == ["/ee_pose", "/lq/episode_events"]
    writer.set_run_metadata(RUN_META)
    writer.add_topic(m.COMMAND)  # a topic added later is in the provisional metadata too
    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert read_run_metadata(bag) == RUN_META and len(info["topics_with_message_count"]) == 3
    writer.write(m.EE_POSE, T0_NS, m.ee_pose_msg(T0_NS, [0, 0, 1], [0, 0, 0, 1]))
    writer.close()
    writer.close()  # idempotent
    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["custom_data"]["lq_bag"] == "closed" and info["message_count"] == 1
    assert not list(bag.glob(".*.tmp"))


def test_reindex_of_a_complete_bag_reproduces_its_metadata(tmp_path):
    write_episode(tmp_path / "ep", 50)
    meta = tmp_path / "ep" / "metadata.yaml"
    closed = yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]
    result = reindex(tmp_path / "ep")
    rebuilt = yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]
    assert result.complete and not result.damage and result.messages == closed["message_count"]
    assert rebuilt["custom_data"].pop("lq_bag") == "reindexed"
    closed["custom_data"].pop("lq_bag")
    assert rebuilt == closed


def test_a_corrupt_chunk_is_caught_by_its_crc_and_reading_goes_on(tmp_path):
    write_episode(tmp_path / "ep", 100)
    (mcap,) = (tmp_path / "ep").glob("*.mcap")
    from mcap.reader import make_reader

    with mcap.open("rb") as f:
        chunk = make_reader(f).get_summary().chunk_indexes[3]
    raw = bytearray(mcap.read_bytes())
    # Flip a byte inside the chunk's compressed records (past its 9-byte record header and 44-byte chunk header).
    raw[chunk.chunk_start_offset + 9 + 44 + chunk.compressed_size // 2] ^= 0xFF
    mcap.write_bytes(bytes(raw))
    scan = scan_mcap(mcap, keep_messages=True)
    assert scan.complete and len(scan.damage) == 1 and f"chunk at byte {chunk.chunk_start_offset}" in scan.damage[0]
    row = score_bag(tmp_path / "ep")
    assert row["partial"] is True and any(f"chunk at byte {chunk.chunk_start_offset}" in w for w in row["warnings"])
    assert row["status"] == "success"  # the outcome is in a later, intact chunk


def test_physics_rate_topics_go_to_chunks_the_default_scoring_never_decompresses(tmp_path, monkeypatch):
    from mcap.reader import make_reader

    from lq_ros.recording import mcap_reader as mcap_stream

    writer = EpisodeBagWriter(tmp_path / "ep", [*m.CORE_TOPICS, m.JOINT_STATES_PHYSICS, m.EE_POSE_PHYSICS])
    writer.set_run_metadata(RUN_META)
    physics_written = 0
    for tick in range(60):
        for k in range(25):  # the tick's 25 physics substeps, then its control-rate messages
            t = T0_NS + tick * TICK_NS - (24 - k) * 2_000_000
            writer.write(m.JOINT_STATES_PHYSICS, t, m.joint_state_msg(t, [], np.full(7, 0.1), np.full(7, 2.0)))
            writer.write(m.EE_POSE_PHYSICS, t, m.ee_pose_msg(t, [0.1, 0.0, 1.0], [0, 0, 0, 1]))
            physics_written += 2
        for item in tick_messages(tick):
            writer.write(*item)
    t_end = T0_NS + 59 * TICK_NS
    writer.write(m.EPISODE_EVENTS, t_end, m.event_msg(t_end, m.EventKind.SUCCESS, 59))
    writer.close()
    (mcap,) = (tmp_path / "ep").glob("*.mcap")
    with mcap.open("rb") as f:
        summary = make_reader(f).get_summary()
    physics_ids = {cid for cid, c in summary.channels.items() if c.topic.endswith("_physics")}
    lanes = [set(index.message_index_offsets) for index in summary.chunk_indexes]
    assert all(ids <= physics_ids or not ids & physics_ids for ids in lanes), lanes
    physics_chunks = sum(ids <= physics_ids for ids in lanes)
    assert physics_chunks >= 5  # one per half second of sim time

    decompressed = []
    real_chunk_data = mcap_stream.StreamingMcapReader._chunk_data
    monkeypatch.setattr(
        mcap_stream.StreamingMcapReader, "_chunk_data",
        lambda self, at, record: decompressed.append(at) or real_chunk_data(self, at, record),
    )  # fmt: skip
    default = score_bag(tmp_path / "ep")
    assert len(decompressed) == len(lanes) - physics_chunks
    decompressed.clear()
    physics = score_bag(tmp_path / "ep", rate="physics", energy_rate="physics")
    assert len(decompressed) == len(lanes)
    assert default["status"] == physics["status"] == "success"
    assert physics["completion_steps"] == default["completion_steps"]
    from lq_ros.scoring.bag_scorer import read_episode

    assert len(read_episode(tmp_path / "ep", physics=True).joints_physics) == physics_written // 2


def test_an_existing_folder_is_never_overwritten(tmp_path):
    (tmp_path / "ep").mkdir()
    with pytest.raises(FileExistsError, match="already exists"):
        EpisodeBagWriter(tmp_path / "ep", [m.EE_POSE])


def test_writer_cost_per_tick_is_small(tmp_path):
    """Flushing every 0.5 s of sim time keeps the writer cheap (a 220-tick episode's messages)."""
    started = time.perf_counter()
    write_episode(tmp_path / "ep", 220)
    per_tick_ms = (time.perf_counter() - started) / 220 * 1e3
    assert per_tick_ms < 5.0, per_tick_ms
