"""A sweep killed with -9 frees its folder's lock at once, while its workers and their nodes still close their
episodes: a resume then started beside them. Now every worker (and every node it launches) holds the folder's
processes lock while it lives, and a resume waits for them to end on their own, or ends them, before it touches
anything."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from lq_ros.run import sweep as sw
from lq_ros.run.sweep import orchestrator
from lq_ros.transport.processes import PROCESSES_LOCK, lock_holders
from tests.run.sweep.test_spec import small_spec

REPO = Path(__file__).resolve().parents[3]
#: A stand-in orphan: holds the folder's processes lock, says so, then lives ``argv[2]`` s (SIGTERM ignored if
#: ``argv[3]`` is "stubborn").
_ORPHAN = """
import signal, sys, time
from pathlib import Path
from lq_ros.transport.processes import hold_shared
if sys.argv[3] == "stubborn":
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
fd = hold_shared(Path(sys.argv[1]))
print("holding", flush=True)
time.sleep(float(sys.argv[2]))
"""


def orphan(out: Path, live_s: float, kind: str = "plain") -> subprocess.Popen:
    out.mkdir(parents=True, exist_ok=True)
    proc = subprocess.Popen([sys.executable, "-c", _ORPHAN, str(out / PROCESSES_LOCK), str(live_s), kind],
                            stdout=subprocess.PIPE, text=True, cwd=REPO)  # fmt: skip
    assert proc.stdout.readline().strip() == "holding"
    return proc


@pytest.fixture
def started(monkeypatch) -> list[tuple[float, list[int]]]:
    """When the sweep's real work began, and who still held the processes lock then."""
    calls: list[tuple[float, list[int]]] = []

    def run_locked(spec, out_dir, *args):
        calls.append((time.monotonic(), lock_holders(Path(out_dir) / PROCESSES_LOCK)))
        return sw.SweepSummary(total=0, skipped=0, out_dir=Path(out_dir))

    monkeypatch.setattr(orchestrator, "_run_locked", run_locked)
    return calls


def test_a_resume_waits_for_orphans_that_end_on_their_own(tmp_path, started):
    spec = sw.expand_spec(small_spec())
    proc = orphan(tmp_path, 2.0)
    t0 = time.monotonic()
    sw.run_sweep(spec, tmp_path, workers=1)
    assert proc.wait(timeout=10) == 0  # it ended on its own
    ((when, holders),) = started
    assert when - t0 >= 1.5 and holders == []


def test_a_resume_ends_orphans_that_do_not_end(tmp_path, started, monkeypatch):
    monkeypatch.setattr(orchestrator, "ORPHAN_WAIT_S", 0.5)
    spec = sw.expand_spec(small_spec())
    proc = orphan(tmp_path, 600.0, "stubborn")  # ignores SIGTERM: ended by SIGKILL
    sw.run_sweep(spec, tmp_path, workers=1)
    assert proc.wait(timeout=30) == -signal.SIGKILL
    ((_, holders),) = started
    assert holders == []


@pytest.mark.slow
@pytest.mark.sim
@pytest.mark.ros
def test_kill_9_of_a_ros_sweep_then_resume_starts_after_its_workers_and_nodes(tmp_path, monkeypatch):
    spec_file = tmp_path / "spec.yaml"
    spec_file.write_text(yaml.safe_dump(small_spec(transport="ros", max_steps=40)))
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "lq_ros.cli", "sweep", str(spec_file), "--workers", "1", "--out", str(out)]
    with open(tmp_path / "sweep.log", "wb") as log:
        proc = subprocess.Popen(cmd, cwd=REPO, stdout=log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 240
        holders: list[int] = []
        while time.monotonic() < deadline and len(holders) < 3:  # the worker and its nodes, mid-episode
            time.sleep(0.2)
            holders = lock_holders(out / PROCESSES_LOCK)
        assert len(holders) >= 3, (tmp_path / "sweep.log").read_text()[-3000:]
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    real_run_locked = orchestrator._run_locked
    seen: list[list[int]] = []

    def run_locked(*args):
        seen.append([pid for pid in holders if Path(f"/proc/{pid}").exists() and "Z" not in _state(pid)])
        return real_run_locked(*args)

    monkeypatch.setattr(orchestrator, "_run_locked", run_locked)
    summary = sw.run_sweep(sw.load_spec(spec_file), out, workers=1)
    assert seen == [[]], "the resume started beside the killed sweep's processes"
    assert len(sw.ResultStore(out).records()) == 4 and summary.ran + summary.skipped == 4


def _state(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return "Z"
