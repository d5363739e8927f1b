"""Latency sweeps: a YAML spec expanded to episodes, run by parallel workers, kept in a durable store.

Layout of a sweep folder (``OUT``)::

    sweep.yaml             the spec as given (provenance)
    manifest.json          every episode key the spec expands to, with its configuration
    results/<key>.json     one finished episode (final status, scored row, attempts); written atomically
    bags/<episode>/        the episode's rosbag2 bag (+ node logs for the ros transport)
    attempts/              a crashed first attempt (its bag, logs and record) before its retry
    logs/<key>.a<N>.log    worker-side output of attempt N
    episodes.jsonl         index of results/ (rebuilt at the end of a sweep; results/ is the truth)

An episode counts as finished only when ``results/<key>.json`` parses, names its key and its bag
exists; anything else (a half-written file, a bag without a record) is run again. The key is
``RunConfig.key()``, a hash of everything that determines the episode.
"""

from __future__ import annotations

import contextlib
import ctypes
import io
import itertools
import json
import math
import multiprocessing as mp
import os
import queue
import shutil
import signal
import tarfile
import tempfile
import time
import traceback
from collections import Counter, deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import yaml

from lq_ros.config import RunConfig
from lq_ros.suites import CONTROL_DT_S, NUM_INIT_STATES, STEP_BUDGETS, latency_ticks

TRANSPORTS = ("ros", "inprocess")
BACKENDS = ("local", "ray")
MODES = ("sync", "async")
#: Protocol parameters a ``modes`` entry may set (scalars or lists; lists multiply).
PROTOCOL_KEYS = ("replan_steps", "hold", "request_threshold", "merge")
SPEC_KEYS = {
    "name", "transport", "timeout_s", "suites", "suite", "tasks", "inits", "seeds", "policies",
    "latencies_s", "modes", "camera_size", "physics_rate", "max_steps",
}  # fmt: skip
#: A crashed episode is run at most this many times in total.
MAX_ATTEMPTS = 2
FINAL_STATUSES = ("success", "failure", "error")
RECORD_FORMAT = 1


class SpecError(ValueError):
    """A sweep spec that cannot be run; the message says where and what is wrong."""


# -- spec ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SweepSpec:
    name: str
    configs: tuple[RunConfig, ...]
    #: Transport the spec asks for (None: the caller's default).
    transport: str | None
    #: Wall-clock limit per ros-transport episode, seconds (None: the launcher's default).
    timeout_s: float | None
    raw: dict


def _as_list(value, where: str) -> list:
    if isinstance(value, list):
        if not value:
            raise SpecError(f"{where}: empty list")
        return value
    return [value]


def _ints(value, where: str, lo: int, hi: int) -> list[int]:
    out = []
    for v in _as_list(value, where):
        if isinstance(v, bool) or not isinstance(v, int):
            raise SpecError(f"{where}: expected integers, got {v!r}")
        if not lo <= v <= hi:
            raise SpecError(f"{where}: {v} is outside {lo}..{hi}")
        out.append(v)
    return out


def num_tasks(suite: str) -> int:
    """Number of tasks LIBERO ships for ``suite`` (imports libero; used for ``tasks: all``)."""
    from libero.libero import benchmark

    return benchmark.get_benchmark_dict()[suite]().n_tasks


