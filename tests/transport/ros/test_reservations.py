"""The lock-file reservations of a stack: the free ROS_DOMAIN_ID search (a lock file this user cannot open costs that
id only, never the search) and the CPU a stack's sim steps on (one per stack while CPUs last).

The lock folders are this user's own (0700, owner checked): a link planted as a lock file is never followed (it
truncated its target to 0 bytes), another user's folder is refused in one line, and a second user gets domains of
their own; domains in use by live ROS processes that hold no lock here (another user's run, an older version's run
locking in the shared folder) are skipped by the automatic search."""

from __future__ import annotations

import fcntl
import importlib
import os
import shutil
import socket
import stat
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from lq_ros.transport.processes import SIM_CPU_ENV
from lq_ros.transport.ros import reservations


@pytest.fixture
def lock_dir(tmp_path, monkeypatch):
    """A private lock folder and four candidate ids (no real run's lock is touched)."""
    monkeypatch.setattr(reservations, "DOMAIN_LOCK_DIR", tmp_path / "domains")
    monkeypatch.setattr(reservations, "DOMAIN_IDS", range(20, 24))
    monkeypatch.setattr(reservations, "SHARED_DOMAIN_LOCK_DIR", tmp_path / "shared")
    monkeypatch.setattr(reservations, "domain_participants_live", lambda domain_id: False)  # (other users' runs: below)
    (tmp_path / "domains").mkdir(mode=0o700)
    return tmp_path / "domains"


def test_unopenable_lock_files_are_skipped(lock_dir, tmp_path):
    (lock_dir / "20.lock").mkdir()  # a directory where a lock file should be
    # Another user's 0644 lock (unwritable here) stands in as a lock file whose open fails: a dangling link
    # into a missing folder fails the same way for every user, root included.
    (lock_dir / "21.lock").symlink_to(tmp_path / "missing" / "21.lock")
    with open(lock_dir / "22.lock", "w") as held:  # a run in progress holds 22
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        with reservations.reserved_domain() as domain:
            assert domain.id == 23
            with pytest.raises(RuntimeError) as refused, reservations.reserved_domain():
                pass
    message = str(refused.value)
    assert "no free ROS domain id among [20, 21, 22, 23]" in message
    assert "not usable: 20 (Is a directory), 21 (Too many levels of symbolic links)" in message
    assert "\n" not in message


