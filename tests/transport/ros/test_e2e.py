"""End to end: the four nodes as real OS processes (rclpy, Fast DDS on loopback, MuJoCo, MCAP)."""

import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from lq_ros.core.run_config import RunConfig
from lq_ros.recording.bag_compare import bag_messages, comparable
from lq_ros.recording.episode_bag import read_run_metadata
from lq_ros.run.episode import run_episode
from lq_ros.transport.inprocess import run_inprocess
from lq_ros.transport.processes import EXECUTOR_ENV, NODE_FORKS_ENV, fastdds_shm_owned
from lq_ros.transport.ros.fork_server import ForkedProcess
from lq_ros.transport.ros.stack import RosStack
from lq_ros.wire import messages as m
from tests.transport.ros.test_lifecycle import wait_until_recording

pytestmark = [pytest.mark.slow, pytest.mark.sim]
REPO = Path(__file__).resolve().parents[3]
SCORE_KEYS = {"success", "completion_time_s", "jerk_mean", "ee_osc", "traj_length", "energy_total_j"}


def shm_files() -> set[str]:
    return {f for f in os.listdir("/dev/shm") if "fastrtps" in f or "fastdds" in f}


def node_descendants(root_pid: int) -> list[int]:
    """PIDs of the node programs below ``root_pid`` in the process tree."""
    out = subprocess.run(["ps", "-eww", "-o", "pid=,ppid=,args="], capture_output=True, text=True).stdout
    children: dict[int, list[tuple[int, str]]] = {}
    for line in out.splitlines():
        pid, ppid, *args = line.split(None, 2)
        children.setdefault(int(ppid), []).append((int(pid), args[0] if args else ""))
    found, todo = [], [root_pid]
    while todo:
        for pid, args in children.get(todo.pop(), []):
            todo.append(pid)
            if "_node" in args and "nodes." in args:
                found.append(pid)
    return found


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(") ")[1][0] != "Z"
    except OSError:
        return False


def test_four_node_episode_bag_and_scores(tmp_path):
    cfg = RunConfig(policy="sine", mode="async", latency_s=0.2, max_steps=30)
    outcome, row = run_episode(cfg, tmp_path, "ros")
    assert outcome.status == "failure", row  # the task is failed, the run is fine
    bag = outcome.bag_path
    assert (bag / "metadata.yaml").exists() and list(bag.glob("*.mcap"))
    meta_yaml = (bag / "metadata.yaml").read_text()
    assert "storage_identifier: mcap" in meta_yaml and "serialization_format: cdr" in meta_yaml
    meta = read_run_metadata(bag)
    assert meta["transport"] == "ros" and meta["config"]["mode"] == "async"
    assert {"mujoco", "robosuite", "libero", "rclpy", "git_commit"} <= set(meta["versions"])
    msgs = bag_messages(bag)
    assert {t.name for t in m.CORE_TOPICS} <= set(msgs)
    assert len(msgs[m.COMMAND.name]) == 30 and len(msgs[m.EE_POSE.name]) == 31
    # The CLI scorer reads the same bag without ROS.
    out = subprocess.run(
        [sys.executable, "-m", "lq_ros.cli", "score", str(bag), "--json"], capture_output=True, text=True, check=True
    )
    scored = json.loads(out.stdout.strip().splitlines()[-1])
    assert SCORE_KEYS <= set(scored) and scored["success"] is False
    assert scored["jerk_mean"] == row["jerk_mean"] and scored["energy_total_j"] > 0
    assert scored["underrun_ticks"] == 0 and scored["hold_ticks"] == 4  # async startup: N = 4 ticks


