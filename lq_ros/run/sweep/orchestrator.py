"""A sweep's orchestration: jobs scheduled onto a pool of workers, results made durable as they finish.

``run_sweep`` is the whole of it: prepare the store (skipping finished episodes), hand jobs to free
workers (keeping a worker on its task so its env is reused), turn each result into a record, retry a
crashed attempt once.
"""

from __future__ import annotations

import json
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import yaml

from lq_ros.core.redact import redact_config, redact_value
from lq_ros.core.run_config import RunConfig
from lq_ros.run.episode import TRANSPORTS
from lq_ros.run.sweep.identity import CODE_FIELD, changes, identities
from lq_ros.run.sweep.local import LocalPool
from lq_ros.run.sweep.ray_pool import RayPool, refuse_token_in_clear
from lq_ros.run.sweep.spec import SweepSpec
from lq_ros.run.sweep.store import (
    RECORD_FORMAT,
    ResultStore,
    StoreError,
    StoreLocked,
    atomic_write_text,
    fsync_tree,
)
from lq_ros.run.sweep.worker import default_workers, env_key
from lq_ros.transport.processes import PROCESSES_LOCK, end_orphans

BACKENDS = ("local", "ray")
#: A crashed episode is run at most this many times in total.
MAX_ATTEMPTS = 2
#: How long a resume waits for the workers and nodes of a killed sweep to end on their own, s (then it ends them).
ORPHAN_WAIT_S = 60.0


@dataclass
class Job:
    cfg: RunConfig
    attempt: int = 1
    previous: list[dict] = field(default_factory=list)  # records of crashed earlier attempts
    code: dict | None = None  # the identity of the code it runs (lq_ros.run.sweep.identity)

    @property
    def key(self) -> str:
        return self.cfg.key()


class Scheduler:
    """Pending jobs grouped by env key; a free worker gets one of its current group first (env reuse),
    else one of the group the fewest workers are on (the rest of the largest group breaks ties)."""

    def __init__(self, jobs: list[Job]) -> None:
        self.groups: dict[tuple, deque[Job]] = {}
        for job in jobs:
            self.groups.setdefault(env_key(job.cfg), deque()).append(job)

    def __len__(self) -> int:
        return sum(len(q) for q in self.groups.values())

    def retry(self, job: Job) -> None:
        self.groups.setdefault(env_key(job.cfg), deque()).appendleft(job)

    def pick(self, current: tuple | None, busy: Counter) -> Job | None:
        live = {k: q for k, q in self.groups.items() if q}
        if not live:
            return None
        key = current if current in live else min(live, key=lambda k: (busy[k], -len(live[k])))
        return live[key].popleft()


@dataclass
class SweepSummary:
    total: int
    skipped: int
    ran: int = 0
    counts: Counter = field(default_factory=Counter)  # final status -> episodes finished in this run
    retried: int = 0
    wall_s: float = 0.0
    out_dir: Path | None = None
    #: Results files of the folder that were not used (name -> why, one line): their episodes run again.
    refused: dict[str, str] = field(default_factory=dict)


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="seconds")


def prepare(
    spec: SweepSpec, out_dir: Path, *, retry_errors: bool = False, overwrite: bool = False
) -> tuple[ResultStore, list[Job], int]:
    """Create the store, write the spec and manifest; returns the jobs still to run and how many are done.

    ``overwrite``: every earlier result of the folder is removed first (all episodes run again). Without it, a
    finished episode made by other code than what runs now (lq_ros.run.sweep.identity) is a StoreError naming
    what changed: a folder never holds results of two versions of a policy.
    """
    store = ResultStore(out_dir)
    if overwrite:
        _remove_results(store)
    store.create()
    codes = identities(spec.configs)
    _refuse_other_code(store, spec, codes, retry_errors)
    atomic_write_text(store.root / "sweep.yaml", yaml.safe_dump(redact_value(spec.raw), sort_keys=False))
    manifest = {"name": spec.name, "episodes": {c.key(): redact_config(c.to_dict()) for c in spec.configs}}
    atomic_write_text(store.root / "manifest.json", json.dumps(manifest, sort_keys=True, indent=1))
    jobs, done = [], 0
    for cfg in spec.configs:
        record = store.load(cfg.key())
        if record is not None and retry_errors and record["status"] == "error":
            store.forget(cfg.key())
            record = None
        if record is not None:
            done += 1
            continue
        previous = store.failed_attempts(cfg.key())
        jobs.append(Job(cfg, attempt=len(previous) + 1, previous=previous, code=codes[cfg.key()]))
    return store, jobs, done


