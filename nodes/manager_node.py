"""Lifecycle manager: moves the stack's managed nodes through their lifecycle, one episode at a time.

The role of nav2's lifecycle_manager or ros2_control's controller manager: it calls each node's standard
services, ``~/set_parameters`` (rcl_interfaces), ``~/change_state`` and ``~/get_state`` (lifecycle_msgs),
nothing else. Which nodes it manages is its ``node_names`` parameter (as nav2's), in activation order: the
recorder (``lq_metrics``) first, the node that starts the episode (the sim, or the bridge to a robot) last.
The launcher (lq_ros/transport/ros/stack.py, which keeps rclpy out of its own process so a killed launcher
leaves no Fast DDS file behind) sends it one JSON object per line on stdin and reads one per line on stdout
(nodes by their ROS names):

- ``{"op": "episode", "params": {node: {name: value}}, "reconfigure": [node, ...]}``: every node to inactive
  with the episode's parameters (configured if it was not, cleaned up and configured again if named),
  then activated in ``node_names`` order. Answers ``{"event": "active"}`` or ``{"event": "failed",
  "node", "transition", "reason"}``; later ``{"event": "done"}``, once the recorder has deactivated itself
  (its bag is closed and scored) and the other nodes were deactivated.
- ``{"op": "stop", "skip": [node, ...]}``: deactivate every active node in the reverse order (the node that
  steps first, the recorder last, which then records a STOPPED event); ``skip`` names dead nodes. Answers
  ``{"event": "stopped"}``.
- ``{"op": "shutdown", "skip": [...]}``: the shutdown transition for every node (they exit), then this
  process exits. Answers ``{"event": "shutdown"}``.

The launcher's pipe is read only when stdin is one (a manager started by hand, ``ros2 run lq_ros manager_node``,
serves its service alone). Beside it, the manager answers ``~/manage_nodes`` (``/lq_manager/manage_nodes``,
lq_msgs/srv/ManageNodes: nav2's ManageLifecycleNodes request) for anyone in the ROS domain: STARTUP, PAUSE,
RESUME, RESET, SHUTDOWN, CONFIGURE, CLEANUP, each over every node of ``node_names``. Both sources are served one
operation at a time, in the order they arrive. An episode that STARTUP or RESUME started is ended like the
launcher's: once the recorder has deactivated itself, the others are deactivated. A PAUSE, RESET or SHUTDOWN
during the launcher's episode ends it (the launcher hears ``{"event": "done"}`` and scores what was recorded).

The service lives on a node of its own, ``lq_manager`` (with the ``node_names`` parameter), spun in a thread: its
callback waits for the operation while the calls to the managed nodes are made and spun by a second, hidden node
(``_lq_manager_calls``) in the main thread.
"""

from __future__ import annotations

import contextlib
import json
import os
import queue
import stat
import sys
import threading
import time
from dataclasses import dataclass, field

import rclpy
from lifecycle_msgs.msg import Transition, TransitionEvent
from lifecycle_msgs.srv import ChangeState, GetState
from lq_msgs.srv import ManageNodes
from rcl_interfaces.srv import SetParameters
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation
from rclpy.node import Node
from rclpy.parameter import Parameter

from lq_ros.transport.processes import end_teardown_after
from lq_ros.wire.node_names import NODE_NAMES, stack_node_names

#: The recorder: the episode is over once it has left the active state (its bag is closed and scored).
RECORDER = NODE_NAMES["metrics"]
#: Wall seconds: a node's services to appear (a cold process imports MuJoCo, torch...), a configure (creates
#: the task's simulator or loads a policy), any other transition or call.
SERVICE_WAIT_S, CONFIGURE_S, CALL_S = 300.0, 600.0, 60.0
#: Wall seconds between two looks at the recorder's state during an episode when no transition event of it was
#: heard (a missed event costs at most this); between get_state attempts.
POLL_PERIOD_S, RETRY_S = 0.5, 2.0
#: Wall seconds between two looks for a node's service that is not there yet (a fresh stack's nodes appear while
#: the manager waits for them). rclpy's ``Client.wait_for_service`` looks every 0.25 s, so a node that appeared
#: just after a look was configured up to 0.25 s late; a look is a query of the local graph cache.
SERVICE_LOOK_S = 0.005
#: Wall seconds a manage_nodes call waits for its operation (queued behind others, configuring every node).
MANAGE_ANSWER_S = 3600.0
#: The node that does the calls to the managed nodes: hidden (a leading underscore), the service node is the face.
CALLS_NODE = "_" + NODE_NAMES["manager"] + "_calls"
#: manage_nodes command -> its name (lq_msgs/srv/ManageNodes; nav2's ManageLifecycleNodes values).
COMMANDS = {
    ManageNodes.Request.STARTUP: "startup", ManageNodes.Request.PAUSE: "pause", ManageNodes.Request.RESUME: "resume",
    ManageNodes.Request.RESET: "reset", ManageNodes.Request.SHUTDOWN: "shutdown",
    ManageNodes.Request.CONFIGURE: "configure", ManageNodes.Request.CLEANUP: "cleanup",
}  # fmt: skip


