"""Concurrent use and numbers at the command line: one line and exit code 2, never a traceback.

- two ``lq run`` of one configuration into one ``--out`` (a FileExistsError traceback): the second is refused;
- a ``--domain-id`` another run holds (a RuntimeError traceback): refused;
- ``--latency 1e308`` (OverflowError), ``1e300`` (accepted, then "File name too long"), an ``empirical:`` file
  holding 1e308, a ``--policy-arg`` of 5000 digits or nested 20,000 deep: each one line.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from lq_ros.core.run_config import RunConfig
from lq_ros.transport.processes import claimed

REPO = Path(__file__).resolve().parents[1]


def lq(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "lq_ros.cli", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout)  # fmt: skip


def refused(result: subprocess.CompletedProcess, *expected: str) -> str:
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1, (result.returncode, result.stderr[-3000:])
    assert "Traceback" not in result.stdout + result.stderr
    for piece in expected:
        assert piece in lines[0], (piece, lines[0])
    return lines[0]


def test_a_second_run_into_the_same_bag_folder_is_refused(tmp_path):
    out = tmp_path / "out"
    bag = out / RunConfig(max_steps=2).episode_name()
    with claimed(bag, "bag folder"):  # what the first `lq run` holds while its episode runs
        result = lq("run", "--transport", "inprocess", "--max-steps", "2", "--out", str(out))
    refused(result, f"bag folder {bag} is being written by another run now")
    assert not out.exists() or not any(out.iterdir())  # nothing started


@pytest.mark.ros
def test_a_domain_id_another_run_holds_is_refused(tmp_path):
    from lq_ros.transport.ros.stack import reserved_domain

    with reserved_domain() as held:
        result = lq(
            "run", "--transport", "ros", "--domain-id", str(held.id), "--max-steps", "2", "--out", str(tmp_path)
        )
    refused(result, f"no free ROS domain id among [{held.id}]")


@pytest.mark.parametrize(
    "latency, says",
    [
        ("1e308", "the constant latency 1e+308 is outside 0..10 s"),
        ("1e300", "the constant latency 1e+300 is outside 0..10 s"),
        ("uniform:0:1e308", "a parameter 1e+308 is outside 0..10 s"),
        ("inf", "must be finite"),
    ],
)
@pytest.mark.parametrize("rounding", ["exact", "nearest"])
def test_huge_latencies_are_one_line(tmp_path, latency, says, rounding):
    result = lq("run", "--transport", "inprocess", "--latency", latency, "--latency-rounding", rounding,
                "--out", str(tmp_path / "out"))  # fmt: skip
    refused(result, says)
    assert not (tmp_path / "out").exists()


def test_an_empirical_file_of_1e308_is_one_line(tmp_path):
    delays = tmp_path / "delays.txt"
    delays.write_text("0.1\n1e308\n")
    refused(lq("run", "--transport", "inprocess", "--latency", f"empirical:{delays}", "--out", str(tmp_path / "o")),
            "line 2: '1e308' is not a latency in 0..10 s")  # fmt: skip


@pytest.mark.parametrize("value", ["9" * 5000, "[" * 20_000 + "]" * 20_000])
def test_policy_arguments_that_json_cannot_hold_are_one_line(tmp_path, value):
    refused(lq("run", "--transport", "inprocess", "--policy", "sine", "--policy-arg", f"amplitude={value}",
               "--out", str(tmp_path / "o")), "amplitude")  # fmt: skip
