"""Sweep specs: a YAML mapping validated and expanded to one RunConfig per episode (docs/guide/sweeps.md)."""

from __future__ import annotations

import itertools
import json
import math
import re
from dataclasses import dataclass
from pathlib import Path

from lq_ros.core.latency import MAX_LATENCY_S, LatencyError, parse_latency
from lq_ros.core.redact import redact_value
from lq_ros.core.run_config import BUDGET_COUNTS, CLOCKS, PROTOCOL_FIELDS, RunConfig
from lq_ros.core.safe_yaml import YamlRefused, load_yaml, read_text_file
from lq_ros.core.suite_constants import (
    BUDGET_PRESETS,
    CONTROL_DT_S,
    NUM_INIT_STATES,
    STEP_BUDGETS,
    latency_ticks,
    round_latency,
)
from lq_ros.run.episode import TRANSPORTS
from lq_ros.run.validation import did_you_mean, num_tasks
from lq_ros.scoring.decisions import PlanError, parse_analysis

MODES = ("sync", "async")
#: The most episodes one spec may expand to (counted before anything is expanded); split larger sweeps.
MAX_EPISODES = 100_000
#: The largest spec file read, bytes.
MAX_SPEC_BYTES = 1 << 20
#: Entries of ``latencies_s`` at most (each may read a trace file).
MAX_LATENCIES = 256
#: ``timeout_s``: wall seconds per episode at most (a day).
MAX_TIMEOUT_S = 86_400.0
#: ``camera_size``: 0 (the policy's) or 1..this px.
MAX_CAMERA_SIZE_PX = 1024
#: ``max_steps``: 0 (the suite's budget) or up to this many ticks.
MAX_STEPS = 100_000
#: Integer protocol parameters (replan_steps, request_threshold, ...) at most.
MAX_PROTOCOL_VALUE = 10_000
#: A sweep name is one path component: the default output folder is bags/sweeps/<name>.
MAX_NAME_BYTES = 255
#: ``package.module:Class`` (dotted identifiers).
_POLICY_PATH = re.compile(r"[A-Za-z_]\w*(\.[A-Za-z_]\w*)*:[A-Za-z_]\w*")
#: Protocol parameters a ``modes`` entry may set (scalars or lists; lists multiply).
PROTOCOL_KEYS = PROTOCOL_FIELDS
SPEC_KEYS = {
    "name", "transport", "timeout_s", "suites", "suite", "tasks", "inits", "seeds", "policies",
    "latencies_s", "latency_rounding", "modes", "camera_size", "physics_rate", "max_steps", "budgets",
    "budget_counts", "clock", "robot", "parts", "analysis",
}  # fmt: skip
#: Every ``lq run`` / ``lq eval`` flag that sets an episode, and the spec key that sets the same thing: one set of
#: names, plural where a spec takes a list. ``modes.<mode>.<key>``: a protocol parameter under its mode;
#: ``policies[].name`` / ``policies[].args``: an entry of ``policies``. tests/test_cli_eval.py checks
#: that every flag of both commands is here (or is no spec setting) and that every key is one a spec takes.
FLAG_TO_SPEC_KEY = {
    "--suite": "suite", "--task": "tasks", "--tasks": "tasks", "--init": "inits", "--inits": "inits",
    "--seed": "seeds", "--seeds": "seeds", "--policy": "policies[].name", "--policy-arg": "policies[].args",
    "--mode": "modes", "--modes": "modes", "--latency": "latencies_s", "--latencies": "latencies_s",
    "--latency-rounding": "latency_rounding", "--replan-steps": "modes.sync.replan_steps", "--hold": "modes.sync.hold",
    "--request-threshold": "modes.async.request_threshold", "--request-slack": "modes.async.request_slack",
    "--merge": "modes.async.merge", "--camera-size": "camera_size", "--physics-rate": "physics_rate",
    "--max-steps": "max_steps", "--budgets": "budgets", "--budget-counts": "budget_counts", "--clock": "clock",
    "--robot": "robot", "--transport": "transport", "--timeout": "timeout_s", "--primary": "analysis.primary",
    "--equivalence-margin": "analysis.equivalence_margin",
}  # fmt: skip
#: Keys that apply to the whole sweep: a ``parts`` entry may not set them.
SWEEP_WIDE_KEYS = {"name", "transport", "timeout_s", "clock", "robot", "parts", "analysis"}
#: The one-suite shorthand: a part's ``suites`` replaces the top level's shorthand, a shorthand key its ``suites``.
_SHORTHAND_KEYS = {"suite", "tasks", "inits"}
#: ``parts`` entries at most.
MAX_PARTS = 64


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


