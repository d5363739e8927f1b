"""``lq collect``: a bad --noise, task or init state is one line naming the value and what is valid, before any
episode runs (no traceback, no "unexpected" bug line)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.test_cli_errors import assert_refused

REPO = Path(__file__).resolve().parents[2]


def lq(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "lq_ros.cli", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=300, env=os.environ | {"PYTHONPATH": str(REPO)})  # fmt: skip


@pytest.mark.parametrize(
    ("noise", "named"),
    [("abc", "'abc' is not a noise std"), ("0,-1", "'-1' (in '0,-1') is not a noise std"),
     ("0,,0.1", "'' (in '0,,0.1') is not a noise std"), ("nan", "'nan' is not a noise std"),
     ("٠.١", "'٠.١' is not a noise std")],
)  # fmt: skip
def test_a_bad_noise_level_is_one_line_with_the_valid_values(tmp_path, noise, named):
    result = lq("collect", "--out", str(tmp_path / "d"), "--noise", noise)
    assert_refused(result, "--noise", named, "numbers >= 0 separated by commas", "'0,0.1,0.2'")
    assert not (tmp_path / "d").exists()


def test_a_task_or_init_state_out_of_range_is_one_line(tmp_path):
    assert_refused(lq("collect", "--out", str(tmp_path / "d"), "--tasks", "12"),
                   "task 12 is out of range: libero_spatial has tasks 0..9")  # fmt: skip
    assert_refused(lq("collect", "--out", str(tmp_path / "d"), "--inits", "60"),
                   "init state 60 is out of range", "0..49")  # fmt: skip


@pytest.mark.slow
def test_a_collection_that_keeps_no_episode_is_one_line_and_writes_nothing(tmp_path):
    """Two ticks are no demonstration: nothing succeeds, so nothing is written (an outcome, not a bug line)."""
    out = tmp_path / "d"
    result = lq("collect", "--out", str(out), "--tasks", "0", "--inits", "10", "--max-steps", "2", "--workers", "1")
    assert result.returncode == 1, result.stderr
    last = result.stderr.strip().splitlines()[-1]  # (each episode's progress line, then the error)
    assert last == (f"error: no episodes to write (no successful demonstration was collected): nothing written to "
                    f"{out}; more --repeats, other --tasks or less --noise"), result.stderr  # fmt: skip
    assert "Traceback" not in result.stderr and "unexpected" not in result.stderr
    assert not (out / "meta").exists() and not (out / "data").exists()
