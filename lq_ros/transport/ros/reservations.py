"""Reservations a ROS stack holds while it runs: a ROS domain id and a CPU for its sim.

Each is an exclusive ``flock`` on a lock file in a folder of this user's own (0700, owner checked), opened without
following a link and never truncated nor written. The stack's nodes inherit the lock, so a domain whose nodes
outlive a killed launcher is not handed out again.
"""

from __future__ import annotations

import fcntl
import os
import socket
import stat
import tempfile
from collections.abc import Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from lq_ros.transport.processes import ResourceBusy, open_lock_file, private_folder, sim_cpu_choice

#: ROS_DOMAIN_IDs handed to concurrent runs (0, the default, is left to other ROS software).
DOMAIN_IDS = range(20, 100)  # below the ephemeral port range (Fast DDS port = 7400 + 250 * id)
#: The lock files of the domain ids and sim CPUs this user's runs hold: folders of this user's own (0700, owner
#: checked), so no other user can plant a file in them or take them over; each lock file is opened without
#: following a link, never truncated nor written.
DOMAIN_LOCK_DIR = Path(tempfile.gettempdir()) / f"lq_ros_domains-{os.getuid()}"
#: The CPUs held by stacks' sims (reserved_sim_cpu), one lock file per CPU.
CPU_LOCK_DIR = Path(tempfile.gettempdir()) / f"lq_ros_cpus-{os.getuid()}"
#: The folder every user shared before the per-user folders: a lock held there is a run of an older version.
#: Only read (a shared lock tried on a file opened read-only), never created or written.
SHARED_DOMAIN_LOCK_DIR = Path(tempfile.gettempdir()) / "lq_ros_domains"
#: Fast DDS's well-known ports (RTPS 2.2 section 9.6.1.1, Fast DDS defaults): a participant of domain d with index i
#: receives discovery traffic on PB + DG * d + d1 + PG * i. Other users' runs, and other ROS software, hold no lock
#: here; a bound port of a domain shows its live participants (the first FASTDDS_PARTICIPANTS indices are tried).
FASTDDS_PB, FASTDDS_DG, FASTDDS_D1, FASTDDS_PG = 7400, 250, 10, 2
FASTDDS_PARTICIPANTS = 32


@dataclass(frozen=True)
class DomainReservation:
    id: int
    #: Descriptor of the lock file: a child started with it (``pass_fds``) keeps the domain reserved until it exits.
    lock_fd: int


#: A lock folder that is not this user's (lq_ros.transport.processes.private_folder): one line.
LockFolderError = ResourceBusy


@contextmanager
def _first_free_lock(lock_dir: Path, candidates: Sequence[int], unusable: list[str], skip=None):
    """Hold an exclusive ``flock`` on the lock file of the first candidate nobody holds; yields (candidate, lock
    descriptor), or None when every candidate is held. A lock file this user cannot open is noted in ``unusable``;
    ``skip(candidate)`` (if given) returns why a candidate is in use elsewhere (noted too), or None.

    The lock belongs to the open lock file, so it lasts while any process holding that file lives (a child started
    with the descriptor in ``pass_fds`` keeps it until it exits).
    """
    private_folder(lock_dir)
    for candidate in candidates:
        try:
            fd = open_lock_file(lock_dir / f"{candidate}.lock")
        except OSError as exc:
            unusable.append(f"{candidate} ({exc.strerror or exc})")
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            continue
        why = skip(candidate) if skip is not None else None
        if why is not None:
            unusable.append(f"{candidate} ({why})")
            os.close(fd)
            continue
        try:
            yield candidate, fd
        finally:
            os.close(fd)  # no LOCK_UN: that would release the lock for the children that still hold it too
        return
    yield None


class DomainUnavailable(ResourceBusy):
    """No domain id could be reserved: one line naming the ids and why each was skipped."""


def held_by_an_older_version(domain_id: int) -> bool:
    """Whether a run of a version before the per-user lock folders holds ``domain_id`` (in the shared folder)."""
    try:
        flags = os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC
        fd = os.open(SHARED_DOMAIN_LOCK_DIR / f"{domain_id}.lock", flags)
    except OSError:
        return False
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            return False
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        return False
    except OSError:
        return True  # an exclusive lock is held
    finally:
        os.close(fd)


def lock_for_older_versions(domain_id: int) -> int | None:
    """While runs of older versions may still pick ids from the shared folder, also hold ``domain_id``'s lock there,
    if that folder is this user's own (a folder of another user's is never written to); the descriptor, or None."""
    try:
        info = os.lstat(SHARED_DOMAIN_LOCK_DIR)
        if not stat.S_ISDIR(info.st_mode) or info.st_uid != os.getuid():
            return None
        fd = open_lock_file(SHARED_DOMAIN_LOCK_DIR / f"{domain_id}.lock")
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        return None
    return fd


def domain_participants_live(domain_id: int) -> bool:
    """Whether a Fast DDS participant of ``domain_id`` lives on this machine (any user's): one of its discovery
    ports is bound. Binding sends nothing."""
    base = FASTDDS_PB + FASTDDS_DG * domain_id + FASTDDS_D1
    for index in range(FASTDDS_PARTICIPANTS):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
            try:
                probe.bind(("0.0.0.0", base + FASTDDS_PG * index))
            except OSError:
                return True
    return False


def domain_in_use_elsewhere(domain_id: int, probe_ports: bool) -> str | None:
    """Why ``domain_id`` is in use by someone who holds no lock in this user's folder, or None."""
    if held_by_an_older_version(domain_id):
        return f"held by a run in {SHARED_DOMAIN_LOCK_DIR}"
    if probe_ports and domain_participants_live(domain_id):
        return "in use by live ROS processes"
    return None


@contextmanager
def reserved_domain(domain_id: int | None = None):
    """Hold an exclusive lock on a ROS domain id for the duration of a run.

    The nodes inherit the lock, so a domain whose nodes outlive a killed launcher is not handed out again. The
    automatic search also skips the domains where live ROS processes (another user's run, other ROS software)
    already have participants; an id the user names is taken unless one of this user's runs holds it (a robot's
    domain has the robot's participants in it).
    """
    candidates = [domain_id] if domain_id is not None else list(DOMAIN_IDS)
    unusable: list[str] = []  # ids skipped and why (a lock file this user cannot open, a domain in use elsewhere)

    def elsewhere(candidate: int) -> str | None:
        return domain_in_use_elsewhere(candidate, probe_ports=domain_id is None)

    with _first_free_lock(DOMAIN_LOCK_DIR, candidates, unusable, skip=elsewhere) as held:
        if held is not None:
            shared = lock_for_older_versions(held[0])
            try:
                yield DomainReservation(*held)
            finally:
                if shared is not None:
                    os.close(shared)
            return
    skipped = f"; not usable: {', '.join(unusable)}" if unusable else ""
    raise DomainUnavailable(f"no free ROS domain id among {candidates} (this user's runs hold the rest){skipped}")


@contextmanager
def reserved_sim_cpu():
    """A CPU this process may run on that no other stack's sim holds (an ``flock``, as for domain ids), or None:
    with fewer than two such CPUs (a sim alone on the only one gains nothing), when every one is held (more
    stacks than CPUs) or when LQ_SIM_CPU (processes.SIM_CPU_ENV) is ``off``. Yields (cpu, lock descriptor) or None."""
    allowed = sorted(os.sched_getaffinity(0))
    if sim_cpu_choice(dict(os.environ)) == "off" or len(allowed) < 2:
        yield None
        return
    with _first_free_lock(CPU_LOCK_DIR, allowed, []) as held:
        yield held