def _suites(raw: dict) -> list[tuple[str, list[int], list[int]]]:
    """(suite, tasks, inits) from ``suites:`` or the one-suite shorthand ``suite/tasks/inits``."""
    short = {k for k in ("suite", "tasks", "inits") if k in raw}
    if "suites" in raw and short:
        raise SpecError(f"give either 'suites' or {sorted(short)}, not both")
    if "suites" in raw:
        entries = raw["suites"]
        if not isinstance(entries, dict) or not entries:
            raise SpecError("suites: expected a mapping suite -> {tasks: ..., inits: ...}")
    else:
        entries = {raw.get("suite", "libero_spatial"): {k: raw[k] for k in ("tasks", "inits") if k in raw}}
    out = []
    for suite, body in entries.items():
        where = f"suites.{suite}"
        if suite not in STEP_BUDGETS:
            raise SpecError(f"{where}: unknown suite; known: {', '.join(STEP_BUDGETS)}")
        body = body or {}
        if not isinstance(body, dict) or set(body) - {"tasks", "inits"}:
            raise SpecError(f"{where}: expected keys 'tasks' and 'inits', got {body!r}")
        if "tasks" not in body or "inits" not in body:
            raise SpecError(
                f"{where}: 'tasks' (a list or 'all') and 'inits' (a list of init-state indices) are required"
            )
        n = num_tasks(suite) if body["tasks"] == "all" or not isinstance(body["tasks"], str) else None
        if body["tasks"] == "all":
            tasks = list(range(n))
        elif isinstance(body["tasks"], str):
            raise SpecError(f"{where}.tasks: expected a list of task ids or 'all', got {body['tasks']!r}")
        else:
            tasks = _ints(body["tasks"], f"{where}.tasks", 0, n - 1)
        inits = _ints(body["inits"], f"{where}.inits", 0, NUM_INIT_STATES - 1)
        out.append((suite, tasks, inits))
    return out


def _policies(raw: dict) -> list[tuple[str, dict]]:
    from lq_ros.policies import REGISTRY

    if "policies" not in raw:
        raise SpecError("'policies' is required (a list of registry names or {name, args} entries)")
    out = []
    for i, entry in enumerate(_as_list(raw["policies"], "policies")):
        where = f"policies[{i}]"
        if isinstance(entry, str):
            name, args = entry, {}
        elif isinstance(entry, dict) and "name" in entry and set(entry) <= {"name", "args"}:
            name, args = entry["name"], entry.get("args") or {}
        else:
            raise SpecError(f"{where}: expected a policy name or {{name: ..., args: {{...}}}}, got {entry!r}")
        if not isinstance(name, str) or (name not in REGISTRY and ":" not in name):
            raise SpecError(f"{where}: unknown policy {name!r}; known: {', '.join(sorted(REGISTRY))} or 'module:Class'")
        if not isinstance(args, dict):
            raise SpecError(f"{where}.args: expected a mapping, got {args!r}")
        out.append((name, args))
    return out


def _latencies(raw: dict) -> list[float]:
    if "latencies_s" not in raw:
        raise SpecError("'latencies_s' is required (injected latencies, seconds)")
    out, by_ticks = [], {}
    for v in _as_list(raw["latencies_s"], "latencies_s"):
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) or v < 0:
            raise SpecError(f"latencies_s: expected non-negative seconds, got {v!r}")
        n = latency_ticks(float(v))
        if n in by_ticks:
            raise SpecError(
                f"latencies_s: {by_ticks[n]} and {v} s both round to N = {n} ticks of {CONTROL_DT_S} s (same episodes)"
            )
        by_ticks[n] = v
        out.append(float(v))
    return out


def _modes(raw: dict) -> list[dict]:
    """Protocol variants: [{mode, replan_steps?, hold?, ...}], the product of each mode's lists."""
    modes = raw.get("modes", list(MODES))
    if isinstance(modes, list | str):
        modes = {m: {} for m in _as_list(modes, "modes")}
    if not isinstance(modes, dict) or not modes:
        raise SpecError("modes: expected a list of modes or a mapping mode -> protocol parameters")
    out = []
    for mode, params in modes.items():
        if mode not in MODES:
            raise SpecError(f"modes: unknown mode {mode!r}; known: {', '.join(MODES)}")
        params = params or {}
        if not isinstance(params, dict) or set(params) - set(PROTOCOL_KEYS):
            raise SpecError(f"modes.{mode}: expected a mapping with keys among {PROTOCOL_KEYS}, got {params!r}")
        keys = list(params)
        for values in itertools.product(*(_as_list(params[k], f"modes.{mode}.{k}") for k in keys)):
            out.append({"mode": mode, **dict(zip(keys, values))})
    return out


