"""Launch the four nodes as OS processes for one episode, and stop every one of them afterwards.

No ros2 launch exists for the PyPI wheels, so this is ours: parameters go in a ROS params YAML
file per run, each child gets PR_SET_PDEATHSIG (it dies with us), its own log file, the run's
ROS_DOMAIN_ID and, unless the user set it, ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST. A node killed
with SIGKILL leaves Fast DDS files in /dev/shm: the launcher notes which files each node owns while
it runs and removes the orphaned ones once every node has exited (lq_ros.procs.ShmTracker). Choosing
Fast DDS's UDP transport alone (FASTDDS_BUILTIN_TRANSPORTS=UDPv4) would not avoid them: with
ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, rmw_fastrtps (Jazzy, 8.4) installs its own shared-memory and
UDP transports and ignores that variable.
"""

from __future__ import annotations

import fcntl
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path

import yaml

from lq_ros.config import RunConfig
from lq_ros.procs import ShmTracker, die_with_parent

NODES = ("sim", "policy", "executor", "metrics")
#: Module of each node program: nodes/<name>_node.py, installed as the package lq_ros_nodes (setup.py).
NODE_MODULE = "lq_ros_nodes.{}_node"
#: ROS_DOMAIN_IDs handed to concurrent runs (0, the default, is left to other ROS software).
DOMAIN_IDS = range(20, 100)  # below the ephemeral port range (Fast DDS port = 7400 + 250 * id)
DOMAIN_LOCK_DIR = Path(tempfile.gettempdir()) / "lq_ros_domains"
#: Wall seconds between two looks at which /dev/shm files the nodes own.
SHM_SAMPLE_PERIOD_S = 0.25


@dataclass(frozen=True)
class DomainReservation:
    id: int
    #: Descriptor of the lock file: a child started with it (``pass_fds``) keeps the domain reserved until it exits.
    lock_fd: int


@contextmanager
def reserved_domain(domain_id: int | None = None):
    """Hold an exclusive lock on a ROS domain id for the duration of a run.

    The lock (``flock``) belongs to the open lock file, so it lasts while any process holding that file
    lives: the nodes inherit it, and a domain whose nodes outlive a killed launcher is not handed out again.
    """
    DOMAIN_LOCK_DIR.mkdir(exist_ok=True)
    candidates = [domain_id] if domain_id is not None else list(DOMAIN_IDS)
    for did in candidates:
        handle = open(DOMAIN_LOCK_DIR / f"{did}.lock", "w")  # noqa: SIM115 - held while the run lasts
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.close()
            continue
        try:
            yield DomainReservation(did, handle.fileno())
        finally:
            handle.close()  # no LOCK_UN: that would release the lock for the nodes that still hold it too
        return
    raise RuntimeError(f"no free ROS domain id among {candidates} (another run holds each)")


def child_environment(domain_id: int, log_dir: Path) -> dict[str, str]:
    env = dict(os.environ)
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env["ROS_DOMAIN_ID"] = str(domain_id)
    env["ROS_LOG_DIR"] = str(log_dir)
    env["PYTHONUNBUFFERED"] = "1"
    return env


def node_parameters(
    cfg: RunConfig, bag_path: Path, cameras: tuple[str, ...], camera_size_px: int, policy_params: dict
) -> dict:
    """The params file: the run's parameters once for every node (``/**``), then what only one node needs
    (derived from the policy: its cameras and render size, its parameters for the bag)."""
    cams = list(cameras) or [""]  # ROS string arrays cannot be empty in YAML
    return {
        "/**": cfg.ros_parameters(),
        "lq_sim": {"cameras": list(cams), "camera_size_px": camera_size_px},
        "lq_metrics": {
            "bag_path": str(bag_path),
            "cameras": list(cams),
            "camera_size_px": camera_size_px,
            "policy_params_json": json.dumps(policy_params),
        },
    }


def params_yaml(params: dict) -> str:
    """A ROS 2 params file: ``{node or /**: {ros__parameters: {...}}}``."""
    return yaml.safe_dump({n: {"ros__parameters": p} for n, p in params.items()}, sort_keys=False)