@dataclass
class ServiceCall:
    """A manage_nodes request, answered by the main loop: (success, message) in ``result`` once ``done`` is set."""

    command: int
    done: threading.Event = field(default_factory=threading.Event)
    result: tuple[bool, str] = (False, "not served")


class TransitionFailed(Exception):
    def __init__(self, node: str, transition: str, reason: str) -> None:
        super().__init__(f"{node} {transition}: {reason}")
        self.node, self.transition, self.reason = node, transition, reason


def managed_node_names(node: Node) -> tuple[str, ...]:
    """The ``node_names`` parameter of ``node`` (declared here): the managed nodes in activation order."""
    node.declare_parameter("node_names", list(stack_node_names(robot=False)))
    names = tuple(node.get_parameter("node_names").value)
    if RECORDER not in names:
        raise ValueError(f"node_names must include the recorder {RECORDER!r}, got {list(names)}")
    return names


class LifecycleManager(Node):
    def __init__(self, node_names: tuple[str, ...]) -> None:
        super().__init__(CALLS_NODE)
        # The managed nodes, in activation order (deactivation: the reverse).
        self.node_names = node_names
        self.change = {n: self.create_client(ChangeState, f"/{n}/change_state") for n in self.node_names}
        self.get = {n: self.create_client(GetState, f"/{n}/get_state") for n in self.node_names}
        self.set_params = {n: self.create_client(SetParameters, f"/{n}/set_parameters") for n in self.node_names}

    # -- service calls --------------------------------------------------------------------------------
    def _wait(self, node: str, what: str, futures_timeout_s: float, *futures) -> list:
        rclpy.spin_until_future_complete(self, _all(futures), timeout_sec=futures_timeout_s)
        if not all(f.done() for f in futures):
            raise TransitionFailed(node, what, f"no answer within {futures_timeout_s:.0f} s")
        return [f.result() for f in futures]

    def _ready(self, node: str, client, what: str, wait_s: float) -> None:
        if not wait_for_service(client, wait_s):
            raise TransitionFailed(node, what, f"service {client.srv_name} not available within {wait_s:.0f} s")

    def state(self, node: str, wait_s: float = SERVICE_WAIT_S) -> str:
        """The node's state label, asked again every RETRY_S until ``wait_s``.

        A node restarted after a SIGKILL is still in the graph under its old participant for a while
        (its lease has not expired), so its service looks ready before the new process serves it and a
        request can go unanswered; get_state is safe to repeat, and once it answers, the calls that are
        not (change_state) reach the live process.
        """
        deadline = time.monotonic() + wait_s
        client = self.get[node]
        while True:
            self._ready(node, client, "get_state", max(0.0, deadline - time.monotonic()))
            future = client.call_async(GetState.Request())
            rclpy.spin_until_future_complete(
                self, future, timeout_sec=min(RETRY_S, max(0.0, deadline - time.monotonic()))
            )
            if future.done():
                return future.result().current_state.label
            client.remove_pending_request(future)
            if time.monotonic() >= deadline:
                raise TransitionFailed(node, "get_state", f"no answer within {wait_s:.0f} s")

    def _request_transition(self, node: str, label: str, wait_s: float):
        """Send ``label`` to ``node`` once its change_state service is there (TransitionFailed if not within
        ``wait_s``); returns the future of its answer."""
        self._ready(node, self.change[node], label, wait_s)
        return self.change[node].call_async(ChangeState.Request(transition=Transition(label=label)))

    def transition(self, nodes: list[str], label: str, timeout_s: float = CALL_S, wait_s: float = SERVICE_WAIT_S):
        """Transition ``label`` for ``nodes`` at once (they run it concurrently); TransitionFailed if one refuses."""
        futures = [self._request_transition(node, label, wait_s) for node in nodes]
        for node, future in zip(nodes, futures, strict=True):
            (resp,) = self._wait(node, label, timeout_s, future)
            if not resp.success:
                raise TransitionFailed(node, label, "refused (see the node's log)")

    def states(self, nodes: list[str], wait_s: float = SERVICE_WAIT_S) -> dict[str, str]:
        """Every node's state label, asked of all at once; a node that does not answer at once (restarted after a
        SIGKILL: :meth:`state`) is asked again on its own. ``wait_s``: for a node's service to appear."""
        futures = {}
        for node in nodes:
            self._ready(node, self.get[node], "get_state", wait_s)
            futures[node] = self.get[node].call_async(GetState.Request())
        rclpy.spin_until_future_complete(self, _all(list(futures.values())), timeout_sec=RETRY_S)
        labels = {}
        for node, future in futures.items():
            if future.done():
                labels[node] = future.result().current_state.label
            else:
                self.get[node].remove_pending_request(future)
                labels[node] = self.state(node, wait_s)
        return labels

    def set_parameters(self, params: dict[str, dict]) -> None:
        """Each node's parameters (``{node: {name: value}}``), sent to all at once."""
        futures = {}
        for node, values in params.items():
            self._ready(node, self.set_params[node], "set_parameters", SERVICE_WAIT_S)
            msgs = [Parameter(k, value=v).to_parameter_msg() for k, v in values.items()]
            futures[node] = self.set_params[node].call_async(SetParameters.Request(parameters=msgs))
        for node, future in futures.items():
            (resp,) = self._wait(node, "set_parameters", CALL_S, future)
            values = params[node]
            bad = [f"{p}: {r.reason}" for p, r in zip(values, resp.results, strict=True) if not r.successful]
            if bad:
                raise TransitionFailed(node, "set_parameters", "; ".join(bad))

    # -- operations ----------------------------------------------------------------------------------
    def episode(self, params: dict[str, dict], reconfigure: list[str]) -> None:
        """Every node to inactive with the episode's parameters, then activated: the recorder first, the node that
        starts the episode last, the ones between together (calls to several nodes go out at once)."""
        states = self.states(list(self.node_names))
        active = [n for n in self.node_names if states[n] == "active"]
        if active:
            self.transition(active, "deactivate")
            states.update(dict.fromkeys(active, "inactive"))
        stale = [n for n in self.node_names if states[n] == "inactive" and n in reconfigure]
        if stale:
            self.transition(stale, "cleanup")
            states.update(dict.fromkeys(stale, "unconfigured"))
        for node in self.node_names:
            if states[node] not in ("inactive", "unconfigured"):
                raise TransitionFailed(node, "configure", f"node is {states[node]}")
        self.set_parameters({node: params.get(node, {}) for node in self.node_names})
        to_configure = [n for n in self.node_names if states[n] == "unconfigured"]
        if to_configure:
            self.transition(to_configure, "configure", CONFIGURE_S)  # concurrently: env creation, policy loading
        first, *between, last = self.node_names
        for group in ([first], between, [last]):
            if group:
                self.transition(group, "activate")

    def end_episode(self) -> None:
        """The recorder has closed and scored the bag: deactivate the other nodes (those still active), all at once."""
        try:
            states = self.states([n for n in self.node_names if n != RECORDER], wait_s=5.0)
            self.transition([n for n, state in states.items() if state == "active"], "deactivate", wait_s=5.0)
        except TransitionFailed as exc:  # e.g. a node that died meanwhile: the stop below finds out
            self.get_logger().error(str(exc))
            self.stop(set())

    # -- manage_nodes (nav2's commands over every node) ----------------------------------------------------
    def manage(self, command: int) -> str:
        """Carry out a manage_nodes command; returns what was done, raises TransitionFailed (or ValueError)."""
        name = COMMANDS.get(command)
        if name is None:
            raise ValueError(
                f"unknown command {command}; known: " + ", ".join(f"{v} ({k})" for k, v in COMMANDS.items())
            )
        wait_s = SERVICE_WAIT_S if name in ("startup", "configure") else 5.0
        states = self.states(list(self.node_names), wait_s=wait_s)
        done: list[str] = []
        if name in ("pause", "reset"):
            active = []
            for node in reversed(self.node_names):  # one by one, the sim first: nothing steps without its peers
                # Asked again right before: the recorder deactivates itself once the sim has stopped the episode.
                if states[node] == "active" and self.state(node, wait_s) == "active":
                    self.transition([node], "deactivate")
                    active.append(node)
                states[node] = "inactive" if states[node] == "active" else states[node]
            done += [f"deactivated {', '.join(active)}"] if active else []
        if name in ("reset", "cleanup"):
            if name == "cleanup" and any(states[n] == "active" for n in self.node_names):
                raise ValueError("cleanup: some nodes are active; pause first")
            inactive = [n for n in self.node_names if states[n] == "inactive"]
            self.transition(inactive, "cleanup")
            done += [f"cleaned up {', '.join(inactive)}"] if inactive else []
        if name in ("startup", "configure"):
            unconfigured = [n for n in self.node_names if states[n] == "unconfigured"]
            self.transition(unconfigured, "configure", CONFIGURE_S)  # concurrently: env creation, policy loading
            states.update(dict.fromkeys(unconfigured, "inactive"))
            done += [f"configured {', '.join(unconfigured)}"] if unconfigured else []
        if name in ("startup", "resume"):
            if any(states[n] == "unconfigured" for n in self.node_names):
                raise ValueError("resume: some nodes are unconfigured; startup (or configure) first")
            inactive = [n for n in self.node_names if states[n] == "inactive"]
            first, *between, last = self.node_names  # the recorder first, the node that starts the episode last
            try:
                for group in ([first], between, [last]):
                    if group := [n for n in group if n in inactive]:
                        self.transition(group, "activate")
            except TransitionFailed:  # no node is left active (the recorder then keeps no bag: nothing started)
                self.stop(set())
                raise
            done += [f"activated {', '.join(inactive)}"] if inactive else []
        if name == "shutdown":
            failed = self.shutdown({n for n, state in states.items() if state == "finalized"})
            if failed:
                raise ValueError("shutdown: " + "; ".join(failed))
            done.append(f"shut down {', '.join(self.node_names)}")
        return f"{name}: " + ("; ".join(done) or "nothing to do")

    def stop(self, skip: set[str]) -> None:
        for node in reversed(self.node_names):
            if node in skip:
                continue
            try:
                if self.state(node, wait_s=5.0) == "active":
                    self.transition([node], "deactivate", wait_s=5.0)
            except TransitionFailed as exc:
                self.get_logger().error(str(exc))

    def shutdown(self, skip: set[str]) -> list[str]:
        """The shutdown transition for every node not in ``skip``: the others all at once (they exit concurrently),
        then the recorder, which closes an unfinished bag once nothing else publishes. A node that is not there,
        refuses or does not answer is logged, and the others still go. Returns what failed, one text per node."""
        others = [n for n in reversed(self.node_names) if n not in skip and n != RECORDER]
        failed = []
        for group in (others, [RECORDER] if RECORDER not in skip else []):
            futures = {}
            for node in group:
                try:
                    futures[node] = self._request_transition(node, "shutdown", 5.0)
                except TransitionFailed as exc:
                    self.get_logger().error(str(exc))
                    failed.append(str(exc))
            rclpy.spin_until_future_complete(self, _all(list(futures.values())), timeout_sec=CALL_S)
            for node, future in futures.items():
                if not future.done():
                    why = f"no answer within {CALL_S:.0f} s"
                elif not future.result().success:
                    why = "refused (see the node's log)"
                else:
                    continue
                failed.append(str(TransitionFailed(node, "shutdown", why)))
                self.get_logger().error(failed[-1])
        return failed


