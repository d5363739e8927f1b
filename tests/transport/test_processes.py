"""Folders marked by their owner's lock (lq_ros.transport.processes): an orphan's is removed, a live one's kept."""

import os
import signal
import subprocess
import sys
import time

from lq_ros.transport.processes import OWNER_LOCK, owned_temp_folder, remove_orphaned_folders

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
