"""Small bags with large costs: what scoring a hostile bag may cost is proportional to what is decoded.

Each bag here is an intact episode bag from the project's writer with one hostile part (a few KB on disk): a
JointState whose name count is 0xFFFFFFFF in a 16 MiB message, a 64 MiB PoseStamped, a message index pointing
at one big message a thousand times, 65,535 channels over 2,000 chunks, a 512 MiB sparse metadata.yaml, a
chunk whose latency is inf or 1e308 or whose timing JSON is nested 200,000 deep, and a bag truncated while it is
read. Each is damage: named, skipped, the rest of the episode scored, in bounded time and memory; none kills the
scorer (a memory-mapped file cut under the reader raised SIGBUS).
"""

from __future__ import annotations

import json
import math
import re
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from lq_ros.recording.episode_bag import EpisodeBagWriter
from lq_ros.recording.mcap_reader import MAX_BULK_PAYLOAD_BYTES, StreamingMcapReader
from lq_ros.scoring.bag_scorer import read_episode, score_bag
from lq_ros.wire import messages as m
from tests.recording.test_hostile_bags import (
    MIB,
    N_TICKS,
    _record,
    chunk_record,
    insert_before_data_end,
    lq,
    mcap_of,
    replayable_bag,
)
from tests.scoring.test_bag_scorer import _stamp, write_with_mcap_library

REPO = Path(__file__).resolve().parents[2]
CDR_LE = b"\x00\x01\x00\x00"


def cdr_header(t_ns: int, frame_id: bytes = b"") -> bytes:
    """Encapsulation, stamp and a NUL-terminated frame id, padded to a 4-byte boundary (CDR offsets from byte 4)."""
    sec, nanosec = divmod(t_ns, 1_000_000_000)
    body = struct.pack("<iI", sec, nanosec) + struct.pack("<I", len(frame_id) + 1) + frame_id + b"\0"
    return CDR_LE + body + b"\0" * (-len(body) % 4)


@pytest.fixture(scope="module")
def intact(tmp_path_factory) -> dict:
    """What ``lq score`` costs on the intact bag: the baseline for wall time and memory."""
    bag = replayable_bag(tmp_path_factory.mktemp("intact") / "ep")
    result = lq("score", str(bag), "--json")
    assert result["returncode"] == 0, result["stderr"]
    return result


def scored_row(result: dict) -> dict:
    assert "Traceback" not in result["stderr"], result["stderr"][-3000:]
    return json.loads(result["stdout"].strip().splitlines()[-1])


def bad_joint_states(t_ns: int, n_bytes: int) -> bytes:
    """A JointState whose name count is 0xFFFFFFFF, zero-filled to ``n_bytes``."""
    payload = cdr_header(t_ns) + struct.pack("<I", 0xFFFFFFFF)
    return payload + bytes(n_bytes - len(payload))


def test_a_sequence_count_beyond_the_message_is_refused_at_once(tmp_path):
    """name count 0xFFFFFFFF: walked string by string, each 1 MB message took about a second (twice: in bulk, then
    alone); a count that cannot fit in the rest of its message is refused before the walk."""
    writer = EpisodeBagWriter(tmp_path / "ep", list(m.CORE_TOPICS))
    writer.write(m.EPISODE_EVENTS, _stamp(0), m.event_msg(_stamp(0), m.EventKind.STARTED, 0))
    for i in range(N_TICKS):
        t_ns = _stamp(i)
        writer.write(m.EE_POSE, t_ns, m.ee_pose_msg(t_ns, [0.1, 0.0, 1.0], [0, 0, 0, 1]))
        writer.write(m.JOINT_STATES, t_ns, m.joint_state_msg(t_ns, np.zeros(7), np.full(7, 0.1), np.full(7, 2.0)))
        if i % 2:
            writer.write(m.JOINT_STATES, t_ns, bad_joint_states(t_ns, 1_000_000))
    writer.write(m.EPISODE_EVENTS, _stamp(N_TICKS - 1), m.event_msg(_stamp(N_TICKS - 1), m.EventKind.SUCCESS, 39))
    writer.close()
    bag = tmp_path / "ep"
    assert mcap_of(bag).stat().st_size < 256 * 1024
    started = time.monotonic()
    data = read_episode(bag)
    assert time.monotonic() - started < 3.0
    assert data.damaged and len(data.ee) == N_TICKS and len(data.joints) == N_TICKS
    # Named per decoded block of the topic (4 MiB each): every bad message counted once, the cause named.
    pattern = r"(\d+) undecodable /joint_states messages? skipped \(string sequence of 4294967295"
    counts = re.findall(pattern, data.warnings[0])
    assert sum(map(int, counts)) == N_TICKS // 2, data.warnings