def index_list(value, where: str, lo: int, hi: int) -> list[int]:
    """Task or init-state indices: a list of integers, or text of ranges and integers (``0-49``, ``0-4,7``)."""
    if not isinstance(value, str):
        return _ints(value, where, lo, hi)
    out: list[int] = []
    for part in value.replace(" ", "").split(","):
        first, dash, last = part.partition("-")
        # isdigit() is true for any script's digits (and int() takes them): ASCII 0-9 only, never another script's.
        if not (part.isascii() and first.isdigit()) or (dash and not last.isdigit()) or len(part) > 12:
            raise SpecError(f"{where}: expected integers or ranges like 0-49 (or 'all'), got {value!r}")
        a, b = int(first), int(last) if dash else int(first)
        if not lo <= a <= b <= hi:
            raise SpecError(f"{where}: {part} is outside {lo}..{hi} (or an empty range)")
        out += range(a, b + 1)
    if len(set(out)) != len(out):
        raise SpecError(f"{where}: {value!r} names an index twice")
    return out


def _n(value) -> int:
    return len(value) if isinstance(value, list) else 1


def _cells(suite, body) -> int:
    if not isinstance(body, dict):
        return 1
    tasks, inits = body.get("tasks"), body.get("inits")
    # 'all' or a range text: counted at its largest (every task, every init state) before anything is expanded.
    known = isinstance(suite, str) and suite in STEP_BUDGETS
    n_tasks = num_tasks(suite) if isinstance(tasks, str) and known else _n(tasks)
    n_inits = NUM_INIT_STATES if isinstance(inits, str) else _n(inits)
    return max(n_tasks, 1) * max(n_inits, 1)


def _parts(raw: dict) -> list[dict] | None:
    """``parts``: several products in one sweep, each the top-level keys with the part's keys over them (a part's
    ``suites`` replaces the top level's ``suite/tasks/inits``, and the other way round). None when there are none."""
    if "parts" not in raw:
        return None
    parts = raw["parts"]
    if not isinstance(parts, list) or not parts or len(parts) > MAX_PARTS:
        raise SpecError(f"parts: expected a list of 1..{MAX_PARTS} mappings, got {_short(parts)}")
    base = {k: v for k, v in raw.items() if k != "parts"}
    merged = []
    for i, part in enumerate(parts):
        if not isinstance(part, dict):
            raise SpecError(f"parts[{i}]: expected a mapping of episode keys, got {_short(part)}")
        wide = set(part) & SWEEP_WIDE_KEYS
        if wide:
            raise SpecError(f"parts[{i}]: {sorted(wide)} apply to the whole sweep; set them at the top level")
        unknown = set(part) - SPEC_KEYS
        if unknown:
            raise SpecError(f"parts[{i}]: unknown key(s) {sorted(unknown, key=str)}{_key_hint(unknown)}; known: "
                            f"{sorted(SPEC_KEYS - SWEEP_WIDE_KEYS)}")  # fmt: skip
        replaced = _SHORTHAND_KEYS if "suites" in part else {"suites"} if set(part) & _SHORTHAND_KEYS else set()
        merged.append({**{k: v for k, v in base.items() if k not in replaced}, **part})
    return merged


def _key_hint(unknown: set) -> str:
    """`` (did you mean 'latencies_s'?)``: the spec key of the first unknown key when that is a flag's name
    (``latency``, ``policy-arg``: FLAG_TO_SPEC_KEY), else the closest spec key."""
    key = str(sorted(unknown, key=str)[0])
    flag = "--" + key.lstrip("-").replace("_", "-")
    if flag in FLAG_TO_SPEC_KEY:
        return f" (did you mean {spec_key_example(FLAG_TO_SPEC_KEY[flag])}?)"
    return did_you_mean(key, sorted(SPEC_KEYS))


