"""Launch the ROS stack as OS processes, drive it through episodes, and stop every process afterwards.

No ros2 launch exists for the PyPI wheels, so this is ours. A :class:`RosStack` starts the four managed
nodes (sim, policy, executor, metrics) and a lifecycle manager (nodes/manager_node.py) once, then runs any
number of episodes on them: per episode it hands the manager the episode's parameters, and the manager
moves the nodes through the standard lifecycle (configure, activate, deactivate, cleanup, shutdown;
docs/design/lifecycle.md). ``lq run`` uses a stack for one episode; a sweep worker keeps one for all its episodes.
This process never initialises rclpy: a launcher killed with SIGKILL leaves no Fast DDS file behind.

The same nodes run both clocks (the run's ``clock``: lockstep on /clock, with ``use_sim_time``, or real time on
the wall clock), so one stack runs episodes of either. Against a robot (``robot``) the bridge (a managed node
too) takes the sim's place, and the stack swaps the two when the episodes ask for it; with the LIBERO stand-in
(``robot: standin``) the ``robot_standin`` program is started for each episode, as a robot of its own that an
operator would reset, unless the user runs it. A policy that needs what the robot does not publish is refused
(one line, lq_ros.robot.observation_builder.check_robot) before anything starts.

Each child gets PR_SET_PDEATHSIG (it dies with us), its own log file, the stack's ROS_DOMAIN_ID and,
unless the user set them, ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and the stack's Fast DDS profile
(FASTDDS_PROFILE). A node that dies mid-episode ends that
episode as an error naming it; the stack restarts it and configures it again for the next episode. A
node killed with SIGKILL leaves Fast DDS files in /dev/shm: the launcher notes which files each node owns
while it runs and removes the orphaned ones (lq_ros.transport.processes.ShmTracker). Choosing
Fast DDS's UDP transport alone (FASTDDS_BUILTIN_TRANSPORTS=UDPv4) would not avoid them: with
ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, rmw_fastrtps (Jazzy, 8.4) installs its own shared-memory and
UDP transports and ignores that variable.
"""

from __future__ import annotations

import contextlib
import json
import os
import select
import shutil
import subprocess
import sys
import time
from collections.abc import Sequence
from contextlib import suppress
from pathlib import Path

import yaml

from lq_ros.core.run_config import RunConfig
from lq_ros.core.shipped import shipped_path
from lq_ros.recording.episode_folder import logs_dir
from lq_ros.robot.observation_builder import Requirements, check_robot
from lq_ros.robot.robot_config import SIM_RECORDER_PARAMETERS, RobotConfig
from lq_ros.transport.processes import (
    ShmTracker,
    die_with_parent,
    executor_choice,
    inherited_locks,
    node_forks_choice,
    owned_temp_folder,
    remove_orphaned_folders,
    sim_cpu_choice,
    stop_processes,
    without_secrets,
)
from lq_ros.transport.ros.fork_server import ForkedProcess, ForkServer, ForkServerError
from lq_ros.transport.ros.reservations import reserved_domain, reserved_sim_cpu
from lq_ros.wire.node_names import MANAGED_NODE_NAMES, NODE_NAMES, stack_roles

#: The managed nodes of a simulated run (against a robot the bridge replaces the sim: stack_roles).
NODES = tuple(MANAGED_NODE_NAMES)
#: The lifecycle manager's program (nodes/manager_node.py), started with the nodes.
MANAGER = "manager"
#: The LIBERO robot stand-in's program (nodes/robot_standin.py): a robot, started per episode when asked for.
STANDIN = "robot"
#: Module of each node program: nodes/<name>_node.py, installed as the package lq_ros_nodes (setup.py).
NODE_MODULE = "lq_ros_nodes.{}_node"
STANDIN_MODULE = "lq_ros_nodes.robot_standin"
#: Wall seconds between two looks at which /dev/shm files the nodes own.
SHM_SAMPLE_PERIOD_S = 0.25
#: A stack's work folder (node logs, the params file) in the temp folder: lq_run_<random>.
WORK_PREFIX = "lq_run_"
#: Fast DDS (2.14, Jazzy) reads its XML profiles from the file this variable names. The stack's processes load
#: its own profile (discovery announced every 0.25 s instead of every 3 s: the file says why) unless the user
#: names a file of their own.
FASTDDS_PROFILES_ENV = "FASTRTPS_DEFAULT_PROFILES_FILE"
FASTDDS_PROFILE = shipped_path("config/dds") / "fastdds_participant.xml"


