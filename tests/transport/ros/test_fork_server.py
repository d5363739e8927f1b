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

from lq_ros.transport.ros.fork_server import SPAWN_REPLY_S, ForkServer, ForkServerError

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
    # Once it names itself it has its parent-death signal (a child whose server dies before that exits with
    # EXIT_STATUS_LOST, 255).
    expected = f"{sys.executable} -m toy_program"
    assert cmdline(child.pid, expected) == expected
    os.kill(server.proc.pid, signal.SIGKILL)
    # Its parent-death signal ended it; the launcher, its subreaper, reaped it and says how.
    assert child.wait(timeout=10) == -signal.SIGTERM
    with pytest.raises(ForkServerError, match="exited"):
        server.spawn("toy_program", [], subprocess.DEVNULL, subprocess.DEVNULL, subprocess.DEVNULL)
    server.close()


def test_a_thread_it_cannot_fork_safely_makes_it_decline(toy_env: dict[str, str], tmp_path: Path) -> None:
    with open(tmp_path / "server.log", "wb") as log, pytest.raises(ForkServerError, match="threads after the imports"):
        ForkServer(["threaded_program"], toy_env, (), log)


def test_a_stopped_server_is_given_up_within_seconds(toy_env: dict[str, str], tmp_path: Path) -> None:
    """SIGSTOP: the spawn fails (the stack then executes its nodes afresh) in seconds, not after a minute."""
    with open(tmp_path / "server.log", "wb") as log:
        server = ForkServer(["toy_program"], toy_env, (), log)
    os.kill(server.proc.pid, signal.SIGSTOP)
    started = time.monotonic()
    with pytest.raises(ForkServerError, match=r"did not answer \(it is stopped\)"):
        server.spawn("toy_program", [], subprocess.DEVNULL, subprocess.DEVNULL, subprocess.DEVNULL)
    server.close()  # (kills it at once: a stopped server would not see its socket close)
    assert time.monotonic() - started < SPAWN_REPLY_S
    assert server.proc.returncode == -signal.SIGKILL


def test_a_server_stopped_while_it_starts_is_given_up_within_seconds(toy_env, tmp_path: Path) -> None:
    (tmp_path / "stopping_program.py").write_text("import os, signal\nos.kill(os.getpid(), signal.SIGSTOP)\n")
    started = time.monotonic()
    with (
        open(tmp_path / "server.log", "wb") as log,
        pytest.raises(ForkServerError, match="did not start: it is stopped"),
    ):
        ForkServer(["stopping_program"], toy_env, (), log)
    assert time.monotonic() - started < 10.0


LAUNCHER = """
import os, signal, subprocess, sys, time
from pathlib import Path
from lq_ros.transport.ros.fork_server import ForkServer
with open(sys.argv[1], "wb") as log:
    server = ForkServer(["toy_program"], dict(os.environ), (), log)
child = server.spawn("toy_program", [], subprocess.PIPE, subprocess.DEVNULL, subprocess.DEVNULL)
child.stdin.write(b"sleep\\n")
child.stdin.flush()
deadline = time.monotonic() + 10  # (until it names itself: it has its parent-death signal then)
while b"toy_program" not in Path(f"/proc/{child.pid}/cmdline").read_bytes() and time.monotonic() < deadline:
    time.sleep(0.01)
os.kill(server.proc.pid, signal.SIGKILL)
code = child.wait(timeout=10)
stat = Path(f"/proc/{child.pid}/stat")
state = stat.read_text().rsplit(")", 1)[1].split()[0] if stat.exists() else "gone"
print(f"code={code} state={state}", flush=True)
server.close()
"""


def test_a_killed_servers_children_leave_no_zombie_where_init_does_not_reap(toy_env, tmp_path: Path) -> None:
    """Under an ancestor that adopts orphans and never reaps them (PID 1 of many containers), the nodes of a killed
    server are reaped by the launcher: none is left a zombie (state Z)."""
    (tmp_path / "launcher.py").write_text(LAUNCHER)
    init = (
        "import ctypes, subprocess, sys; ctypes.CDLL('libc.so.6').prctl(36, 1, 0, 0, 0); "
        "sys.exit(subprocess.call([sys.executable, *sys.argv[1:]]))"
    )
    env = {**toy_env, "PYTHONPATH": f"{toy_env['PYTHONPATH']}:{Path(__file__).resolve().parents[3]}"}
    run = subprocess.run([sys.executable, "-c", init, str(tmp_path / "launcher.py"), str(tmp_path / "server.log")],
                         env=env, capture_output=True, text=True, timeout=60)  # fmt: skip
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == f"code={-signal.SIGTERM} state=gone", run.stdout