def expand_spec(raw: dict, *, default_name: str = "sweep") -> SweepSpec:
    """Validate a parsed spec and expand it to one RunConfig per episode (deterministic order)."""
    if not isinstance(raw, dict):
        raise SpecError(f"a sweep spec is a YAML mapping, got {type(raw).__name__}")
    unknown = set(raw) - SPEC_KEYS
    if unknown:
        raise SpecError(f"unknown key(s) {sorted(unknown)}; known: {sorted(SPEC_KEYS)}")
    transport = raw.get("transport")
    if transport is not None and transport not in TRANSPORTS:
        raise SpecError(f"transport: expected one of {TRANSPORTS}, got {transport!r}")
    timeout_s = raw.get("timeout_s")
    if timeout_s is not None and (not isinstance(timeout_s, int | float) or timeout_s <= 0):
        raise SpecError(f"timeout_s: expected positive seconds, got {timeout_s!r}")
    seeds = _ints(raw.get("seeds", [7]), "seeds", 0, 2**31 - 1)
    common = {}
    for key, typ in (("camera_size", int), ("physics_rate", bool), ("max_steps", int)):
        if key in raw:
            if not isinstance(raw[key], typ) or (typ is int and isinstance(raw[key], bool)):
                raise SpecError(f"{key}: expected {typ.__name__}, got {raw[key]!r}")
            common[key] = raw[key]
    if common.get("max_steps", 0) < 0 or common.get("camera_size", 1) < 1:
        raise SpecError("max_steps must be >= 0 (0: the suite's budget) and camera_size >= 1")
    policies, latencies, modes, suites = _policies(raw), _latencies(raw), _modes(raw), _suites(raw)
    configs: dict[str, RunConfig] = {}
    for (policy, args), proto, latency, (suite, tasks, inits) in itertools.product(policies, modes, latencies, suites):
        for task, init, seed in itertools.product(tasks, inits, seeds):
            try:
                cfg = RunConfig(
                    suite=suite, task=task, init=init, seed=seed, latency_s=latency, policy=policy,
                    policy_args=dict(args), **proto, **common,
                )  # fmt: skip
            except (TypeError, ValueError) as exc:
                raise SpecError(f"{policy} {proto} latency {latency} s: {exc}") from exc
            if cfg.key() in configs:
                raise SpecError(f"the spec lists the same episode twice: {cfg.episode_name()}")
            configs[cfg.key()] = cfg
    name = raw.get("name", default_name)
    if not isinstance(name, str) or not name or "/" in name:
        raise SpecError(f"name: expected a non-empty string without '/', got {name!r}")
    return SweepSpec(name, tuple(configs.values()), transport, timeout_s, raw)


def load_spec(path: Path) -> SweepSpec:
    """Read and expand a sweep spec file; SpecError names the file."""
    path = Path(path)
    try:
        raw = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise SpecError(f"{path}: cannot read ({exc.strerror})") from exc
    except yaml.YAMLError as exc:
        raise SpecError(f"{path}: not valid YAML ({exc})") from exc
    try:
        return expand_spec(raw, default_name=path.stem)
    except SpecError as exc:
        raise SpecError(f"{path}: {exc}") from exc


def check_policies(configs: tuple[RunConfig, ...] | list[RunConfig]) -> None:
    """Build each distinct policy once, so bad policy arguments fail before any episode runs."""
    from lq_ros.policies import make_policy

    seen = set()
    for cfg in configs:
        ident = (cfg.policy, json.dumps(cfg.policy_args, sort_keys=True))
        if ident in seen:
            continue
        seen.add(ident)
        try:
            make_policy(cfg.policy, **cfg.policy_args).close()
        except Exception as exc:  # noqa: BLE001 - any construction failure is a spec problem
            raise SpecError(f"policy {cfg.policy} with args {cfg.policy_args}: {type(exc).__name__}: {exc}") from exc


