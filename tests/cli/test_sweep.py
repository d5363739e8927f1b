"""``lq eval`` / ``lq sweep`` on the console: results of other code refused (``--overwrite`` replaces them), a line
per episode whose chunks were rejected, and Ctrl-C as one line saying how to resume."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from lq_ros.cli.sweep import INTERRUPTED

REPO = Path(__file__).resolve().parents[2]

POLICY = """
import numpy as np

from lq_ros.policies.base import Policy


class Mine(Policy):
    name = "mine"

    def __init__(self, gain: float = {gain}) -> None:
        self.gain, self.requests = gain, 0

    def reset(self, task, seed) -> None:
        self.requests = 0

    def infer(self, obs):
        self.requests += 1
        chunk = np.zeros((4, 7))
        chunk[:, 0], chunk[:, 6] = self.gain, -1.0
        if self.requests == 2:
            chunk[1, 2] = np.nan  # a bad chunk: the executor rejects it and holds
        return chunk
"""


def lq_in(folder: Path, *args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    """``lq ARGS`` run from ``folder`` (its modules importable, as for a user's own policy)."""
    env = os.environ | {"PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, "-m", "lq_ros.cli", *args], cwd=folder, capture_output=True, text=True,
                          timeout=timeout, env=env)  # fmt: skip


EVAL = ("eval", "--policy", "mine_policy:Mine", "--tasks", "0", "--inits", "0", "--latencies", "0", "--modes", "sync",
        "--max-steps", "20", "--workers", "1", "--out", "out")  # fmt: skip


@pytest.mark.slow
@pytest.mark.sim
def test_an_edited_policy_is_refused_on_resume_and_overwrite_reruns(tmp_path):
    (tmp_path / "mine_policy.py").write_text(textwrap.dedent(POLICY.format(gain=0.1)))
    first = lq_in(tmp_path, *EVAL)
    assert first.returncode == 0, first.stderr[-3000:]
    warning = [line for line in first.stderr.splitlines() if line.startswith("warning")]
    assert len(warning) == 1 and "1 chunk rejected, the robot held instead (first: " in warning[0], first.stderr
    # Another commit of the same code (e.g. a docs-only commit) resumes: the commit is provenance, not identity.
    (record,) = (tmp_path / "out" / "results").glob("*.json")
    made = json.loads(record.read_text())
    made["code"]["git_commit"] = "0" * 40
    record.write_text(json.dumps(made))
    resumed = lq_in(tmp_path, *EVAL)
    assert resumed.returncode == 0 and "1 of 1 episodes already finished" in resumed.stderr, resumed.stderr[-3000:]
    (tmp_path / "mine_policy.py").write_text(textwrap.dedent(POLICY.format(gain=0.3)))  # a default changed
    refused = lq_in(tmp_path, *EVAL)
    lines = refused.stderr.strip().splitlines()
    assert refused.returncode == 2 and "Traceback" not in refused.stderr, refused.stderr[-3000:]
    assert "1 of its 1 finished episodes were made by other code" in lines[-1]
    assert "the source of mine_policy:Mine changed" in lines[-1] and "policy_args.gain 0.1 -> 0.3" in lines[-1]
    again = lq_in(tmp_path, *EVAL, "--overwrite")
    assert again.returncode == 0 and "already finished" not in again.stderr, again.stderr[-3000:]


@pytest.mark.slow
@pytest.mark.sim
def test_ctrl_c_is_one_line_saying_how_to_resume(tmp_path):
    (tmp_path / "mine_policy.py").write_text(textwrap.dedent(POLICY.format(gain=0.1)))
    env = os.environ | {"PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    args = ["eval", "--policy", "mine_policy:Mine", "--tasks", "0", "--inits", "0-9", "--latencies", "0", "--modes",
            "sync", "--max-steps", "300", "--workers", "1", "--out", "out"]  # fmt: skip
    proc = subprocess.Popen([sys.executable, "-m", "lq_ros.cli", *args], cwd=tmp_path, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)  # fmt: skip
    deadline = time.monotonic() + 120
    # Once the first of the 10 episodes has its result, the others are still to run (an episode's log file is no
    # such sign: seen only as the last episodes ran, the interrupt then came after the evaluation had ended).
    while not list((tmp_path / "out" / "results").glob("*.json")) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert proc.poll() is None, "the evaluation ended before it could be interrupted"
    os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C in a terminal: the whole process group
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130, stderr[-3000:]
    assert "Traceback" not in stderr and stderr.strip().splitlines()[-1] == INTERRUPTED, stderr[-3000:]