def test_the_bag_closes_on_every_nodes_message_counts_and_holds_what_they_published(tmp_path):
    """The recorder closed the bag because the counts announced by sim, policy and executor had all arrived (not
    after a quiet period): every topic holds exactly what its nodes published (what is sent ahead of the sim:
    commands, observation requests, chunks: what took effect before the end)."""
    cfg = RunConfig(policy="sine", mode="async", latency_s=0.1, max_steps=20, replan_steps=3)
    outcome, _ = run_episode(cfg, tmp_path, "ros")
    assert outcome.status == "failure", outcome.reason
    marker = "every message of the episode arrived; counts: "
    (line,) = [ln for ln in (outcome.bag_path / "logs" / "metrics.log").read_text().splitlines() if marker in ln]
    announced = json.loads(line.split(marker, 1)[1])
    assert set(announced) == {"lq_sim", "lq_policy", "lq_executor"}
    published: dict[str, int] = {}
    for counts in announced.values():
        for topic, n in counts.items():
            published[topic] = published.get(topic, 0) + n
    in_bag = {topic: len(items) for topic, items in bag_messages(outcome.bag_path).items()}
    assert in_bag[m.COMMAND.name] == 20 <= published[m.COMMAND.name]  # (sent ahead of the end: never applied)
    ahead = (m.COMMAND.name, m.OBSERVATION_REQUEST.name, m.ACTION_CHUNK.name)
    assert all(in_bag[t] <= published[t] for t in ahead)
    assert {t: n for t, n in in_bag.items() if t not in ahead} == {
        t: n for t, n in published.items() if t in in_bag and t not in ahead
    }
    assert published[m.EE_POSE.name] == 21 and published[m.ACTION_CHUNK.name] > 0


@pytest.mark.parametrize("mode, latency", [("sync", 0.0), ("sync", 0.15), ("async", 0.0), ("async", 0.2)])
def test_ros_lockstep_equals_inprocess(tmp_path, mode, latency):
    """Bit-identical trajectories, commands and chunks for both transports (wall-clock fields aside)."""
    cfg = RunConfig(policy="sine", mode=mode, latency_s=latency, max_steps=30, replan_steps=3)
    ros, _ = run_episode(cfg, tmp_path / "ros", "ros")
    local = run_inprocess(cfg, tmp_path / "local")
    assert ros.status == local.status == "failure"
    assert comparable(ros.bag_path) == comparable(local.bag_path)


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="the sim is pinned only with two CPUs or more")
def test_the_sim_steps_a_lockstep_episode_on_its_own_cpu_and_any_cpu_between_episodes(tmp_path, monkeypatch):
    """RosStack pins the sim's main thread to its reserved CPU while a lockstep episode is active (LQ_SIM_CPU),
    and lets it run anywhere again for the next configure; the episode is the in-process one, bit for bit.

    The CPU locks are this test's own: stacks of other runs on the machine (a 2-worker sweep holds both CPUs of a
    2-core machine) would leave none to reserve, and the stack then rightly runs unpinned (tests/transport/ros/
    test_reservations.py checks the reservation itself)."""
    from lq_ros.transport.ros import reservations

    monkeypatch.setattr(reservations, "CPU_LOCK_DIR", tmp_path / "cpus")
    cfg = RunConfig(policy="sine", mode="async", latency_s=0.2, max_steps=30, replan_steps=3)
    seen: set[frozenset[int]] = set()
    with RosStack() as stack:
        assert stack.sim_cpu in stack.cpus
        stack.start()
        sim_pid = stack.procs["sim"].pid
        done = threading.Event()

        def sample() -> None:
            while not done.is_set():
                with contextlib.suppress(OSError):
                    seen.add(frozenset(os.sched_getaffinity(sim_pid)))
                time.sleep(0.002)

        sampler = threading.Thread(target=sample)
        sampler.start()
        try:
            ros, _ = run_episode(cfg, tmp_path / "ros", "ros", stack=stack)
        finally:
            done.set()
            sampler.join()
        stack._pin_sim(False)  # what the next episode does before its configure
        assert os.sched_getaffinity(sim_pid) == stack.cpus
    assert frozenset({stack.sim_cpu}) in seen, seen
    local = run_inprocess(cfg, tmp_path / "local")
    assert ros.status == local.status == "failure"
    assert comparable(ros.bag_path) == comparable(local.bag_path)


def test_rclpys_single_threaded_executor_gives_the_same_episode(tmp_path, monkeypatch):
    """The nodes spin rclpy's EventsExecutor by default; LQ_RCLPY_EXECUTOR=single_threaded (the fallback) runs the
    same episode, bit for bit."""
    cfg = RunConfig(policy="sine", mode="async", latency_s=0.2, max_steps=30, replan_steps=3)
    monkeypatch.setenv(EXECUTOR_ENV, "single_threaded")
    ros, _ = run_episode(cfg, tmp_path / "ros", "ros")
    (line,) = [ln for ln in (ros.bag_path / "logs" / "sim.log").read_text().splitlines() if "executor:" in ln]
    assert "SingleThreadedExecutor" in line
    local = run_inprocess(cfg, tmp_path / "local")
    assert ros.status == local.status == "failure"
    assert comparable(ros.bag_path) == comparable(local.bag_path)