def test_a_planted_link_is_never_followed_nor_anything_truncated(lock_dir, tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    (lock_dir / "20.lock").symlink_to(victim)
    os.link(victim, lock_dir / "21.lock")  # a hard link: opened, locked, never written
    with reservations.reserved_domain() as domain:
        assert domain.id == 21
    assert victim.read_text() == "precious"


def test_lock_folders_are_this_users_own(tmp_path, monkeypatch):
    assert reservations.DOMAIN_LOCK_DIR.name == f"lq_ros_domains-{os.getuid()}"
    assert reservations.CPU_LOCK_DIR.name == f"lq_ros_cpus-{os.getuid()}"
    folder = tmp_path / "domains"
    monkeypatch.setattr(reservations, "DOMAIN_LOCK_DIR", folder)
    monkeypatch.setattr(reservations, "DOMAIN_IDS", range(96, 98))
    monkeypatch.setattr(reservations, "SHARED_DOMAIN_LOCK_DIR", tmp_path / "shared")
    monkeypatch.setattr(reservations, "domain_participants_live", lambda domain_id: False)
    with reservations.reserved_domain():
        assert stat.S_IMODE(folder.stat().st_mode) == 0o700
    folder.chmod(0o755)
    with reservations.reserved_domain():
        assert stat.S_IMODE(folder.stat().st_mode) == 0o700  # ours but open: closed again
    folder.rename(tmp_path / "elsewhere")
    folder.symlink_to(tmp_path / "elsewhere")
    with pytest.raises(reservations.LockFolderError, match="is a link or a file, not this user's") as refused:  # noqa: SIM117
        with reservations.reserved_domain():
            pass
    assert "\n" not in str(refused.value)
    if os.getuid() == 0:  # only root can give a folder to another user
        folder.unlink()
        folder.mkdir(mode=0o700)
        os.chown(folder, 65534, -1)
        with (
            pytest.raises(reservations.LockFolderError, match="is a folder of user id 65534"),
            reservations.reserved_domain(),
        ):
            pass


def reserve_as(uid: int, tmp: Path) -> str:
    """In a forked child running as ``uid`` with TMPDIR ``tmp``: the reservations module loaded afresh (its lock folders
    are those of that user), one domain reserved; returns the id, or the error line."""
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: never returns into pytest
        answer = "child failed"
        try:
            os.close(read)
            os.setgid(uid)
            os.setuid(uid)
            os.environ["TMPDIR"] = str(tmp)
            tempfile.tempdir = None
            module = importlib.reload(reservations)
            with module.reserved_domain() as domain:
                answer = str(domain.id)
        except Exception as exc:  # noqa: BLE001 - reported to the parent
            answer = f"{type(exc).__name__}: {exc}"
        finally:
            os.write(write, answer.encode())
            os._exit(0)
    os.close(write)
    with os.fdopen(read) as pipe:
        answer = pipe.read()
    os.waitpid(pid, 0)
    return answer


@pytest.mark.skipif(os.getuid() != 0, reason="switching users needs root")
def test_a_second_user_gets_a_domain_after_the_first(tmp_path):
    """Before: the first user's 0755 folder, shared by name, left every other user without a domain id."""
    shared_tmp = Path(tempfile.mkdtemp(prefix="lq_test_tmp_"))  # like /tmp: every user can reach and write it
    try:
        shared_tmp.chmod(0o1777)
        first = reserve_as(0, shared_tmp)
        second = reserve_as(65534, shared_tmp)
        folders = {p.name: p.lstat() for p in shared_tmp.iterdir()}
    finally:
        shutil.rmtree(shared_tmp)
    assert first.isdigit() and second.isdigit(), (first, second)
    assert folders["lq_ros_domains-0"].st_uid == 0
    assert folders["lq_ros_domains-65534"].st_uid == 65534


def bind_udp(port: int) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", port))
    return sock


def test_domains_in_use_elsewhere_are_skipped_by_the_search_only(tmp_path, monkeypatch):
    """Another user's run (or other ROS software) holds no lock here: its participants' ports show it."""
    monkeypatch.setattr(reservations, "DOMAIN_LOCK_DIR", tmp_path / "domains")
    monkeypatch.setattr(reservations, "SHARED_DOMAIN_LOCK_DIR", tmp_path / "shared")
    free = [d for d in range(99, 40, -1) if not reservations.domain_participants_live(d)][:2]
    monkeypatch.setattr(reservations, "DOMAIN_IDS", free)
    # The discovery port of participant index 3 of the first domain is bound: someone's fourth participant lives.
    with bind_udp(
        reservations.FASTDDS_PB
        + reservations.FASTDDS_DG * free[0]
        + reservations.FASTDDS_D1
        + reservations.FASTDDS_PG * 3
    ):
        assert reservations.domain_participants_live(free[0])
        with reservations.reserved_domain() as domain:
            assert domain.id == free[1]
        with reservations.reserved_domain(free[0]) as domain:
            assert domain.id == free[0]  # named by the user (a robot's domain has the robot's participants)


@pytest.mark.slow
def test_a_live_ros_participant_is_seen_by_its_ports(tmp_path):
    """The port formula against Fast DDS itself: a real rclpy participant in a domain nobody uses."""
    domain = next(d for d in range(99, 40, -1) if not reservations.domain_participants_live(d))
    code = "import rclpy, sys; rclpy.init(); n = rclpy.create_node('probe'); print('up', flush=True); sys.stdin.read()"
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    node = subprocess.Popen(
        [sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env
    )
    try:
        assert node.stdout.readline().strip() == "up"
        deadline = time.monotonic() + 10
        while not reservations.domain_participants_live(domain):
            assert time.monotonic() < deadline, f"no bound discovery port seen for domain {domain}"
            time.sleep(0.1)
    finally:
        node.communicate("", timeout=30)


def test_a_run_of_an_older_version_in_the_shared_folder_is_respected(lock_dir, tmp_path):
    shared = tmp_path / "shared"
    shared.mkdir()
    with open(shared / "20.lock", "w") as older:  # an older version's run holds 20 there
        fcntl.flock(older, fcntl.LOCK_EX | fcntl.LOCK_NB)
        with reservations.reserved_domain() as domain:
            assert domain.id == 21
            with open(shared / "21.lock") as probe, pytest.raises(BlockingIOError):
                fcntl.flock(probe, fcntl.LOCK_SH | fcntl.LOCK_NB)  # held there too, for older versions to see
    (shared / "22.lock").symlink_to(tmp_path / "victim")
    os.chown(shared, os.getuid(), -1)
    with reservations.reserved_domain(22) as domain:
        assert domain.id == 22
    assert not (tmp_path / "victim").exists()  # the link in the shared folder was not followed


def test_a_requested_id_with_an_unopenable_lock_is_refused_with_the_reason(lock_dir):
    (lock_dir / "21.lock").mkdir()
    with pytest.raises(RuntimeError, match=r"among \[21\].*21 \(Is a directory\)"), reservations.reserved_domain(21):
        pass
    with reservations.reserved_domain(22) as domain:
        assert domain.id == 22


@pytest.fixture
def three_cpus(tmp_path, monkeypatch):
    """A private CPU lock folder and a process allowed on CPUs 0, 2 and 5."""
    monkeypatch.setattr(reservations, "CPU_LOCK_DIR", tmp_path / "cpus")
    monkeypatch.setattr(reservations.os, "sched_getaffinity", lambda pid: {5, 0, 2})
    monkeypatch.delenv(SIM_CPU_ENV, raising=False)


def test_each_stacks_sim_gets_a_cpu_of_its_own_while_they_last(three_cpus):
    with (
        reservations.reserved_sim_cpu() as a,
        reservations.reserved_sim_cpu() as b,
        reservations.reserved_sim_cpu() as c,
    ):
        assert [a[0], b[0], c[0]] == [0, 2, 5]
        with reservations.reserved_sim_cpu() as d:
            assert d is None  # more stacks than CPUs: the fourth sim is left to the scheduler
    with reservations.reserved_sim_cpu() as again:
        assert again[0] == 0  # released with the stacks


def test_no_cpu_is_reserved_when_switched_off_or_alone(three_cpus, monkeypatch):
    monkeypatch.setenv(SIM_CPU_ENV, "off")
    with reservations.reserved_sim_cpu() as held:
        assert held is None
    monkeypatch.setenv(SIM_CPU_ENV, "auto")
    monkeypatch.setattr(reservations.os, "sched_getaffinity", lambda pid: {3})
    with reservations.reserved_sim_cpu() as held:
        assert held is None  # one CPU: nothing to keep the sim apart from
    monkeypatch.setenv(SIM_CPU_ENV, "pinned")
    with (
        pytest.raises(ValueError, match="LQ_SIM_CPU must be auto or off, got 'pinned'"),
        reservations.reserved_sim_cpu(),
    ):
        pass
