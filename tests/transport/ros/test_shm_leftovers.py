"""The /dev/shm leftover check of the process tests (tests/transport/ros/test_faults.py) counts only the files of
the test's own processes: a CI run beside another user's ROS episodes counted that run's new port files (a port
whose creator had exited while its peers still used it: a free lock) as its own leftovers."""

from __future__ import annotations

import fcntl
import os
import subprocess
import sys

from tests.transport.ros import test_faults
from tests.transport.ros.test_faults import orphaned_shm, shm_files_of


def make(folder, *names: str) -> None:
    for name in names:
        (folder / name).write_bytes(b"\0" * 64)


def test_only_the_runs_own_files_count(tmp_path, monkeypatch):
    monkeypatch.setattr(test_faults, "SHM", tmp_path)
    make(tmp_path, "fastrtps_port7010", "fastrtps_port7010_el")  # there before the test
    before = set(os.listdir(tmp_path))
    # Files the run's (now dead) processes used, left behind; and another run's port, created meanwhile.
    make(tmp_path, "fastrtps_aaaa", "fastrtps_aaaa_el", "sem.fastrtps_aaaa_mutex")
    make(tmp_path, "fastrtps_port7008", "fastrtps_port7008_el", "sem.fastrtps_port7008_mutex")
    assert orphaned_shm(before) == sorted(
        ["fastrtps_aaaa", "fastrtps_aaaa_el", "sem.fastrtps_aaaa_mutex",
         "fastrtps_port7008", "fastrtps_port7008_el", "sem.fastrtps_port7008_mutex"]
    )  # fmt: skip
    assert orphaned_shm(before, ours={"fastrtps_aaaa"}) == ["fastrtps_aaaa", "fastrtps_aaaa_el",
                                                            "sem.fastrtps_aaaa_mutex"]  # fmt: skip
    # A file of the run that a live process still owns (holds its lock) is not a leftover either.
    with open(tmp_path / "fastrtps_aaaa_el", "rb") as held:
        fcntl.flock(held, fcntl.LOCK_EX)
        assert orphaned_shm(before, ours={"fastrtps_aaaa"}) == []


def test_the_files_a_process_uses_are_seen_while_it_lives(tmp_path, monkeypatch):
    monkeypatch.setattr(test_faults, "SHM", tmp_path)
    make(tmp_path, "fastrtps_bbbb", "fastrtps_port7411", "other_file")
    code = (
        "import mmap, sys, time\n"
        "a = open(sys.argv[1] + '/fastrtps_bbbb', 'r+b'); m = mmap.mmap(a.fileno(), 64); a.close()\n"
        "b = open(sys.argv[1] + '/fastrtps_port7411', 'rb'); c = open(sys.argv[1] + '/other_file', 'rb')\n"
        "print('ready', flush=True); time.sleep(60)\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", code, str(tmp_path)], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
        # Mapped (a segment: its descriptor closed) or open (a port); other files are not Fast DDS's.
        assert shm_files_of([proc.pid]) == {"fastrtps_bbbb", "fastrtps_port7411"}
    finally:
        proc.kill()
        proc.wait()
    assert shm_files_of([proc.pid]) == set()  # gone
