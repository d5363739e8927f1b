"""Local worker processes: the default pool of a sweep."""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import queue
import signal
import time
from pathlib import Path

from lq_ros.core.run_config import RunConfig
from lq_ros.run.sweep.worker import EpisodeWorker
from lq_ros.transport.processes import (
    PROCESSES_LOCK,
    ShmTracker,
    die_with_parent,
    hold_for_children,
    hold_shared,
    sigterm_as_keyboard_interrupt,
    wait_process_group_gone,
)


def _local_worker_main(slot: int, transport: str, bags_dir: str, timeout_s, tasks, results) -> None:
    die_with_parent()  # a worker must not outlive the sweep (kill -9 of the sweep included)
    # Its own process group, which the ROS nodes it launches join: if this worker is killed, the sweep
    # waits for them (they stop on PR_SET_PDEATHSIG) before the episode's bag is kept and retried.
    os.setpgid(0, 0)
    # This worker and the nodes it launches hold the sweep folder's processes lock: a resume after a kill -9 of the
    # sweep waits for them (or ends them) before it touches the folder.
    hold_for_children(hold_shared(Path(bags_dir).parent / PROCESSES_LOCK))
    # The parent decides when workers stop (SIGTERM); a stray SIGINT is ignored. A no-op handler, not
    # SIG_IGN, since an ignored SIGINT would be inherited by the ROS nodes a worker launches.
    signal.signal(signal.SIGINT, lambda *_: None)
    # Stopped by the parent (SIGTERM): unwind like Ctrl-C, so a launcher stops its nodes cleanly.
    sigterm_as_keyboard_interrupt()
    worker = EpisodeWorker(transport, Path(bags_dir), timeout_s)
    parent = os.getppid()
    try:
        while True:
            try:
                item = tasks.get(timeout=1.0)
            except queue.Empty:
                # The sweep was killed (kill -9) after SIGTERM was handled, e.g. by an episode that
                # recorded the interrupt as its outcome: nobody will send work or stop us, so leave.
                if os.getppid() != parent:
                    return
                continue
            if item is None:
                return
            cfg_dict, log_path = item
            results.put((slot, worker.run(RunConfig(**cfg_dict), Path(log_path))))
    except KeyboardInterrupt:  # stopped by the sweep (SIGTERM, or its Ctrl-C): the sweep says so, in one line
        return
    finally:
        worker.close()
        results.cancel_join_thread()  # don't block exit on results a dead sweep will never read


class LocalPool:
    """N worker processes (spawned: no inherited simulator/ROS state), each with its own job queue."""

    def __init__(self, n: int, transport: str, bags_dir: Path, timeout_s: float | None) -> None:
        self._ctx = mp.get_context("spawn")
        self._args = (transport, str(bags_dir), timeout_s)
        self._results = self._ctx.Queue()
        self._procs: list = [None] * n
        self._tasks: list = [None] * n
        for slot in range(n):
            self._start(slot)

    @property
    def size(self) -> int:
        return len(self._procs)

    def _start(self, slot: int) -> None:
        self._tasks[slot] = self._ctx.Queue()
        p = self._ctx.Process(
            target=_local_worker_main, args=(slot, *self._args, self._tasks[slot], self._results), daemon=True
        )
        p.start()
        self._procs[slot] = p

    def submit(self, slot: int, cfg: RunConfig, log_path: Path) -> None:
        self._tasks[slot].put((cfg.to_dict(), str(log_path)))

    def wait(self, busy: set[int], timeout_s: float) -> list[tuple[int, dict]]:
        """Finished results, plus a synthesized error for each busy worker that died."""
        out = []
        with contextlib.suppress(queue.Empty):
            out.append(self._results.get(timeout=timeout_s))
            while True:
                out.append(self._results.get_nowait())
        done = {slot for slot, _ in out}
        for slot in sorted(busy - done):
            p = self._procs[slot]
            if not p.is_alive():
                code = p.exitcode
                found_dead = time.time()
                wait_process_group_gone(p.pid)  # its nodes are still closing the episode's bag
                # Its launcher died with it, and so did the record of its nodes' Fast DDS files: a node that died
                # before removing its segment leaves it. Every segment of this user's made before the worker was
                # found dead and unlocked now is such an orphan (a live participant locks its own as it makes it).
                ShmTracker.stale_segments(min_age_s=time.time() - found_dead).cleanup(ports=False)
                out.append((slot, {"status": "error", "reason": f"worker process died (exit code {code})",
                                   "row": None, "bag": None, "wall_s": None}))  # fmt: skip
                self._start(slot)
        return out

    def close(self) -> None:
        for slot, p in enumerate(self._procs):
            if p.is_alive():
                with contextlib.suppress(Exception):
                    self._tasks[slot].put(None)
        deadline = time.monotonic() + 15
        for p in self._procs:
            p.join(timeout=max(0.1, deadline - time.monotonic()))
        self.terminate()

    def terminate(self) -> None:
        """Stop workers now (SIGTERM: a ros-transport worker's launcher stops its nodes)."""
        for p in self._procs:
            if p.is_alive():
                p.terminate()
        for p in self._procs:
            p.join(timeout=20)
            if p.is_alive():
                p.kill()
                p.join(timeout=5)
