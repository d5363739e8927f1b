"""Offline scorer on bags written here: foreign writers, standard topics only, missing and damaged data.

Every bag is a real rosbag2 MCAP file on disk, written by rosbags (our writer) or by the ``mcap``
library (another tool: zstd chunks, CRCs, small chunks), and read back by the scorer. Expected values
are closed forms of the synthetic motion, not numbers copied from a previous run.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lq_ros.core.suite_constants import CONTROL_DT_S
from lq_ros.recording.episode_bag import EpisodeBagWriter
from lq_ros.scoring import metrics
from lq_ros.scoring.bag_scorer import BagError, read_episode, score_bag
from lq_ros.wire import messages as m

DT = CONTROL_DT_S
N_SAMPLES = 120
JERK_COEFF = np.array([0.3, -0.2, 0.1])  # m/s^3 / 6: p(t) = p0 + c t^3
TORQUE = np.array([2.0, -1.5, 1.0, 0.5, -0.5, 0.25, 0.1])  # N m, constant
VELOCITY = np.array([0.4, -0.2, 0.3, 0.1, 0.2, -0.1, 0.05])  # rad/s, constant
T0_NS = 500_000_000  # tick 0 at 0.5 s, as in our bags


def _cubic_positions(n: int = N_SAMPLES) -> np.ndarray:
    t = np.arange(n) * DT
    return np.array([0.1, 0.0, 1.0]) + JERK_COEFF * t[:, None] ** 3


def _stamp(i: int) -> int:
    return T0_NS + round(i * DT * 1e9)


def _standard_messages(ee_topic: str, joint_topic: str | None, n: int = N_SAMPLES) -> list[tuple[str, str, int, bytes]]:
    """(topic, msgtype, log ns, CDR) of a standard-topics-only recording: PoseStamped + JointState."""
    out = []
    for i, pos in enumerate(_cubic_positions(n)):
        t_ns = _stamp(i)
        out.append((ee_topic, m.EE_POSE.msgtype, t_ns, m.ee_pose_msg(t_ns, pos, [0, 0, 0, 1])))
        if joint_topic:
            joint = m.joint_state_msg(t_ns, np.zeros(7), VELOCITY, TORQUE)
            out.append((joint_topic, m.JOINT_STATES.msgtype, t_ns, joint))
    return out


def write_with_rosbags(path: Path, messages: list[tuple[str, str, int, bytes]]) -> Path:
    """A bag written by rosbags (the writer our own nodes use)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {}
        for topic, msgtype, t_ns, data in messages:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=m.typestore())
            writer.write(conns[topic], t_ns, data)
    return path


def write_with_mcap_library(
    path: Path,
    messages: list[tuple[str, str, int, bytes]],
    chunk_size: int = 2048,
    compression: str = "ZSTD",
    index_types: str = "ALL",
) -> Path:
    """A bag written by another tool: the ``mcap`` library, zstd chunks with CRCs, many small chunks
    (``index_types`` "CHUNK": without message indexes)."""
    from mcap.writer import CompressionType, IndexType, Writer

    path.mkdir(parents=True)
    store = m.typestore()
    with (path / f"{path.name}.mcap").open("wb") as f:
        writer = Writer(
            f, chunk_size=chunk_size, compression=CompressionType[compression], index_types=IndexType[index_types]
        )
        writer.start(profile="ros2", library="test")
        channels: dict[str, int] = {}
        for topic, msgtype, t_ns, data in messages:
            if topic not in channels:
                text, _ = store.generate_msgdef(msgtype)
                schema = writer.register_schema(name=msgtype, encoding="ros2msg", data=text.encode())
                channels[topic] = writer.register_channel(topic=topic, message_encoding="cdr", schema_id=schema)
            writer.add_message(channels[topic], log_time=t_ns, data=data, publish_time=t_ns)
        writer.finish()
    return path


def expected_energy(n_samples: int) -> tuple[float, float, float]:
    """Closed form of eq. 7-9 for constant torque and velocity over n samples of DT."""
    duration = n_samples * DT
    mech = max(0.0, float(TORQUE @ VELOCITY)) * duration  # eq. 7 clips the total power, not per joint
    elec = metrics.ELEC_LOSS_COEFF_W_PER_NM2 * float((TORQUE**2).sum()) * duration
    return mech, elec, metrics.OVERHEAD_POWER_W * duration


