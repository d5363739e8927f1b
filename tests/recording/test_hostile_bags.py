"""Hostile and broken bags: decompression bombs, FIFOs, malformed records and metadata, undecodable messages.

Every bag starts as a real episode bag from the project's writer and is then patched on disk: a crafted
chunk inserted before the data end record, a record rewritten, metadata.yaml replaced. The real ``lq``
command line reads it in a subprocess, as a user would: the answer is one line naming the problem (exit 2
for input that is not a bag, exit 1 with the damage named for a damaged bag), never a traceback or a hang,
in bounded time and memory.
"""

from __future__ import annotations

import functools
import json
import os
import struct
import subprocess
import sys
import time
import zlib
from pathlib import Path

import numpy as np
import pytest
import yaml

from lq_ros.recording.episode_bag import EpisodeBagWriter, reindex, scan_mcap
from lq_ros.recording.mcap_reader import MAX_CHUNK_BYTES, StreamingMcapReader
from lq_ros.scoring.bag_scorer import read_episode, score_bag
from lq_ros.wire import messages as m
from tests.scoring.test_bag_scorer import _offset_of_first, _stamp, write_episode_bag

REPO = Path(__file__).resolve().parents[2]
MIB = 1 << 20
N_TICKS = 40
#: Run a command and report its exit code, output, wall time and peak RSS (the wrapper's only child).
_MEASURE = """
import json, resource, subprocess, sys, time
started = time.monotonic()
result = subprocess.run(sys.argv[1:], capture_output=True, text=True, timeout=120)
print(json.dumps({"returncode": result.returncode, "stdout": result.stdout, "stderr": result.stderr,
                  "wall_s": time.monotonic() - started,
                  "rss_mb": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024}))
"""


def lq(*args: str, timeout: float = 120) -> dict:
    """``lq ARGS`` in a subprocess: returncode, stdout, stderr, wall_s, rss_mb (its peak resident memory)."""
    cmd = [sys.executable, "-c", _MEASURE, sys.executable, "-m", "lq_ros.cli", *args]
    done = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=timeout, check=True)
    return json.loads(done.stdout)


def one_line(result: dict, returncode: int, *expected: str) -> str:
    """The only line on stderr, with the exit code and every expected piece, and no traceback."""
    lines = result["stderr"].strip().splitlines()
    assert result["returncode"] == returncode, (result["returncode"], result["stderr"][-2000:])
    assert "Traceback" not in result["stdout"] + result["stderr"]
    assert len(lines) == 1, result["stderr"]
    for piece in expected:
        assert piece in lines[0], (piece, lines[0])
    return lines[0]


def mcap_of(bag: Path) -> Path:
    return next(bag.glob("*.mcap"))


def insert_before_data_end(bag: Path, record: bytes) -> int:
    """Put ``record`` into the bag's .mcap right before its data end record; its byte offset."""
    mcap = mcap_of(bag)
    raw = mcap.read_bytes()
    at = _offset_of_first(raw, {0x0F})
    mcap.write_bytes(raw[:at] + record + raw[at:])
    return at


def chunk_record(compression: str, compressed: bytes, raw_size: int, crc: int = 0) -> bytes:
    """An MCAP chunk record (opcode 0x06) with whatever header values a hostile file may carry."""
    name = compression.encode()
    body = struct.pack("<QQQI", 0, 0, raw_size, crc) + struct.pack("<I", len(name)) + name
    body += struct.pack("<Q", len(compressed)) + compressed
    return struct.pack("<BQ", 0x06, len(body)) + body


