"""Ray actors as sweep workers: episodes run on any node of a Ray cluster, bags come back to the driver's store.

Without an address, a private single-node Ray on loopback (``ray_init_local``). With ``--address HOST:PORT``,
the cluster started with ``ray start`` (docs/guide/sweeps.md): the actors are spread over its nodes, each episode's
bag and logs travel back to the driver, and every attempt records the node that ran it. Token
authentication (Ray's default for a new cluster) needs the head's token in the driver's environment
(``RAY_AUTH_MODE=token`` and ``RAY_AUTH_TOKEN_PATH`` or ``RAY_AUTH_TOKEN``); a driver that cannot connect
gets one line naming the address and the token it used (:class:`RayConnectError`).
"""

from __future__ import annotations

import contextlib
import io
import ipaddress
import os
import shutil
import socket
import tarfile
import time
from pathlib import Path

from lq_ros.core.run_config import RunConfig
from lq_ros.recording.episode_folder import episode_folders
from lq_ros.run.sweep.worker import EpisodeWorker, default_workers
from lq_ros.transport.processes import (
    PROCESSES_LOCK,
    hold_for_children,
    hold_shared,
    owned_temp_folder,
    remove_orphaned_folders,
)


def _pack_dir(path: Path) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tar:
        tar.add(path, arcname=path.name)
    return buf.getvalue()


def _unpack_dir(data: bytes, dest_parent: Path) -> None:
    with tarfile.open(fileobj=io.BytesIO(data), mode="r:gz") as tar:
        tar.extractall(dest_parent, filter="data")


#: A Ray worker's folder (its bags before they travel, its logs) in the temp folder: lq_ray_worker_<random>.
WORKER_PREFIX = "lq_ray_worker_"


class _RayEpisodeActor:
    """One Ray worker: runs episodes into its own bag folder and ships each bag back with the result."""

    def __init__(self, transport: str, timeout_s: float | None, processes_lock: str | None = None) -> None:
        os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        if processes_lock:  # on the driver's machine: this actor and its nodes hold the sweep folder's lock
            hold_for_children(hold_shared(Path(processes_lock)))
        remove_orphaned_folders(WORKER_PREFIX)  # those of workers that were killed (a Ray cluster's shutdown)
        self.root, self._root_lock = owned_temp_folder(WORKER_PREFIX)
        self.worker = EpisodeWorker(transport, self.root / "bags", timeout_s)

    def run(self, cfg_dict: dict) -> dict:
        import ray

        cfg = RunConfig(**cfg_dict)
        log = self.root / "logs" / f"{cfg.key()}.log"
        log.unlink(missing_ok=True)
        result = self.worker.run(cfg, log)
        result["node"] = {"host": socket.gethostname(), "ip": ray.util.get_node_ip_address(),
                          "ray_node_id": ray.get_runtime_context().get_node_id()}  # fmt: skip
        result["log_text"] = log.read_text(errors="replace") if log.exists() else ""
        bag_dir = self.root / "bags" / cfg.episode_name()
        result["tars"] = []  # the bag (and node logs) travel back to the driver's store
        for src in episode_folders(bag_dir):
            if src.exists():
                result["tars"].append(_pack_dir(src))
                shutil.rmtree(src)
        return result

    def close(self) -> None:
        self.worker.close()
        shutil.rmtree(self.root, ignore_errors=True)
        os.close(self._root_lock)


class RayConnectError(RuntimeError):
    """The driver could not join the Ray cluster at ``--address``; the message is one line."""


def _loopback_only() -> None:
    """Keep every Ray server this process starts (and the driver's own) on 127.0.0.1.

    Ray turns a node address of 127.0.0.1 into the machine's outward address unless
    RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0 (read when ray is imported); with it every Ray server
    listens on 127.0.0.1 only (checked in tests/run/sweep/test_sweep_ray.py).
    """
    os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"  # inherited by every Ray process started below
    from ray._private import ray_constants

    # Imported earlier in this process: apply the same setting to the constant it was read into.
    ray_constants.ENABLE_RAY_CLUSTER = False


def is_loopback_address(address: str) -> bool:
    host = address.rpartition(":")[0] or address
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def _token_source() -> str:
    """Where this driver's Ray authentication token comes from, for an error message."""
    if os.environ.get("RAY_AUTH_TOKEN"):
        return "RAY_AUTH_TOKEN"
    if os.environ.get("RAY_AUTH_TOKEN_PATH"):
        return f"RAY_AUTH_TOKEN_PATH={os.environ['RAY_AUTH_TOKEN_PATH']}"
    default = os.path.expanduser("~/.ray/auth_token")
    return default if os.path.exists(default) else "none"


