"""``lq plan`` as a user runs it: the reference sample sizes, the clustered plan and its assumptions, and a bad value
refused in one line."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def lq_plan(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "lq_ros.cli", "plan", *args], cwd=REPO, capture_output=True,
                          text=True, timeout=120)  # fmt: skip


def test_the_reference_plan_and_a_clustered_one():
    result = lq_plan("--effect", "0.10", "--baseline", "0.5")
    assert result.returncode == 0, result.stderr
    out = result.stdout
    assert "388 independent episodes per arm" in out
    assert "discordance 0.2: 155 independent pairs" in out
    assert "discordance 0.5: 391 independent pairs" in out  # arms independent of each other: little gain
    assert "Assumptions:" in out and "episodes independent" in out
    result = lq_plan("--effect", "0.10", "--baseline", "0.5", "--inits", "10", "--icc", "0.1", "--tasks", "10",
                     "--discordance", "0.2")  # fmt: skip
    assert result.returncode == 0, result.stderr
    out = result.stdout
    assert "74 tasks x 10 = 740 episodes per arm with 10 episodes per task at ICC 0.1 (design effect 1.90)" in out
    assert "30 tasks x 10 = 300 episodes per arm at ICC 0.1 (design effect 1.90)" in out
    assert "Power at 10 tasks x 10 episodes per arm (100 per arm):" in out
    assert "design effect 1 + (m - 1) ICC" in out


def test_a_bad_value_is_one_line():
    result = lq_plan("--effect", "0.1", "--baseline", "0.95")
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1 and "Traceback" not in result.stderr
    assert "baseline + effect in (0, 1)" in lines[0] and "0.95 + 0.1" in lines[0]
    result = lq_plan("--effect", "0.1", "--baseline", "0.5", "--discordance", "0.05")
    assert result.returncode == 2 and "discordance must be above |effect| = 0.1" in result.stderr
