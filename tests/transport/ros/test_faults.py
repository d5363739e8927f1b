"""Faults lose nothing: kill -9 of a node, the recorder, the launcher or a sweep worker, on the real stack.

Every test runs the four real node processes (rclpy, Fast DDS, MuJoCo) through ``lq run`` or ``lq sweep``,
kills one process with SIGKILL mid-episode and checks what is left: the run's exit code and message, no
surviving process, no orphaned Fast DDS file in /dev/shm, and a bag the scorer reads.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterable
from pathlib import Path

import pytest
import yaml

from lq_ros.core.run_config import RunConfig
from lq_ros.recording.bag_compare import bag_messages
from lq_ros.recording.episode_bag import FLUSH_SIM_NS, read_run_metadata, reindex, scan_mcap
from lq_ros.transport.inprocess import run_inprocess
from lq_ros.transport.processes import ShmTracker
from lq_ros.wire import messages as m

pytestmark = [pytest.mark.slow, pytest.mark.sim]
REPO = Path(__file__).resolve().parents[3]
SHM = Path("/dev/shm")
#: A real episode long enough to kill at several moments: 400 ticks (20 s of sim time). The latest kill (7.5 s by
#: the probe, which lags the sim) must come well before the end: with 11 s, a fast lockstep sim once finished the
#: episode, and the recorder closed its bag, before the kill arrived.
CFG = RunConfig(policy="sine", mode="async", latency_s=0.2, max_steps=400)
RUN_ARGS = ["--policy", "sine", "--mode", "async", "--latency", "0.2", "--max-steps", "400"]
#: Topics whose recorded bytes are identical in both transports (chunks carry a measured wall time).
DETERMINISTIC_TOPICS = (m.CLOCK, m.JOINT_STATES, m.EE_POSE, m.ENERGY_INTEGRALS, m.COMMAND, m.OBSERVATION_REQUEST)


# -- process and /dev/shm inspection ----------------------------------------------------------------------


def descendants(pid: int) -> set[int]:
    out, todo = set(), [pid]
    while todo:
        p = todo.pop()
        for task in Path(f"/proc/{p}/task").glob("*"):
            children = task / "children"
            try:
                kids = [int(c) for c in children.read_text().split()]
            except OSError:
                continue
            for c in kids:
                if c not in out:
                    out.add(c)
                    todo.append(c)
    return out


def cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def alive(pid: int) -> bool:
    try:
        return "zombie" not in Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False


def wait_for(predicate, timeout_s: float, what: str, period_s: float = 0.1):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(period_s)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


def node_pids(root: int) -> dict[str, int]:
    """Node name -> pid among the descendants of ``root``."""
    out = {}
    for pid in descendants(root):
        cmd = cmdline(pid)
        for name in ("sim", "policy", "executor", "metrics"):
            if f"lq_ros_nodes.{name}_node" in cmd:
                out[name] = pid
    return out


def four_nodes(root: int) -> dict[str, int] | None:
    nodes = node_pids(root)
    return nodes if len(nodes) == 4 else None


def domain_of(pid: int) -> str:
    env = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
    return next(e.split(b"=", 1)[1].decode() for e in env if e.startswith(b"ROS_DOMAIN_ID="))


def shm_base(name: str) -> str:
    """The Fast DDS file a /dev/shm entry belongs to: its segment or port, without ``sem.``, ``_mutex``, ``_el``."""
    return name.removeprefix("sem.").removesuffix("_mutex").removesuffix("_el")


def shm_files_of(pids: Iterable[int]) -> set[str]:
    """The Fast DDS files (:func:`shm_base` names) that processes ``pids`` have open or mapped now: their segments,
    the ports they read or write, the locks and mutexes of those. Sampled while a run lives, these are the files a
    test may call its run's."""
    out = set()
    for pid in pids:
        paths = []
        try:
            for fd in Path(f"/proc/{pid}/fd").iterdir():
                with contextlib.suppress(OSError):
                    paths.append(os.readlink(fd))
            paths += [line.split(None, 5)[-1] for line in Path(f"/proc/{pid}/maps").read_text().splitlines()]
        except OSError:  # gone
            continue
        for path in paths:
            if path.startswith(f"{SHM}/"):
                name = shm_base(path.removeprefix(f"{SHM}/"))
                out.add(name)
                if path.endswith("_el") and name not in SHM_OWNERS:  # (its creator holds the _el lock open)
                    SHM_OWNERS[name] = f"{pid} {cmdline(pid)[:160]}"
    return {name for name in out if name.startswith(("fastrtps_", "fastdds_"))}


