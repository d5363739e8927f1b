"""Ray actors as sweep workers: episodes run on any node of a Ray cluster, bags come back to the driver's store.

Without an address, a private single-node Ray on loopback (``ray_init_local``). With ``--address HOST:PORT``,
the cluster started with ``ray start`` (docs/guide/sweeps.md): the actors are spread over its nodes, each episode's
bag and logs travel back to the driver, and every attempt records the node that ran it. Token
authentication (Ray's default for a new cluster) needs the head's token in the driver's environment
(``RAY_AUTH_MODE=token`` and ``RAY_AUTH_TOKEN_PATH`` or ``RAY_AUTH_TOKEN``); a driver that cannot connect
gets one line naming the address and the token it used (:class:`RayConnectError`).

The token is a credential. A private Ray gets a fresh token of its own, in a file only this user can read (Ray
would otherwise write ``~/.ray/auth_token``, readable by everyone); the programs the workers launch (ROS nodes, a
policy server) are not given it. A token is not sent in clear to another machine: joining a cluster at a
non-loopback address with a token needs Ray's TLS (``RAY_USE_TLS=1``), or ``LQ_RAY_ALLOW_INSECURE=1`` to allow
it explicitly (the rule the openpi and OpenVLA clients follow for their credentials).
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
from lq_ros.core.safe_write import write_text
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


#: Set to 1 to send a Ray token unencrypted to a cluster on another machine.
ALLOW_INSECURE_ENV = "LQ_RAY_ALLOW_INSECURE"
#: A private Ray's token folder in the temp folder: lq_ray_token_<random> (0700, the token file 0600).
TOKEN_PREFIX = "lq_ray_token_"


def _sends_token() -> bool:
    """Whether Ray will present a token when this driver joins a cluster (token mode, and a token it can read)."""
    if os.environ.get("RAY_AUTH_MODE", "").lower() == "disabled":
        return False
    return bool(
        os.environ.get("RAY_AUTH_TOKEN") or os.environ.get("RAY_AUTH_TOKEN_PATH")
        or os.path.exists(os.path.expanduser("~/.ray/auth_token"))
    )  # fmt: skip


def refuse_token_in_clear(address: str) -> None:
    """RayConnectError when joining ``address`` would send the cluster token unencrypted to another machine."""
    tls = os.environ.get("RAY_USE_TLS", "0").lower() in ("1", "true")
    allowed = os.environ.get(ALLOW_INSECURE_ENV, "0").lower() in ("1", "true")
    if not is_loopback_address(address) and _sends_token() and not tls and not allowed:
        raise RayConnectError(
            f"cannot join the Ray cluster at {address}: its token ({_token_source()}) would travel unencrypted to "
            f"another machine; use Ray's TLS (RAY_USE_TLS=1 with its certificates), a loopback address (e.g. through "
            f"an SSH tunnel), or set {ALLOW_INSECURE_ENV}=1"
        )


class _PrivateToken:
    """A fresh token for a private Ray, in a 0600 file of a 0700 folder, set for this process and the Ray processes
    it starts (RAY_AUTH_MODE, RAY_AUTH_TOKEN_PATH) until :meth:`close` puts the environment back."""

    def __init__(self) -> None:
        import secrets

        remove_orphaned_folders(TOKEN_PREFIX)  # those of drivers killed with SIGKILL
        self.folder, self._lock = owned_temp_folder(TOKEN_PREFIX)
        path = self.folder / "auth_token"
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
        with os.fdopen(fd, "w") as f:
            f.write(secrets.token_hex(32))
        self._saved = {k: os.environ.get(k) for k in ("RAY_AUTH_MODE", "RAY_AUTH_TOKEN", "RAY_AUTH_TOKEN_PATH")}
        os.environ.pop("RAY_AUTH_TOKEN", None)
        os.environ.update(RAY_AUTH_MODE="token", RAY_AUTH_TOKEN_PATH=str(path))
        _reload_ray_auth()

    def close(self) -> None:
        for key, value in self._saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value
        _reload_ray_auth()
        shutil.rmtree(self.folder, ignore_errors=True)
        os.close(self._lock)


def _reload_ray_auth() -> None:
    """Have this process's Ray read RAY_AUTH_MODE and the token again (as ray's own _enable_token_auth does)."""
    from ray._raylet import AuthenticationTokenLoader, Config

    Config.initialize("")
    AuthenticationTokenLoader.instance().reset_cache()  # a token cached by an earlier Ray in this process


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
    refuse_token_in_clear(address)
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


def ray_init_local(num_cpus: int) -> _PrivateToken | None:
    """A private single-node Ray on loopback only: no dashboard, no usage reporting; token authentication with a
    token of its own (returned: close it after ray.shutdown) unless the user turned it off (RAY_AUTH_MODE=disabled)."""
    os.environ["RAY_USAGE_STATS_ENABLED"] = "0"
    _loopback_only()
    # Ray starts workers at nice 15; here the workers are the work (a sim at nice 15 on a busy machine
    # ran ~6x slower than a local worker), so they get the same priority as local workers.
    os.environ.setdefault("RAY_worker_niceness", "0")
    import ray

    token = None if os.environ.get("RAY_AUTH_MODE", "").lower() == "disabled" else _PrivateToken()
    try:
        ray.init(
            num_cpus=num_cpus, _node_ip_address="127.0.0.1", include_dashboard=False, log_to_driver=False,
            configure_logging=False,
        )  # fmt: skip
    except BaseException:
        if token is not None:
            token.close()
        raise
    node_ip = ray.util.get_node_ip_address()
    if node_ip != "127.0.0.1":
        ray.shutdown()
        if token is not None:
            token.close()
        raise RuntimeError(
            f"local Ray came up on {node_ip}, not loopback: import ray only after "
            "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0 is set (lq_ros.run.sweep.ray_init_local does this)"
        )
    return token


class RayPool:
    """Ray actors as workers (one CPU each); results and bags come back to the driver's store."""

    def __init__(self, n: int | None, transport: str, bags_dir: Path, timeout_s: float | None, address: str | None):
        self._token = None
        if address:
            ray_connect(address)
        else:
            self._token = ray_init_local(n or default_workers())
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
            write_text(Path(log_path), result.pop("log_text", ""))  # (never through a link)
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
        self._close_token()

    def _close_token(self) -> None:
        if self._token is not None:
            self._token.close()
            self._token = None

    def terminate(self) -> None:
        for actor in self._actors:
            with contextlib.suppress(Exception):
                self._ray.kill(actor)
        self._ray.shutdown()
        self._close_token()
