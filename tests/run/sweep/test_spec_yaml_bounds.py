"""Sweep specs whose YAML costs more than it says: 2 KB of nested aliases (30 levels of 10 ran past a minute), an
alias inside its own anchor (a RecursionError traceback), a 5000-digit integer and a lone surrogate in ``name``
(tracebacks). Each is refused by ``lq sweep`` in one line with exit code 2, at once, writing nothing; anchors and
merge keys that stay small still work."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

from lq_ros.core.safe_yaml import MAX_DEPTH, MAX_VALUES, YamlRefused, load_yaml
from lq_ros.run import sweep as sw

BASE = """transport: inprocess
suite: libero_spatial
tasks: [0]
inits: [0]
latencies_s: [0.0]
modes: [sync]
max_steps: 4
"""


def alias_bomb(levels: int = 30, width: int = 10) -> str:
    lines = [f"    a0: &a0 [{', '.join(['x'] * width)}]"]
    lines += [f"    a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * width)}]" for i in range(1, levels)]
    return "name: bomb\npolicies:\n- name: sine\n  args:\n" + "\n".join(lines) + "\n"


CASES = {
    "alias bomb": (BASE + alias_bomb(), f"aliases expand to more than {MAX_VALUES} values"),
    "self-referencing alias": (BASE + "name: x\npolicies: &p\n  - *p\n", "alias *p inside its own anchor"),
    "self-referencing mapping": (BASE + "name: x\npolicies: [sine]\nseeds: &s {a: *s}\n", "alias *s inside its own"),
    "5000-digit integer": (BASE + "name: x\npolicies: [sine]\nseeds: [" + "9" * 5000 + "]\n", "integer of 5000 digits"),
    "lone surrogate in name": (BASE + 'name: "\\ud800"\npolicies: [sine]\n', "lone surrogate (line 8)"),
    "deep nesting": (BASE + "name: x\npolicies: [sine]\nseeds: " + "[" * 5000 + "]" * 5000 + "\n", "nested more than"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_costly_yaml_is_one_line_exit_2_at_once(tmp_path, case):
    text, says = CASES[case]
    spec = tmp_path / "spec.yaml"
    spec.write_text(text)
    started = time.monotonic()
    proc = subprocess.run(
        [sys.executable, "-m", "lq_ros.cli", "sweep", str(spec), "--out", str(tmp_path / "out"), "--workers", "1"],
        cwd=tmp_path, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert time.monotonic() - started < 30
    lines = [line for line in (proc.stdout + proc.stderr).splitlines() if line.strip()]
    assert proc.returncode == 2 and len(lines) == 1, (proc.returncode, lines[:20])
    assert lines[0].startswith("error: ") and str(spec) in lines[0] and says in lines[0], lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["spec.yaml"]  # nothing written


def test_small_anchors_and_merge_keys_still_work(tmp_path):
    spec = tmp_path / "spec.yaml"
    spec.write_text(
        BASE
        + "name: anchors\npolicies: [&sine {name: sine, args: {amplitude: 0.1}}, {<<: *sine, args: {amplitude: 0.2}}]\n"
    )
    loaded = sw.load_spec(spec)
    assert sorted(c.policy_args["amplitude"] for c in loaded.configs) == [0.1, 0.2]


def test_bounds_are_counted_on_the_graph_not_by_expanding():
    started = time.monotonic()
    with pytest.raises(YamlRefused, match="aliases expand"):
        load_yaml(alias_bomb(levels=200, width=50), "big.yaml")
    assert time.monotonic() - started < 1.0
    assert load_yaml("a: " + "[" * (MAX_DEPTH - 1) + "]" * (MAX_DEPTH - 1), "x")  # the limit itself is fine
    wide = "[" + ", ".join(["x"] * 1000) + "]"
    assert len(load_yaml(f"a: &a {wide}\nb: [*a, *a, *a]", "x")["b"]) == 3  # 4,000 values: well within


def test_a_spec_path_is_read_as_a_regular_file_only(tmp_path):
    with pytest.raises(sw.SpecError, match="not a regular file"):
        sw.load_spec(Path("/dev/zero"))