#: The first process :func:`shm_files_of` saw holding each file's ``_el`` lock (its creator): named when a file is
#: left behind, so a failure says whose it was.
SHM_OWNERS: dict[str, str] = {}


def orphaned_shm(before: set[str], ours: set[str] | None = None) -> list[str]:
    """Fast DDS files in /dev/shm, new since ``before``, that no live process owns (its ``_el`` lock is free).

    ``ours``: the files the run's own processes used (:func:`shm_files_of`, sampled while they lived); only those
    count. Another run on the machine creates and drops files of its own meanwhile (a port file whose creator has
    exited, while its peers still use it, has a free lock): without ``ours`` they counted as this run's leftovers.
    Files of other live runs are in use (locked), so they never count either. Checked twice, 1 s apart: a file
    another run is creating right now may exist a moment before its lock does.
    """

    def orphans() -> set[str]:
        out = set()
        new = set(os.listdir(SHM)) - before
        if ours is not None:  # only the run's own files
            new = {name for name in new if shm_base(name) in ours}
        # Python multiprocessing's named semaphores (sweep pools): orphaned when no process maps them.
        semaphores = {name for name in new if name.startswith("sem.mp-")}
        if semaphores:
            for maps in Path("/proc").glob("[0-9]*/maps"):
                try:
                    text = maps.read_text()
                except OSError:
                    continue
                semaphores = {name for name in semaphores if name not in text}
            out |= semaphores
        for name in new:
            base = shm_base(name)
            if not base.startswith(("fastrtps_", "fastdds_")):
                continue
            try:
                fd = os.open(SHM / f"{base}_el", os.O_RDWR)
            except FileNotFoundError:
                out.add(name)  # a segment or mutex without its lock file: nobody can own it
                continue
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                out.add(name)
            except OSError:
                pass  # owned by a live participant
            finally:
                os.close(fd)
        return out

    first = orphans()
    time.sleep(1.0)
    return sorted(first & orphans())


# -- running lq and following its sim time -----------------------------------------------------------------


def start_lq(tmp_path: Path, *args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "lq_ros.cli", *args],
        cwd=REPO,
        stdout=open(tmp_path / "lq.out", "wb"),  # noqa: SIM115 - closed with the process
        stderr=open(tmp_path / "lq.err", "wb"),  # noqa: SIM115
    )