@pytest.mark.parametrize("forks", ["on", "off"])
def test_nodes_forked_or_executed_afresh_give_the_same_episode(tmp_path, monkeypatch, forks):
    """By default the stack forks its nodes from a process that imported them (LQ_NODE_FORKS=on); each is a
    process of its own under its program's name. Executed afresh (off), they run the same episode, bit for bit."""
    monkeypatch.setenv(NODE_FORKS_ENV, forks)
    cfg = RunConfig(policy="sine", mode="async", latency_s=0.2, max_steps=30, replan_steps=3)
    with RosStack() as stack:
        stack.start()
        for name, proc in stack.procs.items():
            assert isinstance(proc, ForkedProcess) == (forks == "on"), name
            parent = Path(f"/proc/{proc.pid}/stat").read_text().rsplit(")", 1)[1].split()[1]
            assert (int(parent) == os.getpid()) == (forks == "off"), name  # forks: the fork server's children
        ros, _ = run_episode(cfg, tmp_path / "ros", "ros", stack=stack)
        names = {name: Path(f"/proc/{proc.pid}/cmdline").read_bytes() for name, proc in stack.procs.items()}
    for name, line in names.items():
        assert f"-m\0lq_ros_nodes.{name}_node".encode() in line.replace(b" ", b"\0"), (name, line)
    local = run_inprocess(cfg, tmp_path / "local")
    assert ros.status == local.status == "failure"
    assert comparable(ros.bag_path) == comparable(local.bag_path)


def test_a_fork_server_that_declines_leaves_the_nodes_executed_afresh(tmp_path, monkeypatch):
    """A module the fork server imports starts a thread it does not know to be fork-safe: it declines, the launcher's
    log (kept with the bag) says so, and the episode runs on nodes executed afresh."""
    (tmp_path / "threaded_module.py").write_text(
        "import threading, time\nthreading.Thread(target=time.sleep, args=(600,), daemon=True).start()\n"
    )
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]))
    cfg = RunConfig(policy="sine", mode="async", latency_s=0.2, max_steps=30, replan_steps=3)
    with RosStack() as stack:
        stack.fork_preload = ("threaded_module",)
        ros, _ = run_episode(cfg, tmp_path / "ros", "ros", stack=stack)
        assert not any(isinstance(proc, ForkedProcess) for proc in stack.procs.values())
    assert ros.status == "failure"  # (the sine policy's, as in process)
    log = (ros.bag_path / "logs" / "launcher.log").read_text()
    assert "the node fork server did not start" in log and "threads after the imports" in log, log


def test_a_killed_fork_server_takes_its_idle_nodes_and_the_next_episode_runs_on_nodes_executed_afresh(tmp_path):
    """kill -9 of the fork server between episodes: its nodes end (their parent-death signal), the next episode
    restarts them executed afresh (a server that died is not started again) and runs the same episode."""
    cfg = RunConfig(policy="sine", mode="async", latency_s=0.2, max_steps=30, replan_steps=3)
    with RosStack() as stack:
        first, _ = run_episode(cfg, tmp_path / "first", "ros", stack=stack)
        os.kill(stack._forks.proc.pid, signal.SIGKILL)
        deadline = time.monotonic() + 30.0
        while any(proc.poll() is None for proc in stack.procs.values()) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert all(proc.poll() is not None for proc in stack.procs.values()), "a node outlived its fork server"
        # The launcher, their subreaper, reaped them: no zombie left for a PID 1 that may never reap.
        zombies = [p.pid for p in stack.procs.values() if Path(f"/proc/{p.pid}").exists() and zombie(p.pid)]
        assert zombies == [], zombies
        second, _ = run_episode(cfg, tmp_path / "second", "ros", stack=stack)
        assert not any(isinstance(proc, ForkedProcess) for proc in stack.procs.values())
    assert first.status == second.status == "failure"
    assert comparable(first.bag_path) == comparable(second.bag_path)
    assert "the node fork server has exited" in (second.bag_path / "logs" / "launcher.log").read_text()


