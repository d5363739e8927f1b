"""ROS habits, on real processes: the lifecycle manager's ``~/manage_nodes`` service (nav2's commands) and the policy
node's arguments as parameters of their own, each driven from this process with rclpy, as a ROS user drives them."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from lq_ros.core.run_config import RunConfig
from lq_ros.policies.sine import SinePolicy
from lq_ros.recording.episode_bag import read_run_metadata
from lq_ros.scoring.bag_scorer import score_bag
from lq_ros.transport.processes import die_with_parent
from lq_ros.transport.ros.stack import NODE_MODULE, child_environment, node_parameters, params_yaml, reserved_domain
from lq_ros.wire.node_names import NODE_NAMES, stack_node_names
from tests.transport.ros.test_faults import wait_for
from tests.transport.ros.test_lifecycle import LifecycleClient

pytestmark = [pytest.mark.slow, pytest.mark.sim]

MANAGED = stack_node_names(robot=False)  # lq_metrics, lq_policy, lq_executor, lq_sim


class ManageNodesClient(LifecycleClient):
    """``ros2 service call /lq_manager/manage_nodes lq_msgs/srv/ManageNodes "{command: N}"``, and the lifecycle
    and parameter services of every managed node."""

    def __init__(self, domain_id: int) -> None:
        super().__init__(domain_id, NODE_NAMES["metrics"])
        from lifecycle_msgs.srv import GetState
        from lq_msgs.srv import ManageNodes

        self.ManageNodes = ManageNodes
        self.manage_client = self.node.create_client(ManageNodes, f"/{NODE_NAMES['manager']}/manage_nodes")
        self.getters = {n: self.node.create_client(GetState, f"/{n}/get_state") for n in MANAGED}

    def manage(self, command: str | int) -> tuple[bool, str]:
        value = getattr(self.ManageNodes.Request, command.upper()) if isinstance(command, str) else command
        result = self._call(self.manage_client, self.ManageNodes.Request(command=value), timeout_s=600)
        return result.success, result.message

    def set_on(self, node: str, name: str, value) -> None:
        """``ros2 param set /NODE NAME VALUE``."""
        from rcl_interfaces.srv import SetParameters
        from rclpy.parameter import Parameter

        client = self.node.create_client(SetParameters, f"/{node}/set_parameters")
        request = SetParameters.Request(parameters=[Parameter(name, value=value).to_parameter_msg()])
        (result,) = self._call(client, request).results
        assert result.successful, (node, name, result.reason)

    def states(self) -> dict[str, str]:
        return {n: self._call(c, self.types[1].Request()).current_state.label for n, c in self.getters.items()}

    def _call(self, client, request, timeout_s: float = 60):
        assert client.wait_for_service(timeout_sec=120), client.srv_name
        future = client.call_async(request)
        self.executor.spin_until_future_complete(future, timeout_sec=timeout_s)
        assert future.done(), client.srv_name
        return future.result()


def start(module: str, domain_id: int, lock_fd: int, tmp_path: Path, name: str, *ros_args: str) -> subprocess.Popen:
    """A program on its own in the domain, as a user starts it by hand (stdin: nothing, no launcher)."""
    env = child_environment(domain_id, tmp_path / "ros_logs")
    with open(tmp_path / f"{name}.log", "wb") as log:
        return subprocess.Popen(
            [sys.executable, "-m", module, *(("--ros-args", *ros_args) if ros_args else ())], env=env,
            stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT, preexec_fn=die_with_parent,
            pass_fds=(lock_fd,),
        )  # fmt: skip


def stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.kill()
        proc.wait()


def test_the_manager_answers_manage_nodes_beside_no_launcher(tmp_path):
    """STARTUP runs an episode with the nodes' own parameters (the manager ends it as the launcher's), RESUME the
    next, PAUSE stops it, RESET leaves every node unconfigured, SHUTDOWN ends their processes; the manager stays."""
    cfg = RunConfig(policy="sine", mode="async", latency_s=0.1, max_steps=10)
    params = tmp_path / "params.yaml"
    params.write_text(params_yaml(node_parameters(cfg, tmp_path / "ep1", (), 224, {"chunk_size": 8})))
    with reserved_domain() as domain:
        by_hand = ("--params-file", str(params))
        nodes = [start(NODE_MODULE.format(role), domain.id, domain.lock_fd, tmp_path, role, *by_hand)
                 for role in ("metrics", "policy", "executor", "sim")]  # fmt: skip
        manager = start(NODE_MODULE.format("manager"), domain.id, domain.lock_fd, tmp_path, "manager")
        client = ManageNodesClient(domain.id)
        try:
            ok, message = client.manage("startup")
            assert ok, message
            assert message.startswith("startup: configured ") and "activated lq_metrics" in message
            # The episode ends by itself (10 ticks); the manager then deactivates the others, as for the launcher.
            wait_for(
                lambda: set(client.states().values()) == {"inactive"}, 120, "every node inactive after the episode"
            )
            first = score_bag(tmp_path / "ep1")
            assert first["status"] == "failure" and first["completion_steps"] == 10  # the sine policy never succeeds
            assert read_run_metadata(tmp_path / "ep1")["config"]["max_steps"] == 10
            # The next episode: new parameters between episodes, then RESUME (nothing is configured again).
            client.set_on(NODE_NAMES["metrics"], "bag_path", str(tmp_path / "ep2"))
            for node in MANAGED:
                client.set_on(node, "max_steps", 5000)  # runs until paused
            ok, message = client.manage("resume")
            assert ok and message == "resume: activated " + ", ".join(MANAGED), message
            ok, message = client.manage("pause")
            assert ok and message == "pause: deactivated lq_sim, lq_executor, lq_policy, lq_metrics", message
            assert set(client.states().values()) == {"inactive"}
            second = score_bag(tmp_path / "ep2")  # stopped: a run error, scored over what was recorded
            assert second["status"] == "error" and "stopped" in second["error_reason"], second
            # A refused RESUME (the executor cannot activate): no node is left active, and no bag is written.
            client.set_on(NODE_NAMES["metrics"], "bag_path", str(tmp_path / "ep3"))
            client.set_on(NODE_NAMES["executor"], "merge", "no_such_merge")
            ok, message = client.manage("resume")
            assert not ok and message.startswith("resume: lq_executor activate"), message
            assert set(client.states().values()) == {"inactive"}
            assert not (tmp_path / "ep3").exists()
            client.set_on(NODE_NAMES["executor"], "merge", "replace")
            assert client.manage("pause") == (True, "pause: nothing to do")
            assert client.manage(99)[1].startswith("manage_nodes: unknown command 99; known: startup (0), pause (1)")
            ok, message = client.manage("reset")
            assert ok and message == "reset: cleaned up " + ", ".join(MANAGED), message
            assert set(client.states().values()) == {"unconfigured"}
            ok, message = client.manage("shutdown")
            assert ok, message
            for proc in nodes:
                assert proc.wait(timeout=60) == 0
            assert manager.poll() is None, "the manager keeps serving after SHUTDOWN, as nav2's"
            ok, message = client.manage("resume")  # no node left: a refusal naming the node, not a hang
            assert not ok and message.startswith("resume: lq_metrics get_state: "), message
        finally:
            client.close()
            if manager.poll() is None:
                manager.send_signal(signal.SIGINT)
            assert manager.wait(timeout=30) in (0, -signal.SIGINT)
            for proc in nodes:
                stop(proc)
    log = (tmp_path / "manager.log").read_text()
    assert "manage_nodes startup:" in log and "Traceback" not in log


def test_policy_arguments_are_parameters_one_by_one(tmp_path):
    """``policy_args.<name>``: given at launch, set one by one, refused with the policy's arguments when the policy
    does not take the name, read at configure over the JSON ``policy_args``, cleared by another policy."""
    with reserved_domain() as domain:
        proc = start(NODE_MODULE.format("policy"), domain.id, domain.lock_fd, tmp_path, "policy",
                     "-p", "policy:=sine", "-p", "policy_args.amplitude:=0.25")  # fmt: skip
        client = LifecycleClient(domain.id, NODE_NAMES["policy"])
        try:
            ok, reason = client.set_param("policy_args.chunk", 4)
            assert not ok and "policy 'sine' takes no argument 'chunk'; its arguments: chunk_size: int = 8" in reason
            ok, reason = client.set_param("policy_args.chunk_size", "four")
            assert not ok and "chunk_size='four' is a str, not int" in reason
            assert client.set_param("policy_args.chunk_size", 0) == (True, "")  # a value the constructor refuses
            assert not client.set_state("configure") and client.state() == "unconfigured"
            log = (tmp_path / "policy.log").read_text()
            assert "configure failed: ValueError: chunk_size must be >= 1" in log  # the parameter reached it
            assert client.set_param("policy_args.chunk_size", 4) == (True, "")
            assert client.set_state("configure") and client.state() == "inactive"
            ok, reason = client.set_param("policy_args.amplitude", 0.5)  # between episodes: accepted ...
            assert ok, reason
            assert not client.set_state("activate")  # ... but configure loads it: cleanup and configure first
            assert "policy_args.amplitude changed since configure" in (tmp_path / "policy.log").read_text()
            assert client.set_state("cleanup") and client.set_state("configure") and client.set_state("activate")
            ok, reason = client.set_param("policy_args.chunk_size", 6)
            assert not ok and "deactivate first" in reason
            assert client.set_state("deactivate") and client.set_state("cleanup")
            # Another policy clears the old one's arguments: scripted takes no chunk_size, and configures.
            assert client.set_param("policy", "scripted") == (True, "")
            assert client.set_state("configure"), (tmp_path / "policy.log").read_text()[-2000:]
            assert client.set_state("shutdown")
            assert proc.wait(timeout=30) == 0
        finally:
            client.close()
            stop(proc)
    assert os.path.exists(tmp_path / "policy.log")


class GainSine(SinePolicy):
    """A user's own policy class (``package.module:Class``) with a typed argument."""

    def __init__(self, gain: float = 0.5) -> None:
        super().__init__(amplitude=gain)


