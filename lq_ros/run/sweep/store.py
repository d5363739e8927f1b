"""The durable store of a sweep folder: one atomically written record per finished episode.

An episode counts as finished only when ``results/<key>.json`` is a regular file that parses, names its key, passes
lq_ros/run/sweep/record_check.py field by field and its bag exists; anything else (a half-written file, a bag without
a record, a FIFO or a link where the record should be) is run again, and a refused file is named in ``refused``.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import shutil
from pathlib import Path

from lq_ros.core.bounded_file import FileRefused, read_results_json
from lq_ros.core.run_config import RunConfig
from lq_ros.core.safe_write import WriteRefused, output_folder, write_text
from lq_ros.recording.episode_folder import episode_folders
from lq_ros.run.sweep.record_check import attempt_problem, read_record
from lq_ros.transport.processes import open_lock_file

RECORD_FORMAT = 1
#: The lock file in a sweep folder: a running sweep holds an exclusive flock on it (its pid inside).
LOCK_FILE = ".lock"


#: Sweep folders (real paths) whose lock this process holds: taking it again in the same process is a no-op.
_HELD: set[str] = set()


class StoreError(RuntimeError):
    """A sweep folder that cannot be used; the message (one line) names the folder."""


class StoreLocked(StoreError):
    """Another sweep is running on the folder."""


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write_text(path: Path, text: str) -> None:
    """Write-then-rename with fsync: after a crash the file is either the old one or the whole new one; never
    written through a link (lq_ros/core/safe_write.py)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text(path, text)


def fsync_tree(path: Path) -> None:
    """Flush a finished bag folder to disk before a record points at it (survives a reboot)."""
    for p in sorted(Path(path).rglob("*")):
        if p.is_file():
            with open(p, "rb") as f:
                os.fsync(f.fileno())
    for d in [path, *(p for p in Path(path).rglob("*") if p.is_dir())]:
        _fsync_dir(d)


class ResultStore:
    """Finished episodes of one sweep folder, keyed by RunConfig.key()."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        self.results = self.root / "results"
        self.bags = self.root / "bags"
        self.attempts = self.root / "attempts"
        self.logs = self.root / "logs"
        #: Files of the folder that were not used, each with the one-line reason (FileRefused's text).
        self.refused: dict[str, str] = {}

    @contextlib.contextmanager
    def lock(self):
        """Hold the folder for one sweep: an exclusive, non-blocking flock on ``LOCK_FILE``, released when the
        block ends or the process dies (the kernel drops it; no stale lock after a kill -9). StoreLocked while
        another sweep holds it."""
        try:
            output_folder(self.root, "sweep folder")  # made if missing; not a file, a dangling link, another user's
        except WriteRefused as exc:
            raise StoreError(str(exc)) from None
        held = os.path.realpath(self.root)
        if held in _HELD:  # this process holds it already (lq eval writes its spec under the lock, then runs)
            yield self
            return
        try:
            fd = open_lock_file(self.root / LOCK_FILE, 0o644)  # never through a link, never truncated
            if os.fstat(fd).st_nlink != 1:  # its pid is written into it: never into a file that has another name
                os.close(fd)
                raise OSError(errno.EPERM, "a file with another name (a hard link)")
        except OSError as exc:
            why = "a symbolic link, not followed" if exc.errno == errno.ELOOP else exc.strerror
            raise StoreError(f"{self.root}: cannot use this sweep folder's {LOCK_FILE} ({why})") from None
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.pread(fd, 32, 0).decode(errors="replace").split("\n")[0].strip()
                by = f" (pid {holder})" if holder.isascii() and holder.isdigit() else ""
                raise StoreLocked(
                    f"{self.root}: another lq sweep is running on this folder{by}; wait for it to finish or give "
                    "another --out"
                ) from None
            os.pwrite(fd, f"{os.getpid():<20}\n".encode(), 0)  # fixed width: overwrites the last holder's pid
            _HELD.add(held)
            try:
                yield self
            finally:
                _HELD.discard(held)
        finally:
            os.close(fd)

    def create(self) -> None:
        for d in (self.results, self.bags, self.attempts, self.logs):
            d.mkdir(parents=True, exist_ok=True)

    def record_path(self, key: str) -> Path:
        return self.results / f"{key}.json"

    def load(self, key: str) -> dict | None:
        """The finished record of ``key``, or None when missing, refused (named in ``refused``: not a regular file,
        too large, not JSON, a field that is wrong) or pointing at a lost bag."""
        path = self.record_path(key)
        try:
            record = read_record(path)
        except FileRefused as exc:
            if os.path.lexists(path):  # (a missing record is an episode not run yet)
                self.refused[str(path.relative_to(self.root))] = str(exc)
            return None
        bag = record.get("bag")
        if bag and not (self.root / bag / "metadata.yaml").exists():
            self.refused[str(path.relative_to(self.root))] = f"results file {path}: its bag {bag} has no metadata.yaml"
            return None
        return record

    def records(self) -> list[dict]:
        """Every valid finished record, in file-name order."""
        out = []
        for path in sorted(self.results.glob("*.json")):
            record = self.load(path.stem)
            if record is not None:
                out.append(record)
        return out

    def write(self, record: dict) -> None:
        atomic_write_text(self.record_path(record["key"]), json.dumps(record, sort_keys=True, default=str))

    def failed_attempts(self, key: str) -> list[dict]:
        """Crashed earlier attempts of an unfinished episode (survive a restart of the sweep)."""
        out = []
        for path in sorted(self.attempts.glob(f"{key}.a*.json")):
            try:
                attempt = read_results_json(path, "attempt record")
            except FileRefused as exc:
                self.refused[str(path.relative_to(self.root))] = str(exc)
                continue
            problem = attempt_problem(len(out), attempt)
            if problem is not None:
                self.refused[str(path.relative_to(self.root))] = f"attempt record {path}: {problem}"
                continue
            out.append(attempt)
        return out

    def keep_failed_attempt(self, key: str, attempt: dict, bag: Path | None) -> dict:
        """Move a crashed attempt's bag aside (its retry writes a fresh one) and persist its record."""
        n = attempt["attempt"]
        if bag is not None:
            for src in episode_folders(bag):
                if src.exists():
                    dest = self.attempts / f"{src.name}.a{n}"
                    shutil.rmtree(dest, ignore_errors=True)
                    shutil.move(str(src), dest)
                    if src == bag:
                        attempt["bag"] = str(dest.relative_to(self.root))
        atomic_write_text(self.attempts / f"{key}.a{n}.json", json.dumps(attempt, sort_keys=True, default=str))
        return attempt

    def clear_leftovers(self, cfg: RunConfig) -> None:
        """Remove what an interrupted, unrecorded run of ``cfg`` left (the bag writer needs a new folder)."""
        bag = self.bags / cfg.episode_name()
        for path in episode_folders(bag):
            shutil.rmtree(path, ignore_errors=True)

    def forget(self, key: str) -> None:
        """Drop a finished record (``--retry-errors``); its bag and attempts are cleared on rerun."""
        with contextlib.suppress(FileNotFoundError):
            self.record_path(key).unlink()
        for path in self.attempts.glob(f"{key}.a*.json"):
            path.unlink()

    def write_index(self) -> Path:
        """episodes.jsonl: one finished record per line (rebuilt from results/, atomically)."""
        lines = [json.dumps(r, sort_keys=True, default=str) for r in self.records()]
        path = self.root / "episodes.jsonl"
        atomic_write_text(path, "".join(line + "\n" for line in lines))
        return path
