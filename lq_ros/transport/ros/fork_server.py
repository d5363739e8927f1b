"""Start the node programs as forks of one process that has imported them already.

Every node stays a process of its own: a node that crashes or is killed takes nothing else with it and is restarted
alone. But a node started from scratch spends about 0.3 s of CPU on its interpreter and imports (rclpy, NumPy, its
message types, lq_ros) before it can do anything, and a stack starts five of them at once on the same cores, with
the sim's start-up on the first episode's critical path. The fork server imports the node programs once; each node
is then a fork of it, ready in milliseconds (as multiprocessing's forkserver and Android's zygote do). After the
fork a node runs its program's ``main`` under its own name (``/proc/PID/cmdline`` reads as ``python -m <module>
<args>``, what the stack would have executed), its own standard streams and its own PR_SET_PDEATHSIG.

What makes the fork safe: the server never initialises rclpy (no DDS participant, no executor, no ROS thread
exists before the fork). Importing rclpy and NumPy does start threads: OpenBLAS's (which stops and restarts around
a fork through pthread_atfork) and LTTng-UST's listeners (ros_tracetools), whose own before- and after-fork hooks the
server calls around each fork, as LTTng's liblttng-ust-fork.so does for programs linked to it. The server checks
that these are the only threads before it offers to fork; otherwise it declines and the stack executes each node
afresh, as it does under ``LQ_NODE_FORKS=off``.

Protocol (a SOCK_SEQPACKET socket pair, one JSON object per packet): the launcher sends ``{"preload": [module,
...]}``; the server imports them and answers ``{"ready": pid}`` (or ``{"declined": why}``). Then, per node, the
launcher sends ``{"module": ..., "args": [...]}`` with the child's stdin, stdout and stderr as descriptors; the
server answers ``{"spawned": pid}`` with a pidfd of the child, and later ``{"exited": pid, "code": returncode}``
(negative: killed by that signal), in that order for each child.

    python -m lq_ros.transport.ros.fork_server SOCKET_FD   (started by :class:`ForkServer`)

The node modules are not on its command line: tools that find a node by its module in ``/proc/PID/cmdline`` find
the node, not the server.

A server that stops answering never stalls the stack for long: a fork is answered within :data:`SPAWN_REPLY_S`, and a
server stopped (SIGSTOP, state T) for :data:`STOPPED_GIVE_UP_S` is given up at once, at start or at a spawn; either is
a ForkServerError, and the stack executes its nodes afresh. The launcher is its nodes' subreaper
(PR_SET_CHILD_SUBREAPER): when the server dies, its forks become the launcher's children, and the launcher reaps them
(with their real exit status), so none is left a zombie where PID 1 does not reap.
"""

from __future__ import annotations

import contextlib
import ctypes
import gc
import importlib
import json
import os
import select
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from lq_ros.transport.processes import die_with_parent

#: Bytes of a packet; a spawn request is a module name and a few arguments.
PACKET_BYTES = 65536
#: The exit code reported for a child whose status was lost (the fork server died before it could report it).
EXIT_STATUS_LOST = 255
#: The LTTng-UST library ros_tracetools loads (a wheel-mangled name), found by this prefix in /proc/self/maps.
LTTNG_UST_PREFIX = "liblttng-ust-"
#: Characters of room the server's command line keeps for its children's (a fork names itself within it, so that
#: /proc/PID/environ stays readable): blanks after its own arguments, which ``ps`` shows as nothing.
TITLE_ROOM = 400
#: The threads LTTng-UST starts when it loads (its listeners for a global and a per-user session daemon).
LTTNG_UST_LISTENERS = 2
#: How long a spawn waits for the server's answer, s (a fork takes milliseconds; a busy machine, well under this).
SPAWN_REPLY_S = 10.0
#: How long the server may be seen stopped (SIGSTOP, a debugger) before it is given up, s.
STOPPED_GIVE_UP_S = 1.0
#: How often a wait for the server checks whether it is stopped, s.
STOPPED_POLL_S = 0.2
#: How long closing waits for the forks of a dead server to end (their parent-death signal), s, to reap them.
FORKS_END_WAIT_S = 5.0
_PR_SET_CHILD_SUBREAPER = 36


class ForkServerError(RuntimeError):
    """The fork server did not start, declined to fork, or died: the stack executes its nodes afresh instead."""


# -- the server --------------------------------------------------------------------------------------------------


def _lttng_ust() -> ctypes.CDLL | None:
    """LTTng-UST, if this process has loaded it (with rclpy), for its fork hooks."""
    with open("/proc/self/maps") as maps:
        for line in maps:
            path = line.split()[-1]
            if Path(path).name.startswith(LTTNG_UST_PREFIX) and "tracepoint" not in Path(path).name:
                lib = ctypes.CDLL(path)
                if hasattr(lib, "ust_before_fork"):
                    return lib
    return None