@functools.cache
def zstd_zeros(n: int) -> bytes:
    """A zstd frame of ``n`` zero bytes (its header carries the content size), compressed in 1 MiB steps."""
    import zstandard

    compressor = zstandard.ZstdCompressor().compressobj(size=n)
    block = bytes(MIB)
    return b"".join([*(compressor.compress(block) for _ in range(n // MIB)), compressor.flush()])


@functools.cache
def lz4_zeros(n: int) -> bytes:
    """An lz4 frame of ``n`` zero bytes, compressed in 1 MiB steps."""
    import lz4.frame

    compressor = lz4.frame.LZ4FrameCompressor()
    block = bytes(MIB)
    return b"".join([compressor.begin(), *(compressor.compress(block) for _ in range(n // MIB)), compressor.flush()])


@pytest.fixture(scope="module")
def intact(tmp_path_factory) -> dict[str, dict]:
    """What ``lq score`` and ``lq reindex`` cost on an intact bag of the same size: the memory baseline."""
    bag = write_episode_bag(tmp_path_factory.mktemp("intact") / "ep", n_ticks=N_TICKS)
    score, again = lq("score", str(bag), "--json"), lq("reindex", str(bag))
    assert score["returncode"] == 0 and again["returncode"] == 0, (score["stderr"], again["stderr"])
    return {"score": score, "reindex": again}


# -- 4. decompression bombs ----------------------------------------------------------------------------------

#: name -> (compression, compressed bytes, declared uncompressed size, CRC, what the damage line says).
BOMBS = {
    # 200 MiB of zeros from a 6 KB chunk: stopped after its first 8 MiB step, at the first record header.
    "zstd zeros, 200 MiB declared": (
        "zstd", lambda: zstd_zeros(200 * MIB), 200 * MIB, 0,
        "invalid record header (opcode 0x00, length 0) at chunk offset 0; chunk skipped",
    ),
    # A chunk small enough to decompress in one call, with a valid CRC: the record walk stops at once.
    "zstd zeros, 6 MiB declared, valid CRC": (
        "zstd", lambda: zstd_zeros(6 * MIB), 6 * MIB, zlib.crc32(bytes(6 * MIB)),
        "invalid record header (opcode 0x00, length 0) at chunk offset 0; the rest of the chunk skipped",
    ),
    "lz4 zeros, 200 MiB declared": (
        "lz4", lambda: lz4_zeros(200 * MIB), 200 * MIB, 0,
        "invalid record header (opcode 0x00, length 0) at chunk offset 0; chunk skipped",
    ),
    # lz4 has no size in its frame: 256 MiB come out of 1 MB unless the read stops at the declared size.
    "lz4 zeros, 256 MiB behind 1 MiB declared": (
        "lz4", lambda: lz4_zeros(256 * MIB), MIB, 0, f"decompresses to more than the {MIB} bytes its header declares",
    ),
    "1 TiB declared": (
        "zstd", lambda: zstd_zeros(MIB), 1 << 40, 0,
        f"declares {1 << 40} bytes uncompressed, more than the {MAX_CHUNK_BYTES >> 20} MiB a chunk may hold",
    ),
}  # fmt: skip


def bomb_bag(path: Path, name: str) -> tuple[Path, str]:
    """An intact episode bag with the named bomb chunk before its data end; (bag, expected damage line)."""
    compression, payload, declared, crc, says = BOMBS[name]
    bag = write_episode_bag(path, n_ticks=N_TICKS)
    at = insert_before_data_end(bag, chunk_record(compression, payload(), declared, crc))
    return bag, f"chunk at byte {at}: {says}"


@pytest.mark.parametrize("name", list(BOMBS))
def test_a_decompression_bomb_is_damage_read_in_bounded_time(tmp_path, name):
    bag, expected = bomb_bag(tmp_path / "ep", name)
    started = time.monotonic()
    data = read_episode(bag)
    assert time.monotonic() - started < 3.0  # walking zeros as 9-byte records took seconds per 100 MiB
    assert data.damaged and any(expected in w for w in data.warnings), data.warnings
    # Everything else of the bag is read: the episode and its outcome are intact.
    assert len(data.ee) == N_TICKS and [e[0] for e in data.events] == [m.EventKind.STARTED, m.EventKind.SUCCESS]
    scan = scan_mcap(mcap_of(bag))
    assert scan.complete and len(scan.damage) == 1 and expected in scan.damage[0]
    assert scan.stats.count == 3 * N_TICKS + 2


@pytest.mark.parametrize("command", ["score", "reindex"])
@pytest.mark.parametrize("name", ["zstd zeros, 200 MiB declared", "lz4 zeros, 256 MiB behind 1 MiB declared"])
def test_lq_on_a_bomb_names_it_in_bounded_time_and_memory(tmp_path, intact, command, name):
    bag, expected = bomb_bag(tmp_path / "ep", name)
    result = lq(command, str(bag), *(["--json"] if command == "score" else []))
    assert result["returncode"] == 1, result["stderr"]  # damaged: reported through the exit code
    assert "Traceback" not in result["stderr"] and expected in result["stderr"], result["stderr"]
    if command == "score":
        row = json.loads(result["stdout"].strip().splitlines()[-1])
        assert row["status"] == "success" and row["partial"] is True
        assert any(expected in w for w in row["warnings"])
    else:
        info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        assert info["message_count"] == 3 * N_TICKS + 2 and expected in info["custom_data"]["lq_bag"]
    # A bomb costs at most a decompression step more than an intact bag (it took 263 MB to 2 GB more).
    assert result["rss_mb"] < intact[command]["rss_mb"] + 48, (result["rss_mb"], intact[command]["rss_mb"])
    assert result["wall_s"] < intact[command]["wall_s"] + 10


def test_a_zero_filled_file_tail_ends_the_read_at_once(tmp_path):
    """A crash can leave a preallocated, zero-filled tail: one damage line, not millions of empty records."""
    bag = write_episode_bag(tmp_path / "ep", n_ticks=N_TICKS)
    mcap = mcap_of(bag)
    raw = mcap.read_bytes()
    end = _offset_of_first(raw, {0x0F})
    with mcap.open("r+b") as f:
        f.truncate(end)
        f.seek(0, os.SEEK_END)
        f.write(bytes(64 * MIB))
    started = time.monotonic()
    scan = scan_mcap(mcap)
    data = read_episode(bag)
    assert time.monotonic() - started < 3.0
    line = f"invalid record header (opcode 0x00, length 0) at byte {end}: the rest of the file is unreadable"
    assert scan.damage == [line] and not scan.complete and scan.stats.count == 3 * N_TICKS + 2
    assert data.damaged and line in data.warnings[0] and len(data.ee) == N_TICKS


def test_reindex_streams_the_file(tmp_path, intact):
    """``lq reindex`` holds one chunk at a time, never the whole file nor a list of every record."""
    from tests.scoring.test_bag_scorer import write_with_mcap_library

    rng = np.random.default_rng(0)
    blobs = [("/blob", "std_msgs/msg/String", _stamp(i), rng.bytes(MIB)) for i in range(80)]  # incompressible
    bag = write_with_mcap_library(tmp_path / "big", blobs, chunk_size=MIB, compression="NONE")
    assert mcap_of(bag).stat().st_size > 80 * MIB
    result = lq("reindex", str(bag))
    assert result["returncode"] == 0, result["stderr"]
    assert f"{bag}: 80 messages (complete)" in result["stderr"]
    assert result["rss_mb"] < intact["reindex"]["rss_mb"] + 32, (result["rss_mb"], intact["reindex"]["rss_mb"])


def test_reindex_of_a_flood_of_tiny_records_stops_at_the_read_budget(tmp_path):
    """A chunk of 4,000,000 empty messages (a 20 KB chunk) after a LIBERO-Spatial episode: ``lq reindex`` walked
    every record (about 20 s) and called the bag complete; it walks what the scorer's budget allows for a 220-tick
    episode, counts the episode's messages, and names the rest as damage (exit 1)."""
    import zstandard

    from lq_ros.scoring.read_budget import RECORDS_PER_TICK, SLACK_TICKS

    bag = write_episode_bag(tmp_path / "ep", n_ticks=N_TICKS, config={"suite": "libero_spatial"})
    records = (struct.pack("<BQ", 0x05, 26) + struct.pack("<HIQQ", 999, 0, 0, 0) + bytes(4)) * 4_000_000
    insert_before_data_end(bag, chunk_record("zstd", zstandard.ZstdCompressor().compress(records), len(records)))
    assert mcap_of(bag).stat().st_size < 60_000
    result = lq("reindex", str(bag))
    walked = (
        f"more than the {RECORDS_PER_TICK * (220 + SLACK_TICKS)} records that an episode of at most 220 ticks (its "
        "step budget) may hold walked one by one (every record of every chunk, to count them)"
    )
    line = one_line(result, 1, f"{bag}: ", walked)
    assert int(line.split(": ")[1].split()[0]) >= 3 * N_TICKS + 2  # the episode's messages, counted before the flood
    assert result["wall_s"] < 15, result["wall_s"]
    rebuilt = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert walked in rebuilt["custom_data"]["lq_bag"] and rebuilt["custom_data"]["lq_run"]  # run metadata kept


# -- 5. FIFOs: only regular files are bags -------------------------------------------------------------------


def test_a_fifo_named_like_a_bag_is_refused_never_opened(tmp_path):
    fifo = tmp_path / "x.mcap"
    os.mkfifo(fifo)
    one_line(lq("score", str(fifo), timeout=60), 2, str(fifo), "FIFO")
    folder = tmp_path / "bag"
    folder.mkdir()
    os.mkfifo(folder / "x.mcap")
    # In a bag folder: an error row naming it (a directory of bags keeps its other rows), exit 1.
    scored = lq("score", str(folder), "--json", timeout=60)
    assert scored["returncode"] == 1 and "Traceback" not in scored["stderr"], scored["stderr"]
    row = json.loads(scored["stdout"].strip().splitlines()[-1])
    assert row["status"] == "error" and f"{folder / 'x.mcap'}: a FIFO, not a bag file" in row["error_reason"]
    one_line(lq("reindex", str(folder), timeout=60), 2, f"{folder / 'x.mcap'}: a FIFO")
    one_line(lq("replay", str(folder), timeout=60), 2, "cannot replay", f"{folder / 'x.mcap'}: a FIFO")
    assert not (folder / "metadata.yaml").exists()  # reindex wrote nothing


# -- 10. malformed records and metadata: one line, never a traceback -----------------------------------------

#: Run metadata that passes replay's checks, so its refusal names the bag's damage.
REPLAYABLE = {
    "config": {"policy": "synthetic", "mode": "sync", "latency_s": 0.0, "suite": "libero_spatial", "task": 0,
               "init": 0, "seed": 7},
    "transport": "inprocess", "lockstep": True, "versions": {"git_commit": "abc"},
}  # fmt: skip


def replayable_bag(path: Path, extra: tuple | None = None) -> Path:
    """An episode bag whose metadata replay accepts; ``extra`` (topic, tick, payload) is written mid-episode."""
    from lq_ros.core.executor_protocol import Command

    writer = EpisodeBagWriter(path, list(m.CORE_TOPICS))
    writer.set_run_metadata(REPLAYABLE)
    writer.write(m.EPISODE_EVENTS, _stamp(0), m.event_msg(_stamp(0), m.EventKind.STARTED, 0))
    for i in range(N_TICKS):
        t_ns = _stamp(i)
        writer.write(m.EE_POSE, t_ns, m.ee_pose_msg(t_ns, [0.1, 0.0, 1.0 + 1e-3 * i], [0, 0, 0, 1]))
        writer.write(m.JOINT_STATES, t_ns, m.joint_state_msg(t_ns, np.zeros(7), np.full(7, 0.1), np.full(7, 2.0)))
        writer.write(m.COMMAND, t_ns, m.command_msg(t_ns, Command(i, np.zeros(7), 0, 1, 0)))
        if extra is not None and i == extra[1]:
            writer.write(extra[0], t_ns, extra[2])
    end = _stamp(N_TICKS - 1)
    writer.write(m.EPISODE_EVENTS, end, m.event_msg(end, m.EventKind.SUCCESS, N_TICKS - 1))
    writer.close()
    return path


def _string(text: bytes) -> bytes:
    return struct.pack("<I", len(text)) + text


def _record(op: int, body: bytes) -> bytes:
    return struct.pack("<BQ", op, len(body)) + body


ONE_BYTE_SCHEMA = _record(0x03, b"\x01")
NON_UTF8_CHANNEL = _record(0x04, struct.pack("<HH", 99, 1) + _string(b"\xff\xfe/bad") + _string(b"cdr") + b"\0" * 4)
RECORD_CASES = {
    "1-byte schema record": (ONE_BYTE_SCHEMA, "record 0x03 of 1 bytes, shorter than the 14 it needs; skipped"),
    "non-UTF-8 topic name": (NON_UTF8_CHANNEL, "malformed channel record ('utf-8' codec can't decode byte 0xff"),
}


@pytest.mark.parametrize("where", ["top level", "in a chunk"])
@pytest.mark.parametrize("case", list(RECORD_CASES))
def test_a_malformed_record_is_damage_named_by_every_command(tmp_path, case, where):
    record, says = RECORD_CASES[case]
    bag = replayable_bag(tmp_path / "ep")
    insert_before_data_end(bag, record if where == "top level" else chunk_record("", record, len(record)))
    line = one_line(lq("reindex", str(bag)), 1, f"{bag}: {3 * N_TICKS + 2} messages", says)
    assert "complete" not in line
    one_line(lq("replay", str(bag)), 2, "cannot replay", "bag damaged", says)
    scored = lq("score", str(bag), "--json")
    assert scored["returncode"] == 1 and "Traceback" not in scored["stderr"], scored["stderr"]
    row = json.loads(scored["stdout"].strip().splitlines()[-1])
    assert row["status"] == "success" and row["partial"] is True and any(says in w for w in row["warnings"])


MARKER = "lq_hostile_marker"
METADATA_CASES = {
    "a YAML list": lambda meta: meta.write_text("- rosbag2_bagfile_information\n- 3\n"),
    "a !!python tag": lambda meta: meta.write_text(f"!!python/object/apply:os.system ['touch {MARKER}']\n"),
    "a directory": lambda meta: meta.mkdir(),
    "a FIFO": lambda meta: os.mkfifo(meta),
}


@pytest.mark.parametrize("case", list(METADATA_CASES))
def test_a_broken_metadata_yaml_is_named_in_one_line(tmp_path, case):
    bag = replayable_bag(tmp_path / "ep")
    meta = bag / "metadata.yaml"
    meta.unlink()
    METADATA_CASES[case](meta)
    regular = case in ("a YAML list", "a !!python tag")
    replayed = one_line(lq("replay", str(bag), timeout=60), 2, "cannot replay", "unreadable run metadata", str(meta))
    reindexed = lq("reindex", str(bag), timeout=60)
    if regular:  # an unreadable metadata.yaml is what reindex replaces
        one_line(reindexed, 0, f"{bag}: {3 * N_TICKS + 2} messages (complete)")
        assert yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]["custom_data"]["lq_bag"] == "reindexed"
        meta.unlink()
        METADATA_CASES[case](meta)
    else:  # a directory cannot be replaced, a FIFO is never opened
        one_line(reindexed, 2, f"{meta}: {case}, not a bag file")
        assert case.removeprefix("a ") in replayed
    scored = lq("score", str(bag), "--json", timeout=60)  # scored all the same, the metadata named as a warning
    assert scored["returncode"] == 1 and "Traceback" not in scored["stderr"], scored["stderr"]
    row = json.loads(scored["stdout"].strip().splitlines()[-1])
    assert row["status"] == "success" and any(str(meta) in w for w in row["warnings"])
    assert not (REPO / MARKER).exists() and not (tmp_path / MARKER).exists()  # the tag was never constructed


GARBAGE_CDR = b"\x00\x01\x00\x00" + b"\xff" * 40  # a valid encapsulation header, then an impossible string length


def test_an_undecodable_event_is_one_damage_record_the_rest_is_scored(tmp_path):
    bag = replayable_bag(tmp_path / "ep", extra=(m.EPISODE_EVENTS, 10, GARBAGE_CDR))
    scored = lq("score", str(bag), "--json")
    assert scored["returncode"] == 1 and "Traceback" not in scored["stderr"], scored["stderr"]
    row = json.loads(scored["stdout"].strip().splitlines()[-1])
    says = "1 undecodable /lq/episode_events message skipped"
    assert row["status"] == "success" and row["completion_steps"] == N_TICKS - 1 and row["partial"] is True
    assert any(says in w for w in row["warnings"]), row["warnings"]
    one_line(lq("replay", str(bag)), 2, "cannot replay", "bag damaged", "undecodable /lq/episode_events message")


def test_an_undecodable_pose_costs_that_pose_only(tmp_path):
    """Bulk-decoded topics too: one bad message is skipped and counted, its chunk's other messages are kept."""
    bag = replayable_bag(tmp_path / "ep", extra=(m.EE_POSE, 10, GARBAGE_CDR))
    data = read_episode(bag)
    assert len(data.ee) == N_TICKS and data.damaged
    assert any("1 undecodable /ee_pose message skipped" in w for w in data.warnings), data.warnings
    row = score_bag(bag)
    assert row["status"] == "success" and row["partial"] is True


def test_reindex_and_reader_agree_on_a_hostile_bag(tmp_path):
    """One record walker: the scorer's reader and lq reindex see the same damage and the same messages."""
    bag = replayable_bag(tmp_path / "ep")
    insert_before_data_end(bag, NON_UTF8_CHANNEL + chunk_record("zstd", zstd_zeros(MIB), 1 << 40))
    result = reindex(bag)
    reader = StreamingMcapReader(mcap_of(bag), None)
    n_batched = sum(len(b) for b in reader.batches())
    assert result.messages == n_batched == 3 * N_TICKS + 2
    assert [d.removeprefix(f"{mcap_of(bag).name}: ") for d in result.damage] == reader.damage
    assert len(reader.damage) == 2 and reader.complete


def test_a_million_malformed_records_are_given_up_on_not_listed(tmp_path):
    """Damage is bounded too: a file of tiny malformed records stops after MAX_DAMAGE problems, in time."""
    from lq_ros.recording.mcap_reader import MAX_DAMAGE

    bag = replayable_bag(tmp_path / "ep")
    at = insert_before_data_end(bag, ONE_BYTE_SCHEMA * 1_000_000)
    started = time.monotonic()
    scan = scan_mcap(mcap_of(bag))
    data = read_episode(bag)
    assert time.monotonic() - started < 3.0
    stop = at + MAX_DAMAGE * len(ONE_BYTE_SCHEMA)
    assert len(scan.damage) == MAX_DAMAGE + 1 and not scan.complete
    assert scan.damage[0] == f"byte {at}: record 0x03 of 1 bytes, shorter than the 14 it needs; skipped"
    assert scan.damage[-1] == f"more than {MAX_DAMAGE} problems: reading stopped at byte {stop}"
    assert scan.stats.count == 3 * N_TICKS + 2 and len(data.ee) == N_TICKS and data.damaged