def spec_key_example(path: str) -> str:
    """A FLAG_TO_SPEC_KEY path as the YAML that sets it: ``modes.sync.hold`` -> ``modes: {sync: {hold: ...}}``, a
    top-level key quoted (``'seeds'``)."""
    if path == "policies[].name":
        return "policies: [NAME]"
    if path == "policies[].args":
        return "policies: [{name: NAME, args: {KEY: VALUE}}]"
    if "." not in path:
        return repr(path)
    head, *rest = path.split(".")
    return f"{head}: " + "".join("{" + part + ": " for part in rest) + "..." + "}" * len(rest)


def _short(value) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def count_episodes(raw: dict) -> int:
    """The episodes ``raw`` expands to, from its list lengths alone (nothing is expanded or read; a malformed
    part counts once, and is refused by the validation that follows)."""
    parts = _parts(raw)
    if parts is not None:
        return sum(count_episodes(part) for part in parts)
    n = 1
    for key, default in (("policies", None), ("latencies_s", None), ("seeds", None), ("budget_counts", None)):
        n *= max(_n(raw.get(key, default)), 1)
    modes = raw.get("modes", list(MODES))
    if isinstance(modes, dict):
        variants = 0
        for params in modes.values():
            k = 1
            for value in params.values() if isinstance(params, dict) else ():
                k *= max(_n(value), 1)
            variants += k
        n *= max(variants, 1)
    else:
        n *= max(_n(modes), 1)
    if isinstance(raw.get("suites"), dict):
        cells = sum(_cells(suite, body) for suite, body in raw["suites"].items())
    else:
        cells = _cells(raw.get("suite", "libero_spatial"), raw)
    return n * max(cells, 1)


def _count_text(n: int) -> str:
    return f"{n:,}" if n < 10**15 else f"about 10^{len(str(n)) - 1}"


def _name(name) -> str:
    """A sweep name: one path component (no '/', NUL, '.' or '..'), at most MAX_NAME_BYTES bytes."""
    if (
        not isinstance(name, str)
        or not name
        or "/" in name
        or "\0" in name
        or name in (".", "..")
        or len(name.encode(errors="replace")) > MAX_NAME_BYTES
    ):
        raise SpecError(
            f"name: expected a folder name (one path component: no '/', not '.' or '..', at most "
            f"{MAX_NAME_BYTES} bytes), got {name!r}"
        )
    return name


def _number(value, where: str, lo: float, hi: float, *, lo_open: bool = False) -> float:
    """A finite number in [lo, hi] ((lo, hi] with ``lo_open``); booleans are no numbers."""
    ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or not (lo < value if lo_open else lo <= value) or not value <= hi:
        interval = f"{'(' if lo_open else '['}{lo:g}, {hi:g}]"
        raise SpecError(f"{where}: expected a finite number in {interval}, got {value!r}")
    return value


def _finite_args(value, where: str) -> None:
    """Policy arguments: every number finite (NaN or infinity is never a meaningful argument)."""
    if isinstance(value, float) and not math.isfinite(value):
        raise SpecError(f"{where}: expected a finite number, got {value!r}")
    if isinstance(value, dict):
        for k, v in value.items():
            _finite_args(v, f"{where}.{k}")
    elif isinstance(value, list):
        for i, v in enumerate(value):
            _finite_args(v, f"{where}[{i}]")


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
            raise SpecError(
                f"{where}: unknown suite{did_you_mean(suite, STEP_BUDGETS)}; known: {', '.join(STEP_BUDGETS)}"
            )
        body = body or {}
        if not isinstance(body, dict) or set(body) - {"tasks", "inits"}:
            raise SpecError(f"{where}: expected keys 'tasks' and 'inits', got {body!r}")
        if "tasks" not in body or "inits" not in body:
            raise SpecError(f"{where}: 'tasks' and 'inits' are required (a list, ranges like '0-49', or 'all')")
        n = num_tasks(suite)
        tasks = list(range(n)) if body["tasks"] == "all" else index_list(body["tasks"], f"{where}.tasks", 0, n - 1)
        inits = (
            list(range(NUM_INIT_STATES))
            if body["inits"] == "all"
            else index_list(body["inits"], f"{where}.inits", 0, NUM_INIT_STATES - 1)
        )
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
            raise SpecError(
                f"{where}: expected a policy name or {{name: ..., args: {{...}}}}, got {redact_value(entry)!r}"
            )
        if not isinstance(name, str) or (name not in REGISTRY and not _POLICY_PATH.fullmatch(name)):
            hint = did_you_mean(name, sorted(REGISTRY)) if isinstance(name, str) else ""
            known = f"{', '.join(sorted(REGISTRY))} or 'package.module:Class'"
            raise SpecError(f"{where}: unknown policy {name!r}{hint}; known: {known}")
        if not isinstance(args, dict):
            raise SpecError(f"{where}.args: expected a mapping, got {args!r}")
        _finite_args(args, f"{where}.args")
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
    entries = _as_list(raw["latencies_s"], "latencies_s")
    if len(entries) > MAX_LATENCIES:
        raise SpecError(f"latencies_s: {len(entries)} entries; at most {MAX_LATENCIES}")
    for v in entries:
        if isinstance(v, str) and ":" in v:
            try:
                dist = parse_latency(v)
            except LatencyError as exc:
                raise SpecError(f"latencies_s: {exc}") from None
            _latency_bounds(dist)
            if dist.text in texts:
                raise SpecError(f"latencies_s: {v!r} is listed twice")
            texts.add(dist.text)
            out.append({"latency_dist": dist.text})
            continue
        if isinstance(v, str):
            try:
                v = float(v if v.isascii() else "not ASCII")  # float() takes any script's digits: only 0-9 here
            except ValueError:
                raise SpecError(f"latencies_s: expected seconds or a distribution, got {v!r}") from None
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) or not 0 <= v <= MAX_LATENCY_S:
            raise SpecError(
                f"latencies_s: expected non-negative seconds up to {MAX_LATENCY_S:g} or a distribution, got {v!r}"
            )
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