def wait_for_service(client, timeout_s: float, look_s: float = SERVICE_LOOK_S) -> bool:
    """Whether ``client``'s service is there, waiting up to ``timeout_s`` for it (rclpy's
    ``Client.wait_for_service``, looking every ``look_s`` instead of every 0.25 s)."""
    deadline = time.monotonic() + timeout_s
    while not client.service_is_ready():
        if not client.context.ok() or time.monotonic() >= deadline:
            return client.service_is_ready()
        time.sleep(look_s)
    return True


def _all(futures):
    """A future done when all of ``futures`` are (spin_until_future_complete takes one)."""
    from rclpy.task import Future

    combined = Future()

    def check(_=None) -> None:
        if all(f.done() for f in futures) and not combined.done():
            combined.set_result(True)

    for f in futures:
        f.add_done_callback(check)
    check()
    return combined


def read_ops(ops: queue.SimpleQueue, wake) -> None:
    """Put each of the launcher's lines on ``ops`` (None once stdin closes: the launcher is gone) and wake the spin."""
    buffer = b""
    while True:
        chunk = os.read(sys.stdin.fileno(), 65536)
        if not chunk:
            break
        buffer += chunk
        while b"\n" in buffer:
            line, buffer = buffer.split(b"\n", 1)
            ops.put(json.loads(line))
        wake.trigger()
    ops.put(None)
    wake.trigger()