def test_a_message_too_big_for_its_type_is_skipped_unread(tmp_path):
    """A 16 MiB JointState: more than any joint state holds; skipped before it is copied or walked."""
    bag = replayable_bag(tmp_path / "ep", extra=(m.JOINT_STATES, 10, bad_joint_states(_stamp(10), 16 * MIB)))
    assert mcap_of(bag).stat().st_size < 64 * 1024
    started = time.monotonic()
    data = read_episode(bag)
    assert time.monotonic() - started < 3.0
    assert data.damaged and len(data.ee) == N_TICKS and len(data.joints) == N_TICKS
    says = f"1 /joint_states message larger than the {MAX_BULK_PAYLOAD_BYTES} bytes a sensor_msgs/msg/JointState"
    assert any(says in w for w in data.warnings), data.warnings


def test_a_huge_bulk_message_is_skipped_before_it_is_copied(tmp_path, intact):
    """One 64 MiB PoseStamped (a 2 KB bag) took 1.24 GB to score: index arrays 17x the chunk."""
    big = cdr_header(_stamp(10), bytes(64 * MIB))
    big += np.zeros(7).tobytes()  # position and orientation
    bag = replayable_bag(tmp_path / "ep", extra=(m.EE_POSE, 10, big))
    assert mcap_of(bag).stat().st_size < 64 * 1024
    result = lq("score", str(bag), "--json")
    row = scored_row(result)
    assert result["returncode"] == 1 and row["status"] == "success" and row["partial"] is True
    says = f"larger than the {MAX_BULK_PAYLOAD_BYTES} bytes a geometry_msgs/msg/PoseStamped may have; skipped"
    assert any(says in w for w in row["warnings"]), row["warnings"]
    # The chunk is decompressed (64 MiB, its CRC checked), nothing more.
    assert result["rss_mb"] < intact["rss_mb"] + 112, (result["rss_mb"], intact["rss_mb"])


def events_channel_id(bag: Path) -> int:
    reader = StreamingMcapReader(mcap_of(bag), None)
    for _ in reader.messages():
        pass
    return next(c.id for c in reader.channels.values() if c.topic == m.EPISODE_EVENTS.name)


def message_record(channel_id: int, t_ns: int, payload: bytes) -> bytes:
    return _record(0x05, struct.pack("<HIQQ", channel_id, 0, t_ns, t_ns) + payload)


def message_index(channel_id: int, entries: list[tuple[int, int]]) -> bytes:
    body = b"".join(struct.pack("<QQ", t, off) for t, off in entries)
    return _record(0x07, struct.pack("<HI", channel_id, len(body)) + body)


def test_a_message_index_naming_one_message_a_thousand_times_is_not_believed(tmp_path):
    """The index is the file's word, not the chunk's: entries that overlap are damage, the records are walked."""
    bag = replayable_bag(tmp_path / "ep")
    cid = events_channel_id(bag)
    import zstandard

    payload = cdr_header(_stamp(5)) + bytes(4 * MIB)  # an undecodable event of 4 MiB
    records = message_record(cid, _stamp(5), payload)
    chunk = chunk_record("zstd", zstandard.ZstdCompressor().compress(records), len(records))
    insert_before_data_end(bag, chunk + message_index(cid, [(_stamp(5), 0)] * 1000))
    started = time.monotonic()
    data = read_episode(bag)
    assert time.monotonic() - started < 5.0  # copying the message once per entry: 4 GB
    assert data.damaged and [e[0] for e in data.events] == [m.EventKind.STARTED, m.EventKind.SUCCESS]
    assert any("message index of the chunk" in w and "records walked instead" in w for w in data.warnings)
    assert any("1 undecodable /lq/episode_events message skipped" in w for w in data.warnings), data.warnings


def test_many_channels_over_many_chunks_cost_what_they_hold(tmp_path):
    """65,535 channels and 2,000 chunks: the set of every known topic was rebuilt per chunk (21 s)."""
    bag = replayable_bag(tmp_path / "ep")
    channels = b"".join(
        _record(0x04, struct.pack("<HH", cid, 0) + _len(f"/c{cid}".encode()) + _len(b"cdr") + b"\0" * 4)
        for cid in range(1000, 1000 + 64535)
    )
    records = message_record(1000, _stamp(3), CDR_LE + bytes(12))
    one_chunk = chunk_record("", records, len(records)) + message_index(1000, [(_stamp(3), 0)])
    insert_before_data_end(bag, channels + one_chunk * 2000)
    started = time.monotonic()
    data = read_episode(bag)
    assert time.monotonic() - started < 5.0
    assert not data.damaged and len(data.ee) == N_TICKS, data.warnings


def _len(text: bytes) -> bytes:
    return struct.pack("<I", len(text)) + text