def _threads() -> int:
    return len(os.listdir("/proc/self/task"))


def _fork(lttng: ctypes.CDLL | None) -> int:
    """os.fork with LTTng-UST's hooks around it: its listener threads hold no lock across the fork, and the child
    starts its own (liblttng-ust-fork.so's wrapper, called by hand)."""
    if lttng is None:
        return os.fork()
    saved = ctypes.create_string_buffer(128)  # a sigset_t: LTTng blocks every signal across the fork
    lttng.ust_before_fork(saved)
    pid = os.fork()
    (lttng.ust_after_fork_child if pid == 0 else lttng.ust_after_fork_parent)(saved)
    return pid


@dataclass
class _Request:
    module: str
    args: list[str]
    fds: list[int]


def _serve(sock: socket.socket, lttng: ctypes.CDLL | None) -> _Request | None:
    """Fork a child per request and report each child's exit; returns in a child (its request) or at EOF (None)."""
    wake_r, wake_w = os.pipe2(os.O_NONBLOCK | os.O_CLOEXEC)
    signal.signal(signal.SIGCHLD, lambda *_: None)  # a handler, so the wakeup fd hears every exit
    signal.set_wakeup_fd(wake_w)
    while True:
        readable, _, _ = select.select([sock, wake_r], [], [])
        if wake_r in readable:
            with contextlib.suppress(BlockingIOError):
                os.read(wake_r, 4096)
        while True:  # reap (a child's exit is reported after its spawn: it is reaped on a later pass)
            try:
                pid, status = os.waitpid(-1, os.WNOHANG)
            except ChildProcessError:
                break
            if pid == 0:
                break
            sock.send(json.dumps({"exited": pid, "code": os.waitstatus_to_exitcode(status)}).encode())
        if sock not in readable:
            continue
        message, fds, _, _ = socket.recv_fds(sock, PACKET_BYTES, 3)
        if not message:
            return None  # the launcher closed its end
        request = json.loads(message)
        pid = _fork(lttng)
        if pid == 0:
            signal.set_wakeup_fd(-1)
            signal.signal(signal.SIGCHLD, signal.SIG_DFL)
            for fd in (wake_r, wake_w):
                os.close(fd)
            sock.close()
            return _Request(request["module"], request["args"], fds)
        for fd in fds:
            os.close(fd)
        pidfd = os.pidfd_open(pid)
        socket.send_fds(sock, [json.dumps({"spawned": pid}).encode()], [pidfd])
        os.close(pidfd)


def _become(request: _Request, server_pid: int, set_title: Callable[[str], None]) -> None:
    """In a fresh fork: the node's own streams, name, argv, signals and parent-death signal."""
    die_with_parent()
    if os.getppid() != server_pid:  # the server died between the fork and the line above
        os._exit(EXIT_STATUS_LOST)
    for target, fd in enumerate(request.fds):
        os.dup2(fd, target)
        os.close(fd)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    module = importlib.import_module(request.module)  # (preloaded: the imported module itself)
    sys.argv = [module.__file__ or request.module, *request.args]
    # (SPT_NOENV: the title takes the room of the server's command line only, and /proc/PID/environ stays readable)
    os.environ["SPT_NOENV"] = "1"
    set_title(" ".join([sys.executable, "-m", request.module, *request.args]))
    del os.environ["SPT_NOENV"]


def main() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a terminal's Ctrl-C is the launcher's and the nodes' to handle
    sock = socket.socket(fileno=int(sys.argv[1]))
    preload = json.loads(sock.recv(PACKET_BYTES) or b'{"preload": []}')["preload"]
    started_with = _threads()  # 1, unless something the interpreter ran at start-up (a sitecustomize) started one
    import numpy  # noqa: F401, PLC0415 - first: the threads it adds are OpenBLAS's (fork-safe: pthread_atfork)
    from setproctitle import setproctitle  # noqa: PLC0415 - each fork names itself

    known_threads = 1 + _threads() - started_with
    for module in preload:
        importlib.import_module(module)
    lttng = _lttng_ust()
    known_threads += LTTNG_UST_LISTENERS if lttng is not None else 0
    if _threads() > known_threads:  # a thread the fork would leave behind, holding who knows what lock
        reason = f"{_threads()} threads after the imports, {known_threads} known to be safe to fork"
        sock.send(json.dumps({"declined": reason}).encode())
        return
    gc.collect()
    gc.freeze()  # the imported objects stay put in every child: the collector never writes to their pages
    server_pid = os.getpid()
    sock.send(json.dumps({"ready": server_pid}).encode())
    request = _serve(sock, lttng)
    if request is None:  # the launcher is done: no ROS entity or file of ours to clean up, so no teardown to wait for
        sys.stdout.flush()
        os._exit(0)
    _become(request, server_pid, setproctitle)
    sys.modules[request.module].main()


