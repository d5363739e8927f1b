"""Managed nodes and the long-lived stack, on real processes (rclpy, Fast DDS on loopback, MuJoCo).

The lifecycle is driven here exactly as a user drives it (``ros2 lifecycle set``, ``ros2 param set``):
through the nodes' standard services from another process.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from lq_ros.core.run_config import RunConfig
from lq_ros.recording.bag_compare import comparable
from lq_ros.transport.inprocess import run_inprocess
from lq_ros.transport.processes import die_with_parent, fastdds_shm_owned
from lq_ros.transport.ros.stack import NODE_MODULE, RosStack, child_environment, launch_nodes, reserved_domain
from tests.transport.ros.test_faults import SHM, ClockProbe, alive, cmdline, orphaned_shm, wait_for

pytestmark = [pytest.mark.slow, pytest.mark.sim]


class LifecycleClient:
    """The calls ``ros2 lifecycle get/set`` and ``ros2 param set`` make, from a test process of its own domain."""

    def __init__(self, domain_id: int, node: str) -> None:
        import rclpy
        import rclpy.executors
        from lifecycle_msgs.srv import ChangeState, GetState
        from rcl_interfaces.srv import SetParameters

        self.rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node("lq_test_client", context=self.context)
        self.executor = rclpy.executors.SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.change = self.node.create_client(ChangeState, f"/{node}/change_state")
        self.get = self.node.create_client(GetState, f"/{node}/get_state")
        self.params = self.node.create_client(SetParameters, f"/{node}/set_parameters")
        self.types = ChangeState, GetState, SetParameters

    def _call(self, client, request):
        assert client.wait_for_service(timeout_sec=120), client.srv_name
        future = client.call_async(request)
        self.executor.spin_until_future_complete(future, timeout_sec=60)
        assert future.done(), client.srv_name
        return future.result()

    def state(self) -> str:
        return self._call(self.get, self.types[1].Request()).current_state.label

    def set_state(self, label: str) -> bool:
        from lifecycle_msgs.msg import Transition

        return self._call(self.change, self.types[0].Request(transition=Transition(label=label))).success

    def set_param(self, name: str, value) -> tuple[bool, str]:
        from rclpy.parameter import Parameter

        req = self.types[2].Request(parameters=[Parameter(name, value=value).to_parameter_msg()])
        (result,) = self._call(self.params, req).results
        return result.successful, result.reason

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.try_shutdown(context=self.context)


def start_node(role: str, domain_id: int, lock_fd: int, tmp_path: Path) -> subprocess.Popen:
    """One node program on its own in the domain (its output in ``tmp_path/<role>.log``), as a user starts it."""
    env = child_environment(domain_id, tmp_path / "ros_logs")
    with open(tmp_path / f"{role}.log", "wb") as log:
        return subprocess.Popen(
            [sys.executable, "-m", NODE_MODULE.format(role)], env=env, stdout=log, stderr=subprocess.STDOUT,
            preexec_fn=die_with_parent, pass_fds=(lock_fd,),
        )  # fmt: skip


def test_lifecycle_transitions_through_the_standard_services(tmp_path):
    """configure, activate, parameters refused while active, deactivate, cleanup, shutdown: the process exits."""
    before_shm = set(os.listdir(SHM))
    with reserved_domain() as domain:
        proc = start_node("executor", domain.id, domain.lock_fd, tmp_path)
        client = LifecycleClient(domain.id, "lq_executor")
        try:
            assert client.state() == "unconfigured"
            assert client.set_param("mode", "async") == (True, "")
            assert client.set_state("configure") and client.state() == "inactive"
            assert client.set_param("latency_s", 0.2) == (True, "")  # an episode parameter, between episodes
            assert client.set_state("activate") and client.state() == "active"
            ok, reason = client.set_param("latency_s", 0.1)
            assert not ok and "deactivate first" in reason
            assert client.set_state("deactivate") and client.state() == "inactive"
            assert not client.set_state("configure")  # not a transition of the inactive state
            assert client.set_param("merge", "no_such_merge") == (True, "")
            assert not client.set_state("activate") and client.state() == "inactive"  # refused, with its reason
            assert (
                "activate failed: ValueError: unknown merge 'no_such_merge'" in (tmp_path / "executor.log").read_text()
            )
            assert client.set_state("cleanup") and client.state() == "unconfigured"
            assert client.set_state("shutdown")
            assert proc.wait(timeout=30) == 0  # finalized: the program ends by itself
        finally:
            client.close()
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    assert orphaned_shm(before_shm) == []


#: One long-lived stack runs these in sequence: the protocol, latency, init state, seed, policy and task change
#: between episodes (a policy change cleans up and configures the policy node only, a task change the sim
#: node; the rest only reset the env, softly).
SEQUENCE = (
    RunConfig(policy="sine", mode="sync", latency_s=0.1, max_steps=25, replan_steps=3),
    RunConfig(policy="sine", mode="async", latency_s=0.2, max_steps=25, init=1, seed=3),
    RunConfig(policy="scripted", mode="sync", latency_s=0.0, max_steps=25, init=2),
    RunConfig(policy="scripted", mode="async", latency_s=0.1, max_steps=25, task=1),
    RunConfig(policy="sine", mode="async", latency_s=0.0, max_steps=25, replan_steps=3),
    RunConfig(policy="sine", mode="sync", latency_s=0.1, max_steps=25, replan_steps=3),  # = the first
)


def test_long_lived_stack_is_bit_identical_to_in_process_and_to_a_fresh_stack(tmp_path):
    before_shm = set(os.listdir(SHM))
    bags, pids = [], []
    with RosStack() as stack:
        for k, cfg in enumerate(SEQUENCE):
            bag, reason = stack.run_episode(cfg, tmp_path / f"stack{k}")
            assert reason == "", reason
            bags.append(bag)
            pids.append({n: p.pid for n, p in stack.procs.items()})
            assert pids[k] == pids[0], "no process was restarted"
        procs = list(stack.procs.values())
    assert all(p.returncode == 0 for p in procs), [p.returncode for p in procs]  # shut down through the lifecycle
    for k, (cfg, bag) in enumerate(zip(SEQUENCE, bags, strict=True)):
        local = run_inprocess(cfg, tmp_path / f"local{k}")
        assert comparable(bag) == comparable(local.bag_path), f"episode {k}: {cfg}"
    # The last episode again, on a stack of its own: the stack's history changes nothing.
    fresh, reason = launch_nodes(SEQUENCE[-1], tmp_path / "fresh")
    assert reason == ""
    assert comparable(fresh) == comparable(bags[-1]) == comparable(bags[0])
    # The env was created once per task: episodes 1 and 2 (a new policy) reused episode 0's env (soft reset).
    created = ["creating libero_spatial task" in (bag / "logs" / "sim.log").read_text() for bag in bags]
    assert created == [True, False, False, True, True, False]
    assert orphaned_shm(before_shm) == []


#: The killed episode: long enough that the clock probe, started with it, is subscribed well before its end
#: (the sine policy never succeeds, so it would run 1000 ticks); the kill comes at sim time KILL_AT_NS.
KILLED_CFG = RunConfig(policy="sine", mode="async", latency_s=0.2, max_steps=1000)
KILL_AT_NS = 2_000_000_000  # tick 40


def kill_node(stack: RosStack, name: str) -> int:
    """SIGKILL the process that runs node ``name`` now, as the stack knows it (never a PID noted earlier:
    the stack may have replaced the process since); returns its PID.

    Through a pidfd, so a PID that was reaped and reused meanwhile is never signalled: the fd is opened
    before checking the stack has not reaped the process, so it refers to that very process.
    """
    proc = stack.procs[name]
    fd = os.pidfd_open(proc.pid)
    try:
        assert proc.returncode is None, f"{name} node already exited ({proc.returncode})"
        assert f"{NODE_MODULE.format(name)} " in cmdline(proc.pid), cmdline(proc.pid)
        signal.pidfd_send_signal(fd, signal.SIGKILL)
    finally:
        os.close(fd)
    return proc.pid


def test_a_node_killed_mid_episode_is_restarted_and_the_next_episode_runs(tmp_path):
    before_shm = set(os.listdir(SHM))
    next_cfg = RunConfig(policy="sine", mode="sync", latency_s=0.1, max_steps=20, init=2)
    seen: set[int] = set()
    with RosStack() as stack, ThreadPoolExecutor(1) as pool:
        for victim in ("sim", "policy"):
            out = tmp_path / victim
            out.mkdir()
            # The probe follows this episode's /clock (the previous episode's publishers are gone with it).
            probe = ClockProbe(out, str(stack.domain.id), watch=lambda: [p.pid for p in stack.procs.values()])
            seen.add(probe.proc.pid)

            def kill_at_sim_time(probe: ClockProbe = probe, victim: str = victim) -> tuple[int, int]:
                now_ns = probe.wait_until(KILL_AT_NS)
                return now_ns, kill_node(stack, victim)

            try:
                killer = pool.submit(kill_at_sim_time)
                bag, reason = stack.run_episode(KILLED_CFG, out)
                if not reason and not killer.done():  # (a failure of the probe, not of the stack: say which)
                    pytest.fail(f"the episode ran to its end ({bag.name}) without the kill: the clock probe had read "
                                f"{probe.now_ns()} ns of sim time, waiting for {KILL_AT_NS}")  # fmt: skip
                assert reason == f"{victim} node exited with code -9", reason
                killed_at_ns, pid = killer.result(timeout=60)
            finally:
                probe.stop()  # before the next episode, which must run exactly as without it
            seen |= {p.pid for p in stack.procs.values()}
            assert stack.procs[victim].pid == pid, "the process that ran the episode is the one killed"
            assert killed_at_ns < KILLED_CFG.budget * 50_000_000  # mid-episode (20 Hz ticks)
            # The survivors were deactivated: the recorder closed the bag with a STOPPED event, a run error.
            assert json.loads((bag / "score.json").read_text())["status"] == "error"

            after, reason = stack.run_episode(next_cfg, tmp_path / f"{victim}_next")
            assert reason == "", reason
            assert stack.procs[victim].pid != pid
            assert stack.restarts == ({"sim": 1} if victim == "sim" else {"sim": 1, "policy": 1})
            if victim == "sim":  # the new process configured (created its env) for this episode
                assert "creating libero_spatial task 0" in (after / "logs" / "sim.log").read_text()
            seen |= {p.pid for p in stack.procs.values()}
            local = run_inprocess(next_cfg, tmp_path / f"{victim}_local")
            assert comparable(after) == comparable(local.bag_path)
    wait_for(lambda: not any(alive(p) for p in seen), 60, "every process of the stack to exit")
    assert orphaned_shm(before_shm) == []


def test_processes_started_before_the_first_episode_run_it(tmp_path):
    """RosStack.start() before any episode (as the killed-manager test does): the nodes start on the default
    parameters and run the first episode. They used to die in rclpy.init for want of the params file, which
    the first episode writes, and that episode silently ran on replacements: a PID noted after start() was
    dead by the time of a kill (the old killed-node test's failure, when the test process was slow enough)."""
    with RosStack() as stack:
        stack.start()
        started = {n: p.pid for n, p in stack.procs.items()}
        # Each process has created its ROS participant (it owns Fast DDS files) or died trying.
        wait_for(
            lambda: all(p.poll() is not None or fastdds_shm_owned(p.pid) for p in stack.procs.values()),
            120,
            "every process to initialise ROS",
        )
        dead = stack._dead()
        assert not dead, {n: (stack.work / f"{n}.log").read_text()[-500:] for n in dead}
        bag, reason = stack.run_episode(RunConfig(policy="sine", max_steps=5), tmp_path)
        assert reason == "", reason
        assert {n: p.pid for n, p in stack.procs.items()} == started and stack.restarts == {}


def test_a_refused_activation_is_the_episode_error_with_its_reason_and_the_stack_goes_on(tmp_path):
    # The scripted expert cannot inpaint against an executing prefix: its node refuses to activate for rtc.
    refused = RunConfig(policy="scripted", mode="async", latency_s=0.2, merge="rtc", max_steps=10)
    fine = RunConfig(policy="scripted", mode="async", latency_s=0.2, max_steps=10)
    with RosStack() as stack:
        bag, reason = stack.run_episode(refused, tmp_path)
        assert reason.startswith("policy node: activate failed: ValueError: merge 'rtc' (real-time chunking)"), reason
        # The recorder was already active, but no episode started: it keeps no bag (the run is an error by its
        # reason alone), and the node logs are kept beside where the bag would have been.
        assert not bag.exists() and (bag.with_name(bag.name + ".logs") / "policy.log").exists()
        bag, reason = stack.run_episode(fine, tmp_path)
        assert reason == "" and (bag / "score.json").exists()


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGKILL])
def test_an_interrupted_ros_sweep_leaves_no_process_and_no_shm_file(tmp_path, sig):
    import yaml

    from tests.transport.ros.test_faults import descendants

    spec = tmp_path / "spec.yaml"
    spec.write_text(yaml.safe_dump({"name": "stop", "transport": "ros", "tasks": [0], "inits": [0, 1, 2],
                                    "policies": ["sine"], "latencies_s": [0.1], "modes": ["async"],
                                    "max_steps": 60}))  # fmt: skip
    before_shm = set(os.listdir(SHM))
    out = tmp_path / "out"
    with open(tmp_path / "sweep.log", "wb") as log:
        sweep = subprocess.Popen(
            [sys.executable, "-m", "lq_ros.cli", "sweep", str(spec), "--workers", "1", "--out", str(out)],
            stdout=log, stderr=subprocess.STDOUT,
        )  # fmt: skip
    seen: set[int] = set()
    try:
        # The second episode runs on the stack of the first: interrupt it there.
        wait_for(lambda: len(list((out / "results").glob("*.json"))) >= 1, 300, "the first episode")
        seen |= descendants(sweep.pid) | {sweep.pid}
        semaphores = mapped_semaphores(seen)
        time.sleep(3.0)
        seen |= descendants(sweep.pid)
        semaphores |= mapped_semaphores(seen)
        assert len(seen) >= 7, seen  # sweep, worker, manager and the four nodes (at least)
        sweep.send_signal(sig)
        sweep.wait(timeout=120)
    finally:
        if sweep.poll() is None:
            sweep.kill()
    wait_for(lambda: not any(alive(p) for p in seen), 90, "every process of the sweep to exit")
    # The sweep's own multiprocessing semaphores are gone. (Other runs on the machine create and drop theirs
    # meanwhile, so unattributed sem.mp-* files are not counted; Fast DDS files are attributed by their locks.)
    assert not semaphores & set(os.listdir(SHM)), semaphores
    assert [f for f in orphaned_shm(before_shm) if not f.startswith("sem.mp-")] == []