class ClockProbe:
    """A subscriber to the run's /clock in its domain (tests/clock_probe.py).

    It is a participant of the run's domain that the launcher does not know about: its own Fast DDS
    files, left behind when a peer is killed, are removed here (lq_ros.transport.processes.ShmTracker), so that what
    the test finds in /dev/shm is the run's. It also outlives the run: after the launcher has removed a
    killed node's port files, the probe's discovery traffic to that node (until its lease expires)
    creates them again (a segment and its mutex, without the ``_el`` lock that only a port's reader
    holds). So the probe also notes the files of the run's nodes (``watch``) and removes, once it has
    stopped, whichever of them its own writes brought back.
    """

    def __init__(self, tmp_path: Path, domain: str, watch: Callable[[], Iterable[int]] = tuple) -> None:
        self.shm = ShmTracker()
        self.used: set[str] = set()  # every Fast DDS file the probe and the run's nodes were seen using
        self.watch = watch  # the run's node pids, asked again at every look (a restarted node is new)
        self.file = tmp_path / "clock_ns"
        env = dict(os.environ, ROS_DOMAIN_ID=domain, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "tests.clock_probe", str(self.file)], cwd=REPO, env=env,
            stdout=subprocess.DEVNULL, stderr=open(tmp_path / "probe.err", "wb"),  # noqa: SIM115
        )  # fmt: skip

    def now_ns(self) -> int:
        self.shm.sample([self.proc.pid, *self.watch()])
        self.used |= shm_files_of([self.proc.pid, *self.watch()])
        try:
            return int(self.file.read_text())
        except (OSError, ValueError):
            return 0

    def wait_until(self, t_ns: int, timeout_s: float = 180.0) -> int:
        return wait_for(lambda: self.now_ns() if self.now_ns() >= t_ns else 0, timeout_s, f"sim time {t_ns} ns")

    def stop(self) -> None:
        self.shm.sample([self.proc.pid, *self.watch()])
        self.used |= shm_files_of([self.proc.pid, *self.watch()])
        self.proc.send_signal(signal.SIGINT)
        try:
            self.proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self.shm.cleanup()


def start_run_and_probe(tmp_path: Path, *extra: str) -> tuple[subprocess.Popen, dict[str, int], ClockProbe]:
    cli = start_lq(tmp_path, "run", *RUN_ARGS, "--out", str(tmp_path / "out"), "--json", *extra)
    try:
        nodes = wait_for(lambda: four_nodes(cli.pid), 120, "the four nodes")
        return cli, nodes, ClockProbe(tmp_path, domain_of(nodes["sim"]), watch=nodes.values)
    except BaseException:
        cli.kill()
        raise


def assert_nothing_left(pids, before_shm: set[str], ours: set[str] | None = None) -> None:
    wait_for(lambda: not any(alive(p) for p in pids), 60, "every process of the run to exit")
    left = orphaned_shm(before_shm, ours)
    assert left == [], {name: SHM_OWNERS.get(shm_base(name), "creator not seen") for name in left}


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> dict[str, list[tuple[int, bytes]]]:
    """The same episode in process: what the killed recorder's bag must be a prefix of."""
    bag = run_inprocess(CFG, tmp_path_factory.mktemp("reference")).bag_path
    return bag_messages(bag)


# -- the recorder killed with SIGKILL ----------------------------------------------------------------------


