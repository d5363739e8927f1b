"""lq_ros/cli.py's ``entry`` (the ``lq`` command): the exit code and everything printed or registered to run at
exit survive leaving without the interpreter's teardown; a process that loaded ROS exits the normal way, with it."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest


def run_entry(tmp_path, code: int, before: str = "") -> subprocess.CompletedProcess:
    marker, teardown = tmp_path / "atexit", tmp_path / "teardown"
    script = textwrap.dedent(
        f"""
        import atexit, sys
        {before}
        from lq_ros import cli
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