def test_a_sparse_huge_metadata_file_is_not_read_whole(tmp_path, intact):
    """A 512 MiB sparse metadata.yaml was read whole (633 MB): only its first MAX_METADATA_BYTES are looked at."""
    from lq_ros.recording.episode_bag import MAX_METADATA_BYTES

    bag = replayable_bag(tmp_path / "ep")
    with (bag / "metadata.yaml").open("r+b") as f:
        f.truncate(512 * MIB)
    result = lq("score", str(bag), "--json")
    row = scored_row(result)
    assert row["status"] == "success", row
    assert any(f"more than {MAX_METADATA_BYTES} bytes" in w for w in row["warnings"]), row["warnings"]
    assert result["rss_mb"] < intact["rss_mb"] + 32, (result["rss_mb"], intact["rss_mb"])


def chunk_bag(path: Path, injected_latency_s: float = 0.0, timing_json: str | None = None) -> Path:
    """An episode bag written by the mcap library (as another tool would: the project's writer refuses to log a
    chunk at an impossible time) with one ActionChunk of the given fields."""
    from lq_ros.core.executor_protocol import Command

    def event(i: int, kind: int) -> tuple:
        return (m.EPISODE_EVENTS.name, m.EPISODE_EVENTS.msgtype, _stamp(i), m.event_msg(_stamp(i), kind, i))

    messages = [event(0, m.EventKind.STARTED)]
    for i in range(N_TICKS):
        t_ns = _stamp(i)
        messages += [
            (m.EE_POSE.name, m.EE_POSE.msgtype, t_ns, m.ee_pose_msg(t_ns, [0.1, 0.0, 1.0 + 1e-3 * i], [0, 0, 0, 1])),
            (m.COMMAND.name, m.COMMAND.msgtype, t_ns, m.command_msg(t_ns, Command(i, np.zeros(7), 0, 1, 0))),
        ]
    chunk = m.chunk_msg(_stamp(4), 1, 4, injected_latency_s, 0.01, np.zeros((2, 7)), "synthetic")
    if timing_json is not None:
        msg = m.deserialize(chunk, m.ACTION_CHUNK.msgtype)
        msg.timing_json = timing_json
        chunk = m.serialize(msg, m.ACTION_CHUNK.msgtype)
    messages += [
        (m.ACTION_CHUNK.name, m.ACTION_CHUNK.msgtype, _stamp(4), chunk),
        event(N_TICKS - 1, m.EventKind.SUCCESS),
    ]
    return write_with_mcap_library(path, sorted(messages, key=lambda item: item[2]))


@pytest.mark.parametrize(
    "fields",
    [
        {"injected_latency_s": math.inf},
        {"injected_latency_s": 1e308},
        {"injected_latency_s": -0.05},
        {"timing_json": "[" * 200_000 + "]" * 200_000},
    ],
    ids=["latency inf", "latency 1e308", "latency negative", "timing 200k deep"],
)
def test_an_impossible_chunk_is_skipped_as_damage_the_rest_scored(tmp_path, fields):
    bag = chunk_bag(tmp_path / "ep", **fields)
    row = score_bag(bag)
    assert row["status"] == "success" and row["partial"] is True, row
    assert any("1 undecodable /lq/action_chunk message skipped" in w for w in row["warnings"]), row["warnings"]


_TRUNCATE_WHILE_READING = """
import sys
from pathlib import Path
from lq_ros.recording.mcap_reader import MAX_BULK_PAYLOAD_BYTES, StreamingMcapReader
path = Path(sys.argv[1])
reader = StreamingMcapReader(path, None)
seen = 0
for batch in reader.batches():
    seen += len(batch)
    if seen >= 10 and path.stat().st_size > 1 << 20:
        with path.open("r+b") as f:
            f.truncate(path.stat().st_size // 2)
print(seen)
print("\\n".join(reader.damage))
"""


def test_a_bag_cut_while_it_is_read_is_damage_not_sigbus(tmp_path):
    rng = np.random.default_rng(0)
    blobs = [("/blob", "std_msgs/msg/String", _stamp(i), rng.bytes(256 * 1024)) for i in range(64)]  # incompressible
    bag = write_with_mcap_library(tmp_path / "big", blobs, chunk_size=512 * 1024, compression="NONE")
    done = subprocess.run(
        [sys.executable, "-c", _TRUNCATE_WHILE_READING, str(mcap_of(bag))], cwd=REPO, capture_output=True, text=True,
        timeout=120,
    )  # fmt: skip
    assert done.returncode == 0, (done.returncode, done.stderr[-2000:])  # -7: SIGBUS
    seen, *damage = done.stdout.strip().splitlines()
    assert 10 <= int(seen) < 64 and len(damage) == 1 and "truncated" in damage[0], done.stdout