def stdin_is_the_launchers() -> bool:
    """The launcher talks through a pipe on stdin; a terminal, /dev/null or a file is no launcher."""
    try:
        mode = os.fstat(sys.stdin.fileno()).st_mode
    except (OSError, ValueError, AttributeError):  # stdin closed or missing
        return False
    return stat.S_ISFIFO(mode) or stat.S_ISSOCK(mode)


def serve(manager: LifecycleManager, replies, ops: queue.SimpleQueue, wake, launcher: bool) -> None:
    """Answer the operations on ``ops`` (the launcher's lines, manage_nodes calls) until the launcher's shutdown or
    until it goes away (stdin closed); without a ``launcher``, until ROS shuts down.

    Nothing here polls on a period: the operations arrive through threads that wake the spin (a guard condition),
    and the end of an episode is the recorder's own transition event (lifecycle_msgs TransitionEvent on
    ``/lq_metrics/transition_event``), confirmed with ``get_state`` (a stale event of an earlier episode must not
    end this one). A look every POLL_PERIOD_S covers an event that was never heard.
    """
    heard = []  # the recorder's transition events since the last look at its state
    manager.create_subscription(TransitionEvent, f"/{RECORDER}/transition_event", heard.append, 10)
    running = False  # an episode is active: watch the recorder
    waiting = False  # the launcher waits for this episode's "done"
    poll = None  # (get_state future of the recorder, when it was sent)
    next_look = 0.0  # monotonic time of the next look at the recorder's state without an event
    recorder = manager.get[RECORDER]

    def reply(obj: dict) -> None:
        replies.write(json.dumps(obj) + "\n")
        replies.flush()

    def forget_poll() -> None:
        nonlocal poll
        if poll is not None and not poll[0].done():
            recorder.remove_pending_request(poll[0])
        poll = None

    def watch() -> None:
        nonlocal running, next_look
        running = True
        heard.clear()
        next_look = time.monotonic() + POLL_PERIOD_S

    while rclpy.ok():
        # Never blocks longer than a look: a stop from the launcher (a node died) wakes it at once, even when the
        # recorder is the node that died and will never answer.
        look_now = running and poll is None and bool(heard)
        rclpy.spin_once(manager, timeout_sec=0.0 if look_now else POLL_PERIOD_S if running else None)
        while not ops.empty():
            op = ops.get()
            if op is None:
                return  # the launcher is gone
            forget_poll()
            if isinstance(op, ServiceCall):
                name = COMMANDS.get(op.command, "")
                try:
                    op.result = (True, manager.manage(op.command))
                except (TransitionFailed, ValueError) as exc:
                    op.result = (False, f"{name or 'manage_nodes'}: {exc}")
                finally:
                    op.done.set()
                manager.get_logger().info(f"manage_nodes {name or op.command}: {op.result[1]}")
                if name in ("startup", "resume") and op.result[0]:
                    watch()  # the episode it started is ended like the launcher's
                elif name in ("pause", "reset", "shutdown"):
                    running = False
                    if waiting:  # the launcher's episode was stopped: what was recorded is all there is
                        waiting = False
                        reply({"event": "done"})
                continue
            skip = set(op.get("skip", ()))
            running = waiting = False
            if op["op"] == "episode":
                try:
                    manager.episode(op["params"], op.get("reconfigure", []))
                except TransitionFailed as exc:
                    reply({"event": "failed", "node": exc.node, "transition": exc.transition, "reason": exc.reason})
                    continue
                watch()
                waiting = True
                reply({"event": "active"})
            elif op["op"] == "stop":
                manager.stop(skip)
                reply({"event": "stopped"})
            elif op["op"] == "shutdown":
                manager.shutdown(skip)
                reply({"event": "shutdown"})
                return
        if not running:
            continue
        if poll is None and (heard or time.monotonic() >= next_look):
            heard.clear()
            poll = (recorder.call_async(GetState.Request()), time.monotonic())
            next_look = time.monotonic() + POLL_PERIOD_S
        elif poll is not None and poll[0].done():
            recorded = poll[0].result().current_state.label != "active"
            poll = None
            if recorded:
                running = False
                manager.end_episode()
                if waiting:
                    waiting = False
                    reply({"event": "done"})
        elif poll is not None and time.monotonic() - poll[1] > RETRY_S:
            forget_poll()  # asked again on the next pass