# -- durable store ---------------------------------------------------------------------------


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write_text(path: Path, text: str) -> None:
    """Write-then-rename with fsync: after a crash the file is either the old one or the whole new one."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)  # mkstemp makes it private; results are for everyone who can read the folder
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    _fsync_dir(path.parent)


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

    def create(self) -> None:
        for d in (self.results, self.bags, self.attempts, self.logs):
            d.mkdir(parents=True, exist_ok=True)

    def record_path(self, key: str) -> Path:
        return self.results / f"{key}.json"

    def load(self, key: str) -> dict | None:
        """The finished record of ``key``, or None when missing, half-written or pointing at a lost bag."""
        try:
            record = json.loads(self.record_path(key).read_text())
        except (OSError, ValueError):
            return None
        if not isinstance(record, dict) or record.get("key") != key or record.get("status") not in FINAL_STATUSES:
            return None
        bag = record.get("bag")
        if bag and not (self.root / bag / "metadata.yaml").exists():
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
            with contextlib.suppress(OSError, ValueError):
                out.append(json.loads(path.read_text()))
        return out

    def keep_failed_attempt(self, key: str, attempt: dict, bag: Path | None) -> dict:
        """Move a crashed attempt's bag aside (its retry writes a fresh one) and persist its record."""
        n = attempt["attempt"]
        if bag is not None:
            for src in (bag, bag.with_name(bag.name + ".logs")):
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
        for path in (bag, bag.with_name(bag.name + ".logs")):
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


# -- one episode -----------------------------------------------------------------------------


def _env_key(cfg: RunConfig) -> tuple:
    """Episodes with equal keys can share one worker's env and policy instance."""
    return (cfg.suite, cfg.task, cfg.policy, json.dumps(cfg.policy_args, sort_keys=True), cfg.camera_size,
            cfg.physics_rate)  # fmt: skip


@contextlib.contextmanager
def _capture_output(log_path: Path) -> Iterator[None]:
    """Send this process's stdout/stderr (fd level, so C libraries too) to ``log_path``."""
    import sys

    log_path.parent.mkdir(parents=True, exist_ok=True)
    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    with open(log_path, "ab") as log:
        os.dup2(log.fileno(), 1)
        os.dup2(log.fileno(), 2)
        try:
            yield
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])


class EpisodeWorker:
    """Runs episodes one after another, like one sweep worker process (local or a Ray actor).

    In-process transport: the LiberoEnv and the policy of the previous episode are reused when the
    next one has the same task, policy and camera setup (env creation dominates a short episode;
    tests/test_sweep.py checks a reused env gives the same bag as a fresh one).
    """

    def __init__(self, transport: str, bags_dir: Path, timeout_s: float | None = None) -> None:
        if transport not in TRANSPORTS:
            raise ValueError(f"transport must be one of {TRANSPORTS}, got {transport!r}")
        self.transport = transport
        self.bags_dir = Path(bags_dir)
        self.timeout_s = timeout_s
        self._cached: tuple | None = None  # (env key, env, policy)

    def run(self, cfg: RunConfig, log_path: Path) -> dict:
        """Run ``cfg`` once; returns {status, reason, row, bag, wall_s}. Never raises for episode failures."""
        from lq_ros.scoring import score_bag, to_json

        started = time.monotonic()
        bag = self.bags_dir / cfg.episode_name()
        row, reason = None, ""
        with _capture_output(log_path):
            try:
                if self.transport == "inprocess":
                    from lq_ros.runner import run_inprocess

                    env, policy = self._env_policy(cfg)
                    outcome = run_inprocess(cfg, self.bags_dir, env=env, policy=policy)
                    row = json.loads(to_json(score_bag(outcome.bag_path)))
                else:
                    from lq_ros.launcher import launch_episode

                    outcome, row = launch_episode(cfg, self.bags_dir, timeout_s=self.timeout_s)
                status, reason = outcome.status, outcome.reason
                if status == "error" and outcome.reason:
                    print(f"episode error: {outcome.reason}", flush=True)
            except Exception as exc:  # noqa: BLE001 - a crash outside the episode loop is still an error
                traceback.print_exc()
                status, reason = "error", f"{type(exc).__name__}: {exc}"
                self.close()  # a half-built env must not be reused
        if row is not None:
            row["status"] = status  # the outcome decides (a run error may leave a good-looking bag)
            if status == "error":
                row["success"] = None
                row["error_reason"] = row.get("error_reason") or reason
        return {
            "status": status,
            "reason": reason,
            "row": row,
            "bag": str(bag) if (bag / "metadata.yaml").exists() else None,
            "wall_s": time.monotonic() - started,
        }

    def _env_policy(self, cfg: RunConfig):
        from lq_ros.env import LiberoEnv
        from lq_ros.policies import make_policy

        key = _env_key(cfg)
        if self._cached is None or self._cached[0] != key:
            self.close()
            policy = make_policy(cfg.policy, **cfg.policy_args)
            env = LiberoEnv(
                cfg.suite, cfg.task, camera_names=policy.camera_names, camera_size=cfg.camera_size,
                record_physics=cfg.physics_rate,
            )  # fmt: skip
            self._cached = (key, env, policy)
        return self._cached[1], self._cached[2]

    def close(self) -> None:
        if self._cached is not None:
            _, env, policy = self._cached
            self._cached = None
            with contextlib.suppress(Exception):
                policy.close()
            with contextlib.suppress(Exception):
                env.close()


