"""``lq run``: the table says where the run folder is and what its less obvious columns mean; the ROS domain is
--domain-id, else an exported ROS_DOMAIN_ID (ROS tools see the nodes), else a free one, and is printed."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from lq_ros.transport.ros.stack import reserved_domain
from tests.test_cli_errors import assert_refused

REPO = Path(__file__).resolve().parents[2]


def lq_env(*args: str, **env: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "lq_ros.cli", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=600, env=os.environ | env)  # fmt: skip


def test_version_names_the_package_version_and_commit():
    import lq_ros

    result = lq_env("--version")
    want = rf"lq {re.escape(lq_ros.__version__)} \(commit \S+\)\n"
    assert result.returncode == 0 and re.fullmatch(want, result.stdout), result


@pytest.mark.sim
def test_the_table_says_where_the_run_folder_is_and_what_budget_and_switch_step_are(tmp_path):
    result = lq_env("run", "--policy", "sine", "--max-steps", "5", "--transport", "inprocess", "--out", str(tmp_path))
    assert result.returncode == 0, result.stderr[-2000:]
    text = " ".join(result.stdout.replace("│", " ").split())
    assert f"run folder: {tmp_path}/" in text and "see the run folder" not in text
    assert "budget: what the tick budget counts" in text and "switch step: mean executed step" in text


def test_an_exported_domain_held_by_another_run_is_refused_in_one_line(tmp_path):
    with reserved_domain() as held:
        result = lq_env("run", "--policy", "sine", "--max-steps", "5", "--out", str(tmp_path),
                        ROS_DOMAIN_ID=str(held.id))  # fmt: skip
    assert_refused(result, f"among [{held.id}]")


def test_a_bad_exported_domain_is_one_line(tmp_path):
    result = lq_env("run", "--policy", "sine", "--out", str(tmp_path), ROS_DOMAIN_ID="lab")
    assert_refused(result, "ROS_DOMAIN_ID='lab' is not a ROS domain id")
    ok = lq_env("run", "--policy", "sine", "--max-steps", "5", "--transport", "inprocess", "--out", str(tmp_path),
                ROS_DOMAIN_ID="lab")  # fmt: skip
    assert ok.returncode == 0, ok.stderr[-2000:]  # (in process: no ROS, the variable is not read)


@pytest.mark.slow
@pytest.mark.sim
def test_the_nodes_run_in_the_exported_domain(tmp_path):
    with reserved_domain() as free:
        domain = free.id  # free now; released for the run
    result = lq_env("run", "--policy", "sine", "--max-steps", "5", "--out", str(tmp_path), ROS_DOMAIN_ID=str(domain))
    assert result.returncode == 0, result.stderr[-3000:]
    assert f"ROS_DOMAIN_ID={domain} (ROS_DOMAIN_ID)" in result.stderr.splitlines()
    free = lq_env("run", "--policy", "sine", "--max-steps", "5", "--out", str(tmp_path / "b"), ROS_DOMAIN_ID="")
    assert re.search(r"^ROS_DOMAIN_ID=\d+ \(a free one\)$", free.stderr, re.M), free.stderr[-3000:]