def serve_manage_nodes(node: Node, ops: queue.SimpleQueue, wake) -> tuple[SingleThreadedExecutor, threading.Thread]:
    """``~/manage_nodes`` on ``node``, spun by an executor of its own in a thread (both returned: shut the executor
    down, then join the thread): each call waits there until the main loop has carried out its operation."""

    def on_call(request, response):
        call = ServiceCall(int(request.command))
        ops.put(call)
        wake.trigger()
        if not call.done.wait(MANAGE_ANSWER_S):
            call.result = (False, f"no answer within {MANAGE_ANSWER_S:.0f} s (the manager is busy or stuck)")
        response.success, response.message = call.result
        return response

    node.create_service(ManageNodes, "~/manage_nodes", on_call)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    # Not a daemon: a daemon thread still inside rcl's wait when the interpreter finalizes aborted the process
    # (SIGABRT on SIGINT, seen in CI); main joins it once the executor is shut down.
    thread = threading.Thread(target=_spin_quietly, args=(executor,), name="manage_nodes")
    thread.start()
    return executor, thread


def _spin_quietly(executor: SingleThreadedExecutor) -> None:
    try:
        executor.spin()
    except (ExternalShutdownException, KeyboardInterrupt):  # ROS shutting down with the process
        pass
    except rclpy_implementation.RCLError:
        # A signal's shutdown between spin's check of the context and its next wait set makes rcl refuse the
        # wait set (seen under load); only an error while the context is still valid is a failure.
        if executor.context.ok():
            raise