def _refuse_other_code(store: ResultStore, spec: SweepSpec, codes: dict[str, dict], retry_errors: bool) -> None:
    """StoreError (one line naming what changed) if a finished episode the spec would skip was made by other code;
    before the folder is touched."""
    stale: dict[str, set] = {}
    finished = 0
    for cfg in spec.configs:
        record = store.load(cfg.key())
        if record is None or (retry_errors and record["status"] == "error"):
            continue
        finished += 1
        for change in changes(record.get(CODE_FIELD), codes[cfg.key()]):
            stale.setdefault(change, set()).add(cfg.key())
    links = sorted(name for name in store.refused if (store.root / name).is_symlink())
    if links:  # (its record could not be written either: a link is never written through)
        raise StoreError(
            f"{store.root / links[0]}: a link where a results file is written; not followed (remove it, or give "
            "another --out)"
        )
    if stale:
        n = len(set().union(*stale.values()))
        raise StoreError(
            f"{store.root}: {n} of its {finished} finished episodes were made by other code "
            f"({'; '.join(list(stale)[:3])}); rerun them with --overwrite (all its results are replaced), "
            "or give another --out"
        )


def _remove_results(store: ResultStore) -> None:
    """Everything earlier sweeps wrote into the folder's results, bags, attempts and logs (``--overwrite``)."""
    import shutil

    for folder in (store.results, store.bags, store.attempts, store.logs):
        shutil.rmtree(folder, ignore_errors=True)
    (store.root / "episodes.jsonl").unlink(missing_ok=True)


def run_sweep(
    spec: SweepSpec,
    out_dir: Path,
    *,
    workers: int | None = None,
    transport: str | None = None,
    backend: str = "local",
    address: str | None = None,
    retry_errors: bool = False,
    overwrite: bool = False,
    on_progress: Callable[[SweepSummary, dict | None], None] | None = None,
) -> SweepSummary:
    """Run every unfinished episode of ``spec`` into ``out_dir``; finished ones are skipped.

    ``on_progress(summary, record)`` is called once at the start (record None) and after every
    finished episode. A crashed attempt is kept under attempts/ and run once more; a second crash
    is the episode's final result (status error).
    """
    transport = transport or spec.transport or "ros"
    if transport not in TRANSPORTS:
        raise ValueError(f"transport must be one of {TRANSPORTS}, got {transport!r}")
    if transport != "ros" and any(cfg.clock == "realtime" for cfg in spec.configs):
        raise ValueError(f"the spec's clock is realtime, which runs through ROS only: transport ros, not {transport}")
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if workers is not None and workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if backend == "ray" and address:
        refuse_token_in_clear(address)  # before the folder is touched: a token never travels in clear
    # One sweep per folder at a time, for the sweep's whole life: a second one would schedule the same
    # episodes and clear the first one's bags in flight as leftovers (StoreLocked names the folder).
    with ResultStore(out_dir).lock():
        # A sweep killed with -9 frees the folder's lock at once, while its workers and their nodes still close their
        # episodes: wait for them (they end on their own, PR_SET_PDEATHSIG), or end them, before anything is touched.
        left = end_orphans(Path(out_dir) / PROCESSES_LOCK, ORPHAN_WAIT_S)
        if left:
            raise StoreLocked(f"{out_dir}: processes of an earlier sweep on this folder still run (pids {left})")
        return _run_locked(spec, out_dir, workers, transport, backend, address, retry_errors, overwrite, on_progress)


