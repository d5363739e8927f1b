"""Bounded reading of hostile bags: duplicate lifecycle events are damage, and a flood of messages that compresses to
a few kilobytes costs what the episode's budget allows (lq_ros.scoring.read_budget), not what the file holds.

The bags are real episodes from our writer, rewritten with the ``mcap`` library in large chunks without message
indexes, with the floods added (identical messages compress to almost nothing), and a metadata.yaml from our
writer. The floods are scored by the real ``lq score`` in a subprocess, which reports its peak memory and wall time.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from lq_ros.core.types import TaskStateSample
from lq_ros.recording.bag_compare import bag_messages
from lq_ros.recording.episode_bag import EpisodeBagWriter
from lq_ros.scoring.bag_scorer import read_episode, score_bag
from lq_ros.scoring.read_budget import MESSAGES_PER_TICK, SLACK_TICKS
from lq_ros.wire import messages as m
from tests.recording.test_hostile_bags import lq
from tests.scoring.test_bag_scorer import _stamp, write_episode_bag, write_with_mcap_library

N_TICKS = 100
EVENTS = m.EPISODE_EVENTS.name
#: The run metadata of the rewritten bags: a LIBERO-Spatial episode, read for at most its 220 ticks.
METADATA = {"config": {"policy": "synthetic", "mode": "sync", "latency_s": 0.0, "suite": "libero_spatial", "task": 0,
                       "init": 0, "seed": 7}, "versions": {"git_commit": "abc"}}  # fmt: skip
TICKS_READ = 220 + SLACK_TICKS


def rewritten(path: Path, floods: list[tuple[str, str, int, bytes]], *, after_first_event: bool = True) -> Path:
    """write_episode_bag's episode (N_TICKS, a success) rewritten in 1 MiB chunks with ``floods`` (topic, msgtype,
    log ns, bytes) right after its STARTED event (or at the end), with a metadata.yaml of METADATA from our writer."""
    base = write_episode_bag(path.with_name(path.name + "_base"), n_ticks=N_TICKS)
    types = {t.name: t.msgtype for t in m.CORE_TOPICS}
    messages = sorted((t_ns, topic, raw) for topic, items in bag_messages(base).items() for t_ns, raw in items)
    out = [(topic, types[topic], t_ns, raw) for t_ns, topic, raw in messages]
    at = next(i for i, item in enumerate(out) if item[0] == EVENTS) + 1 if after_first_event else len(out)
    write_unindexed(path, out[:at] + floods + out[at:])
    meta = EpisodeBagWriter(path.with_name(path.name + "_meta"), [])
    meta.set_run_metadata(METADATA)
    meta.close()
    shutil.copy(meta.path / "metadata.yaml", path / "metadata.yaml")
    return path


def write_unindexed(path: Path, messages: list[tuple[str, str, int, bytes]]) -> Path:
    """A bag of 1 MiB zstd chunks without message indexes (16 bytes a message: most of a flood's size)."""
    return write_with_mcap_library(path, messages, chunk_size=1 << 20, index_types="CHUNK")


def started(n: int) -> list[tuple[str, str, int, bytes]]:
    event = m.event_msg(_stamp(0), m.EventKind.STARTED, 0)
    return [(EVENTS, m.EPISODE_EVENTS.msgtype, _stamp(0), event)] * n


def scored(bag: Path) -> tuple[dict, dict]:
    """``lq score BAG --json`` in a subprocess: its row and its measure (wall_s, rss_mb)."""
    result = lq("score", str(bag), "--json")
    assert result["returncode"] in (0, 1) and "Traceback" not in result["stderr"], result["stderr"][-2000:]
    return json.loads(result["stdout"].strip().splitlines()[-1]), result


def test_duplicate_started_events_are_damage_and_the_first_is_used(tmp_path):
    bag = rewritten(tmp_path / "ep", started(1_000))
    row = score_bag(bag)
    assert row["status"] == "success" and row["completion_steps"] == N_TICKS - 1 and row["jerk_mean"] is not None
    assert row["partial"] is True and row["damaged_topics"] == [EVENTS]
    assert any(f"1000 duplicate {EVENTS} events skipped (1000 STARTED" in w for w in row["warnings"]), row["warnings"]
    assert [e[0] for e in read_episode(bag).events] == [m.EventKind.STARTED, m.EventKind.SUCCESS]


def test_an_event_recorded_twice_is_damage_and_two_different_ends_are_not(tmp_path):
    end = _stamp(N_TICKS - 1)
    success = (EVENTS, m.EPISODE_EVENTS.msgtype, end, m.event_msg(end, m.EventKind.SUCCESS, N_TICKS - 1))
    twice = score_bag(rewritten(tmp_path / "twice", [success], after_first_event=False))
    assert twice["status"] == "success" and twice["partial"] is True and twice["damaged_topics"] == [EVENTS]
    assert any("1 SUCCESS" in w for w in twice["warnings"]), twice["warnings"]
    # The recorder stopped after the outcome (a STOPPED event after the SUCCESS): two ends, no damage, the first counts.
    stop = m.event_msg(end + 1, m.EventKind.STOPPED, N_TICKS - 1, "recording stopped")
    stopped = score_bag(rewritten(tmp_path / "stopped", [(EVENTS, m.EPISODE_EVENTS.msgtype, end + 1, stop)],
                                  after_first_event=False))  # fmt: skip
    assert stopped["status"] == "success" and stopped["partial"] is False and stopped["damaged_topics"] == []


def test_60000_started_events_in_a_tiny_bag_score_in_seconds_as_damage(tmp_path):
    """More events than the episode's budget: the rest, the outcome among them, is skipped as damage (the episode is
    an error: its outcome was lost to the damage, never a success read past a flood)."""
    bag = rewritten(tmp_path / "ep", started(60_000))
    assert sum(f.stat().st_size for f in bag.iterdir()) < 60_000
    row, cost = scored(bag)
    assert cost["wall_s"] < 60 and cost["rss_mb"] < 1024, cost
    assert row["partial"] is True and row["damaged_topics"] == [EVENTS] and row["jerk_mean"] is not None
    budget = MESSAGES_PER_TICK["events"] * TICKS_READ
    flood = f"{EVENTS}: more than the {budget} messages"
    assert any(flood in w for w in row["warnings"]) and any("duplicate" in w for w in row["warnings"]), row["warnings"]
    assert row["status"] == "error" and "bag damaged before the episode outcome" in row["error_reason"]


def flood_state(n_names: int) -> bytes:
    """A task state of ``n_names`` objects (the same at every copy: it compresses to nothing)."""
    names = tuple(f"object_{i:04d}_of_a_flood" for i in range(n_names))
    sample = TaskStateSample(
        object_names=names, object_pos=np.zeros((n_names, 3)), object_quat_xyzw=np.tile([0.0, 0, 0, 1], (n_names, 1)),
        gripper_contact=np.zeros(n_names, bool), grasped=np.zeros(n_names, bool), predicate_names=("(on a b)",),
        predicate_values=np.zeros(1, bool),
    )  # fmt: skip
    return m.task_state_msgs(_stamp(1), 1, sample)[1][2]


def test_a_task_state_flood_is_damage_within_the_episode_budget(tmp_path):
    """15,000 task states of 200 objects each (3,000,000 names once decoded) in a bag of ~80 KB."""
    state = flood_state(200)
    bag = rewritten(tmp_path / "ep", [(m.TASK_STATE.name, m.TASK_STATE.msgtype, _stamp(1), state)] * 15_000)
    assert sum(f.stat().st_size for f in bag.iterdir()) < 100_000
    row, cost = scored(bag)
    assert cost["wall_s"] < 60 and cost["rss_mb"] < 1024, cost
    assert row["status"] == "success" and row["jerk_mean"] is not None and row["energy_total_j"] is not None
    assert row["partial"] is True and m.TASK_STATE.name in row["damaged_topics"]
    budget = MESSAGES_PER_TICK["task"] * TICKS_READ
    assert any(f"{m.TASK_STATE.name}: more than the {budget} messages" in w for w in row["warnings"]), row["warnings"]
    assert row["failure_mode"] is None and "contradictory" in row["failure_mode_reason"]


def test_task_states_with_too_many_objects_are_skipped_as_undecodable(tmp_path):
    bag = rewritten(tmp_path / "ep", [(m.TASK_STATE.name, m.TASK_STATE.msgtype, _stamp(1), flood_state(300))] * 3)
    row = score_bag(bag)
    assert row["partial"] is True and row["damaged_topics"] == [m.TASK_STATE.name]
    assert any(f"3 undecodable {m.TASK_STATE.name} messages" in w and "300 objects" in w for w in row["warnings"])


def test_chunks_of_millions_of_tiny_records_without_an_index_are_walked_up_to_the_budget(tmp_path):
    """Three chunks of 4,000,000 empty messages of an unknown channel each (a 40 KB bag): each record is a Python
    step of the walk (21 s a chunk); the walk stops at the budget, the episode before them is intact."""
    import struct

    import zstandard

    from lq_ros.scoring.read_budget import RECORDS_PER_TICK
    from tests.recording.test_hostile_bags import chunk_record, insert_before_data_end

    bag = rewritten(tmp_path / "ep", [])
    records = (struct.pack("<BQ", 0x05, 26) + struct.pack("<HIQQ", 999, 0, 0, 0) + bytes(4)) * 4_000_000
    chunk = chunk_record("zstd", zstandard.ZstdCompressor().compress(records), len(records))
    for _ in range(3):
        insert_before_data_end(bag, chunk)
    assert sum(f.stat().st_size for f in bag.iterdir()) < 60_000
    row, cost = scored(bag)
    assert cost["wall_s"] < 60 and cost["rss_mb"] < 1024, cost
    assert row["status"] == "success" and row["jerk_mean"] is not None and row["partial"] is True
    walked = f"more than the {RECORDS_PER_TICK * TICKS_READ} records that an episode of at most 220 ticks"
    assert any(walked in w for w in row["warnings"]), row["warnings"]