# -- scheduling ------------------------------------------------------------------------------


@dataclass
class Job:
    cfg: RunConfig
    attempt: int = 1
    previous: list[dict] = field(default_factory=list)  # records of crashed earlier attempts

    @property
    def key(self) -> str:
        return self.cfg.key()


class Scheduler:
    """Pending jobs grouped by env key; a free worker gets one of its current group first (env reuse),
    else one of the group the fewest workers are on (the rest of the largest group breaks ties)."""

    def __init__(self, jobs: list[Job]) -> None:
        self.groups: dict[tuple, deque[Job]] = {}
        for job in jobs:
            self.groups.setdefault(_env_key(job.cfg), deque()).append(job)

    def __len__(self) -> int:
        return sum(len(q) for q in self.groups.values())

    def retry(self, job: Job) -> None:
        self.groups.setdefault(_env_key(job.cfg), deque()).appendleft(job)

    def pick(self, current: tuple | None, busy: Counter) -> Job | None:
        live = {k: q for k, q in self.groups.items() if q}
        if not live:
            return None
        key = current if current in live else min(live, key=lambda k: (busy[k], -len(live[k])))
        return live[key].popleft()


def _die_with_parent() -> None:
    """A worker must not outlive the sweep (kill -9 of the sweep included)."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


def _raise_keyboard_interrupt(*_) -> None:
    raise KeyboardInterrupt


def _local_worker_main(slot: int, transport: str, bags_dir: str, timeout_s, tasks, results) -> None:
    _die_with_parent()
    # Ctrl-C reaches the whole process group: the parent decides when workers stop. A no-op handler,
    # not SIG_IGN, since an ignored SIGINT would be inherited by the ROS nodes a worker launches.
    signal.signal(signal.SIGINT, lambda *_: None)
    # Stopped by the parent (SIGTERM): unwind like Ctrl-C, so a launcher stops its nodes cleanly.
    signal.signal(signal.SIGTERM, _raise_keyboard_interrupt)
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


# -- Ray backend -----------------------------------------------------------------------------


def _pack_dir(path: Path) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tar:
        tar.add(path, arcname=path.name)
    return buf.getvalue()


def _unpack_dir(data: bytes, dest_parent: Path) -> None:
    with tarfile.open(fileobj=io.BytesIO(data), mode="r:gz") as tar:
        tar.extractall(dest_parent, filter="data")


class _RayEpisodeActor:
    """One Ray worker: runs episodes into its own bag folder and ships each bag back with the result."""

    def __init__(self, transport: str, timeout_s: float | None) -> None:
        os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        self.root = Path(tempfile.mkdtemp(prefix="lq_ray_worker_"))
        self.worker = EpisodeWorker(transport, self.root / "bags", timeout_s)

    def run(self, cfg_dict: dict) -> dict:
        cfg = RunConfig(**cfg_dict)
        log = self.root / "logs" / f"{cfg.key()}.log"
        log.unlink(missing_ok=True)
        result = self.worker.run(cfg, log)
        result["log_text"] = log.read_text(errors="replace") if log.exists() else ""
        bag_dir = self.root / "bags" / cfg.episode_name()
        result["tars"] = []  # the bag (and node logs) travel back to the driver's store
        for src in (bag_dir, bag_dir.with_name(bag_dir.name + ".logs")):
            if src.exists():
                result["tars"].append(_pack_dir(src))
                shutil.rmtree(src)
        return result

    def close(self) -> None:
        self.worker.close()
        shutil.rmtree(self.root, ignore_errors=True)


def ray_init_local(num_cpus: int) -> None:
    """A private single-node Ray on loopback only: no dashboard, no usage reporting.

    Ray turns a node address of 127.0.0.1 into the machine's outward address unless
    RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0 (read when ray is imported); with it every Ray server
    listens on 127.0.0.1 only (checked in tests/test_sweep_ray.py).
    """
    os.environ["RAY_USAGE_STATS_ENABLED"] = "0"
    os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"  # inherited by every Ray process started below
    # Ray starts workers at nice 15; here the workers are the work (a sim at nice 15 on a busy machine
    # ran ~6x slower than a local worker), so they get the same priority as local workers.
    os.environ.setdefault("RAY_worker_niceness", "0")
    import ray
    from ray._private import ray_constants

    # Imported earlier in this process: apply the same setting to the constant it was read into.
    ray_constants.ENABLE_RAY_CLUSTER = False

    ray.init(
        num_cpus=num_cpus, _node_ip_address="127.0.0.1", include_dashboard=False, log_to_driver=False,
        configure_logging=False,
    )  # fmt: skip
    node_ip = ray.util.get_node_ip_address()
    if node_ip != "127.0.0.1":
        ray.shutdown()
        raise RuntimeError(
            f"local Ray came up on {node_ip}, not loopback: import ray only after "
            "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0 is set (lq_ros.sweep.ray_init_local does this)"
        )


class RayPool:
    """Ray actors as workers (one CPU each); results and bags come back to the driver's store."""

    def __init__(self, n: int | None, transport: str, bags_dir: Path, timeout_s: float | None, address: str | None):
        if address:
            import ray

            os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
            ray.init(address=address, log_to_driver=False)
        else:
            ray_init_local(n or default_workers())
        import ray

        self._ray = ray
        self._bags_dir = Path(bags_dir)
        if n is None:
            n = max(1, int(ray.cluster_resources().get("CPU", 1)))
        self._actor_cls = ray.remote(num_cpus=1, max_restarts=0)(_RayEpisodeActor)
        self._args = (transport, timeout_s)
        self._actors = [self._actor_cls.remote(*self._args) for _ in range(n)]
        self._pending: dict = {}  # ObjectRef -> (slot, log_path)

    @property
    def size(self) -> int:
        return len(self._actors)

    def submit(self, slot: int, cfg: RunConfig, log_path: Path) -> None:
        self._pending[self._actors[slot].run.remote(cfg.to_dict())] = (slot, log_path)

    def wait(self, busy: set[int], timeout_s: float) -> list[tuple[int, dict]]:
        ray = self._ray
        if not self._pending:
            time.sleep(timeout_s)
            return []
        ready, _ = ray.wait(list(self._pending), num_returns=1, timeout=timeout_s)
        out = []
        for ref in ready:
            slot, log_path = self._pending.pop(ref)
            try:
                result = ray.get(ref)
            except ray.exceptions.RayError as exc:  # the actor died, or failed outside the episode
                result = {"status": "error", "reason": f"Ray worker failed: {type(exc).__name__}", "row": None,
                          "bag": None, "wall_s": None, "log_text": str(exc)}  # fmt: skip
                if isinstance(exc, ray.exceptions.RayActorError | ray.exceptions.WorkerCrashedError):
                    self._actors[slot] = self._actor_cls.remote(*self._args)
            Path(log_path).parent.mkdir(parents=True, exist_ok=True)
            Path(log_path).write_text(result.pop("log_text", ""))
            for data in result.pop("tars", []):
                _unpack_dir(data, self._bags_dir)
            if result.get("bag"):
                result["bag"] = str(self._bags_dir / Path(result["bag"]).name)
            out.append((slot, result))
        return out

    def close(self) -> None:
        ray = self._ray
        with contextlib.suppress(Exception):
            ray.get([a.close.remote() for a in self._actors], timeout=30)
        ray.shutdown()

    def terminate(self) -> None:
        for actor in self._actors:
            with contextlib.suppress(Exception):
                self._ray.kill(actor)
        self._ray.shutdown()