# -- standard topics, foreign writers ---------------------------------------------------------------------


@pytest.mark.parametrize("writer", [write_with_rosbags, write_with_mcap_library])
def test_standard_topics_only_bag_on_custom_topics(tmp_path, writer):
    bag = writer(tmp_path / "robot", _standard_messages("/robot/ee_pose", "/robot/joint_states"))
    row = score_bag(bag, ee_topic="/robot/ee_pose", joint_topic="/robot/joint_states")
    # No episode events: the outcome is unknown (null), never a failure; the trajectory is still scored.
    assert row["status"] == "unknown" and row["success"] is None
    assert row["jerk_mean"] == pytest.approx(6 * np.linalg.norm(JERK_COEFF), rel=1e-9)
    assert row["jerk_p90"] == pytest.approx(6 * np.linalg.norm(JERK_COEFF), rel=1e-9)
    assert row["traj_length"] == pytest.approx(metrics.trajectory_length(_cubic_positions()), rel=1e-12)
    mech, elec, overhead = expected_energy(N_SAMPLES)
    assert row["energy_mech_j"] == pytest.approx(mech, rel=1e-9)
    assert row["energy_elec_j"] == pytest.approx(elec, rel=1e-9)
    assert row["energy_overhead_j"] == pytest.approx(overhead, rel=1e-9)
    assert row["energy_total_j"] == pytest.approx(mech + elec + overhead, rel=1e-9)
    assert row["energy_per_step_j"] == pytest.approx((mech + elec + overhead) / N_SAMPLES, rel=1e-9)
    assert row["partial"] is False and row["trajectory_rate_hz"] == 20.0
    # What the bag cannot say is null with a reason.
    assert row["latency_real_mean_s"] is None and "no action chunks" in row["null_reasons"]["latency_real_mean_s"]


def test_default_topics_do_not_see_custom_topics(tmp_path):
    bag = write_with_rosbags(tmp_path / "robot", _standard_messages("/robot/ee_pose", "/robot/joint_states"))
    row = score_bag(bag)  # /ee_pose and /joint_states are not in this bag
    assert row["jerk_mean"] is None and "/ee_pose" in row["null_reasons"]["jerk_mean"]
    assert row["energy_total_j"] is None and "/joint_states" in row["null_reasons"]["energy_total_j"]


def test_missing_joint_topic_nulls_energy_and_scores_the_rest(tmp_path):
    bag = write_with_rosbags(tmp_path / "ee_only", _standard_messages("/ee_pose", None))
    row = score_bag(bag)
    assert row["jerk_mean"] == pytest.approx(6 * np.linalg.norm(JERK_COEFF), rel=1e-9)
    for key in ("energy_mech_j", "energy_elec_j", "energy_overhead_j", "energy_total_j", "energy_per_step_j"):
        assert row[key] is None
        assert row["null_reasons"][key] == "no joint states on /joint_states"


def test_joint_states_without_effort_are_reported(tmp_path):
    messages = _standard_messages("/ee_pose", None)
    messages += [("/joint_states", m.JOINT_STATES.msgtype, _stamp(i), m.joint_state_msg(_stamp(i), np.zeros(7), [], []))
                 for i in range(N_SAMPLES)]  # fmt: skip
    row = score_bag(write_with_rosbags(tmp_path / "no_effort", messages))
    assert row["energy_total_j"] is None and "lack velocity or effort" in row["null_reasons"]["energy_total_j"]


def test_wrong_message_type_on_a_topic_is_a_clear_error(tmp_path):
    messages = [("/ee_pose", m.JOINT_STATES.msgtype, _stamp(0), m.joint_state_msg(_stamp(0), [0.0], [0.0], [0.0]))]
    bag = write_with_rosbags(tmp_path / "wrong", messages)
    with pytest.raises(
        BagError, match=r"/ee_pose holds sensor_msgs/msg/JointState.*needs geometry_msgs/msg/PoseStamped"
    ):
        score_bag(bag)