def main() -> None:
    # Replies go to the launcher on the original stdout; everything else (rclpy's console log) to stderr.
    replies = os.fdopen(os.dup(1), "w")
    os.dup2(2, 1)
    service = None
    try:
        rclpy.init()
        face = Node(NODE_NAMES["manager"])  # the service and the node_names parameter
        manager = LifecycleManager(managed_node_names(face))
        ops: queue.SimpleQueue = queue.SimpleQueue()
        wake = manager.create_guard_condition(lambda: None)
        launcher = stdin_is_the_launchers()
        if launcher:
            threading.Thread(target=read_ops, args=(ops, wake), daemon=True).start()
        service = serve_manage_nodes(face, ops, wake)
        try:
            serve(manager, replies, ops, wake, launcher)
        finally:
            end_teardown_after()  # a teardown that hangs (an orphan's peers gone) ends, not spins on
            stop_serving(*service)
            manager.destroy_node()
            face.destroy_node()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        rclpy.try_shutdown()
        if service is not None:
            stop_serving(*service)  # (again, if a signal cut the first: the thread must end before the process)


def stop_serving(executor: SingleThreadedExecutor, thread: threading.Thread) -> None:
    """Shut the manage_nodes executor down and wait for its thread (its spin returns once it is shut down or ROS
    is)."""
    with contextlib.suppress(KeyboardInterrupt, ExternalShutdownException):
        executor.shutdown(timeout_sec=1.0)
        thread.join(timeout=10.0)


if __name__ == "__main__":
    main()
