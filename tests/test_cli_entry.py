"""lq_ros/cli/application.py's ``entry`` (the ``lq`` command): the exit code and everything printed or registered to
run at exit survive leaving without the interpreter's teardown; a process that loaded ROS exits the normal way, with
it."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest


def run_entry(tmp_path, code: int, before: str = "") -> subprocess.CompletedProcess:
    marker, teardown = tmp_path / "atexit", tmp_path / "teardown"
    script = textwrap.dedent(
        f"""
        import atexit, sys
        {before}
        from lq_ros.cli import application as cli
        atexit.register(lambda: open({str(marker)!r}, "w").write("ran"))

        def main():
            print("row", flush=False)  # buffered: must still reach the pipe
            sys.stderr.write("note")
            return {code}

        cli.main = main
        try:
            cli.entry()
        except SystemExit:  # the normal exit (the interpreter's teardown follows); os._exit raises nothing
            open({str(teardown)!r}, "w").write("ran")
            raise
        print("never")
        """
    )
    return subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("code", [0, 1, 2])
def test_the_exit_code_output_and_exit_handlers_survive(tmp_path, code):
    proc = run_entry(tmp_path, code)
    assert (proc.returncode, proc.stdout, proc.stderr) == (code, "row\n", "note")
    assert (tmp_path / "atexit").read_text() == "ran"
    assert not (tmp_path / "teardown").exists(), "the teardown was skipped"


def test_a_process_that_loaded_ros_exits_the_normal_way(tmp_path):
    proc = run_entry(tmp_path, 3, before="import rclpy")
    assert (proc.returncode, proc.stdout) == (3, "row\n")
    assert (tmp_path / "atexit").read_text() == "ran"
    assert (tmp_path / "teardown").read_text() == "ran", "DDS's destructors must run: the normal exit"


LQ = Path(sys.executable).parent / "lq"  # the installed command: its own folder, not the current one, on sys.path
EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "my_policy.py"


@pytest.mark.sim
def test_a_policy_module_in_the_current_directory_is_importable(tmp_path):
    """``lq run --policy my_policy:MyPolicy`` from the folder that holds my_policy.py, as ``python -m`` would."""
    shutil.copy(EXAMPLE, tmp_path / "my_policy.py")
    args = [str(LQ), "run", "--policy", "my_policy:MyPolicy", "--policy-arg", "lift_m=0.1", "--transport",
            "inprocess", "--max-steps", "5", "--json", "--out", "bags"]  # fmt: skip
    proc = subprocess.run(args, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    row = json.loads(proc.stdout)  # stdout holds the row alone: LIBERO's start-up lines went to stderr
    assert row["status"] == "failure" and row["completion_steps"] == 5
    assert (tmp_path / "bags").is_dir()


def test_pythonsafepath_keeps_the_current_directory_out(tmp_path):
    shutil.copy(EXAMPLE, tmp_path / "my_policy.py")
    env = {**os.environ, "PYTHONSAFEPATH": "1"}
    proc = subprocess.run([str(LQ), "run", "--policy", "my_policy:MyPolicy", "--transport", "inprocess"], cwd=tmp_path,
                          env=env, capture_output=True, text=True, timeout=300)  # fmt: skip
    assert proc.returncode == 2 and "cannot import module 'my_policy'" in proc.stderr
    assert not (tmp_path / "bags").exists()
