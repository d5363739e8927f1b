"""The fork server: nodes forked from a process that imported them, with Popen's behaviour where the stack uses it."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from lq_ros.transport.ros.fork_server import EXIT_STATUS_LOST, ForkServer, ForkServerError

PROGRAM = """
import os, sys, time
IMPORTED_IN = os.getpid()

def main():
    print(f"argv={sys.argv[1:]} env={os.environ.get('TOY_VALUE')} imported_before_fork={IMPORTED_IN != os.getpid()}")
    print("to stderr", file=sys.stderr, flush=True)
    line = sys.stdin.readline().split()
    if line and line[0] == "sleep":
        time.sleep(60)
    sys.exit(int(line[0]) if line else 0)
"""


@pytest.fixture
def toy_env(tmp_path: Path) -> dict[str, str]:
    (tmp_path / "toy_program.py").write_text(textwrap.dedent(PROGRAM))
    (tmp_path / "threaded_program.py").write_text(
        "import threading, time\nthreading.Thread(target=time.sleep, args=(60,), daemon=True).start()\n"
    )
    return {**os.environ, "PYTHONPATH": str(tmp_path), "TOY_VALUE": "inherited"}


def cmdline(pid: int, expected: str) -> str:
    """The process's command line once it reads ``expected`` (a fork names itself first thing), or after 10 s."""
    deadline = time.monotonic() + 10.0
    while True:
        line = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode().strip()
        if line == expected or time.monotonic() > deadline:
            return line
        time.sleep(0.01)


def test_a_forked_program_runs_as_if_executed(toy_env: dict[str, str], tmp_path: Path) -> None:
    with open(tmp_path / "server.log", "wb") as log:
        server = ForkServer(["toy_program"], toy_env, (), log)
    try:
        child = server.spawn("toy_program", ["--ros-args", "x"], subprocess.PIPE, subprocess.PIPE, subprocess.STDOUT)
        expected = f"{sys.executable} -m toy_program --ros-args x"
        assert cmdline(child.pid, expected) == expected
        server_line = Path(f"/proc/{server.proc.pid}/cmdline").read_bytes()
        assert b"toy_program" not in server_line  # (a tool that finds a node by its module finds the node only)
        environ = Path(f"/proc/{child.pid}/environ").read_bytes().split(b"\0")  # (kept readable by the naming)
        assert b"TOY_VALUE=inherited" in environ
        assert child.poll() is None
        child.stdin.write(b"3\n")
        child.stdin.flush()
        out = child.stdout.read().decode()
        assert child.wait(timeout=10) == 3
        assert "argv=['--ros-args', 'x'] env=inherited imported_before_fork=True" in out
        assert "to stderr" in out
    finally:
        server.close()


def test_kill_and_signals_are_reported_like_popen(toy_env: dict[str, str], tmp_path: Path) -> None:
    with open(tmp_path / "server.log", "wb") as log:
        server = ForkServer(["toy_program"], toy_env, (), log)
    try:
        children = [
            server.spawn("toy_program", [], subprocess.PIPE, subprocess.DEVNULL, subprocess.DEVNULL) for _ in range(3)
        ]
        for child in children:
            child.stdin.write(b"sleep\n")
            child.stdin.flush()
        time.sleep(0.5)
        os.kill(children[0].pid, signal.SIGKILL)  # as the fault tests and a user's kill -9 do
        children[1].terminate()
        with pytest.raises(subprocess.TimeoutExpired):
            children[2].wait(timeout=0.2)
        assert children[0].wait(timeout=10) == -signal.SIGKILL
        assert children[1].wait(timeout=10) == -signal.SIGTERM
        assert children[2].poll() is None
        children[2].kill()
        assert children[2].wait(timeout=10) == -signal.SIGKILL
        children[2].kill()  # a signal to an ended child goes nowhere (its PID may be another process's by now)
    finally:
        server.close()


def test_a_dead_server_ends_its_children_and_is_reported(toy_env: dict[str, str], tmp_path: Path) -> None:
    with open(tmp_path / "server.log", "wb") as log:
        server = ForkServer(["toy_program"], toy_env, (), log)
    child = server.spawn("toy_program", [], subprocess.PIPE, subprocess.DEVNULL, subprocess.DEVNULL)
    child.stdin.write(b"sleep\n")
    child.stdin.flush()
    os.kill(server.proc.pid, signal.SIGKILL)
    assert child.wait(timeout=10) == EXIT_STATUS_LOST  # its parent-death signal ended it; nobody could say how
    with pytest.raises(ForkServerError, match="exited"):
        server.spawn("toy_program", [], subprocess.DEVNULL, subprocess.DEVNULL, subprocess.DEVNULL)
    server.close()


def test_a_thread_it_cannot_fork_safely_makes_it_decline(toy_env: dict[str, str], tmp_path: Path) -> None:
    with open(tmp_path / "server.log", "wb") as log, pytest.raises(ForkServerError, match="threads after the imports"):
        ForkServer(["threaded_program"], toy_env, (), log)