def _stop(procs: dict[str, subprocess.Popen], grace_s: float = 10.0) -> None:
    """SIGINT (clean rclpy shutdown), then SIGTERM, then SIGKILL whatever is left."""
    for sig, wait_s in ((signal.SIGINT, grace_s), (signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
        alive = [p for p in procs.values() if p.poll() is None]
        if not alive:
            return
        for p in alive:
            p.send_signal(sig)
        deadline = time.monotonic() + wait_s
        for p in alive:
            with suppress(subprocess.TimeoutExpired):
                p.wait(timeout=max(0.0, deadline - time.monotonic()))
    if any(p.poll() is None for p in procs.values()):
        raise RuntimeError("child processes survived SIGKILL")


def launch_nodes(
    cfg: RunConfig,
    out_dir: Path,
    *,
    domain_id: int | None = None,
    timeout_s: float | None = None,
) -> tuple[Path, str]:
    """Run one episode through the four-node stack; returns its bag folder and the launch error ("" if none).

    The launch (not the task) failed when a node crashes or the episode does not end within
    ``timeout_s`` wall seconds. Scoring and the outcome are ``lq_ros.episode.run_episode``'s.
    """
    from lq_ros.policies import make_policy

    out_dir = Path(out_dir)
    bag_path = out_dir / cfg.episode_name()
    # The policy node builds its own instance; this one only tells cameras and parameters.
    probe = make_policy(cfg.policy, **cfg.policy_args)
    cameras, policy_params = probe.camera_names, probe.params()
    camera_size_px = cfg.camera_size_for(probe.render_size)
    probe.close()
    timeout_s = timeout_s or 120.0 + cfg.budget * 1.0
    work = Path(tempfile.mkdtemp(prefix="lq_run_"))
    params_file = work / "params.yaml"
    params = node_parameters(cfg, bag_path, cameras, camera_size_px, policy_params)
    params_file.write_text(params_yaml(params))
    procs: dict[str, subprocess.Popen] = {}
    shm = ShmTracker()
    reason = ""
    with reserved_domain(domain_id) as domain:
        env = child_environment(domain.id, work / "ros_logs")
        try:
            for name in NODES:
                log = open(work / f"{name}.log", "wb")  # noqa: SIM115 - closed with the process
                procs[name] = subprocess.Popen(
                    [sys.executable, "-m", NODE_MODULE.format(name), "--ros-args", "--params-file", str(params_file)],
                    env=env,
                    stdout=log,
                    stderr=subprocess.STDOUT,
                    stdin=subprocess.DEVNULL,
                    preexec_fn=die_with_parent,
                    pass_fds=(domain.lock_fd,),
                )
                log.close()
            deadline = time.monotonic() + timeout_s
            next_sample = 0.0
            while True:
                if time.monotonic() >= next_sample:
                    shm.sample(p.pid for p in procs.values() if p.returncode is None)
                    next_sample = time.monotonic() + SHM_SAMPLE_PERIOD_S
                if procs["metrics"].poll() is not None:
                    if procs["metrics"].returncode != 0:
                        reason = f"metrics node exited with code {procs['metrics'].returncode}"
                    break
                crashed = [n for n, p in procs.items() if p.poll() is not None]
                if crashed:
                    reason = ", ".join(f"{n} node exited with code {procs[n].returncode}" for n in crashed)
                    break
                if time.monotonic() > deadline:
                    reason = f"episode did not end within {timeout_s:.0f} s (wall clock)"
                    break
                time.sleep(0.05)
        finally:
            shm.sample(p.pid for p in procs.values() if p.returncode is None)
            _stop(procs)
            removed = shm.cleanup()
            if removed:
                (work / "launcher.log").write_text(f"removed orphaned Fast DDS files from /dev/shm: {removed}\n")
            _collect_logs(work, bag_path)
    return bag_path, reason


def _collect_logs(work: Path, bag_path: Path) -> None:
    """Keep the node logs inside the bag folder (or beside it when no bag was written)."""
    dest = bag_path / "logs" if bag_path.exists() else bag_path.with_name(bag_path.name + ".logs")
    dest.mkdir(parents=True, exist_ok=True)
    for log in work.glob("*.log"):
        shutil.copy(log, dest / log.name)
    shutil.rmtree(work, ignore_errors=True)