def wait_until_recording(out: Path) -> None:
    """Until the episode's bag below ``out`` has grown twice: the STARTED event's chunk, then the first
    0.5 s of sim time (the sim is stepping, ~10 ticks into a 220-tick episode). A fixed sleep after the bag
    appeared was a race: on idle cores a 220-tick sine episode ends within 2 s."""
    sizes: list[int] = []

    def grown_twice() -> bool:
        size = max((f.stat().st_size for f in out.glob("*/*.mcap")), default=0)
        if size and (not sizes or size > sizes[-1]):
            sizes.append(size)
        return len(sizes) >= 3  # header, STARTED chunk, first data chunk

    wait_for(grown_twice, 120, "the episode's first data chunk")


def mapped_semaphores(pids: set[int]) -> set[str]:
    """Python multiprocessing semaphores (/dev/shm/sem.mp-*) that the processes ``pids`` have mapped."""
    out = set()
    for pid in pids:
        try:
            maps = Path(f"/proc/{pid}/maps").read_text()
        except OSError:
            continue
        out |= {line.rsplit("/", 1)[1] for line in maps.splitlines() if "/dev/shm/sem.mp-" in line}
    return out


def test_a_killed_lifecycle_manager_ends_the_episode_and_the_stack(tmp_path):
    before_shm = set(os.listdir(SHM))
    cfg = RunConfig(policy="sine", mode="async", latency_s=0.2, max_steps=220)
    stack = RosStack()
    try:
        stack.start()
        pids = {p.pid for p in stack.procs.values()}
        pid = stack.procs["manager"].pid

        def kill_when_running() -> None:
            wait_until_recording(tmp_path)
            os.kill(pid, signal.SIGKILL)

        killer = threading.Thread(target=kill_when_running)
        killer.start()
        bag, reason = stack.run_episode(cfg, tmp_path)
        killer.join()
        assert reason == "lifecycle manager exited with code -9"
        assert stack.closed  # a sweep worker starts a new stack for its next episode
        assert json.loads((bag / "score.json").read_text())["status"] == "error"  # recorder stopped by SIGINT
        assert (bag / "logs" / "manager.log").exists()
    finally:
        stack.close()
    wait_for(lambda: not any(alive(p) for p in pids), 60, "every process of the stack to exit")
    assert orphaned_shm(before_shm) == []
