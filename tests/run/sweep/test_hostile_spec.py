"""Hostile sweep specs and a busy sweep folder: every mistake is one line and exit code 2, in bounded time,
with nothing written anywhere; a second ``lq sweep`` on a folder in use is refused and the first is untouched."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from lq_ros.run import sweep as sw
from lq_ros.run.sweep.spec import MAX_EPISODES

REPO = Path(__file__).resolve().parents[3]
BASE = {
    "transport": "inprocess", "suite": "libero_spatial", "tasks": [0], "inits": [0], "policies": ["sine"],
    "latencies_s": [0.0], "modes": ["sync"], "max_steps": 4,
}  # fmt: skip
#: 1000 seeds x 50 inits x 10 tasks x 20 latencies x 100 replan_steps = 10^9 episodes in about 7 KB of YAML.
HUGE = BASE | {
    "seeds": list(range(1000)),
    "inits": list(range(50)),
    "tasks": list(range(10)),
    "latencies_s": [round(0.05 * i, 2) for i in range(20)],
    "modes": {"sync": {"replan_steps": list(range(1, 101))}},
}


def _files(tmp: Path) -> dict[str, bytes | None]:
    """Every file and folder under ``tmp`` (contents of the regular files)."""
    out = {}
    for p in sorted(tmp.rglob("*")):
        out[str(p.relative_to(tmp))] = p.read_bytes() if p.is_file() and not p.is_fifo() else None
    return out


def _make(tmp: Path, case: str) -> Path:
    """Write the spec of ``case`` (and what it points at) into ``tmp``; returns the spec path."""
    spec = tmp / "spec.yaml"
    binary = tmp / "binary.trace"
    binary.write_bytes(bytes(range(256)) * 8)  # not text (invalid UTF-8, NUL bytes): /bin/ls alike
    big = tmp / "big.trace"
    big.write_text("0.1\n" * 300_000)  # 1.2 MB of valid numbers: over the cap
    far = tmp / "far.trace"
    far.write_text("0.1\n1e300\n")
    fields = {
        "huge": HUGE,
        "name_dotdot": {"name": ".."},
        "name_dot": {"name": "."},
        "name_slash": {"name": "../../escape"},
        "name_nul": {"name": "a\0b"},
        "name_long": {"name": "x" * 300},
        "timeout_nan": {"timeout_s": float("nan")},
        "timeout_inf": {"timeout_s": float("inf")},
        "timeout_bool": {"timeout_s": True},
        "timeout_negative": {"timeout_s": -5},
        "trace_dev_zero": {"latencies_s": ["trace:/dev/zero"]},
        "trace_binary": {"latencies_s": [f"trace:{binary}"]},
        "trace_dir": {"latencies_s": [f"trace:{tmp}"]},
        "trace_big": {"latencies_s": [f"trace:{big}"]},
        "trace_far": {"latencies_s": [f"trace:{far}"]},
        "camera_float": {"camera_size": 1e9},
        "camera_int": {"camera_size": 10**9},
        "camera_2000": {"camera_size": 2000},
        "latency_1e300": {"latencies_s": [1e300]},
        "latency_nan": {"latencies_s": [float("nan")]},
        "latency_11": {"latencies_s": [11.0]},
        "uniform_far": {"latencies_s": ["uniform:0:1e300"]},
        "lognormal_heavy": {"latencies_s": ["lognormal:10:10"]},
        "too_many_latencies": {"latencies_s": [f"uniform:0:{i / 1000}" for i in range(1, 300)]},
        "policy_not_a_policy": {"policies": ["collections:OrderedDict"]},
        "policy_path": {"policies": ["../../etc:passwd"]},
        "policy_nan_arg": {"policies": [{"name": "sine", "args": {"amplitude": float("nan")}}]},
        "replan_nan": {"modes": {"sync": {"replan_steps": float("nan")}}},
        "replan_huge": {"modes": {"sync": {"replan_steps": 10**9}}},
        "max_steps_huge": {"max_steps": 10**12},
        "mixed_unknown_keys": {1: 2, "bogus": 3},
    }
    if case == "fifo_spec":
        spec = tmp / "spec.fifo"
        os.mkfifo(spec)
    elif case == "binary_spec":
        spec.write_bytes(b"name: \xff\xfe\n")
    elif case == "deep_yaml":
        spec.write_text("a: " + "[" * 50_000 + "]" * 50_000 + "\n")
    else:
        spec.write_text(yaml.safe_dump(BASE | fields[case], allow_unicode=True, sort_keys=False))
    return spec


CASES = [
    "huge", "name_dotdot", "name_dot", "name_slash", "name_nul", "name_long", "timeout_nan", "timeout_inf",
    "timeout_bool", "timeout_negative", "trace_dev_zero", "trace_binary", "trace_dir", "trace_big", "trace_far",
    "camera_float", "camera_int", "camera_2000", "latency_1e300", "latency_nan", "latency_11", "uniform_far",
    "lognormal_heavy", "too_many_latencies", "policy_not_a_policy", "policy_path", "policy_nan_arg", "replan_nan",
    "replan_huge", "max_steps_huge", "mixed_unknown_keys", "fifo_spec", "binary_spec", "deep_yaml",
]  # fmt: skip


@pytest.mark.parametrize("case", CASES)
def test_hostile_spec_is_one_line_exit_2_and_writes_nothing(tmp_path, case):
    spec = _make(tmp_path, case)
    before = _files(tmp_path)
    out = tmp_path / "out"
    proc = subprocess.run(
        [sys.executable, "-m", "lq_ros.cli", "sweep", str(spec), "--out", str(out), "--workers", "1"],
        cwd=tmp_path, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    lines = [line for line in (proc.stdout + proc.stderr).splitlines() if line.strip()]
    assert proc.returncode == 2, (case, proc.stdout[-2000:], proc.stderr[-2000:])
    assert len(lines) == 1 and lines[0].startswith("error: "), (case, lines[:20])
    assert "Traceback" not in lines[0] and str(spec) in lines[0]
    assert _files(tmp_path) == before  # no --out folder, no default bags/sweeps/<name>, nothing else


def test_a_billion_episode_spec_is_refused_by_counting_not_expanding():
    start = time.perf_counter()
    with pytest.raises(sw.SpecError, match=r"expands to 1,000,000,000 episodes; a sweep runs at most 100,000"):
        sw.expand_spec(HUGE)
    assert time.perf_counter() - start < 0.5  # enumerating it took hours
    assert sw.spec.count_episodes(HUGE) == 10**9
    # The count is the expansion's length: at the limit a spec is accepted and counted exactly.
    ok = BASE | {"seeds": list(range(5)), "latencies_s": [0.0, 0.05], "modes": {"sync": {"replan_steps": [1, 2]}}}
    assert sw.spec.count_episodes(ok) == len(sw.expand_spec(ok).configs) == 20 <= MAX_EPISODES


def test_bounded_values_inside_the_limits_still_pass(tmp_path):
    trace = tmp_path / "server.trace"
    trace.write_text("# delays\n0.1\n0.25\n")
    spec = sw.expand_spec(
        BASE
        | {
            "name": "ok-name_1.v2",
            "timeout_s": 600,
            "camera_size": 1024,
            "latencies_s": [10.0, f"trace:{trace}", "lognormal:0.2:0.5"],
            "modes": {"sync": {"replan_steps": [5, 8]}},
        }
    )
    assert spec.name == "ok-name_1.v2" and len(spec.configs) == 6


# -- one sweep per folder --------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.sim
def test_second_sweep_on_a_busy_folder_is_refused_and_the_first_runs_intact(tmp_path):
    first_spec = tmp_path / "first.yaml"
    first_spec.write_text(yaml.safe_dump(BASE | {"name": "first", "latencies_s": [0.0, 0.1], "max_steps": 6}))
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "lq_ros.cli", "sweep", str(first_spec), "--out", str(out), "--workers", "1"]
    log = open(tmp_path / "first.log", "wb")  # noqa: SIM115 - closed below
    first = subprocess.Popen(cmd, cwd=REPO, stdout=log, stderr=subprocess.STDOUT)
    try:
        # The first holds the folder once it has written its manifest (under the lock).
        deadline = time.monotonic() + 120
        while not (out / "manifest.json").exists():
            assert first.poll() is None and time.monotonic() < deadline, (tmp_path / "first.log").read_text()
            time.sleep(0.05)
        assert first.poll() is None, "the first sweep ended before the second could be started: make it longer"
        start = time.monotonic()
        second = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=120)
        refused_in = time.monotonic() - start
        still_running = first.poll() is None
        first.wait(timeout=300)
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()
        log.close()
    lines = [line for line in (second.stdout + second.stderr).splitlines() if line.strip()]
    assert second.returncode == 2 and len(lines) == 1, lines
    assert str(out) in lines[0] and "another lq sweep is running on this folder" in lines[0]
    assert f"pid {first.pid}" in lines[0]
    assert still_running and refused_in < 30  # refused at once (interpreter start-up), not after waiting
    assert first.returncode == 0, (tmp_path / "first.log").read_text()[-3000:]
    # The first's results are whole: both episodes finished, their bags in place, nothing moved to attempts/.
    store = sw.ResultStore(out)
    records = store.records()
    assert len(records) == 2 and all(r["status"] == "failure" and len(r["attempts"]) == 1 for r in records)
    assert not any(store.attempts.iterdir())
    # The lock dies with its holder: the folder is free again (a resumed sweep skips both episodes).
    again = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0 and "2 skipped" in again.stderr + again.stdout, again.stderr[-2000:]