# -- the launcher's side -----------------------------------------------------------------------------------------


def become_subreaper() -> None:
    """Adopt this process's orphaned descendants (PR_SET_CHILD_SUBREAPER): a dead fork server's children become ours
    to reap. A no-op where prctl does not exist (not Linux)."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(_PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0)


def is_stopped(pid: int) -> bool:
    """Whether process ``pid`` is stopped (state T: SIGSTOP; t: traced) per /proc; False if it is gone."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat[stat.rfind(")") + 2 : stat.rfind(")") + 3] in ("T", "t")


class ForkedProcess:
    """A node forked by a :class:`ForkServer`, with the part of ``subprocess.Popen``'s interface the stack uses.

    Its exit status comes from the server (its parent); signals go through a pidfd, so they never reach another
    process that later took the same PID.
    """

    def __init__(self, server: ForkServer, pid: int, pidfd: int, args: list[str], stdin=None, stdout=None) -> None:
        self.server, self.pid, self.pidfd, self.args = server, pid, pidfd, args
        self.stdin, self.stdout = stdin, stdout
        self.returncode: int | None = None

    def _exited(self, code: int) -> None:
        self.returncode = code
        with contextlib.suppress(OSError):
            os.close(self.pidfd)

    def _gone(self) -> bool:
        """Whether the process has ended (its pidfd is readable), for when its parent can no longer say how."""
        return bool(select.select([self.pidfd], [], [], 0)[0])

    def _reap(self) -> int:
        """The exit code of an ended child whose server died: reaped here (the launcher is its subreaper, so it
        is no zombie); EXIT_STATUS_LOST when another process reaped it."""
        try:
            info = os.waitid(os.P_PIDFD, self.pidfd, os.WEXITED | os.WNOHANG)
        except OSError:  # (ChildProcessError: not ours, e.g. the server reaped it before it died)
            return EXIT_STATUS_LOST
        if info is None:
            return EXIT_STATUS_LOST
        return info.si_status if info.si_code == os.CLD_EXITED else -info.si_status

    def poll(self) -> int | None:
        if self.returncode is None:
            self.server.pump(0.0)
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.poll() is None:
            remaining = None if deadline is None else deadline - time.monotonic()
            if remaining is not None and remaining <= 0:
                raise subprocess.TimeoutExpired(self.args, timeout)
            self.server.pump(0.05 if remaining is None else min(remaining, 0.05))
        return self.returncode

    def send_signal(self, sig: int) -> None:
        if self.returncode is None:
            with contextlib.suppress(ProcessLookupError, OSError):
                signal.pidfd_send_signal(self.pidfd, sig)

    def terminate(self) -> None:
        self.send_signal(signal.SIGTERM)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)


