"""The free ROS_DOMAIN_ID search: a lock file this user cannot open costs that id only, never the search."""

from __future__ import annotations

import fcntl

import pytest

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