@pytest.mark.parametrize("kill_at_s", [0.6, 3.0, 7.5])
def test_killed_recorder_leaves_a_bag_scored_up_to_the_last_half_second(tmp_path, reference, kill_at_s):
    before_shm = set(os.listdir(SHM))
    cli, nodes, probe = start_run_and_probe(tmp_path)
    try:
        probe.wait_until(int(kill_at_s * 1e9))
        # The probe's reading lags the sim: one taken just before the kill is a lower bound of the sim time at
        # the kill. The sim runs on until the launcher stops it (how far depends on how fast the machine is). A
        # reading taken a fixed time after the kill is no upper bound on a loaded machine (seen: 0.3 s later the
        # probe read 50 ms less than a pose the recorder had written), so the bound is the sim's last /clock: the
        # probe's reading once the run has ended and its last message has had time to arrive.
        t_kill_min = probe.now_ns()
        os.kill(nodes["metrics"], signal.SIGKILL)
        cli.wait(timeout=120)
        time.sleep(1.0)
        t_kill_max = probe.now_ns()
    finally:
        probe.stop()
        if cli.poll() is None:
            cli.kill()
    assert cli.returncode == 1
    assert "metrics node exited with code -9" in (tmp_path / "lq.err").read_text()
    assert_nothing_left([*nodes.values(), probe.proc.pid], before_shm, probe.used)

    bag = tmp_path / "out" / CFG.episode_name()
    # metadata.yaml existed from the start, with the run's configuration.
    assert read_run_metadata(bag)["config_key"] == CFG.key()
    (mcap,) = bag.glob("*.mcap")
    scan = scan_mcap(mcap, keep_messages=True)
    assert not scan.complete and scan.damage  # no end records: the recorder died
    got: dict[str, list] = {}
    for topic, t_ns, data in scan.messages:
        got.setdefault(topic, []).append((t_ns, data))
    poses = got.get(m.EE_POSE.name, [])
    last_ns = max((t for t, _ in poses), default=0)
    assert last_ns <= t_kill_max
    # At most the last 0.5 s of sim time before the kill is lost (the writer flushes every FLUSH_SIM_NS of
    # sim time), plus the tick in flight and its delivery: 0.2 s.
    lost_at_most_ns = FLUSH_SIM_NS + 200_000_000
    if t_kill_min - lost_at_most_ns > reference[m.EE_POSE.name][0][0]:
        assert last_ns >= t_kill_min - lost_at_most_ns, (last_ns, t_kill_min)
    # What survived is exactly the start of the episode, byte for byte.
    for topic in DETERMINISTIC_TOPICS:
        kept = sorted(got.get(topic.name, []))
        assert kept == reference[topic.name][: len(kept)], topic.name

    # The scorer reads it: partial, a run error (never a success or failure), exit code 1.
    scored = subprocess.run([sys.executable, "-m", "lq_ros.cli", "score", str(bag), "--json"], cwd=REPO,
                            capture_output=True, text=True, timeout=120)  # fmt: skip
    assert scored.returncode == 1, scored.stderr
    row = json.loads(scored.stdout.strip().splitlines()[-1])
    assert row["partial"] is True and row["status"] == "error" and row["success"] is None
    assert row["policy"].startswith("sine")  # provenance from the provisional metadata.yaml

    # lq reindex rebuilds the counts from what is readable.
    result = reindex(bag)
    assert result.messages == len(scan.messages) and not result.complete
    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    counts = {t["topic_metadata"]["name"]: t["message_count"] for t in info["topics_with_message_count"]}
    assert counts[m.EE_POSE.name] == len(poses) and info["message_count"] == len(scan.messages)
    assert info["custom_data"]["lq_bag"].startswith("reindexed (damaged")


# -- any other process killed ------------------------------------------------------------------------------


@pytest.mark.parametrize("victim", ["sim", "policy", "executor"])
def test_killed_node_ends_the_run_as_an_error_and_leaves_nothing(tmp_path, victim):
    before_shm = set(os.listdir(SHM))
    cli, nodes, probe = start_run_and_probe(tmp_path)
    try:
        probe.wait_until(3_000_000_000)
        os.kill(nodes[victim], signal.SIGKILL)
        cli.wait(timeout=120)
    finally:
        probe.stop()
        if cli.poll() is None:
            cli.kill()
    assert cli.returncode == 1
    err = (tmp_path / "lq.err").read_text()
    assert f"{victim} node exited with code -9" in err and "Traceback" not in err
    assert_nothing_left([*nodes.values(), probe.proc.pid], before_shm, probe.used)
    row = json.loads((tmp_path / "lq.out").read_text().strip().splitlines()[-1])
    assert row["status"] == "error" and row["success"] is None
    # The recorder was stopped cleanly: a complete bag that says the episode never ended.
    bag = tmp_path / "out" / CFG.episode_name()
    assert bag_messages(bag)[m.EE_POSE.name], "rosbags reads the closed bag"
    assert any(bag.glob("logs/*.log"))


