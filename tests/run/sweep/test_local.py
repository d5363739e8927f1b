"""lq_ros/run/sweep/local.py: a worker that dies is replaced, and what its nodes left in /dev/shm is removed.

A real worker process of the pool is killed with SIGKILL; the Fast DDS files are planted by the test under names of
its own (a segment no one holds, one this process holds, a port), so nothing of another run is touched.
"""

from __future__ import annotations

import fcntl
import os
import signal
import uuid
from pathlib import Path

from lq_ros.run.sweep.local import LocalPool
from lq_ros.transport.processes import SHM_DIR


def plant(name: str) -> list[Path]:
    """A Fast DDS file as a participant makes it: the file and its ``_el`` lock file."""
    files = [SHM_DIR / name, SHM_DIR / f"{name}_el"]
    for path in files:
        path.write_bytes(b"")
    return files


def test_a_dead_workers_orphaned_segments_are_removed_and_nothing_live(tmp_path):
    tag = uuid.uuid4().hex[:12]
    orphan = plant(f"fastrtps_{tag}0")  # its owner (a node of the worker) died: nobody holds the lock
    live = plant(f"fastrtps_{tag}1")
    port = plant(f"fastrtps_port{tag}")  # shared by a domain's participants: never removed here
    held = os.open(live[1], os.O_RDWR)
    fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)  # a live participant's segment
    (tmp_path / "bags").mkdir()
    pool = LocalPool(1, "inprocess", tmp_path / "bags", None)
    try:
        os.kill(pool._procs[0].pid, signal.SIGKILL)
        pool._procs[0].join(timeout=30)
        results = pool.wait({0}, timeout_s=0.1)
        assert [(slot, r["status"]) for slot, r in results] == [(0, "error")]
        assert "worker process died" in results[0][1]["reason"]
        assert not any(path.exists() for path in orphan)
        assert all(path.exists() for path in (*live, *port))
        assert pool._procs[0].is_alive()  # replaced
    finally:
        pool.close()
        os.close(held)
        for path in (*orphan, *live, *port):
            path.unlink(missing_ok=True)
