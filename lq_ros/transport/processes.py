"""Process-lifetime helpers shared by the launcher, the sweep workers and the CLI.

No rclpy here: these run in processes that must not initialise ROS (the CLI, a sweep worker) and in a
child between fork and exec (``preexec_fn``).
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import fcntl
import gc
import os
import shutil
import signal
import stat
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from types import FrameType
from typing import NoReturn

#: The environment variable that chooses the executor every node spins, and its values (the first: the default).
#: ``events`` is rclpy.experimental.EventsExecutor: it dispatches each callback from C++ as its event arrives, where
#: rclpy's SingleThreadedExecutor (``single_threaded``) rebuilds its wait set in Python for every message; a lockstep
#: tick that waits for a message chain through three nodes (the chunk due, the request, the observation) waits
#: about a third less (benchmarks/bench_transport.py).
EXECUTOR_ENV, EXECUTORS = "LQ_RCLPY_EXECUTOR", ("events", "single_threaded")
#: Lockstep episodes run the sim node's stepping thread on a CPU of its own (lq_ros.transport.ros.stack): ``auto``
#: picks one that no other stack's sim holds, ``off`` leaves the choice to the OS scheduler.
SIM_CPU_ENV, SIM_CPU_CHOICES = "LQ_SIM_CPU", ("auto", "off")
#: The stack starts its nodes as forks of a process that has imported them (``on``: lq_ros.transport.ros.fork_server)
#: or executes each afresh (``off``).
NODE_FORKS_ENV, NODE_FORKS_CHOICES = "LQ_NODE_FORKS", ("on", "off")


def executor_choice(environ: dict[str, str]) -> str:
    """The executor ``environ`` chooses (ValueError naming the valid values)."""
    name = environ.get(EXECUTOR_ENV) or EXECUTORS[0]
    if name not in EXECUTORS:
        raise ValueError(f"{EXECUTOR_ENV} must be {' or '.join(EXECUTORS)}, got {name!r}")
    return name


def sim_cpu_choice(environ: dict[str, str]) -> str:
    """What :data:`SIM_CPU_ENV` says (ValueError naming the valid values)."""
    choice = environ.get(SIM_CPU_ENV) or SIM_CPU_CHOICES[0]
    if choice not in SIM_CPU_CHOICES:
        raise ValueError(f"{SIM_CPU_ENV} must be {' or '.join(SIM_CPU_CHOICES)}, got {choice!r}")
    return choice


def node_forks_choice(environ: dict[str, str]) -> str:
    """What :data:`NODE_FORKS_ENV` says (ValueError naming the valid values)."""
    choice = environ.get(NODE_FORKS_ENV) or NODE_FORKS_CHOICES[0]
    if choice not in NODE_FORKS_CHOICES:
        raise ValueError(f"{NODE_FORKS_ENV} must be {' or '.join(NODE_FORKS_CHOICES)}, got {choice!r}")
    return choice


#: prctl option from <linux/prctl.h>.
_PR_SET_PDEATHSIG = 1


def exit_uncollected(code: int = 0) -> NoReturn:
    """Leave through the interpreter's own exit after one garbage collection instead of the teardown's several.

    The exit handlers, the modules' teardown and C++'s static destructors (Fast DDS removes its shared-memory
    files in them) all still run, and whatever is garbage now is collected (finalized) first, as the first
    collection of a normal exit would; ``gc.freeze()`` then takes every object still alive out of the collector's
    reach, so the teardown's later collections skip them (with a simulator loaded those collections were most of a
    process's exit: 0.3-0.5 s, against about 0.1 s for this one). What they would have freed, the OS frees. Call it
    once every file that matters is closed and every ROS entity destroyed, from a frame that holds none of them.
    """
    sys.stdout.flush()
    sys.stderr.flush()
    gc.collect()
    gc.freeze()
    sys.exit(code)


def die_with_parent() -> None:
    """Have the kernel send this process SIGTERM when its parent dies, even by kill -9.

    Called first thing in a child (a launched node via ``preexec_fn``, a sweep worker), so nothing
    outlives the program that started it. A no-op where prctl does not exist (not Linux).
    """
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)


#: Wall seconds a node may take to leave once it stops spinning (closing its episode and bag, destroying its ROS
#: entities, Fast DDS's teardown) before the kernel ends it. No stop a launcher makes waits longer: it gives a node
#: 10 s after SIGINT and 5 s after SIGTERM, then SIGKILL (:func:`stop_processes`). This bounds the nodes nobody
#: stops: an executor node whose sweep worker had been ended was seen spinning at 65 % of a core for an hour, and a
#: node whose fork server was killed still alive 30 s after its parent-death signal.
TEARDOWN_LIMIT_S = 20


def end_teardown_after(seconds: int = TEARDOWN_LIMIT_S) -> None:
    """Have the kernel end this process with SIGALRM if it is still alive ``seconds`` from now.

    SIGALRM's default action runs no Python, so it ends a process stuck in C code that holds the GIL too.
    """
    signal.signal(signal.SIGALRM, signal.SIG_DFL)
    signal.alarm(seconds)


def orphan_check() -> Callable[[], bool]:
    """A check that turns true once this process has been left to init (PID 1): the program that started it and
    every subreaper above it are gone, so nobody will stop it any more. Never true for a process started by PID 1
    itself (a container whose first process is the launcher)."""
    started_by_init = os.getppid() == 1
    return lambda: not started_by_init and os.getppid() == 1


def stop_processes(procs: dict[str, subprocess.Popen], grace_s: float = 10.0) -> None:
    """SIGINT (clean rclpy shutdown), then SIGTERM, then SIGKILL whatever is left."""
    for sig, wait_s in ((signal.SIGINT, grace_s), (signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
        alive = [p for p in procs.values() if p.poll() is None]
        if not alive:
            return
        for p in alive:
            p.send_signal(sig)
        deadline = time.monotonic() + wait_s
        for p in alive:
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.wait(timeout=max(0.0, deadline - time.monotonic()))
    if any(p.poll() is None for p in procs.values()):
        raise RuntimeError("child processes survived SIGKILL")


def raise_keyboard_interrupt(*_) -> None:
    """Signal handler that unwinds like Ctrl-C, so ``finally`` blocks stop children cleanly."""
    raise KeyboardInterrupt


def sigterm_as_keyboard_interrupt() -> Callable[[int, FrameType | None], object] | int | None:
    """SIGTERM (a job runner, a parent stopping its workers) stops like Ctrl-C; returns the previous handler."""
    return signal.signal(signal.SIGTERM, raise_keyboard_interrupt)


class ResourceBusy(RuntimeError):
    """Something another run holds, or that is not this user's to use (a domain id, an output folder, a lock
    folder): the message is one line naming it and what to do."""


def private_folder(path: Path) -> Path:
    """``path`` as a folder only this user can write (made 0700 if missing); ResourceBusy if another user owns
    it or it is not a plain folder (a link, a file)."""
    with contextlib.suppress(FileExistsError):
        os.mkdir(path, 0o700)
    info = os.lstat(path)
    if not stat.S_ISDIR(info.st_mode) or info.st_uid != os.getuid():
        what = "a link or a file" if not stat.S_ISDIR(info.st_mode) else f"a folder of user id {info.st_uid}"
        raise ResourceBusy(
            f"lock folder {path} is {what}, not this user's (id {os.getuid()}): remove it, or point TMPDIR elsewhere"
        )
    if stat.S_IMODE(info.st_mode) & 0o077:
        os.chmod(path, 0o700)  # ours, but open to others: close it (its lock files are checked one by one anyway)
    return path


def open_lock_file(path: Path, mode: int = 0o600) -> int:
    """A descriptor of the lock file ``path`` (made if missing): never through a link, never truncated, only a
    regular file of this user; OSError otherwise (a link: "Too many levels of symbolic links")."""
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC, mode)
    info = os.fstat(fd)
    if not stat.S_ISREG(info.st_mode) or info.st_uid != os.getuid():
        os.close(fd)
        raise OSError(errno.EPERM, "not a regular file of this user")
    return fd


#: Per-user folder of the locks that claim output folders (:func:`claimed`).
CLAIM_DIR = Path(tempfile.gettempdir()) / f"lq_ros_claims-{os.getuid()}"


@contextlib.contextmanager
def claimed(path: Path, what: str = "folder") -> Iterator[None]:
    """Hold ``path`` (e.g. an episode's bag folder) for this process: a second claim of the same path, by another
    process, is ResourceBusy at once (two ``lq run`` of one configuration into one ``--out`` raced to create the
    same bag folder). The lock lives in this user's private folder, keyed by the absolute path; nothing is written
    next to ``path``."""
    import hashlib

    key = hashlib.sha256(str(Path(path).absolute()).encode()).hexdigest()[:32]
    fd = open_lock_file(private_folder(CLAIM_DIR) / f"{key}.lock")
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise ResourceBusy(
                f"{what} {path} is being written by another run now; wait for it or choose another"
            ) from None
        yield
    finally:
        os.close(fd)


#: Locks this process holds that every process it launches must hold too (pass_fds), so that such a lock is
#: free only once the whole process tree has exited.
_INHERITED_LOCKS: list[int] = []


def hold_for_children(fd: int) -> None:
    """Have the processes this one launches (a stack's nodes) inherit and hold the lock of ``fd``."""
    _INHERITED_LOCKS.append(fd)


def inherited_locks() -> tuple[int, ...]:
    return tuple(_INHERITED_LOCKS)


#: The lock file in a sweep folder that its workers, and the nodes they launch, hold shared while they live.
PROCESSES_LOCK = ".processes.lock"


def hold_shared(path: Path) -> int:
    """A shared ``flock`` on ``path`` (made if missing; never through a link), held until the descriptor closes and
    by every child that inherits it (blocks while an exclusive holder waits for earlier holders to leave)."""
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
    fcntl.flock(fd, fcntl.LOCK_SH)
    return fd


def lock_holders(path: Path) -> list[int]:
    """The live processes (this user's, that /proc shows) with ``path`` open: who holds its lock."""
    target = str(Path(path).resolve())
    holders = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            if any(os.readlink(fd) == target for fd in (entry / "fd").iterdir()):
                holders.append(int(entry.name))
        except OSError:  # gone meanwhile, or another user's
            continue
    return holders


def end_orphans(path: Path, wait_s: float, grace_s: float = 10.0) -> list[int]:
    """Wait up to ``wait_s`` for the processes holding ``path`` (a killed sweep's workers and nodes, ending on their
    own) to leave; then end those left (SIGTERM, then SIGKILL after ``grace_s``). Returns the pids still holding
    it after all that (empty: free)."""
    if wait_until_free(path, wait_s):
        return []
    for sig in (signal.SIGTERM, signal.SIGKILL):
        for pid in lock_holders(path):
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.kill(pid, sig)
        if wait_until_free(path, grace_s):
            return []
    return lock_holders(path)


def wait_until_free(path: Path, timeout_s: float) -> bool:
    """Wait until nobody holds a lock on ``path`` (an exclusive flock can be taken; it is released at once);
    whether that happened within ``timeout_s``. A missing file is free."""
    try:
        fd = os.open(path, os.O_RDWR | os.O_NOFOLLOW | os.O_CLOEXEC)
    except FileNotFoundError:
        return True
    try:
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                return True
            except BlockingIOError:
                if time.monotonic() >= deadline:
                    return False
                time.sleep(0.2)
    finally:
        os.close(fd)


#: Environment variables that carry a credential only the process that reads them needs (a Ray cluster's token):
#: never handed to the programs the stack launches (nodes, a policy server).
SECRET_ENV = ("RAY_AUTH_TOKEN", "RAY_AUTH_TOKEN_PATH")


def without_secrets(env: dict[str, str]) -> dict[str, str]:
    """``env`` without :data:`SECRET_ENV` (for a child that is not a Ray process)."""
    return {k: v for k, v in env.items() if k not in SECRET_ENV}


#: Where Fast DDS keeps its shared-memory transport files (segments, ports, their locks and mutexes).
SHM_DIR = Path("/dev/shm")
_FASTDDS_PREFIXES = ("fastrtps_", "fastdds_")


def fastdds_shm_owned(pid: int) -> set[str]:
    """Fast DDS shared-memory files that process ``pid`` owns (``set()`` if it is gone).

    Fast DDS holds an exclusive ``flock`` on ``<name>_el`` for every segment and port it created, for
    as long as it lives: the open ``_el`` descriptors name exactly the process's own files.
    """
    owned = set()
    fd_dir = Path(f"/proc/{pid}/fd")
    try:
        fds = list(fd_dir.iterdir())
    except OSError:
        return owned
    for fd in fds:
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        name = target.removeprefix(f"{SHM_DIR}/")
        if name != target and name.endswith("_el") and name.startswith(_FASTDDS_PREFIXES):
            owned.add(name[: -len("_el")])
    return owned


class ShmTracker:
    """Remembers the Fast DDS shared-memory files of some processes and removes those they left behind.

    A participant killed with SIGKILL leaves its segment and its ports (with their ``_el`` lock files and
    ``sem.*_mutex``) in /dev/shm; its peers, even when they exit cleanly, then keep their port files
    (without ``_el``), since the dead peer still counts as a user. ``sample`` the processes while they
    run; once they have exited, ``cleanup`` removes each remembered file that no live process owns. It
    takes the file's ``_el`` lock first (creating it if missing), so a file that a live participant owns
    or is taking over is never touched.
    """

    def __init__(self) -> None:
        self.names: set[str] = set()

    def sample(self, pids) -> None:
        for pid in pids:
            self.names |= fastdds_shm_owned(pid)

    @classmethod
    def stale_segments(cls, min_age_s: float = 60.0) -> ShmTracker:
        """A tracker of every Fast DDS data segment in /dev/shm older than ``min_age_s``.

        For runs that died all at once (a machine-wide SIGKILL leaves nobody to clean up): their segments
        stay forever. A segment has exactly one owner, which holds its ``_el`` lock while it lives, so
        ``cleanup`` removes only the dead ones; only this user's are considered. Port files are shared between
        participants and left alone.
        """
        tracker = cls()
        now = time.time()
        for path in SHM_DIR.glob("fastrtps_*_el"):
            name = path.name.removesuffix("_el")
            if name.startswith("fastrtps_port"):
                continue
            with contextlib.suppress(FileNotFoundError):
                info = path.lstat()
                if info.st_uid == os.getuid() and now - info.st_mtime >= min_age_s:  # never another user's
                    tracker.names.add(name)
        return tracker

    def cleanup(self, ports: bool = True) -> list[str]:
        """Remove the orphaned files; returns their names.

        ``ports=False`` while other participants of the domain live on: a port file is shared by every
        participant that uses the port, but only its creator holds the lock, so once the creator has exited
        nothing tells whether others still use it. Removing it then cut the survivors off from the participants
        started next ("Failed init_port ... open_and_lock_file failed", an episode that never started). Ports are
        kept in mind and removed once the whole stack has gone.
        """
        removed = []
        for name in sorted(self.names):
            if not ports and name.startswith("fastrtps_port"):
                continue
            files = (SHM_DIR / name, SHM_DIR / f"sem.{name}_mutex")
            lock_path = SHM_DIR / f"{name}_el"
            if not lock_path.exists() and not any(f.exists() for f in files):
                continue  # Fast DDS removed them itself (a clean exit)
            with ownerless(lock_path, create=True) as free:
                if not free:
                    continue  # a live participant owns it
                for path in (*files, lock_path):
                    with contextlib.suppress(FileNotFoundError):
                        path.unlink()
                        removed.append(path.name)
        return removed


@contextlib.contextmanager
def ownerless(lock_path: Path, create: bool = False) -> Iterator[bool]:
    """True, holding the lock of ``lock_path``, when nobody else holds it (its owner is gone); False when a live
    process holds it or the file cannot be opened (``create``: make it if missing)."""
    try:
        # Never through a link (/dev/shm and the temp folder are shared by every user).
        fd = os.open(lock_path, os.O_RDWR | os.O_NOFOLLOW | os.O_CLOEXEC | (os.O_CREAT if create else 0), 0o644)
    except OSError:
        yield False
        return
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            yield False
            return
        yield True
    finally:
        os.close(fd)


#: The lock file in a folder made by :func:`owned_temp_folder`: locked for as long as the folder's owner lives.
OWNER_LOCK = ".owner.lock"


def owned_temp_folder(prefix: str, parent: Path | None = None) -> tuple[Path, int]:
    """A new temporary folder, and the descriptor of the lock that marks it in use.

    The lock (``flock``) lasts until the descriptor is closed or the process dies, kill -9 included; the owner
    removes the folder itself when done, and :func:`remove_orphaned_folders` removes those of owners that died.
    """
    folder = Path(tempfile.mkdtemp(prefix=prefix, dir=parent))
    fd = os.open(folder / OWNER_LOCK, os.O_RDWR | os.O_CREAT, 0o600)
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # (a new file: nobody else has it)
    return folder, fd


def remove_orphaned_folders(prefix: str, parent: Path | None = None, min_age_s: float = 60.0) -> list[Path]:
    """Remove the folders :func:`owned_temp_folder` made with ``prefix`` whose owner died without removing them
    (a launcher killed with SIGKILL leaves its node logs); returns them.

    A folder counts once its lock file is older than ``min_age_s`` and nobody holds the lock; folders without a
    lock file (not made by :func:`owned_temp_folder`), links and other users' folders are left alone.
    """
    removed = []
    now = time.time()
    for lock_path in Path(parent or tempfile.gettempdir()).glob(f"{prefix}*/{OWNER_LOCK}"):
        try:
            folder, lock = lock_path.parent.lstat(), lock_path.lstat()
        except OSError:  # removed meanwhile
            continue
        if not stat.S_ISDIR(folder.st_mode) or folder.st_uid != os.getuid() or not stat.S_ISREG(lock.st_mode):
            continue  # another user's folder (or a link): never touched
        if now - lock.st_mtime < min_age_s:
            continue
        with ownerless(lock_path) as free:
            if free:  # (else its owner lives)
                shutil.rmtree(lock_path.parent, ignore_errors=True)
                removed.append(lock_path.parent)
    return removed


def process_group_members(pgid: int) -> list[int]:
    """Live (non-zombie) processes whose process group is ``pgid``."""
    out = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        # pid (comm) state ppid pgrp ...: comm may hold spaces and parentheses, so split after the last ')'.
        fields = stat[stat.rindex(")") + 2 :].split()
        if fields[0] != "Z" and int(fields[2]) == pgid:
            out.append(int(entry.name))
    return out


def wait_process_group_gone(pgid: int, timeout_s: float = 30.0, kill_after_s: float = 20.0) -> bool:
    """Wait until no process of group ``pgid`` is left (SIGKILL to the group after ``kill_after_s``).

    A sweep worker leads its own group, so the ROS nodes it launched can be waited for after the worker
    itself was killed. Returns whether the group is gone.
    """
    started = time.monotonic()
    killed = False
    while process_group_members(pgid):
        elapsed = time.monotonic() - started
        if elapsed > timeout_s:
            return False
        if elapsed > kill_after_s and not killed:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(pgid, signal.SIGKILL)
            killed = True
        time.sleep(0.1)
    return True
