"""The lock-file reservations of a stack: the free ROS_DOMAIN_ID search (a lock file this user cannot open costs that
id only, never the search) and the CPU a stack's sim steps on (one per stack while CPUs last)."""

from __future__ import annotations

import fcntl

import pytest

from lq_ros.transport.processes import SIM_CPU_ENV
from lq_ros.transport.ros import stack


@pytest.fixture
def lock_dir(tmp_path, monkeypatch):
    """A private lock folder and four candidate ids (no real run's lock is touched)."""
    monkeypatch.setattr(stack, "DOMAIN_LOCK_DIR", tmp_path / "domains")
    monkeypatch.setattr(stack, "DOMAIN_IDS", range(20, 24))
    (tmp_path / "domains").mkdir()
    return tmp_path / "domains"


def test_unopenable_lock_files_are_skipped(lock_dir, tmp_path):
    (lock_dir / "20.lock").mkdir()  # a directory where a lock file should be
    # Another user's 0644 lock (unwritable here) stands in as a lock file whose open fails: a dangling link
    # into a missing folder fails the same way for every user, root included.
    (lock_dir / "21.lock").symlink_to(tmp_path / "missing" / "21.lock")
    with open(lock_dir / "22.lock", "w") as held:  # a run in progress holds 22
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        with stack.reserved_domain() as domain:
            assert domain.id == 23
            with pytest.raises(RuntimeError) as refused, stack.reserved_domain():
                pass
    message = str(refused.value)
    assert "no free ROS domain id among [20, 21, 22, 23]" in message
    assert "lock files not usable by this user: 20 (Is a directory), 21 (No such file or directory)" in message


def test_a_requested_id_with_an_unopenable_lock_is_refused_with_the_reason(lock_dir):
    (lock_dir / "21.lock").mkdir()
    with pytest.raises(RuntimeError, match=r"among \[21\].*21 \(Is a directory\)"), stack.reserved_domain(21):
        pass
    with stack.reserved_domain(22) as domain:
        assert domain.id == 22


@pytest.fixture
def three_cpus(tmp_path, monkeypatch):
    """A private CPU lock folder and a process allowed on CPUs 0, 2 and 5."""
    monkeypatch.setattr(stack, "CPU_LOCK_DIR", tmp_path / "cpus")
    monkeypatch.setattr(stack.os, "sched_getaffinity", lambda pid: {5, 0, 2})
    monkeypatch.delenv(SIM_CPU_ENV, raising=False)


def test_each_stacks_sim_gets_a_cpu_of_its_own_while_they_last(three_cpus):
    with stack.reserved_sim_cpu() as a, stack.reserved_sim_cpu() as b, stack.reserved_sim_cpu() as c:
        assert [a[0], b[0], c[0]] == [0, 2, 5]
        with stack.reserved_sim_cpu() as d:
            assert d is None  # more stacks than CPUs: the fourth sim is left to the scheduler
    with stack.reserved_sim_cpu() as again:
        assert again[0] == 0  # released with the stacks


def test_no_cpu_is_reserved_when_switched_off_or_alone(three_cpus, monkeypatch):
    monkeypatch.setenv(SIM_CPU_ENV, "off")
    with stack.reserved_sim_cpu() as held:
        assert held is None
    monkeypatch.setenv(SIM_CPU_ENV, "auto")
    monkeypatch.setattr(stack.os, "sched_getaffinity", lambda pid: {3})
    with stack.reserved_sim_cpu() as held:
        assert held is None  # one CPU: nothing to keep the sim apart from
    monkeypatch.setenv(SIM_CPU_ENV, "pinned")
    with pytest.raises(ValueError, match="LQ_SIM_CPU must be auto or off, got 'pinned'"), stack.reserved_sim_cpu():
        pass