# -- the sweep -------------------------------------------------------------------------------


@dataclass
class SweepSummary:
    total: int
    skipped: int
    ran: int = 0
    counts: Counter = field(default_factory=Counter)  # final status -> episodes finished in this run
    retried: int = 0
    wall_s: float = 0.0
    out_dir: Path | None = None

    @property
    def episodes_per_s(self) -> float:
        return self.ran / self.wall_s if self.wall_s > 0 else 0.0


def default_workers() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="seconds")


def prepare(spec: SweepSpec, out_dir: Path, *, retry_errors: bool = False) -> tuple[ResultStore, list[Job], int]:
    """Create the store, write the spec and manifest; returns the jobs still to run and how many are done."""
    store = ResultStore(out_dir)
    store.create()
    atomic_write_text(store.root / "sweep.yaml", yaml.safe_dump(spec.raw, sort_keys=False))
    manifest = {"name": spec.name, "episodes": {c.key(): c.to_dict() for c in spec.configs}}
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
        jobs.append(Job(cfg, attempt=len(previous) + 1, previous=previous))
    return store, jobs, done


def run_sweep(
    spec: SweepSpec,
    out_dir: Path,
    *,
    workers: int | None = None,
    transport: str | None = None,
    backend: str = "local",
    address: str | None = None,
    retry_errors: bool = False,
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
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if workers is not None and workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    store, jobs, done = prepare(spec, out_dir, retry_errors=retry_errors)
    summary = SweepSummary(total=len(spec.configs), skipped=done, out_dir=store.root)
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
            busy = Counter(_env_key(j.cfg) for j in running.values())
            for slot in range(pool.size):
                if slot in running:
                    continue
                job = sched.pick(current.get(slot), busy)
                if job is None:
                    break
                store.clear_leftovers(job.cfg)
                running[slot], current[slot] = job, _env_key(job.cfg)
                busy[current[slot]] += 1
                pool.submit(slot, job.cfg, store.logs / f"{job.key}.a{job.attempt}.log")
            for slot, result in pool.wait(set(running), timeout_s=0.5):
                job = running.pop(slot)
                record = _finish(store, job, result, transport, spec.name)
                if record is None:  # crashed first attempt: run it again
                    summary.retried += 1
                    previous = store.failed_attempts(job.key)
                    sched.retry(Job(job.cfg, attempt=job.attempt + 1, previous=previous))
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
        "config": job.cfg.to_dict(),
        "transport": transport,
        "status": result["status"],
        "bag": attempt.get("bag"),
        "row": row,
        "attempts": [*job.previous, attempt],
        "finished_at": attempt["finished_at"],
    }
    store.write(record)
    return record


