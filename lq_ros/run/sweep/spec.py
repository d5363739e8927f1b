"""Sweep specs: a YAML mapping validated and expanded to one RunConfig per episode (docs/sweeps.md)."""

from __future__ import annotations

import itertools
import json
import math
from dataclasses import dataclass
from pathlib import Path

import yaml

from lq_ros.core.latency import LatencyError, parse_latency
from lq_ros.core.run_config import PROTOCOL_FIELDS, RunConfig
from lq_ros.core.suite_constants import CONTROL_DT_S, NUM_INIT_STATES, STEP_BUDGETS, latency_ticks, round_latency
from lq_ros.run.episode import TRANSPORTS

MODES = ("sync", "async")
#: Protocol parameters a ``modes`` entry may set (scalars or lists; lists multiply).
PROTOCOL_KEYS = PROTOCOL_FIELDS
SPEC_KEYS = {
    "name", "transport", "timeout_s", "suites", "suite", "tasks", "inits", "seeds", "policies",
    "latencies_s", "latency_rounding", "modes", "camera_size", "physics_rate", "max_steps",
}  # fmt: skip


class SpecError(ValueError):
    """A sweep spec that cannot be run; the message says where and what is wrong."""


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


def _latencies(raw: dict) -> list[dict]:
    """RunConfig latency fields per entry: a constant in whole control ticks (``latency_rounding: nearest``
    rounds on purpose) as ``latency_s``, or a distribution (lq_ros/core/latency.py) as ``latency_dist``."""
    if "latencies_s" not in raw:
        raise SpecError("'latencies_s' is required (injected latencies, seconds, or distributions)")
    rounding = raw.get("latency_rounding", "exact")
    if rounding not in ("exact", "nearest"):
        raise SpecError(f"latency_rounding: expected exact or nearest, got {rounding!r}")
    out, by_ticks, texts = [], {}, set()
    for v in _as_list(raw["latencies_s"], "latencies_s"):
        if isinstance(v, str) and ":" in v:
            try:
                dist = parse_latency(v)
            except LatencyError as exc:
                raise SpecError(f"latencies_s: {exc}") from None
            if dist.text in texts:
                raise SpecError(f"latencies_s: {v!r} is listed twice")
            texts.add(dist.text)
            out.append({"latency_dist": dist.text})
            continue
        if isinstance(v, str):
            try:
                v = float(v)
            except ValueError:
                raise SpecError(f"latencies_s: expected seconds or a distribution, got {v!r}") from None
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) or v < 0:
            raise SpecError(f"latencies_s: expected non-negative seconds or a distribution, got {v!r}")
        if rounding == "nearest":
            v = round_latency(float(v))
        try:
            n = latency_ticks(float(v))
        except ValueError as exc:
            raise SpecError(f"latencies_s: {exc}") from None
        if n in by_ticks:
            raise SpecError(
                f"latencies_s: {by_ticks[n]} and {v} s are both N = {n} ticks of {CONTROL_DT_S} s (same episodes)"
            )
        by_ticks[n] = v
        out.append({"latency_s": float(v)})
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
    if common.get("max_steps", 0) < 0 or common.get("camera_size", 0) < 0:
        raise SpecError("max_steps must be >= 0 (0: the suite's budget) and camera_size >= 0 (0: the policy's)")
    policies, latencies, modes, suites = _policies(raw), _latencies(raw), _modes(raw), _suites(raw)
    configs: dict[str, RunConfig] = {}
    for (policy, args), proto, latency, (suite, tasks, inits) in itertools.product(policies, modes, latencies, suites):
        for task, init, seed in itertools.product(tasks, inits, seeds):
            try:
                cfg = RunConfig(
                    suite=suite, task=task, init=init, seed=seed, policy=policy,
                    policy_args=dict(args), **latency, **proto, **common,
                )  # fmt: skip
            except (TypeError, ValueError) as exc:
                what = latency.get("latency_dist") or f"{latency['latency_s']} s"
                raise SpecError(f"{policy} {proto} latency {what}: {exc}") from exc
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
    """Check and build each distinct policy once, so bad policy arguments fail before any episode runs
    (lq_ros.run.validation: an argument the policy does not take or of the wrong type, a value it refuses)."""
    from lq_ros.run.validation import InputError, check_policy, policy_class

    seen, merges = set(), set()
    for cfg in configs:
        try:
            if (cfg.policy, cfg.merge) not in merges:
                merges.add((cfg.policy, cfg.merge))
                policy_class(cfg.policy).check_merge(cfg.merge)  # e.g. rtc with a policy that takes no prefix
            ident = (cfg.policy, json.dumps(cfg.policy_args, sort_keys=True))
            if ident not in seen:
                seen.add(ident)
                check_policy(cfg.policy, cfg.policy_args)
        except InputError as exc:
            raise SpecError(f"policies: {exc}") from None
        except ValueError as exc:
            raise SpecError(str(exc)) from exc