def _latency_bounds(dist) -> None:
    """A distribution's parameters, trace values and applied mean within [0, MAX_LATENCY_S]."""
    values = [*dist.params, *dist.trace]
    if any(v > MAX_LATENCY_S for v in values):
        what = "a value of the trace" if dist.trace else "a parameter"
        raise SpecError(
            f"latencies_s: {dist.label}: {what} exceeds {MAX_LATENCY_S:g} s (latencies are 0..{MAX_LATENCY_S:g} s)"
        )
    if dist.mean_s() > MAX_LATENCY_S:
        raise SpecError(
            f"latencies_s: {dist.label}: applied mean {dist.mean_s():.4g} s exceeds {MAX_LATENCY_S:g} s "
            f"(latencies are 0..{MAX_LATENCY_S:g} s)"
        )


def _protocol_value(key: str, value, where: str) -> None:
    """A protocol parameter of the type of RunConfig's field; integers at most MAX_PROTOCOL_VALUE (the lower
    bounds are RunConfig's own)."""
    default = getattr(RunConfig(), key)
    if isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int) or not -1 <= value <= MAX_PROTOCOL_VALUE:
            raise SpecError(f"{where}: expected an integer in -1..{MAX_PROTOCOL_VALUE}, got {value!r}")
    elif isinstance(default, str) and not isinstance(value, str):
        raise SpecError(f"{where}: expected a name, got {value!r}")


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
            raise SpecError(f"modes: unknown mode {mode!r}{did_you_mean(mode, MODES)}; known: {', '.join(MODES)}")
        params = params or {}
        if not isinstance(params, dict) or set(params) - set(PROTOCOL_KEYS):
            raise SpecError(f"modes.{mode}: expected a mapping with keys among {PROTOCOL_KEYS}, got {params!r}")
        keys = list(params)
        for k in keys:
            for value in _as_list(params[k], f"modes.{mode}.{k}"):
                _protocol_value(k, value, f"modes.{mode}.{k}")
        for values in itertools.product(*(_as_list(params[k], f"modes.{mode}.{k}") for k in keys)):
            out.append({"mode": mode, **dict(zip(keys, values))})
    return out


