"""Real-time bags scored like lockstep ones, on real processes (rclpy, Fast DDS on loopback, MuJoCo).

Chunk boundaries: the scorer's replay follows what the wall-clock executor and sim did (late chunks, missed
commands; lq_ros/scoring/chunk_boundary.py). A killed node: the recorded part is scored, the row an error
(lq_ros/scoring/bag_scorer.py). The policy sleeps 0.1 s per inference, so with Δt_sim = 0.2 s every chunk
arrives at least 0.3 s after its request, past its due tick's 25 ms deadline: each one is late, whatever the
machine's load. Assertions hold at any timing: they compare the row with what the bag itself records.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lq_ros.core.control import ControlMode, hold_action
from lq_ros.core.executor_protocol import Source
from lq_ros.core.run_config import RunConfig
from lq_ros.core.suite_constants import DUMMY_ACTION
from lq_ros.recording.bag_compare import bag_messages
from lq_ros.recording.episode_bag import read_run_metadata, scan_mcap
from lq_ros.scoring import chunk_boundary as boundary
from lq_ros.scoring import metrics
from lq_ros.scoring.bag_scorer import read_episode, score_bag
from lq_ros.wire import messages as m
from tests.transport.ros.test_faults import alive, four_nodes, start_lq, wait_for
from tests.transport.ros.test_realtime_e2e import _lq_run

pytestmark = [pytest.mark.slow, pytest.mark.sim]
SLEEPY = ["--policy", "lq_ros.policies.sleepy:SleepyPolicy", "--policy-arg", "sleep_s=0.1"]
ASYNC = ["--clock", "realtime", "--mode", "async", "--latency", "0.2"]
ROBOT_TOPICS = {"ee_topic": "/robot/ee_pose", "joint_topic": "/robot/joint_states"}


def executed_commands(bag: Path, missed: list[int]) -> list[tuple[np.ndarray, int, int]]:
    """(arm action, source, request id) per tick of what ran, read with rosbags: the recorded /lq/command, or the
    stop hold where the sim missed it."""
    cmds = sorted((m.deserialize(raw, m.COMMAND.msgtype) for _, raw in bag_messages(bag)[m.COMMAND.name]),
                  key=lambda c: c.tick)  # fmt: skip
    assert [c.tick for c in cmds] == list(range(len(cmds)))
    out, last = [], np.asarray(DUMMY_ACTION, dtype=np.float64)
    for c in cmds:
        if c.tick in missed:
            last = hold_action(ControlMode.RELATIVE, last)
            out.append((last, int(Source.HOLD_INFERENCE), 0))
        else:
            last = np.asarray(c.action, dtype=np.float64)
            out.append((last, int(c.source), int(c.request_id)))
    return out


def check_boundaries(bag: Path, row: dict, missed: list[int], **topics) -> dict[int, int]:
    """The row's switch fields against a recomputation from the executed commands (replace: switches are the only
    handovers); returns request id -> tick its chunk took effect."""
    assert not any("replay failed" in why for why in row.get("null_reasons", {}).values()), row["null_reasons"]
    ran = executed_commands(bag, missed)
    switches, last = [], None
    for t, (_, source, rid) in enumerate(ran):
        if source == Source.CHUNK:
            if last is not None and rid != last:
                switches.append(t)
            last = rid
    assert len(switches) >= 2 and row["chunk_switches"] == len(switches)
    steps = [np.linalg.norm(ran[t][0][:6] - ran[t - 1][0][:6]) for t in switches]
    assert row["switch_executed_step_mean"] == pytest.approx(np.mean(steps), rel=1e-9)
    assert row["chunk_overlap_ends"] == 0 and row["chunks_overlapping"] == 0
    data = read_episode(bag, **topics)
    cmds = boundary.Commands(**{k: np.concatenate([g[k] for g in data.command_groups]) for k in data.command_groups[0]})
    found = boundary.analyse("async", "replace", data.chunk_records, cmds, realtime=True, missed_ticks=missed)
    return found.applied_ticks


def check_late_chunks(bag: Path, applied: dict[int, int]) -> None:
    """Every chunk took effect after its due tick, and the ticks it was late add up to the executor's own count
    (it counts one per tick a due chunk had not arrived; a chunk still outstanding at the end adds its own)."""
    data = read_episode(bag)
    due = {c.request_id: c.due_tick for c in data.chunk_records}
    assert applied and all(applied[r] > due[r] for r in applied), (applied, due)
    late = sum(applied[r] - due[r] for r in applied)
    counted = read_run_metadata(bag)["realtime"]["executor"]["late_chunks"]
    assert late <= counted
    if data.requests == len(applied):
        assert late == counted


def test_realtime_sim_episode_has_chunk_boundary_metrics(tmp_path):
    row, _ = _lq_run(tmp_path, *ASYNC, *SLEEPY, "--max-steps", "100")
    assert row["status"] in ("success", "failure"), row
    bag = next(p for p in tmp_path.iterdir() if (p / "metadata.yaml").exists())
    sim = read_run_metadata(bag)["realtime"]["sim"]
    missed = sim["missed_command_ticks"]
    assert sim["missed_commands"] == len(missed)
    applied = check_boundaries(bag, row, missed)
    check_late_chunks(bag, applied)
    assert score_bag(bag)["chunk_switches"] == row["chunk_switches"]  # the recorder's row is the scorer's


def test_a_sim_running_late_answers_each_request_with_its_tick(tmp_path):
    """A sim whose steps take longer than the period falls behind the executor's wall clock. It answered a request
    for tick t with the state it had (tick t - 1): the policy's observation was a tick older than the request, the
    executor counted the chunk's stale rows from the request's tick, and the scorer's replay found a request made
    before the previous chunk took effect (seen on a loaded machine). The answer now waits for tick t."""
    from lq_ros.transport.ros.stack import launch_nodes

    cfg = RunConfig(policy="lq_ros.policies.sleepy:SleepyPolicy", policy_args={"sleep_s": 0.1}, clock="realtime",
                    mode="async", latency_s=0.2, max_steps=40)  # fmt: skip
    bag, error = launch_nodes(cfg, tmp_path, node_parameters_extra={"lq_sim": {"step_delay_s": 0.07}})
    assert error == ""
    assert read_run_metadata(bag)["realtime"]["sim"]["overrun_ticks"] >= 10  # the sim ran late throughout
    messages = bag_messages(bag)
    requested = {r.request_id: r.tick for r in (m.deserialize(raw, m.OBSERVATION_REQUEST.msgtype)
                                                 for _, raw in messages[m.OBSERVATION_REQUEST.name])}  # fmt: skip
    seen = {c.request_id: c.observation_tick for c in (m.deserialize(raw, m.ACTION_CHUNK.msgtype)
                                                        for _, raw in messages[m.ACTION_CHUNK.name])}  # fmt: skip
    # (A request past the episode's last tick, made by the wall clock while the sim catches up, is answered at once.)
    within = [r for r in seen if requested[r] < cfg.max_steps]
    assert len(within) >= 3 and all(seen[r] == requested[r] for r in within), (requested, seen)
    row = json.loads((bag / "score.json").read_text())
    assert row["status"] in ("success", "failure"), row
    assert not any("replay failed" in why for why in row.get("null_reasons", {}).values()), row["null_reasons"]


def test_robot_standin_episode_has_chunk_boundary_metrics(tmp_path):
    """A robot applies every command when it arrives (nothing missed); its 100 Hz pose gives the jerk windows in
    time."""
    row, _ = _lq_run(tmp_path, *ASYNC, "--robot", "standin", *SLEEPY, "--max-steps", "100")
    assert row["status"] in ("success", "failure"), row
    bag = next(p for p in tmp_path.iterdir() if (p / "metadata.yaml").exists())
    applied = check_boundaries(bag, row, [], **ROBOT_TOPICS)
    check_late_chunks(bag, applied)
    assert row["trajectory_rate_hz"] == 100.0
    assert row["chunk_switch_jerk_mean"] is not None, row["null_reasons"].get("chunk_switch_jerk_mean")


def test_killed_executor_leaves_a_realtime_bag_scored_up_to_its_end(tmp_path):
    """kill -9 of the executor mid-episode: the recorder stamps STOPPED at the wall time it stopped (after the last
    sample); the row stays an error and its trajectory and energy metrics are those of the samples recorded between
    the start and that event, as for a lockstep bag cut the same way."""
    cli = start_lq(tmp_path, "run", "--clock", "realtime", "--policy", "sine", "--mode", "async", "--latency", "0.2",
                   "--max-steps", "600", "--out", str(tmp_path / "out"), "--json")  # fmt: skip
    try:
        nodes = wait_for(lambda: four_nodes(cli.pid), 120, "the four nodes")

        def poses_recorded() -> int:
            files = list((tmp_path / "out").glob("*/*.mcap"))
            scan = scan_mcap(files[0]) if files else None
            stats = scan.stats.topics.get(m.EE_POSE.name) if scan else None
            return stats.count if stats else 0

        wait_for(lambda: poses_recorded() >= 60, 120, "3 s of the episode recorded", period_s=0.5)
        os.kill(nodes["executor"], signal.SIGKILL)
        cli.wait(timeout=120)
    finally:
        if cli.poll() is None:
            cli.kill()
            cli.wait()
    assert cli.returncode == 1
    assert "executor node exited with code -9" in (tmp_path / "lq.err").read_text()
    wait_for(lambda: not any(alive(p) for p in nodes.values()), 60, "every node to exit")

    (bag,) = (tmp_path / "out").iterdir()
    scored = subprocess.run([sys.executable, "-m", "lq_ros.cli", "score", str(bag), "--json"], capture_output=True,
                            text=True, timeout=120)  # fmt: skip
    row = json.loads(scored.stdout.strip().splitlines()[-1])
    assert row["status"] == "error" and row["success"] is None
    events = [m.deserialize(raw, m.EPISODE_EVENTS.msgtype) for _, raw in bag_messages(bag)[m.EPISODE_EVENTS.name]]
    t0, t1 = m.stamp_ns(events[0]), m.stamp_ns(events[-1])
    assert events[-1].kind == m.EventKind.STOPPED
    poses = [(t, m.deserialize(raw, m.EE_POSE.msgtype).pose.position) for t, raw in bag_messages(bag)[m.EE_POSE.name]]
    pos = np.array([[p.x, p.y, p.z] for t, p in sorted(poses, key=lambda x: x[0]) if t0 <= t <= t1])
    assert len(pos) >= 60
    assert row["jerk_mean"] == pytest.approx(metrics.jerk_mean(pos, 0.05), rel=1e-9), row["null_reasons"]
    assert row["traj_length"] == pytest.approx(metrics.trajectory_length(pos), rel=1e-9)
    assert row["ee_osc"] is not None and row["energy_total_j"] is not None, row["null_reasons"]
    # The executor's plan is in the bag; what the sim missed is not (it was stopped before reporting it).
    assert row["chunks_overlapping"] == 0
    assert "did not report" in row["null_reasons"]["chunk_switches"]
    outcome_keys = {"completion_steps", "completion_time_s", "censored"}
    assert set(row["null_reasons"]) - set(boundary.KEYS) == outcome_keys, row["null_reasons"]