def zombie(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except OSError:
        return False


def test_a_stopped_fork_server_is_given_up_in_seconds_and_the_stack_starts_executed_afresh(tmp_path):
    """SIGSTOP of the fork server before the nodes start: the stack start gives it up within seconds (a stopped
    server would never answer; it used to wait 60 s), ends it, and the episode runs on nodes executed afresh."""
    cfg = RunConfig(policy="sine", mode="async", latency_s=0.2, max_steps=30, replan_steps=3)
    with RosStack() as stack:
        server = stack._fork_server()  # (started and ready, no node forked yet)
        os.kill(server.proc.pid, signal.SIGSTOP)
        started = time.monotonic()
        stack.start()
        assert time.monotonic() - started < 30.0
        assert server.proc.returncode == -signal.SIGKILL
        assert not any(isinstance(proc, ForkedProcess) for proc in stack.procs.values())
        outcome, _ = run_episode(cfg, tmp_path / "ros", "ros", stack=stack)
    assert outcome.status == "failure"  # (the sine policy's, as in process)
    log = (outcome.bag_path / "logs" / "launcher.log").read_text()
    assert "the node fork server did not answer (it is stopped); the nodes are executed afresh" in log, log


def test_same_config_and_seed_give_identical_bags_and_scores(tmp_path):
    cfg = RunConfig(policy="sine", mode="sync", latency_s=0.1, max_steps=25, physics_rate=True)
    first, row1 = run_episode(cfg, tmp_path / "a", "ros")
    second, row2 = run_episode(cfg, tmp_path / "b", "ros")
    assert comparable(first.bag_path) == comparable(second.bag_path)
    wall = {k for k in row1 if k.startswith("latency_real")} | {"versions"}
    assert {k: v for k, v in row1.items() if k not in wall} == {k: v for k, v in row2.items() if k not in wall}


def test_malformed_chunk_rejected_through_ros(tmp_path):
    cfg = RunConfig(policy="faulty", policy_args={"fault": "bounds", "at_requests": [2]}, max_steps=20, replan_steps=4)
    outcome, row = run_episode(cfg, tmp_path, "ros")
    assert outcome.status == "failure" and row["chunks_rejected"] == 1
    commands = [m.deserialize(r, m.COMMAND.msgtype) for _, r in bag_messages(outcome.bag_path)[m.COMMAND.name]]
    assert all(np.all(np.abs(c.action) <= 1.0) for c in commands)
    assert all(c.request_id != 2 for c in commands)


def test_policy_crash_is_an_error(tmp_path):
    cfg = RunConfig(policy="faulty", policy_args={"fault": "raise", "at_requests": [1]}, max_steps=20)
    outcome, row = run_episode(cfg, tmp_path, "ros")
    assert outcome.status == "error" and row["success"] is None
    assert "injected failure" in row["error_reason"]


def test_policy_reset_failure_is_an_error_with_its_reason(tmp_path):
    # LIBERO-Goal task 5 (push the plate) is a task the scripted expert declines at reset.
    cfg = RunConfig(suite="libero_goal", task=5, policy="scripted", max_steps=20)
    outcome, row = run_episode(cfg, tmp_path, "ros")
    assert outcome.status == "error" and row["success"] is None
    assert "reset failed: PolicyError" in row["error_reason"] and "plate" in row["error_reason"]


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL])
def test_no_process_or_shm_file_outlives_a_killed_cli(tmp_path, sig):
    cli = subprocess.Popen(
        [sys.executable, "-m", "lq_ros.cli", "run", "--policy", "sine", "--out", str(tmp_path)],
        stdout=subprocess.DEVNULL,
        stderr=open(tmp_path / "cli.log", "wb"),  # noqa: SIM115
        cwd=REPO,
    )
    # Only this CLI's nodes and their files: other ROS runs may share the machine (and /dev/shm).
    deadline = time.monotonic() + 60
    while len(nodes := node_descendants(cli.pid)) < 4 and time.monotonic() < deadline:
        time.sleep(0.2)
    assert len(nodes) >= 4, (tmp_path / "cli.log").read_text()  # sim, policy, executor, metrics (+ helpers)
    wait_until_recording(tmp_path)  # the episode is under way
    owned = set().union(*(fastdds_shm_owned(pid) for pid in nodes))
    assert owned, "the nodes hold no Fast DDS file: nothing to check"
    assert cli.poll() is None, "the run ended before it could be interrupted"
    cli.send_signal(sig)
    cli.wait(timeout=60)
    deadline = time.monotonic() + 30
    while any(_alive(pid) for pid in nodes) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not [pid for pid in nodes if _alive(pid)]
    left = {f for f in shm_files() if f.removesuffix("_el") in owned}
    assert not left, left