def expand_spec(raw: dict, *, default_name: str = "sweep") -> SweepSpec:
    """Validate a parsed spec and expand it to one RunConfig per episode (deterministic order)."""
    if not isinstance(raw, dict):
        raise SpecError(f"a sweep spec is a YAML mapping, got {type(raw).__name__}")
    unknown = set(raw) - SPEC_KEYS
    if unknown:
        raise SpecError(f"unknown key(s) {sorted(unknown, key=str)}{_key_hint(unknown)}; known: {sorted(SPEC_KEYS)}")
    total = count_episodes(raw)  # before anything is expanded: a spec of a few KB can multiply to 10^9
    if total > MAX_EPISODES:
        raise SpecError(
            f"the spec expands to {_count_text(total)} episodes; a sweep runs at most {MAX_EPISODES:,} "
            "(split it into several sweeps)"
        )
    name = _name(raw.get("name", default_name))
    transport = raw.get("transport")
    if transport is not None and transport not in TRANSPORTS:
        raise SpecError(f"transport: expected one of {TRANSPORTS}, got {transport!r}")
    timeout_s = raw.get("timeout_s")
    if timeout_s is not None:
        _number(timeout_s, "timeout_s", 0, MAX_TIMEOUT_S, lo_open=True)
    clock_and_robot = _clock_and_robot(raw, transport)
    configs: dict[str, RunConfig] = {}
    parts = _parts(raw)
    for i, part in enumerate(parts or [raw]):
        try:
            _expand_product(part, clock_and_robot, configs)
        except SpecError as exc:
            raise SpecError(f"parts[{i}]: {exc}" if parts else str(exc)) from exc
    try:  # the declared primary comparisons and equivalence margin (lq_ros/scoring/decisions.py)
        parse_analysis(raw.get("analysis"), policy_names=sorted({c.policy for c in configs.values()}))
    except PlanError as exc:
        raise SpecError(str(exc)) from None
    return SweepSpec(name, tuple(configs.values()), transport, timeout_s, raw)


def _expand_product(raw: dict, clock_and_robot: dict, configs: dict[str, RunConfig]) -> None:
    """Add one product's episodes to ``configs`` (key -> RunConfig, in order); refuse an episode already there."""
    seeds = _ints(raw.get("seeds", [7]), "seeds", 0, 2**31 - 1)
    common = {}
    for key, typ in (("camera_size", int), ("physics_rate", bool), ("max_steps", int), ("budgets", str)):
        if key in raw:
            if not isinstance(raw[key], typ) or (typ is int and isinstance(raw[key], bool)):
                raise SpecError(f"{key}: expected {typ.__name__}, got {raw[key]!r}")
            common[key] = raw[key]
    common.update(clock_and_robot)
    if not 0 <= common.get("max_steps", 0) <= MAX_STEPS:
        raise SpecError(f"max_steps: expected 0 (the suite's budget) or 1..{MAX_STEPS} ticks, got {raw['max_steps']}")
    if common.get("budgets", "paper") not in BUDGET_PRESETS:
        raise SpecError(f"budgets: expected one of {', '.join(BUDGET_PRESETS)}, got {raw['budgets']!r}")
    if not 0 <= common.get("camera_size", 0) <= MAX_CAMERA_SIZE_PX:
        raise SpecError(
            f"camera_size: expected 0 (the policy's) or 1..{MAX_CAMERA_SIZE_PX} px, got {raw['camera_size']}"
        )
    policies, latencies, modes, suites = _policies(raw), _latencies(raw), _modes(raw), _suites(raw)
    budgets = _budget_counts(raw)
    declared: dict[str, int] = {}
    for (policy, args), proto, latency, budget_counts, (suite, tasks, inits) in itertools.product(
        policies, modes, latencies, budgets, suites
    ):
        proto = _with_replan_steps(proto, policy, args, declared)
        for task, init, seed in itertools.product(tasks, inits, seeds):
            try:
                cfg = RunConfig(
                    suite=suite, task=task, init=init, seed=seed, policy=policy,
                    policy_args=dict(args), budget_counts=budget_counts, **latency, **proto, **common,
                )  # fmt: skip
            except (TypeError, ValueError) as exc:
                what = latency.get("latency_dist") or f"{latency['latency_s']} s"
                raise SpecError(f"{policy} {proto} latency {what}: {exc}") from exc
            if cfg.key() in configs:
                raise SpecError(f"the spec lists the same episode twice: {cfg.episode_name()}")
            configs[cfg.key()] = cfg


def _with_replan_steps(proto: dict, policy: str, args: dict, declared: dict[str, int]) -> dict:
    """A sync protocol's ``replan_steps``: the spec's (source ``flag``), else the policy's declared reference
    protocol's (source ``policy``; lq_ros.policies.declared_replan_steps, once per policy and arguments). A policy
    that cannot be made here keeps RunConfig's default: check_policies refuses it, in one line, before any run."""
    if proto["mode"] != "sync":
        return proto
    if "replan_steps" in proto:
        return {**proto, "replan_steps_source": "flag"}
    ident = json.dumps([policy, args], sort_keys=True, default=str)
    if ident not in declared:
        from lq_ros.policies import declared_replan_steps

        try:
            declared[ident] = declared_replan_steps(policy, dict(args))
        except Exception:  # noqa: BLE001 - check_policies names the problem
            declared[ident] = 0
    if not declared[ident]:
        return proto
    return {**proto, "replan_steps": declared[ident], "replan_steps_source": "policy"}