def test_killed_launcher_takes_every_node_with_it(tmp_path):
    before_shm = set(os.listdir(SHM))
    cli, nodes, probe = start_run_and_probe(tmp_path)
    try:
        probe.wait_until(3_000_000_000)
        os.kill(cli.pid, signal.SIGKILL)
        cli.wait(timeout=30)
        wait_for(lambda: not any(alive(p) for p in nodes.values()), 60, "the nodes to exit")
    finally:
        probe.stop()
    assert_nothing_left([*nodes.values(), probe.proc.pid], before_shm, probe.used)
    # The recorder, told to stop, closed its bag with a STOPPED event: a scored run error.
    bag = tmp_path / "out" / CFG.episode_name()
    scored = subprocess.run([sys.executable, "-m", "lq_ros.cli", "score", str(bag), "--json"], cwd=REPO,
                            capture_output=True, text=True, timeout=120)  # fmt: skip
    row = json.loads(scored.stdout.strip().splitlines()[-1])
    assert row["status"] == "error" and row["partial"] is False


def test_killed_sweep_worker_is_replaced_and_its_episode_retried(tmp_path):
    spec = tmp_path / "spec.yaml"
    spec.write_text(
        yaml.safe_dump(
            {
                "name": "faults",
                "transport": "ros",
                "tasks": [0],
                "inits": [0],
                "policies": ["sine"],
                "latencies_s": [0.2],
                "modes": ["async"],
                "max_steps": 120,
            }
        )  # fmt: skip
    )
    before_shm = set(os.listdir(SHM))
    out = tmp_path / "sweep"
    sweep = start_lq(tmp_path, "sweep", str(spec), "--workers", "1", "--out", str(out))
    seen: set[int] = set()
    try:
        nodes = wait_for(lambda: four_nodes(sweep.pid), 180, "the four nodes")
        seen |= set(nodes.values())
        worker = next(p for p in descendants(sweep.pid) if "spawn_main" in cmdline(p) and nodes["sim"] in
                      descendants(p))  # fmt: skip
        probe = ClockProbe(tmp_path, domain_of(nodes["sim"]), watch=nodes.values)
        try:
            probe.wait_until(2_000_000_000)
            os.kill(worker, signal.SIGKILL)
            seen |= descendants(sweep.pid)
        finally:
            probe.stop()
        seen.add(probe.proc.pid)
        used = set(probe.used)
        while sweep.poll() is None:
            seen |= descendants(sweep.pid)
            used |= shm_files_of(descendants(sweep.pid))
            time.sleep(0.2)
    finally:
        if sweep.poll() is None:
            sweep.kill()
    assert sweep.returncode == 0, (tmp_path / "lq.err").read_text()[-3000:]
    assert_nothing_left(seen, before_shm, used)
    (record,) = [json.loads(p.read_text()) for p in (out / "results").glob("*.json")]
    assert record["status"] == "failure" and record["row"]["completion_steps"] == 120
    first, second = record["attempts"]
    assert first["status"] == "error" and "worker process died (exit code -9)" in first["reason"]
    assert second["status"] == "failure"
    # The crashed attempt is kept with its bag, which the scorer reads (the recorder was stopped, not killed).
    assert (out / first["bag"] / "metadata.yaml").exists()


def test_stale_segments_of_dead_runs_are_removed_and_live_ones_kept(tmp_path):
    """A run killed all at once leaves its segments with nobody to clean up; the next stack removes them."""
    import fcntl

    from lq_ros.transport.processes import ShmTracker

    dead, live = "fastrtps_00lqtestdead0000", "fastrtps_00lqtestlive0000"
    old = time.time() - 3600
    for name in (dead, live):
        for path in (SHM / name, SHM / f"{name}_el"):
            path.write_bytes(b"")
            os.utime(path, (old, old))
    holder = os.open(SHM / f"{live}_el", os.O_RDWR)
    fcntl.flock(holder, fcntl.LOCK_EX)  # a live participant holds its segment's lock
    try:
        removed = ShmTracker.stale_segments().cleanup()
        assert {dead, f"{dead}_el"} <= set(removed)
        assert not (SHM / dead).exists() and (SHM / live).exists()
    finally:
        os.close(holder)
        for path in (SHM / live, SHM / f"{live}_el"):
            path.unlink(missing_ok=True)
