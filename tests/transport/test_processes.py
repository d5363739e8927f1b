"""Folders marked by their owner's lock (lq_ros.transport.processes): an orphan's is removed, a live one's kept;
links and other users' folders and shared-memory files are never touched."""

import os
import signal
import subprocess
import sys
import time

from lq_ros.transport import processes
from lq_ros.transport.processes import OWNER_LOCK, ShmTracker, owned_temp_folder, ownerless, remove_orphaned_folders

PREFIX = "lq_owned_"


def owner_process(parent) -> tuple[subprocess.Popen, str]:
    """A process that makes an owned folder under ``parent`` and keeps it; returns it and the folder's path."""
    code = (
        "import sys, time; from pathlib import Path; from lq_ros.transport.processes import owned_temp_folder; "
        f"folder, _ = owned_temp_folder({PREFIX!r}, Path({str(parent)!r})); print(folder, flush=True); time.sleep(60)"
    )
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    return proc, proc.stdout.readline().strip()


def test_the_folder_of_an_owner_killed_with_sigkill_is_removed_and_a_live_owners_kept(tmp_path):
    dead, dead_folder = owner_process(tmp_path)
    live, live_folder = owner_process(tmp_path)
    try:
        dead.send_signal(signal.SIGKILL)
        dead.wait(timeout=10)
        (tmp_path / "not_owned_here").mkdir()  # another prefix: never looked at
        assert remove_orphaned_folders(PREFIX, tmp_path, min_age_s=0.0) == [tmp_path / os.path.basename(dead_folder)]
        assert not os.path.exists(dead_folder)
        assert os.path.exists(os.path.join(live_folder, OWNER_LOCK)) and (tmp_path / "not_owned_here").is_dir()
    finally:
        live.kill()
        live.wait(timeout=10)


def test_a_young_orphan_and_this_processs_own_folder_are_kept(tmp_path):
    mine, fd = owned_temp_folder(PREFIX, tmp_path)
    orphan, orphan_fd = owned_temp_folder(PREFIX, tmp_path)
    os.close(orphan_fd)  # its owner is gone, but only just
    try:
        assert remove_orphaned_folders(PREFIX, tmp_path, min_age_s=60.0) == []
        old = time.time() - 120.0
        os.utime(orphan / OWNER_LOCK, (old, old))
        assert remove_orphaned_folders(PREFIX, tmp_path, min_age_s=60.0) == [orphan]
        assert mine.is_dir() and not orphan.exists()
    finally:
        os.close(fd)


def test_a_folder_without_a_lock_file_is_left_alone(tmp_path):
    (tmp_path / f"{PREFIX}legacy").mkdir()
    assert remove_orphaned_folders(PREFIX, tmp_path, min_age_s=0.0) == []
    assert (tmp_path / f"{PREFIX}legacy").is_dir()


def test_links_and_other_users_folders_are_left_alone(tmp_path):
    """The temp folder is shared: a link named like an owned folder, or another user's folder, is never removed."""
    target = tmp_path / "someone_elses"
    target.mkdir()
    (target / OWNER_LOCK).touch()
    (tmp_path / f"{PREFIX}link").symlink_to(target)
    others, fd = owned_temp_folder(PREFIX, tmp_path)
    os.close(fd)
    if os.getuid() == 0:
        os.chown(others, 65534, -1)
    else:
        others = None
    assert remove_orphaned_folders(PREFIX, tmp_path, min_age_s=0.0) == []
    assert (target / OWNER_LOCK).exists() and (others is None or others.is_dir())


def test_ownerless_never_follows_a_link(tmp_path):
    victim = tmp_path / "victim"
    (tmp_path / "x_el").symlink_to(victim)
    with ownerless(tmp_path / "x_el", create=True) as free:
        assert not free
    assert not victim.exists()


def test_stale_shared_memory_of_other_users_is_not_considered(tmp_path, monkeypatch):
    monkeypatch.setattr(processes, "SHM_DIR", tmp_path)
    old = time.time() - 600
    for name in ("fastrtps_mine", "fastrtps_theirs"):
        (tmp_path / f"{name}_el").touch()
        os.utime(tmp_path / f"{name}_el", (old, old))
    if os.getuid() == 0:
        os.chown(tmp_path / "fastrtps_theirs_el", 65534, -1)
    else:
        os.chmod(tmp_path, 0o700)
    tracker = ShmTracker.stale_segments()
    assert "fastrtps_mine" in tracker.names
    assert os.getuid() != 0 or "fastrtps_theirs" not in tracker.names


def test_a_teardown_that_hangs_is_ended_by_the_kernel():
    """end_teardown_after: a process that never leaves (here a busy loop that never releases control to a signal
    handler's Python: a regular expression's backtracking, in C, holding the GIL) is ended by SIGALRM's default
    action; one that leaves in time exits with its own code."""
    hang = ("from lq_ros.transport.processes import end_teardown_after; import re; end_teardown_after(1); "
            "re.match(r'(a+)+$', 'a' * 64 + 'b')")  # fmt: skip
    started = time.monotonic()
    ended = subprocess.run([sys.executable, "-c", hang], timeout=60)
    assert ended.returncode == -signal.SIGALRM and time.monotonic() - started < 30
    leaves = "from lq_ros.transport.processes import end_teardown_after; end_teardown_after(30); raise SystemExit(3)"
    assert subprocess.run([sys.executable, "-c", leaves], timeout=60).returncode == 3


def test_a_process_left_to_init_knows_it(monkeypatch):
    """orphan_check: false while the parent that started a process lives, true once the process has been left to
    init (PID 1); never true for a process that init started (a container's launcher). Reparenting itself is the
    kernel's: where a subreaper lives above (a stack's launcher, systemd --user), an orphan goes there instead."""
    parent = [4242]
    monkeypatch.setattr(processes.os, "getppid", lambda: parent[0])
    left_alone = processes.orphan_check()
    assert not left_alone()
    parent[0] = 1
    assert left_alone()
    assert not processes.orphan_check()()  # started by init: it stays false