def test_a_user_class_arguments_are_checked_at_configure_like_a_registered_ones(tmp_path):
    """``policy_args.<name>`` of a ``package.module:Class``: a name it does not take and a value of the wrong type
    are refused at configure, in one line with its arguments (a registered policy's: as they are set, above)."""
    user_class = f"{__name__}:GainSine"
    with reserved_domain() as domain:
        for i, (arg, expected) in enumerate([
            ("policy_args.bogus:=1", f"policy '{user_class}' takes no argument 'bogus'; its arguments: gain: float"),
            ("policy_args.gain:=fast", f"policy '{user_class}': gain='fast' is a str, not float"),
        ]):  # fmt: skip
            proc = start(NODE_MODULE.format("policy"), domain.id, domain.lock_fd, tmp_path, f"policy{i}",
                         "-p", f"policy:={user_class}", "-p", arg)  # fmt: skip
            client = LifecycleClient(domain.id, NODE_NAMES["policy"])
            try:
                assert not client.set_state("configure") and client.state() == "unconfigured"
                log = (tmp_path / f"policy{i}.log").read_text()
                assert f"configure failed: InputError: {expected}" in log, log[-2000:]
                assert client.set_state("shutdown")
                assert proc.wait(timeout=30) == 0
            finally:
                client.close()
                stop(proc)