class ForkServer:
    """A process that has imported ``modules`` and forks a node per :meth:`spawn`.

    ``env`` and ``pass_fds`` are every child's (the server holds the run's lock descriptors, and each child inherits
    them); the server's own output goes to ``log``. ForkServerError if it does not start within ``timeout_s`` or
    declines to fork.
    """

    def __init__(self, modules: list[str], env: dict[str, str], pass_fds: tuple[int, ...], log, timeout_s=60.0):
        become_subreaper()  # before any fork: the server's children are ours to reap if it dies
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        self.sock = ours
        self.children: dict[int, ForkedProcess] = {}
        self.dead = False
        try:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", __name__, str(theirs.fileno()), " " * TITLE_ROOM],
                env=env,
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
                preexec_fn=die_with_parent,
                pass_fds=(*pass_fds, theirs.fileno()),
            )
        finally:
            theirs.close()
        self.sock.send(json.dumps({"preload": modules}).encode())
        ready = self._receive(timeout_s, watch=True)
        if ready is None or "ready" not in ready[0]:
            why = "it exited" if ready is None else ready[0].get("declined", ready[0])
            if ready is None and not self.dead:
                why = "it is stopped" if is_stopped(self.proc.pid) else f"no answer within {timeout_s:g} s"
            self.close()
            raise ForkServerError(f"the node fork server did not start: {why}")

    def _readable(self, timeout_s: float | None, watch: bool) -> bool:
        """Whether a packet arrives within ``timeout_s``; ``watch``: give up early (False) once the server has been
        seen stopped for STOPPED_GIVE_UP_S (it would not answer before someone continues it)."""
        if not watch:
            return bool(select.select([self.sock], [], [], timeout_s)[0])
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        stopped_since = None
        while True:
            now = time.monotonic()
            wait = STOPPED_POLL_S if deadline is None else max(0.0, min(STOPPED_POLL_S, deadline - now))
            if select.select([self.sock], [], [], wait)[0]:
                return True
            now = time.monotonic()
            if deadline is not None and now >= deadline:
                return False
            if not is_stopped(self.proc.pid):
                stopped_since = None
            elif stopped_since is None:
                stopped_since = now
            elif now - stopped_since >= STOPPED_GIVE_UP_S:
                return False

    def _receive(self, timeout_s: float | None, watch: bool = False) -> tuple[dict, list[int]] | None:
        """The next packet (and its descriptors), or None on EOF or when ``timeout_s`` passes first (``watch``: or
        once the server is seen stopped, see _readable)."""
        if not self._readable(timeout_s, watch):
            return None
        try:
            message, fds, _, _ = socket.recv_fds(self.sock, PACKET_BYTES, 1)
        except OSError:
            message, fds = b"", []
        if not message:
            self._died()
            return None
        return json.loads(message), fds

    def _died(self) -> None:
        """The server is gone: its children end (their parent-death signal) with no one left to report how."""
        self.dead = True
        for child in self.children.values():
            if child.returncode is None and child._gone():
                child._exited(child._reap())

    def pump(self, timeout_s: float) -> None:
        """Take in the server's exit reports: wait up to ``timeout_s`` for the first, then take what is there."""
        if self.dead:
            self._died()
            if timeout_s > 0:
                time.sleep(timeout_s)
            return
        while True:
            packet = self._receive(timeout_s)
            if packet is None:
                return
            self._take_report(*packet)
            timeout_s = 0.0

    def _take_report(self, message: dict, fds: list[int]) -> None:
        """An exit report: the child it names has ended with its code (descriptors, which it has none of, closed)."""
        for fd in fds:
            os.close(fd)
        if "exited" in message and message["exited"] in self.children:
            self.children.pop(message["exited"])._exited(message["code"])

    def spawn(self, module: str, args: list[str], stdin, stdout, stderr) -> ForkedProcess:
        """Fork ``python -m module args``; the streams as Popen takes them: a file or descriptor, subprocess.DEVNULL,
        subprocess.PIPE (stdin, stdout), subprocess.STDOUT (stderr)."""
        if self.dead:
            raise ForkServerError("the node fork server has exited")
        ends, theirs = {}, []
        for name, stream in (("stdin", stdin), ("stdout", stdout), ("stderr", stderr)):
            if stream == subprocess.PIPE:
                r, w = os.pipe2(os.O_CLOEXEC)
                ends[name] = open(w, "wb") if name == "stdin" else open(r, "rb")  # noqa: SIM115 - the caller's
                theirs.append(r if name == "stdin" else w)
            elif stream == subprocess.STDOUT:
                theirs.append(os.dup(theirs[1]))
            elif stream == subprocess.DEVNULL:
                theirs.append(os.open(os.devnull, os.O_RDWR | os.O_CLOEXEC))
            else:
                theirs.append(os.dup(stream if isinstance(stream, int) else stream.fileno()))
        try:
            socket.send_fds(self.sock, [json.dumps({"module": module, "args": args}).encode()], theirs)
        except OSError as exc:
            self._died()
            raise ForkServerError(f"the node fork server has exited ({exc})") from exc
        finally:
            for fd in theirs:
                os.close(fd)
        while True:
            packet = self._receive(SPAWN_REPLY_S, watch=True)
            if packet is None:
                if self.dead:
                    raise ForkServerError("the node fork server has exited")
                why = "it is stopped" if is_stopped(self.proc.pid) else f"not within {SPAWN_REPLY_S:g} s"
                raise ForkServerError(f"the node fork server did not answer ({why})")
            message, fds = packet
            if "spawned" in message:
                child = ForkedProcess(self, message["spawned"], fds[0], [module, *args], **ends)
                self.children[child.pid] = child
                return child
            self._take_report(message, fds)

    def close(self) -> None:
        """End the server (its children, if any are left, get their parent-death signal, end, and are reaped)."""
        self.sock.close()
        self.dead = True
        if is_stopped(self.proc.pid):  # (a stopped server would not see its socket close)
            self.proc.kill()
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.proc.wait(timeout=5.0)
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        deadline = time.monotonic() + FORKS_END_WAIT_S
        while True:
            self._died()  # reaps the forks that have ended
            if all(c.returncode is not None for c in self.children.values()) or time.monotonic() > deadline:
                return
            time.sleep(0.02)


if __name__ == "__main__":
    main()