def test_energy_constants_are_parameters(tmp_path):
    bag = write_with_rosbags(tmp_path / "robot", _standard_messages("/ee_pose", "/joint_states"))
    row = score_bag(bag, elec_coeff=0.01, overhead_w=0.0)
    duration = N_SAMPLES * DT
    assert row["energy_elec_j"] == pytest.approx(0.01 * float((TORQUE**2).sum()) * duration, rel=1e-9)
    assert row["energy_overhead_j"] == 0.0


# -- our own episode bags: damage --------------------------------------------------------------------------


def write_episode_bag(
    path: Path, n_ticks: int = 400, end_kind: int = m.EventKind.SUCCESS, end_after_ns: int = 0,
    config: dict | None = None, metadata: dict | None = None,
) -> Path:  # fmt: skip
    """An episode bag from our writer: STARTED, n_ticks of state and commands, SUCCESS (or ``end_kind``) at the
    last sample (or ``end_after_ns`` after it)."""
    from lq_ros.core.executor_protocol import Command

    writer = EpisodeBagWriter(path, list(m.CORE_TOPICS))
    config = {"policy": "synthetic", "mode": "sync", "latency_s": 0.0, "suite": "s", "task": 0, "init": 0, "seed": 7,
              **(config or {})}  # fmt: skip
    writer.set_run_metadata({"config": config, "versions": {"git_commit": "abc"}, **(metadata or {})})
    writer.write(m.EPISODE_EVENTS, _stamp(0), m.event_msg(_stamp(0), m.EventKind.STARTED, 0))
    for i, pos in enumerate(_cubic_positions(n_ticks)):
        t_ns = _stamp(i)
        writer.write(m.EE_POSE, t_ns, m.ee_pose_msg(t_ns, pos, [0, 0, 0, 1]))
        writer.write(m.JOINT_STATES, t_ns, m.joint_state_msg(t_ns, np.zeros(7), VELOCITY, TORQUE))
        cmd = Command(tick=i, action=np.zeros(7), source=0, request_id=1, chunk_index=0)
        writer.write(m.COMMAND, t_ns, m.command_msg(t_ns, cmd))
    end = _stamp(n_ticks - 1) + end_after_ns
    writer.write(m.EPISODE_EVENTS, end, m.event_msg(end, end_kind, n_ticks - 1))
    writer.close()
    return path


def test_intact_episode_bag_scores_success(tmp_path):
    row = score_bag(write_episode_bag(tmp_path / "ep"))
    assert row["status"] == "success" and row["completion_steps"] == 399 and row["partial"] is False
    assert row["hold_ticks"] == 0 and row["policy"] == "synthetic"


def test_the_row_records_where_the_protocol_came_from_the_budget_preset_and_the_policys_seed(tmp_path):
    from lq_ros.core.seeding import LEROBOT_SEED_TAG, episode_seed

    config = {"suite": "libero_spatial", "budgets": "lerobot", "replan_steps": 10, "replan_steps_source": "policy"}
    metadata = {"camera_size_px": 360, "policy_params": {"seeding": "episode"}}
    row = score_bag(write_episode_bag(tmp_path / "ep", config=config, metadata=metadata))
    assert (row["budgets"], row["step_budget"]) == ("lerobot", 280)  # LeRobot 0.6's Spatial budget, not 220
    assert (row["replan_steps"], row["replan_steps_source"]) == (10, "policy")
    assert (row["camera_size_px"], row["camera_size_source"]) == (360, "policy")
    assert row["policy_seed"] == episode_seed(7, "libero_spatial", 0, 0, LEROBOT_SEED_TAG)
    plain = score_bag(write_episode_bag(tmp_path / "plain"))
    assert plain["policy_seed"] is None and plain["replan_steps_source"] is None


def _offsets_of(raw: bytes, opcode: int) -> list[int]:
    """Byte offsets of every top-level MCAP record with ``opcode`` in the data section."""
    offsets, off = [], 8
    while raw[off] != 0x0F:  # data end
        if raw[off] == opcode:
            offsets.append(off)
        off += 9 + int.from_bytes(raw[off + 1 : off + 9], "little")
    return offsets


def _offset_of_first(raw: bytes, opcodes: set[int]) -> int:
    """Byte offset of the first top-level MCAP record with one of ``opcodes`` (walks record headers)."""
    off = 8  # magic
    while raw[off] not in opcodes:
        off += 9 + int.from_bytes(raw[off + 1 : off + 9], "little")
    return off