def child_environment(domain_id: int, log_dir: Path) -> dict[str, str]:
    env = without_secrets(dict(os.environ))  # a Ray token is the sweep driver's, not the nodes
    executor_choice(env)  # a wrong value is refused here, in one line, not by five node processes
    sim_cpu_choice(env)
    node_forks_choice(env)
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env.setdefault(FASTDDS_PROFILES_ENV, str(FASTDDS_PROFILE))
    env["ROS_DOMAIN_ID"] = str(domain_id)
    env["ROS_LOG_DIR"] = str(log_dir)
    env["PYTHONUNBUFFERED"] = "1"
    return env


def episode_timeout_s(cfg: RunConfig) -> float:
    """Wall seconds an episode may take before it is a run error: 120 s + 1 s per tick of budget (either clock: a
    lockstep tick takes tens of ms, a real-time one 50 ms, a slow remote policy much longer)."""
    return 120.0 + cfg.budget * 1.0


def node_parameters(
    cfg: RunConfig,
    bag_path: Path,
    cameras: tuple[str, ...],
    camera_size_px: int,
    policy_params: dict,
    robot: RobotConfig | None = None,
    requirements: Requirements | None = None,
    history_ticks: int = 1,
    control_mode: str = "relative",
) -> dict:
    """The params file: the run's parameters once for every node (``/**``, with ``use_sim_time`` on in lockstep),
    then what only one node needs (derived from the policy: its cameras and render size, its parameters for the
    bag; against a robot, what the bridge must wait for and what the recorder records and scores)."""
    cams = list(cameras) or [""]  # ROS string arrays cannot be empty in YAML (copied per node: no YAML aliases)
    recorder = {
        "bag_path": str(bag_path),
        "cameras": list(cams),
        "camera_size_px": camera_size_px,
        "policy_params_json": json.dumps(policy_params),
    }
    params = {"/**": {**cfg.ros_parameters(), "use_sim_time": cfg.clock == "lockstep"}}
    if robot is None:
        params[NODE_NAMES["sim"]] = {"cameras": list(cams), "camera_size_px": camera_size_px,
                                     "history_ticks": history_ticks, "control_mode": control_mode}  # fmt: skip
        recorder.update(SIM_RECORDER_PARAMETERS)
    else:
        needs_objects = bool(requirements and requirements.objects)
        params[NODE_NAMES["bridge"]] = {"cameras": list(cams), "needs_object_poses": needs_objects}
        recorder.update(robot.recorder_parameters())
        params[NODE_NAMES["robot"]] = {"robot_config": str(robot.source), "camera_size_px": camera_size_px}
    params[NODE_NAMES["metrics"]] = recorder
    return params


def params_yaml(params: dict) -> str:
    """A ROS 2 params file: ``{node or /**: {ros__parameters: {...}}}``."""
    return yaml.safe_dump({n: {"ros__parameters": p} for n, p in params.items()}, sort_keys=False)


class StackDead(RuntimeError):
    """The lifecycle manager died: the stack cannot run another episode (start a new one)."""


def policy_key(cfg: RunConfig) -> tuple:
    """What the policy node loads at configure (its CONFIGURE_FIELDS): the policy and its arguments."""
    return (cfg.policy, json.dumps(cfg.policy_args, sort_keys=True))