# -- command line ----------------------------------------------------------------------------


def run_with_progress(spec: SweepSpec, out_dir: Path, *, console=None, **kwargs) -> SweepSummary:
    """run_sweep with a rich progress bar: episodes done, successes, failures, errors, ETA."""
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    console = console or Console(stderr=True)
    progress = Progress(
        TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
        TextColumn("[green]✓ {task.fields[ok]}[/] [yellow]✗ {task.fields[fail]}[/] [red]! {task.fields[err]}[/]"
                   " [dim]retried {task.fields[retried]}[/]"),
        TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(), console=console, transient=False,
    )  # fmt: skip
    state: dict = {}

    def update(summary: SweepSummary, record: dict | None) -> None:
        if "task" not in state:
            pending = summary.total - summary.skipped
            state["task"] = progress.add_task(spec.name, total=pending, ok=0, fail=0, err=0, retried=0)
            if summary.skipped:
                console.print(f"{summary.skipped} of {summary.total} episodes already finished in {out_dir}: skipped")
        c = summary.counts
        progress.update(state["task"], completed=summary.ran, ok=c["success"], fail=c["failure"], err=c["error"],
                        retried=summary.retried)  # fmt: skip
        if record is not None and record["status"] == "error":
            progress.console.print(f"[red]error[/red] {record['episode']}: {record['row'].get('error_reason')}")

    previous = signal.signal(signal.SIGTERM, _raise_keyboard_interrupt)  # SIGTERM stops it like Ctrl-C
    try:
        with progress:
            return run_sweep(spec, out_dir, on_progress=update, **kwargs)
    finally:
        signal.signal(signal.SIGTERM, previous)