def _mcap(bag: Path) -> Path:
    return next(bag.glob("*.mcap"))


def test_truncated_own_bag_is_an_error_naming_the_file_never_a_task_outcome(tmp_path):
    bag = write_episode_bag(tmp_path / "ep")
    mcap = _mcap(bag)
    mcap.write_bytes(mcap.read_bytes()[: mcap.stat().st_size // 2])
    row = score_bag(bag)
    assert row["status"] == "error" and row["success"] is None and row["partial"] is True
    assert str(mcap) in row["warnings"][0] and "truncated" in row["warnings"][0]
    assert "bag damaged before the episode outcome" in row["error_reason"]


def test_truncated_multichunk_bag_scores_the_readable_prefix(tmp_path):
    bag = write_with_mcap_library(tmp_path / "robot", _standard_messages("/ee_pose", "/joint_states"))
    mcap = _mcap(bag)
    mcap.write_bytes(mcap.read_bytes()[: int(mcap.stat().st_size * 0.6)])
    data = read_episode(bag)
    assert data.damaged and str(mcap) in data.warnings[-1] and "truncated" in data.warnings[-1]
    n_read = len(data.ee)
    assert 10 < n_read < N_SAMPLES  # some chunks survive, the cut one and the rest are gone
    row = score_bag(bag)
    assert row["partial"] is True
    assert row["traj_length"] == pytest.approx(metrics.trajectory_length(_cubic_positions(n_read)), rel=1e-12)
    assert row["jerk_mean"] == pytest.approx(6 * np.linalg.norm(JERK_COEFF), rel=1e-9)


@pytest.mark.parametrize("compression", ["NONE", "ZSTD"])
def test_corrupt_chunk_is_skipped_and_named(tmp_path, compression):
    messages = _standard_messages("/ee_pose", "/joint_states")
    bag = write_with_mcap_library(tmp_path / "robot", messages, compression=compression)
    mcap = _mcap(bag)
    raw = bytearray(mcap.read_bytes())
    chunks = _offsets_of(bytes(raw), 0x06)
    assert len(chunks) > 5
    at = chunks[len(chunks) // 2]
    raw[at + 9 + 60] ^= 0xFF  # one flipped byte inside a middle chunk's payload
    mcap.write_bytes(bytes(raw))
    data = read_episode(bag)
    assert data.damaged and f"{mcap}: chunk at byte {at}:" in data.warnings[0]
    if compression == "NONE":
        assert "CRC mismatch" in data.warnings[0]
    # The chunks after the corrupt one are still read ...
    assert data.ee.arrays(None, None)[0][-1] == _stamp(N_SAMPLES - 1)
    # ... and the hole it leaves is not silently bridged: the trajectory metrics are null with the reason.
    row = score_bag(bag)
    assert row["partial"] is True and row["jerk_mean"] is None
    assert row["null_reasons"]["jerk_mean"].startswith("EE pose series rejected: gap of")


def test_not_an_mcap_file_raises_naming_it(tmp_path):
    bag = tmp_path / "junk"
    bag.mkdir()
    (bag / "junk.mcap").write_bytes(b"this is not a bag at all")
    with pytest.raises(BagError, match=r"junk\.mcap: not an MCAP file"):
        score_bag(bag)


def test_recorder_killed_before_closing(tmp_path):
    """A killed recorder leaves an MCAP without its end records and no metadata.yaml: partial, an error."""
    bag = write_episode_bag(tmp_path / "ep")
    (bag / "metadata.yaml").unlink()
    mcap = _mcap(bag)
    raw = mcap.read_bytes()
    mcap.write_bytes(raw[: _offset_of_first(raw, {0x0C, 0x0F})])  # every chunk intact, no end records
    row = score_bag(bag)
    assert row["partial"] is True and "no end record" in row["warnings"][0]
    # All chunks were readable, so the outcome survived; only the provenance is gone.
    assert row["status"] == "success" and row["policy"] is None


def test_complete_mcap_without_metadata_is_a_plain_foreign_bag(tmp_path):
    bag = write_episode_bag(tmp_path / "ep")
    (bag / "metadata.yaml").unlink()
    row = score_bag(_mcap(bag))  # a single .mcap file path is accepted too
    assert row["status"] == "success" and row["partial"] is False and row["warnings"] == []


# -- the command line: a directory of bags -----------------------------------------------------------------


def test_cli_scores_a_directory_writes_tables_and_names_the_damaged_bag(tmp_path):
    root = tmp_path / "bags"
    write_episode_bag(root / "good_a")
    write_episode_bag(root / "good_b", n_ticks=300)
    broken = write_episode_bag(root / "broken")
    mcap = _mcap(broken)
    mcap.write_bytes(mcap.read_bytes()[:200])
    result = subprocess.run([sys.executable, "-m", "lq_ros.cli", "score", str(root), "--n-boot", "200"],
                            capture_output=True, text=True, timeout=120)  # fmt: skip
    assert result.returncode == 1, result.stderr  # a damaged bag is reported through the exit code
    assert str(mcap) in result.stderr
    assert "| synthetic" in result.stdout and "success %" in result.stdout
    import pandas as pd

    episodes = pd.read_parquet(root / "episodes.parquet")
    assert sorted(episodes["status"]) == ["error", "success", "success"]
    aggregates = pd.read_csv(root / "aggregates.csv")
    assert len(aggregates) == 1
    agg = aggregates.iloc[0]
    # The broken run is an error: not in the success rate, counted apart.
    assert (agg["n"], agg["n_success"], agg["n_error"], agg["success_rate"]) == (3, 2, 1, 1.0)
    assert agg["git_commits"] == "abc" and str(agg["seeds"]) == "7"
    assert agg["completion_steps_mean"] == pytest.approx((399 + 299) / 2)


def test_cli_json_for_one_bag(tmp_path):
    bag = write_episode_bag(tmp_path / "ep")
    result = subprocess.run([sys.executable, "-m", "lq_ros.cli", "score", str(bag), "--json"],
                            capture_output=True, text=True, check=True, timeout=120)  # fmt: skip
    row = json.loads(result.stdout.strip().splitlines()[-1])
    assert row["status"] == "success" and row["versions"] == {"git_commit": "abc"}


def test_scoring_needs_no_ros_and_no_simulator(tmp_path):
    """The scorer runs on any machine with Python: rclpy, MuJoCo and robosuite are never imported."""
    bag = write_episode_bag(tmp_path / "ep")
    code = (
        "import sys; from lq_ros.scoring.aggregate import score_directory; "
        f"assert score_directory({str(bag)!r})['status'].tolist() == ['success']; "
        "print(sorted(k for k in ('rclpy', 'mujoco', 'robosuite', 'libero', 'torch') if k in sys.modules))"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120)
    assert result.stdout.strip() == "[]"


# -- episodes without an outcome; real-time chunk boundaries ------------------------------------------------------


@pytest.mark.parametrize("end_after_ns", [0, 41_000_000])
def test_an_episode_without_an_outcome_is_scored_up_to_its_end_event(tmp_path, end_after_ns):
    """A real-time recorder stopped by a killed node stamps its STOPPED event at the wall time it stopped, after
    the last sample (41 ms here): the recorded part is scored as in lockstep (where the event is at the last
    sample), and the row stays an error. An episode with an outcome still needs samples up to its end event."""
    bag = write_episode_bag(tmp_path / "stopped", 200, m.EventKind.STOPPED, end_after_ns)
    row = score_bag(bag)
    assert row["status"] == "error" and row["success"] is None and row["partial"] is False
    pos = _cubic_positions(200)
    assert row["jerk_mean"] == pytest.approx(metrics.jerk_mean(pos, DT), rel=1e-9)
    assert row["traj_length"] == pytest.approx(metrics.trajectory_length(pos), rel=1e-9)
    assert row["energy_mech_j"] == pytest.approx(expected_energy(199)[0], rel=1e-9)
    success = score_bag(write_episode_bag(tmp_path / "success", 200, m.EventKind.SUCCESS, end_after_ns))
    if end_after_ns:
        assert success["jerk_mean"] is None and "incomplete" in success["null_reasons"]["jerk_mean"]
        assert success["partial"] is True
    else:
        assert success["jerk_mean"] == row["jerk_mean"]


def write_realtime_bag(path: Path, chunks, cmds, latency_s: float, metadata: dict, merge: str = "replace") -> Path:
    """A real-time async episode bag: the chunks and commands of a stream, a 20 Hz pose, a timeout at the end."""
    writer = EpisodeBagWriter(path, list(m.CORE_TOPICS))
    config = {"policy": "synthetic", "mode": "async", "merge": merge, "latency_s": latency_s, "suite": "s",
              "task": 0, "init": 0, "seed": 7, "clock": "realtime", "robot": ""}  # fmt: skip
    writer.set_run_metadata({"config": config, "clock": "realtime", **metadata})
    writer.write(m.EPISODE_EVENTS, _stamp(0), m.event_msg(_stamp(0), m.EventKind.STARTED, 0))
    n = len(cmds.tick)
    for i, pos in enumerate(_cubic_positions(n + 1)):
        writer.write(m.EE_POSE, _stamp(i), m.ee_pose_msg(_stamp(i), pos, [0, 0, 0, 1]))
    for c in chunks:
        t_ns = _stamp(c.observation_tick)
        data = m.chunk_msg(t_ns, c.request_id, c.observation_tick, latency_s, 0.01, c.actions, "synthetic")
        writer.write(m.ACTION_CHUNK, _stamp(c.due_tick), data)
    from lq_ros.core.executor_protocol import Command

    for t in range(n):
        cmd = Command(int(cmds.tick[t]), cmds.action[t], int(cmds.source[t]), int(cmds.request_id[t]),
                      int(cmds.chunk_index[t]))  # fmt: skip
        writer.write(m.COMMAND, _stamp(t), m.command_msg(_stamp(t), cmd))
    writer.write(m.EPISODE_EVENTS, _stamp(n), m.event_msg(_stamp(n), m.EventKind.TIMEOUT, n, "step budget"))
    writer.close()
    return path


def test_realtime_bag_boundaries_follow_late_chunks_and_missed_commands(tmp_path):
    from lq_ros.core.executor_protocol import ExecutorConfig
    from lq_ros.scoring import chunk_boundary as boundary
    from tests.scoring.test_chunk_boundary import late_pattern, ramp_chunk, run_core_realtime

    chunks, cmds, applied = run_core_realtime(ExecutorConfig(mode="async", latency_ticks=2), 80, ramp_chunk,
                                              late_pattern)  # fmt: skip
    missed = [14, 40, 41]  # 14: a switch
    sim = {"missed_commands": 3, "missed_command_ticks": missed, "node": "sim"}
    row = score_bag(write_realtime_bag(tmp_path / "rt", chunks, cmds, 0.1, {"realtime": {"sim": sim}}))
    expected = boundary.analyse("async", "replace", chunks, cmds, realtime=True, missed_ticks=missed)
    assert row["chunk_switches"] == len(expected.switch_ticks) > 10, row["null_reasons"]
    assert row["switch_executed_step_mean"] == pytest.approx(expected.executed_steps.mean(), rel=1e-12)
    assert row["chunk_switch_jump_max"] == pytest.approx(expected.jumps.max(), rel=1e-12)
    # Missed ticks change what ran: not the same as ignoring them.
    ignored = boundary.analyse("async", "replace", chunks, cmds, realtime=True)
    assert row["switch_executed_step_mean"] != pytest.approx(ignored.executed_steps.mean(), rel=1e-9)

    # The sim did not report (stopped by a killed peer), or listed fewer ticks than it missed: the plan's fields
    # only, the rest null with the reason.
    for name, stats, why in [
        ("nostats", {"realtime": {}}, "did not report which commands it missed"),
        ("cut", {"realtime": {"sim": {**sim, "missed_commands": 250}}}, "missed 250 commands"),
        ("junk", {"realtime": {"sim": {**sim, "missed_command_ticks": "9,40"}}}, "not a list of ticks"),
    ]:
        row = score_bag(write_realtime_bag(tmp_path / name, chunks, cmds, 0.1, stats))
        assert row["chunks_overlapping"] == 0 and row["chunk_switches"] is None
        assert why in row["null_reasons"]["switch_executed_step_mean"]