def _run_locked(
    spec: SweepSpec,
    out_dir: Path,
    workers: int | None,
    transport: str,
    backend: str,
    address: str | None,
    retry_errors: bool,
    overwrite: bool,
    on_progress: Callable[[SweepSummary, dict | None], None] | None,
) -> SweepSummary:
    store, jobs, done = prepare(spec, out_dir, retry_errors=retry_errors, overwrite=overwrite)
    summary = SweepSummary(total=len(spec.configs), skipped=done, out_dir=store.root, refused=dict(store.refused))
    if on_progress:
        on_progress(summary, None)
    started = time.monotonic()
    if not jobs:
        store.write_index()
        return summary
    if backend == "ray":
        pool = RayPool(workers, transport, store.bags, spec.timeout_s, address)
    else:
        pool = LocalPool(min(workers or default_workers(), len(jobs)), transport, store.bags, spec.timeout_s)
    sched = Scheduler(jobs)
    running: dict[int, Job] = {}
    current: dict[int, tuple] = {}
    try:
        while len(sched) or running:
            busy = Counter(env_key(j.cfg) for j in running.values())
            for slot in range(pool.size):
                if slot in running:
                    continue
                job = sched.pick(current.get(slot), busy)
                if job is None:
                    break
                store.clear_leftovers(job.cfg)
                running[slot], current[slot] = job, env_key(job.cfg)
                busy[current[slot]] += 1
                pool.submit(slot, job.cfg, store.logs / f"{job.key}.a{job.attempt}.log")
            for slot, result in pool.wait(set(running), timeout_s=0.5):
                job = running.pop(slot)
                record = _finish(store, job, result, transport, spec.name)
                if record is None:  # crashed first attempt: run it again
                    summary.retried += 1
                    previous = store.failed_attempts(job.key)
                    sched.retry(Job(job.cfg, attempt=job.attempt + 1, previous=previous, code=job.code))
                    continue
                summary.ran += 1
                summary.counts[record["status"]] += 1
                summary.wall_s = time.monotonic() - started
                if on_progress:
                    on_progress(summary, record)
        pool.close()
    except BaseException:
        pool.terminate()
        raise
    finally:
        summary.wall_s = time.monotonic() - started
        store.write_index()
    return summary


def _finish(store: ResultStore, job: Job, result: dict, transport: str, sweep_name: str) -> dict | None:
    """Turn a worker result into a durable record; None when the attempt crashed and may be retried."""
    bag = Path(result["bag"]) if result.get("bag") else None
    attempt = {
        "attempt": job.attempt,
        "status": result["status"],
        "reason": result.get("reason") or "",
        "log": str((store.logs / f"{job.key}.a{job.attempt}.log").relative_to(store.root)),
        "wall_s": result.get("wall_s"),
        "finished_at": _now(),
    }
    if result.get("node"):  # a Ray worker: the node that ran it
        attempt["node"] = result["node"]
    if result["status"] == "error" and job.attempt < MAX_ATTEMPTS:
        store.keep_failed_attempt(job.key, attempt, bag if bag is not None else store.bags / job.cfg.episode_name())
        return None
    if bag is not None:
        attempt["bag"] = str(bag.relative_to(store.root))
        fsync_tree(bag)
    row = result.get("row") or {
        "episode": job.cfg.episode_name(), "status": "error", "success": None, "error_reason": attempt["reason"],
        **{k: getattr(job.cfg, k) for k in ("policy", "mode", "latency_s", "suite", "task", "init", "seed")},
    }  # fmt: skip
    row["transport"] = row.get("transport") or transport
    record = {
        "format": RECORD_FORMAT,
        "key": job.key,
        "sweep": sweep_name,
        "episode": job.cfg.episode_name(),
        "config": redact_config(job.cfg.to_dict()),
        "transport": transport,
        "status": result["status"],
        "bag": attempt.get("bag"),
        "row": row,
        "attempts": [*job.previous, attempt],
        "finished_at": attempt["finished_at"],
        CODE_FIELD: job.code,
        "warnings": result.get("warnings") or [],  # console lines (lq_ros.run.episode_notes), e.g. rejected chunks
    }
    store.write(record)
    return record