def ray_connect(address: str) -> None:
    """Join an existing cluster (``ray start``) as the driver; RayConnectError in one line if that fails."""
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    kwargs = {}
    if is_loopback_address(address):  # a cluster on this machine's loopback: the driver joins the head's address
        _loopback_only()
        host = address.rpartition(":")[0].strip("[]")
        kwargs["_node_ip_address"] = "127.0.0.1" if host == "localhost" else host
    import ray

    try:
        ray.init(address=address, log_to_driver=False, configure_logging=False, **kwargs)
    except (ConnectionError, ray.exceptions.RaySystemError, ray.exceptions.AuthenticationError) as exc:
        raise RayConnectError(
            f"cannot join the Ray cluster at {address} ({type(exc).__name__}: {' '.join(str(exc).split())}); "
            f"check the address (ray status on the head) and, with token authentication, that this driver has "
            f"the head's token (RAY_AUTH_MODE=token and RAY_AUTH_TOKEN_PATH or RAY_AUTH_TOKEN; this driver's "
            f"token: {_token_source()}, RAY_AUTH_MODE={os.environ.get('RAY_AUTH_MODE', 'unset')})"
        ) from None


def ray_init_local(num_cpus: int) -> None:
    """A private single-node Ray on loopback only: no dashboard, no usage reporting."""
    os.environ["RAY_USAGE_STATS_ENABLED"] = "0"
    _loopback_only()
    # Ray starts workers at nice 15; here the workers are the work (a sim at nice 15 on a busy machine
    # ran ~6x slower than a local worker), so they get the same priority as local workers.
    os.environ.setdefault("RAY_worker_niceness", "0")
    import ray

    ray.init(
        num_cpus=num_cpus, _node_ip_address="127.0.0.1", include_dashboard=False, log_to_driver=False,
        configure_logging=False,
    )  # fmt: skip
    node_ip = ray.util.get_node_ip_address()
    if node_ip != "127.0.0.1":
        ray.shutdown()
        raise RuntimeError(
            f"local Ray came up on {node_ip}, not loopback: import ray only after "
            "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0 is set (lq_ros.run.sweep.ray_init_local does this)"
        )


class RayPool:
    """Ray actors as workers (one CPU each); results and bags come back to the driver's store."""

    def __init__(self, n: int | None, transport: str, bags_dir: Path, timeout_s: float | None, address: str | None):
        if address:
            ray_connect(address)
        else:
            ray_init_local(n or default_workers())
        import ray

        self._ray = ray
        self._bags_dir = Path(bags_dir)
        if n is None:
            n = max(1, int(ray.cluster_resources().get("CPU", 1)))
        # SPREAD: one actor per node before a second on any (a cluster's nodes share the episodes).
        self._actor_cls = ray.remote(num_cpus=1, max_restarts=0, scheduling_strategy="SPREAD")(_RayEpisodeActor)
        # A private Ray runs its actors on this machine: they hold the sweep folder's processes lock, as local workers
        # do (a resume after a kill -9 waits for them). A cluster's actors may run elsewhere: its own files there.
        lock = None if address else str(self._bags_dir.parent / PROCESSES_LOCK)
        self._args = (transport, timeout_s, lock)
        self._actors = [self._actor_cls.remote(*self._args) for _ in range(n)]
        self._pending: dict = {}  # ObjectRef -> (slot, log_path)

    @property
    def size(self) -> int:
        return len(self._actors)

    def submit(self, slot: int, cfg: RunConfig, log_path: Path) -> None:
        self._pending[self._actors[slot].run.remote(cfg.to_dict())] = (slot, log_path)

    def wait(self, busy: set[int], timeout_s: float) -> list[tuple[int, dict]]:
        ray = self._ray
        if not self._pending:
            time.sleep(timeout_s)
            return []
        ready, _ = ray.wait(list(self._pending), num_returns=1, timeout=timeout_s)
        out = []
        for ref in ready:
            slot, log_path = self._pending.pop(ref)
            try:
                result = ray.get(ref)
            except ray.exceptions.RayError as exc:  # the actor died, or failed outside the episode
                result = {"status": "error", "reason": f"Ray worker failed: {type(exc).__name__}", "row": None,
                          "bag": None, "wall_s": None, "log_text": str(exc)}  # fmt: skip
                if isinstance(exc, ray.exceptions.RayActorError | ray.exceptions.WorkerCrashedError):
                    self._actors[slot] = self._actor_cls.remote(*self._args)
            Path(log_path).parent.mkdir(parents=True, exist_ok=True)
            Path(log_path).write_text(result.pop("log_text", ""))
            for data in result.pop("tars", []):
                _unpack_dir(data, self._bags_dir)
            if result.get("bag"):
                result["bag"] = str(self._bags_dir / Path(result["bag"]).name)
            out.append((slot, result))
        return out

    def close(self) -> None:
        ray = self._ray
        with contextlib.suppress(Exception):
            ray.get([a.close.remote() for a in self._actors], timeout=30)
        ray.shutdown()

    def terminate(self) -> None:
        for actor in self._actors:
            with contextlib.suppress(Exception):
                self._ray.kill(actor)
        self._ray.shutdown()