def configure_keys(cfg: RunConfig, cameras: Sequence[str], camera_size_px: int) -> dict[str, tuple]:
    """Per node, what it loads at configure (the CONFIGURE_FIELDS of nodes/*_node.py); ``cameras`` and
    ``camera_size_px`` are those the policy asks for. A changed key means cleanup + configure of that node
    (a rebuilt env, a reloaded policy); anything else changes with a soft reset at activation. A new policy
    on the same task keeps the simulator; a new task keeps the policy.

    The single source of that decision: the launcher reconfigures nodes by it and the in-process sweep
    worker rebuilds its env and policy by it (lq_ros.run.sweep.worker).
    """
    return {
        "sim": (cfg.suite, cfg.task, cfg.physics_rate, tuple(c for c in cameras if c), camera_size_px),
        "bridge": (cfg.robot, cfg.suite, cfg.task),
        "policy": policy_key(cfg),
        "executor": (),
        "metrics": (),
    }


class RosStack:
    """The managed nodes of a run (stack_roles) and their lifecycle manager, kept up for any number of episodes.

    Use as a context manager (or call :meth:`close`): the domain id is reserved and the processes run
    until then. :meth:`run_episode` never raises for a broken episode; it returns the reason instead.
    """

    def __init__(self, domain_id: int | None = None) -> None:
        self._exit = contextlib.ExitStack()
        self.domain = self._exit.enter_context(reserved_domain(domain_id))
        remove_orphaned_folders(WORK_PREFIX)  # those of launchers killed with SIGKILL (their nodes' logs)
        self.work, self._work_lock = owned_temp_folder(WORK_PREFIX)
        self.params_file = self.work / "params.yaml"
        # A node (re)started reads this file in rclpy.init and dies without it ("Couldn't parse params file"):
        # processes started before the first episode (start()) get the defaults, which that episode's
        # set_parameters calls then override, as they override every later episode's file.
        self._write_params({"/**": RunConfig().ros_parameters()})
        self.env = child_environment(self.domain.id, self.work / "ros_logs")
        # The CPU this stack's sim steps on in lockstep episodes (None: the OS scheduler's choice); see _pin_sim.
        self.cpus = os.sched_getaffinity(0)
        held = self._exit.enter_context(reserved_sim_cpu())
        self.sim_cpu, cpu_lock = held if held is not None else (None, None)
        # The nodes hold the run's locks too (a domain, a CPU, a sweep's processes lock): free only once all are gone.
        self._lock_fds = (self.domain.lock_fd,) + ((cpu_lock,) if cpu_lock is not None else ()) + inherited_locks()
        self.procs: dict[str, subprocess.Popen | ForkedProcess] = {}
        # Nodes start as forks of a process that imported them (None: not started yet; False: executed afresh),
        # the node programs of its roles and these modules.
        self._forks: ForkServer | bool | None = None if node_forks_choice(self.env) == "on" else False
        self.fork_preload: tuple[str, ...] = ()
        self.shm = ShmTracker()
        ShmTracker.stale_segments().cleanup()  # segments of runs that died all at once, nobody left to clean
        self._replies = b""
        self._keys: dict[str, tuple] | None = None  # configure_keys of the configured nodes
        # (policy key, cameras, params, render size, requirements, history ticks, control mode)
        self._probe: tuple | None = None
        self.roles: tuple[str, ...] = stack_roles(robot=False)  # the managed nodes, in activation order
        self.episodes = 0
        self.restarts: dict[str, int] = {}
        self.closed = False

    def __enter__(self) -> RosStack:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- processes -----------------------------------------------------------------------------------
    def _spawn(self, name: str) -> None:
        log = open(self.work / f"{name}.log", "ab")  # noqa: SIM115 - closed once the process has it
        manager = name == MANAGER
        if manager:  # (the nodes it manages, as nav2's node_names)
            args = ["--ros-args", "-p", f"node_names:=[{','.join(NODE_NAMES[r] for r in self.roles)}]"]
        else:
            args = ["--ros-args", "--params-file", str(self.params_file)]
        module = STANDIN_MODULE if name == STANDIN else NODE_MODULE.format(name)
        streams = {
            "stdout": subprocess.PIPE if manager else log,
            "stderr": log if manager else subprocess.STDOUT,
            "stdin": subprocess.PIPE if manager else subprocess.DEVNULL,
        }
        try:
            forks = self._fork_server()
            if forks is not None:
                try:
                    self.procs[name] = forks.spawn(module, args, **streams)
                    return
                except ForkServerError as exc:  # it died: this stack's nodes are executed afresh from now on
                    forks.close()
                    self._fork_server_unusable(exc)
            self.procs[name] = subprocess.Popen(
                [sys.executable, "-m", module, *args],
                env=self.env,
                preexec_fn=die_with_parent,
                pass_fds=self._lock_fds,
                **streams,
            )
        finally:
            log.close()
            if manager:
                self._replies = b""

    def _fork_server(self) -> ForkServer | None:
        """The stack's fork server (started with the stack's node programs imported), or None: execute afresh."""
        if self._forks is False:
            return None
        if isinstance(self._forks, ForkServer):
            if not self._forks.dead:
                return self._forks
            self._forks.close()
            self._fork_server_unusable(ForkServerError("the node fork server has exited"))
            return None
        modules = [NODE_MODULE.format(role) for role in (*self.roles, MANAGER)] + list(self.fork_preload)
        with open(self.work / "fork_server.log", "ab") as log:
            try:
                self._forks = ForkServer(modules, self.env, self._lock_fds, log)
            except ForkServerError as exc:  # (declined: a thread it cannot fork safely) same nodes, started slower
                self._fork_server_unusable(exc)
                return None
        return self._forks

    def _fork_server_unusable(self, exc: ForkServerError) -> None:
        """Execute this stack's nodes afresh from now on (the same nodes, started slower), and say why in the
        launcher's log, which is kept with the episode's bag. A server that died once is not started again."""
        with open(self.work / "launcher.log", "a") as launcher_log:
            launcher_log.write(f"{exc}; the nodes are executed afresh\n")
        self._forks = False

    def _write_params(self, params: dict) -> None:
        """Replace the params file atomically: a node starting meanwhile reads the old or the new one, whole."""
        tmp = self.params_file.with_suffix(".tmp")
        tmp.write_text(params_yaml(params))
        os.replace(tmp, self.params_file)

    def start(self) -> None:
        """Start whatever is not running (the first episode: all; after a crash: the dead node).

        Every episode calls it; calling it before the first one starts the processes early. A node found dead
        here is replaced (and counted in ``restarts``): its PID is not the one noted before.
        """
        forking = self._forks is not False  # (None: the server starts with the first node)
        self._start_missing()
        if forking and self._forks is False:  # the fork server was given up meanwhile: its forks ended with it
            self._start_missing()

    def _start_missing(self) -> None:
        # The sim first: its env is the longest to build, and the processes start on the same cores.
        for name in (*sorted(self.roles, key=lambda role: role != "sim"), MANAGER):
            p = self.procs.get(name)
            if p is not None and p.poll() is None:
                continue
            if p is not None:
                self.restarts[name] = self.restarts.get(name, 0) + 1
                if name != MANAGER:
                    # Configure every node again with this episode, not only the fresh (unconfigured) one: a
                    # node that died during a reconfigure leaves the survivors' configurations unknown, and a
                    # stale configuration must never be activated.
                    self._keys = None
            self._spawn(name)

    def _pin_sim(self, pin: bool) -> None:
        """Run the sim node's main thread (its stepping) on the stack's own CPU (``pin``), or on any CPU again.

        A lockstep episode's wall time is the sim's stepping plus the waits for the other nodes, which wake on
        every tick's messages: left to the scheduler, the sim is moved between the CPUs they wake on and steps
        through cold caches (benchmarks/bench_stack_options.py measures the difference). Only
        the main thread is pinned, and only while a lockstep episode is active: threads it starts meanwhile inherit
        the CPU, so configure (the env, the renderer) runs unpinned; a real-time episode is left to the scheduler.
        """
        sim = self.procs.get("sim")
        if self.sim_cpu is None or sim is None or sim.poll() is not None:
            return
        with suppress(OSError):  # (it may be exiting)
            os.sched_setaffinity(sim.pid, {self.sim_cpu} if pin else self.cpus)

    def _dead(self) -> list[str]:
        return [n for n, p in self.procs.items() if p.poll() is not None]

    def _use_roles(self, roles: tuple[str, ...]) -> None:
        """Run ``roles`` from now on: a robot episode after simulated ones swaps the sim for the bridge (and back).

        The manager and the node that leaves are stopped (the manager is restarted with the new node_names); the
        nodes both sets share keep running and are configured again (their peers changed)."""
        if roles == self.roles:
            return
        leaving = [n for n in (*self.roles, MANAGER) if n not in roles or n == MANAGER]
        manager = self.procs.get(MANAGER)
        if manager is not None and manager.poll() is None:
            self._send({"op": "stop", "skip": [NODE_NAMES[n] for n in self._dead() if n != MANAGER]})
            self._await(("stopped",), time.monotonic() + 60.0, tolerate=tuple(self._dead()))
        self._stop({n: self.procs.pop(n) for n in leaving if n in self.procs})
        self.roles = roles
        self._keys = None

    def _stop(self, procs: dict[str, subprocess.Popen], ports: bool = False) -> None:
        """Stop these processes (SIGINT, SIGTERM, then SIGKILL) and remove the /dev/shm files they leave.

        ``ports``: also the shared port files (:meth:`ShmTracker.cleanup`): only once no node of the stack lives on.
        """
        self.shm.sample(p.pid for p in self.procs.values() if p.returncode is None)
        stop_processes(procs)
        for p in procs.values():
            for pipe in (p.stdin, p.stdout):
                if pipe is not None:
                    with suppress(OSError):
                        pipe.close()
        removed = self.shm.cleanup(ports=ports)
        if removed:
            with open(self.work / "launcher.log", "a") as f:
                f.write(f"removed orphaned Fast DDS files from /dev/shm: {removed}\n")

    def _send(self, op: dict) -> None:
        manager = self.procs[MANAGER]
        try:
            manager.stdin.write((json.dumps(op) + "\n").encode())
            manager.stdin.flush()
        except (BrokenPipeError, ValueError):
            pass  # noticed as a dead manager by the caller

    def _await(
        self, events: tuple[str, ...], deadline: float | None, tolerate: tuple[str, ...] = ()
    ) -> tuple[dict | None, str]:
        """Wait for a manager reply in ``events``; returns (reply, "") or (None, why not: crash or timeout).

        A process in ``tolerate`` (known dead already) is no reason to stop waiting; the manager is.
        """
        manager = self.procs[MANAGER]
        fd = manager.stdout.fileno()
        next_sample = 0.0
        while True:
            while b"\n" in self._replies:
                line, self._replies = self._replies.split(b"\n", 1)
                reply = json.loads(line)
                if reply.get("event") in events or reply.get("event") == "failed":
                    return reply, ""
            if time.monotonic() >= next_sample:
                self.shm.sample(p.pid for p in self.procs.values() if p.returncode is None)
                next_sample = time.monotonic() + SHM_SAMPLE_PERIOD_S
            dead = [n for n in self._dead() if n not in tolerate or n == MANAGER]
            if dead:
                return None, ", ".join(f"{_label(n)} exited with code {self.procs[n].returncode}" for n in dead)
            if deadline is not None and time.monotonic() > deadline:
                return None, "timeout"
            readable, _, _ = select.select([fd], [], [], 0.05)
            if readable:
                chunk = os.read(fd, 65536)
                if chunk:
                    self._replies += chunk

    # -- episodes ------------------------------------------------------------------------------------
    def run_episode(
        self,
        cfg: RunConfig,
        out_dir: Path,
        timeout_s: float | None = None,
        *,
        start_standin: bool | None = None,
        node_parameters_extra: dict[str, dict] | None = None,
    ) -> tuple[Path, str]:
        """Run one episode into ``out_dir / cfg.episode_name()``; returns its bag folder and the error ("" if none).

        The run (not the task) failed when a node dies, refuses a transition, or the episode does not end
        within ``timeout_s`` wall seconds (default: :func:`episode_timeout_s`, from the request). A robot that
        cannot feed the policy is refused before anything starts (ValueError). ``start_standin``: start the
        LIBERO stand-in for a ``robot: standin`` episode (default: yes); ``node_parameters_extra``: more
        parameters by node name (e.g. ``{"lq_sim": {"step_delay_s": 0.06}}``).
        """
        from lq_ros.policies import make_policy

        if self.closed:
            raise StackDead("the stack was closed")
        bag_path = Path(out_dir) / cfg.episode_name()
        if self._probe is None or self._probe[0] != policy_key(cfg):
            # This process's own instance only tells cameras and parameters (the policy node builds its own);
            # kept while the policy stays the same (a learned policy loads its weights to answer).
            probe = make_policy(cfg.policy, **cfg.policy_args)
            self._probe = (
                policy_key(cfg), probe.camera_names, probe.params(), probe.render_size, Requirements.of(probe),
                probe.observation_history_ticks, str(probe.control_mode),
            )  # fmt: skip
            probe.close()
        _, cameras, policy_params, render_size, requirements, history_ticks, control_mode = self._probe
        robot = check_robot(cfg.robot, requirements, cfg.policy) if cfg.robot else None
        camera_size_px = cfg.camera_size_for(render_size)
        timeout_s = timeout_s or episode_timeout_s(cfg)
        params = node_parameters(
            cfg, bag_path, cameras, camera_size_px, policy_params, robot, requirements, history_ticks, control_mode
        )
        for node, extra in (node_parameters_extra or {}).items():
            params[node] = {**params.get(node, {}), **extra}
        self._write_params(params)  # what a (re)started node starts with
        if start_standin is None:
            start_standin = robot is not None and robot.name == "libero_standin"
        log_marks = self._log_sizes()
        try:
            self._use_roles(stack_roles(robot=robot is not None))
            self.start()
            if start_standin:
                self._spawn(STANDIN)  # a robot of its own, reset (restarted) for every episode
            keys = configure_keys(cfg, cameras, camera_size_px)
            per_node = {NODE_NAMES[n]: {**params["/**"], **params.get(NODE_NAMES[n], {})} for n in self.roles}
            # All after a refused transition or a restarted node (None): configure everything again (cleanup of
            # an unconfigured node is skipped, so a fresh stack just configures).
            reconfigure = [NODE_NAMES[n] for n in self.roles if self._keys is None or keys[n] != self._keys[n]]
            self._pin_sim(False)  # whatever configure starts (the renderer's threads) may use every CPU
            self._send({"op": "episode", "params": per_node, "reconfigure": reconfigure})
            deadline = time.monotonic() + timeout_s
            reply, reason = self._await(("active",), deadline)
            if reply is not None and reply["event"] == "failed":
                reason = self._failure_reason(reply)
                self._keys = None  # configure everything again next time
            elif reply is not None:
                self._keys = keys
                self._pin_sim(cfg.clock == "lockstep")
                reply, reason = self._await(("done",), deadline)
            if reason == "timeout":
                reason = f"episode did not end within {timeout_s:.0f} s (wall clock)"
            if reason:
                self._end_broken_episode(logs_to=(bag_path, log_marks))
        except BaseException:  # Ctrl-C, SIGTERM of a sweep worker: the nodes stop, the recorder closes its bag
            self.close(logs_to=(bag_path, log_marks))
            raise
        finally:
            if STANDIN in self.procs and not self.closed:
                self._stop({STANDIN: self.procs.pop(STANDIN)})
        self.episodes += 1
        if not self.closed:  # (closed: collected already)
            self._collect_logs(bag_path, log_marks)
        return bag_path, reason

    def _failure_reason(self, reply: dict) -> str:
        role = {NODE_NAMES[r]: r for r in self.roles}.get(reply["node"], reply["node"])
        transition, why = reply["transition"], reply["reason"]
        detail = self._last_log_line(role, f"{transition} failed:") if role in self.roles else ""
        return f"{role} node: {transition} failed: {detail or why}"

    def _last_log_line(self, name: str, marker: str) -> str:
        """The last line of a node's log containing ``marker``, from the marker on (a refused transition's reason)."""
        try:
            lines = (self.work / f"{name}.log").read_text(errors="replace").splitlines()
        except OSError:
            return ""
        for line in reversed(lines):
            if marker in line:
                return line.split(marker, 1)[1].strip()
        return ""

    def _end_broken_episode(self, logs_to: tuple[Path, dict[str, int]]) -> None:
        """Deactivate the live nodes (the recorder closes its bag with a STOPPED event); keep the stack.

        Dead nodes are restarted (and configured) with the next episode; the manager's death ends the stack.
        """
        dead = tuple(self._dead())
        if MANAGER not in dead:
            self._send({"op": "stop", "skip": [NODE_NAMES[n] for n in dead if n in self.roles]})
            self._await(("stopped",), time.monotonic() + 60.0, tolerate=dead)
        if MANAGER in self._dead():
            self.close(logs_to)
            return
        if self._dead():
            self.shm.cleanup(ports=False)  # the dead nodes' orphaned /dev/shm files (a live node's are never touched)

    def _log_sizes(self) -> dict[str, int]:
        return {n: (self.work / f"{n}.log").stat().st_size if (self.work / f"{n}.log").exists() else 0
                for n in (*NODES, "bridge", MANAGER, STANDIN)}  # fmt: skip

    def _collect_logs(self, bag_path: Path, marks: dict[str, int]) -> None:
        """Keep this episode's part of every node log inside the bag folder (or beside it when no bag was written)."""
        dest = logs_dir(bag_path)
        dest.mkdir(parents=True, exist_ok=True)
        for name, offset in marks.items():
            src = self.work / f"{name}.log"
            if src.exists():
                with open(src, "rb") as f:
                    f.seek(offset if src.stat().st_size >= offset else 0)
                    (dest / f"{name}.log").write_bytes(f.read())
        launcher_log = self.work / "launcher.log"
        if launcher_log.exists():
            shutil.copy(launcher_log, dest / "launcher.log")

    # -- shutdown ------------------------------------------------------------------------------------
    def close(self, logs_to: tuple[Path, dict[str, int]] | None = None) -> None:
        """Shut the nodes down through the lifecycle, stop whatever is left, remove orphaned /dev/shm files.

        ``logs_to``: (bag folder, log offsets) of an interrupted episode, whose logs are kept with its bag.
        """
        if self.closed:
            return
        self.closed = True
        try:
            manager = self.procs.get(MANAGER)
            if manager is not None and manager.poll() is None:
                dead = tuple(self._dead())
                self._send({"op": "shutdown", "skip": [NODE_NAMES[n] for n in dead if n in self.roles]})
                # Nodes exit as they are shut down: only the manager's own exit ends the wait early.
                self._await(("shutdown",), time.monotonic() + 30.0, tolerate=tuple(self.procs))
                for p in self.procs.values():
                    with suppress(subprocess.TimeoutExpired):
                        p.wait(timeout=10.0)
        finally:
            self._stop(self.procs, ports=True)
            if isinstance(self._forks, ForkServer):
                self._forks.close()
            if logs_to is not None:
                with suppress(OSError):
                    self._collect_logs(*logs_to)
            self._exit.close()
            shutil.rmtree(self.work, ignore_errors=True)
            os.close(self._work_lock)


def _label(name: str) -> str:
    return "lifecycle manager" if name == MANAGER else f"{name} node"


def launch_nodes(
    cfg: RunConfig,
    out_dir: Path,
    *,
    domain_id: int | None = None,
    timeout_s: float | None = None,
    **episode_options,
) -> tuple[Path, str]:
    """Run one episode on a stack of its own (``lq run``); returns its bag folder and the launch error ("" if none).

    ``episode_options`` go to :meth:`RosStack.run_episode`. Scoring and the outcome are
    ``lq_ros.run.episode.run_episode``'s.
    """
    with RosStack(domain_id) as stack:
        return stack.run_episode(cfg, out_dir, timeout_s, **episode_options)