def _clock_and_robot(raw: dict, transport: str | None) -> dict:
    """``clock`` (lockstep or realtime) and ``robot`` (a robot YAML or a shipped name; needs realtime)."""
    out = {}
    clock = raw.get("clock", "lockstep")
    if clock not in CLOCKS:
        raise SpecError(f"clock: expected one of {', '.join(CLOCKS)}, got {clock!r}")
    if clock != "lockstep":
        if transport == "inprocess":
            raise SpecError("clock: realtime runs through ROS only (transport: ros)")
        out["clock"] = clock
    robot = raw.get("robot", "")
    if robot:
        if not isinstance(robot, str):
            raise SpecError(f"robot: expected a robot YAML or a shipped robot name, got {robot!r}")
        if clock != "realtime":
            raise SpecError("robot: a robot runs on wall-clock time: it needs clock: realtime")
        from lq_ros.robot.robot_config import load_robot_config

        try:
            load_robot_config(robot)
        except (OSError, ValueError) as exc:
            raise SpecError(f"robot: {exc}") from None
        out["robot"] = robot
    return out


def _budget_counts(raw: dict) -> list[str]:
    """``budget_counts``: one of BUDGET_COUNTS or a list of them (a list runs every cell under each budget)."""
    value = raw.get("budget_counts", "all")
    values = value if isinstance(value, list) else [value]
    if not values or any(v not in BUDGET_COUNTS for v in values) or len(set(values)) != len(values):
        raise SpecError(f"budget_counts: expected one of {', '.join(BUDGET_COUNTS)} or a list of them, got {value!r}")
    return values


def load_spec(path: Path) -> SweepSpec:
    """Read and expand a sweep spec file; SpecError names the file."""
    path = Path(path)
    try:
        # A regular file only, bounded; aliases, nesting, integer digits and lone surrogates bounded too
        # (lq_ros.core.safe_yaml), each refusal one line.
        raw = load_yaml(read_text_file(path, MAX_SPEC_BYTES, "spec"), str(path))
    except YamlRefused as exc:
        raise SpecError(str(exc)) from None
    try:
        return expand_spec(raw, default_name=path.stem)
    except SpecError as exc:
        raise SpecError(f"{path}: {exc}") from exc


def _check_seeds(configs: tuple[RunConfig, ...] | list[RunConfig]) -> None:
    """Refuse a second seed for a policy whose episodes do not depend on the seed (``Policy.seed_varies`` False,
    measured by benchmarks/seed_replication.py): the episode would repeat bit for bit and count one draw twice."""
    from lq_ros.run.validation import InputError, policy_class

    seeds: dict[str, set[int]] = {}
    for cfg in configs:
        seeds.setdefault(cfg.policy, set()).add(cfg.seed)
    for policy, values in seeds.items():
        if len(values) < 2:
            continue
        try:
            varies = getattr(policy_class(policy), "seed_varies", None)
        except InputError:
            continue  # refused with its own message by the policy checks
        if varies is False:
            raise SpecError(
                f"seeds: {sorted(values)} for policy {policy!r}, whose episodes do not depend on the seed "
                "(benchmarks/seed_replication.py): a second seed repeats the first episode and would count it "
                "twice; give one seed"
            )


def check_policies(configs: tuple[RunConfig, ...] | list[RunConfig]) -> None:
    """Check and build each distinct policy once, so bad policy arguments fail before any episode runs
    (lq_ros.run.validation: an argument the policy does not take or of the wrong type, a value it refuses)."""
    from lq_ros.run.validation import InputError, check_policy, policy_class

    seen, merges = set(), set()
    _check_seeds(configs)
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
        except Exception as exc:  # noqa: BLE001 - whatever a policy's check raises is a refusal, in one line
            raise SpecError(f"policies: policy {cfg.policy!r}: {type(exc).__name__}: {exc}") from None
