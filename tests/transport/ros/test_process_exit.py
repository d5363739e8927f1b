"""lq_ros.transport.processes.exit_uncollected, the node programs' exit: without the teardown's garbage collections,
a process that still runs a ROS node removes its own Fast DDS shared-memory files as it leaves (rclpy's exit
handler and Fast DDS's destructors still run), runs its other exit handlers, flushes what it printed and keeps its
exit code."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest

from lq_ros.transport.processes import SHM_DIR
from lq_ros.transport.ros.stack import child_environment, reserved_domain

NODE_THEN_EXIT = textwrap.dedent(
    """
    import atexit, json, os, sys
    import rclpy
    from std_msgs.msg import String
    from lq_ros.transport.processes import exit_uncollected, fastdds_shm_owned

    marker, owned_file = sys.argv[1], sys.argv[2]
    rclpy.init()
    node = rclpy.create_node("exit_probe")
    node.create_publisher(String, "/exit_probe", 10).publish(String(data="x"))
    cycle = [node]  # a reference cycle reaching a live node: frozen, never collected
    cycle.append(cycle)
    with open(owned_file, "w") as f:
        json.dump(sorted(fastdds_shm_owned(os.getpid())), f)
    # ROS is not shut down here: the exit must do it (with os._exit instead, the files stay and this test fails).
    atexit.register(lambda: open(marker, "w").write("ran"))
    print("row", flush=False)  # buffered: must still reach the pipe
    exit_uncollected(4)
    """
)


@pytest.mark.serial  # a Fast DDS port file the probe used may be another run's too (the same port number)
def test_a_node_process_leaves_no_shm_file_and_keeps_its_output_and_exit_code(tmp_path):
    marker, owned_file = tmp_path / "atexit", tmp_path / "owned.json"
    with reserved_domain() as domain:
        env = child_environment(domain.id, tmp_path / "ros_logs")
        proc = subprocess.run(
            [sys.executable, "-c", NODE_THEN_EXIT, str(marker), str(owned_file)],
            env=env, capture_output=True, text=True, timeout=120,
        )  # fmt: skip
    assert (proc.returncode, proc.stdout) == (4, "row\n"), proc.stderr
    assert marker.read_text() == "ran"
    owned = json.loads(owned_file.read_text())
    assert owned, "the probe owned no Fast DDS file: nothing was checked"
    left = [name for name in owned if os.path.exists(f"{SHM_DIR}/{name}") or os.path.exists(f"{SHM_DIR}/{name}_el")]
    assert left == [], f"Fast DDS files the exited process left: {left}"
