"""Sweeps: scheduling, workers (env reuse), resume after a kill, retry-once, the ros transport.

Spec expansion: tests/run/sweep/test_spec.py; the durable store: tests/run/sweep/test_store.py;
Ray: tests/run/sweep/test_sweep_ray.py.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import yaml

from lq_ros.core.run_config import RunConfig
from lq_ros.core.types import Observation, TaskInfo
from lq_ros.policies.base import Policy
from lq_ros.recording.bag_compare import comparable
from lq_ros.run import sweep as sw
from tests.run.sweep.test_spec import small_spec

REPO = Path(__file__).resolve().parents[3]
#: Row fields measured on the wall clock (or naming the machine), excluded when comparing reruns.
WALL_FIELDS = {"latency_real_mean_s", "latency_real_p50_s", "latency_real_p90_s", "latency_real_max_s", "versions"}


def test_scheduler_keeps_a_worker_on_its_task_and_spreads_the_rest():
    cfgs = [RunConfig(policy="sine", task=t, init=i) for t in (0, 1) for i in range(3)]
    sched = sw.Scheduler([sw.Job(c) for c in cfgs])
    first = sched.pick(None, Counter())
    busy = Counter({sw.env_key(first.cfg): 1})
    second = sched.pick(None, busy)
    assert first.cfg.task != second.cfg.task  # the idle worker goes where nobody is
    again = sched.pick(sw.env_key(first.cfg), busy)
    assert again.cfg.task == first.cfg.task  # a worker stays on its env while it has jobs


# -- running ---------------------------------------------------------------------------------


def _rows(store: sw.ResultStore) -> dict[str, dict]:
    return {r["key"]: {k: v for k, v in r["row"].items() if k not in WALL_FIELDS} for r in store.records()}


@pytest.mark.slow
@pytest.mark.sim
def test_two_local_workers_then_resume_reruns_only_unfinished(tmp_path):
    spec = sw.expand_spec(small_spec())
    summary = sw.run_sweep(spec, tmp_path, workers=2)
    assert summary.ran == 4 and summary.counts == {"failure": 4} and summary.skipped == 0
    store = sw.ResultStore(tmp_path)
    first = _rows(store)
    assert len(first) == 4 and all(r["status"] == "failure" for r in first.values())
    index = [json.loads(line) for line in (tmp_path / "episodes.jsonl").read_text().splitlines()]
    assert {r["key"] for r in index} == set(first)
    for record in store.records():
        assert (tmp_path / record["bag"] / "metadata.yaml").exists()
        assert (tmp_path / record["attempts"][0]["log"]).exists()
    # A truncated record and a lost bag: exactly those two episodes run again, with the same results.
    k1, k2 = sorted(first)[:2]
    text = store.record_path(k1).read_text()
    store.record_path(k1).write_text(text[:100])
    lost = json.loads(store.record_path(k2).read_text())["bag"]
    subprocess.run(["rm", "-rf", str(tmp_path / lost)], check=True)
    again = sw.run_sweep(spec, tmp_path, workers=2)
    assert again.skipped == 2 and again.ran == 2
    assert _rows(store) == first  # deterministic: a rerun reproduces the scores exactly
    assert sw.run_sweep(spec, tmp_path, workers=2).ran == 0


@pytest.mark.slow
@pytest.mark.sim
def test_reused_env_gives_the_same_episode_as_a_fresh_one(tmp_path):
    target = RunConfig(policy="scripted", mode="async", latency_s=0.2, init=1, max_steps=25)
    other = RunConfig(policy="scripted", mode="sync", latency_s=0.1, init=0, max_steps=30)
    fresh = sw.EpisodeWorker("inprocess", tmp_path / "fresh")
    a = fresh.run(target, tmp_path / "a.log")
    fresh.close()
    reused = sw.EpisodeWorker("inprocess", tmp_path / "reused")
    reused.run(other, tmp_path / "b.log")
    env_before = reused._cached[1]
    b = reused.run(target, tmp_path / "c.log")
    assert reused._cached[1] is env_before  # really the same env object
    reused.close()
    assert a["status"] == b["status"] != "error"
    assert comparable(Path(a["bag"])) == comparable(Path(b["bag"]))


class ExitOncePolicy(Policy):
    """Kills its worker process on the first request of the first episode run (marker file), then acts
    like a zero policy: exercises the retry of an episode whose worker died."""

    name = "exit_once"

    def __init__(self, marker: str) -> None:
        self.marker = Path(marker)

    def reset(self, task: TaskInfo, seed: int) -> None:
        pass

    def infer(self, obs: Observation) -> np.ndarray:
        if not self.marker.exists():
            self.marker.write_text("died once")
            os._exit(3)
        return np.tile([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0], (4, 1))


@pytest.mark.slow
@pytest.mark.sim
def test_crashed_episodes_are_retried_once_and_kept_with_their_logs(tmp_path):
    marker = tmp_path / "marker"
    raw = small_spec(
        latencies_s=[0.0],
        modes=["sync"],
        policies=[
            {"name": "faulty", "args": {"fault": "raise", "at_requests": [1]}},
            {"name": "tests.run.sweep.test_sweep:ExitOncePolicy", "args": {"marker": str(marker)}},
        ],
    )
    summary = sw.run_sweep(sw.expand_spec(raw), tmp_path / "out", workers=1)
    assert summary.retried == 2 and summary.counts == {"error": 1, "failure": 1}
    store = sw.ResultStore(tmp_path / "out")
    by_policy = {r["config"]["policy"]: r for r in store.records()}
    faulty = by_policy["faulty"]
    assert faulty["status"] == "error" and len(faulty["attempts"]) == 2
    assert all("injected failure" in a["reason"] for a in faulty["attempts"])
    assert "injected failure" in faulty["row"]["error_reason"]
    first = faulty["attempts"][0]
    assert first["bag"].startswith("attempts/") and (tmp_path / "out" / first["bag"] / "metadata.yaml").exists()
    assert (tmp_path / "out" / faulty["bag"] / "metadata.yaml").exists()  # the final (second) attempt's bag
    died = by_policy["tests.run.sweep.test_sweep:ExitOncePolicy"]
    assert died["status"] == "failure" and [a["status"] for a in died["attempts"]] == ["error", "failure"]
    assert "worker process died (exit code 3)" in died["attempts"][0]["reason"]
    assert (tmp_path / "out" / died["attempts"][0]["log"]).exists()


def _descendants(pid: int) -> set[int]:
    out, todo = set(), [pid]
    while todo:
        p = todo.pop()
        for task in Path(f"/proc/{p}/task").glob("*"):
            children = (task / "children").read_text().split() if (task / "children").exists() else []
            for c in map(int, children):
                if c not in out:
                    out.add(c)
                    todo.append(c)
    return out


@pytest.mark.slow
@pytest.mark.sim
def test_kill_9_mid_sweep_then_restart_skips_finished(tmp_path):
    spec_file = tmp_path / "spec.yaml"
    spec_file.write_text(yaml.safe_dump(small_spec(max_steps=6)))
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "lq_ros.cli", "sweep", str(spec_file), "--workers", "1", "--out", str(out)]
    log = open(tmp_path / "sweep.log", "wb")  # noqa: SIM115 - closed below
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=log, stderr=subprocess.STDOUT)
    deadline = time.monotonic() + 180
    while time.monotonic() < deadline and len(list((out / "results").glob("*.json"))) < 1:
        time.sleep(0.2)
    workers = _descendants(proc.pid)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    log.close()
    finished = {p.stem for p in (out / "results").glob("*.json")}
    assert 1 <= len(finished) < 4, (tmp_path / "sweep.log").read_text()[-2000:]
    # Workers get SIGTERM from the kernel when the sweep dies (PR_SET_PDEATHSIG) and unwind like Ctrl-C,
    # closing their env; on a loaded machine that takes a few seconds, so poll instead of one fixed sleep.
    alive = list(workers)
    deadline = time.monotonic() + 30
    while alive and time.monotonic() < deadline:
        time.sleep(0.5)
        alive = [p for p in alive if Path(f"/proc/{p}").exists() and "zombie" not in _state(p)]
    assert not alive, f"worker outlived the sweep: {[_cmdline(p) for p in alive]}"
    spec = sw.load_spec(spec_file)
    summary = sw.run_sweep(spec, out, workers=1)
    assert summary.skipped == len(finished) and summary.ran == 4 - len(finished)
    assert len(sw.ResultStore(out).records()) == 4


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()[:200]
    except OSError:
        return "?"


def _state(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/status").read_text().split("State:")[1].split("\n")[0].lower()
    except (OSError, IndexError):
        return "zombie"


@pytest.mark.slow
@pytest.mark.sim
@pytest.mark.ros
@pytest.mark.serial  # its /dev/shm check counts every new Fast DDS file of the machine
def test_ros_transport_sweep_runs_the_four_node_stack(tmp_path):
    """One worker, four episodes (sync and async): one long-lived stack runs them all, nothing is left after."""
    from lq_ros.transport.inprocess import run_inprocess
    from tests.transport.ros.test_faults import orphaned_shm

    before_shm = set(os.listdir("/dev/shm"))
    spec = sw.expand_spec(small_spec(transport="ros", latencies_s=[0.1], inits=[0, 1], max_steps=10))
    summary = sw.run_sweep(spec, tmp_path, workers=1)
    records = sw.ResultStore(tmp_path).records()
    assert summary.counts == {"failure": 4}, [r["row"].get("error_reason") for r in records]
    sim_logs = []
    for record in records:
        assert record["transport"] == "ros" and record["row"]["transport"] == "ros"
        assert record["row"]["completion_steps"] == 10
        sim_logs.append((tmp_path / record["bag"] / "logs" / "sim.log").read_text())  # node logs kept per bag
        local = run_inprocess(RunConfig(**record["config"]), tmp_path / "local")
        assert comparable(tmp_path / record["bag"]) == comparable(local.bag_path)
    # The task's env was created once: the stack outlived the first episode.
    assert sum("creating libero_spatial task 0" in log for log in sim_logs) == 1
    assert orphaned_shm(before_shm) == []


@pytest.mark.slow
@pytest.mark.sim
@pytest.mark.ros
def test_realtime_and_robot_sweeps(tmp_path):
    """A spec with clock: realtime runs wall-clock episodes, one with robot: standin runs them against the
    stand-in robot through the bridge, each on one long-lived stack per worker (its sim or bridge configured
    once for both episodes); a realtime spec is refused with the in-process transport."""
    for over, node, configured in (
        ({"clock": "realtime"}, "sim", "creating libero_spatial task 0"),
        ({"clock": "realtime", "robot": "standin"}, "bridge", "for libero_spatial task 0"),
    ):
        spec = sw.expand_spec(
            small_spec(transport="ros", latencies_s=[0.1], modes=["async"], inits=[0, 1], max_steps=20, **over)
        )
        out = tmp_path / "_".join(over.values())
        summary = sw.run_sweep(spec, out, workers=1)
        records = sw.ResultStore(out).records()
        assert summary.counts == {"failure": 2}, [r["row"].get("error_reason") for r in records]
        for record in records:
            assert record["row"]["clock"] == "realtime" and record["row"]["status"] == "failure"
        logs = [(out / r["bag"] / "logs" / f"{node}.log").read_text() for r in records]
        assert sum(configured in log for log in logs) == 1, "the stack outlived the first episode"
    with pytest.raises(ValueError, match="runs through ROS only"):
        sw.run_sweep(spec, tmp_path / "inprocess", workers=1, transport="inprocess")
