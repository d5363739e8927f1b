"""The ROS package's manifests: package.xml declares every ROS package the code uses, and a colcon-style install
puts the programs where ``ros2 run lq_ros <program>`` looks (``<prefix>/lib/lq_ros``, setup.cfg)."""

from __future__ import annotations

import ast
import configparser
import os
import re
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
#: Where the ROS code lives: the package and the node programs.
SOURCES = (REPO / "lq_ros", REPO / "nodes")
#: A ROS interface type named in code: "sensor_msgs/msg/JointState" (rosbags' typestore, rclpy_helpers.msg_class).
TYPE_NAME = re.compile(r"[\"']([a-z][a-z0-9_]*)/(?:msg|srv|action)/[A-Z]\w*[\"']")
#: package.xml elements that declare a dependency the installed package needs.
RUN_DEPENDS = ("depend", "exec_depend")


def ament_packages() -> set[str]:
    """The ROS packages installed in this environment (the ament resource index the ROS wheels install)."""
    index = Path(sys.prefix) / "share" / "ament_index" / "resource_index" / "packages"
    return {p.name for p in index.iterdir()}


def used_ros_packages() -> dict[str, set[str]]:
    """ROS package -> the files that import it or name one of its types."""
    ros = ament_packages()
    used: dict[str, set[str]] = {}
    for root in SOURCES:
        for path in root.rglob("*.py"):
            text = path.read_text()
            names = {m.group(1) for m in TYPE_NAME.finditer(text)}
            for node in ast.walk(ast.parse(text)):
                if isinstance(node, ast.Import):
                    names |= {a.name.split(".")[0] for a in node.names}
                elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                    names.add(node.module.split(".")[0])
            for name in names & (ros | {m.group(1) for m in TYPE_NAME.finditer(text)}):
                used.setdefault(name, set()).add(str(path.relative_to(REPO)))
    used.pop("lq_ros", None)  # the package itself
    return used


def declared(manifest: Path = REPO / "package.xml") -> set[str]:
    root = ET.parse(manifest).getroot()
    return {e.text.strip() for tag in RUN_DEPENDS for e in root.iter(tag) if e.text}


def test_package_xml_declares_every_ros_package_the_code_uses():
    assert {"rclpy", "lifecycle_msgs", "rcl_interfaces", "std_msgs"} <= ament_packages()  # the index was read
    used = used_ros_packages()
    assert {"rclpy", "lifecycle_msgs", "rcl_interfaces", "lq_msgs", "sensor_msgs"} <= set(used)  # the code was read
    missing = {name: sorted(files)[:3] for name, files in used.items() if name not in declared()}
    assert missing == {}, f"package.xml lacks <exec_depend> for {missing}"


def test_the_check_finds_an_undeclared_package(tmp_path):
    manifest = tmp_path / "package.xml"
    manifest.write_text((REPO / "package.xml").read_text().replace("<exec_depend>lifecycle_msgs</exec_depend>", ""))
    assert "lifecycle_msgs" in used_ros_packages() and "lifecycle_msgs" not in declared(manifest)


def test_setup_cfg_sends_the_programs_to_lib_of_the_package():
    cfg = configparser.ConfigParser()
    cfg.read(REPO / "setup.cfg")
    assert cfg["develop"]["script_dir"] == cfg["install"]["install_scripts"] == "$base/lib/lq_ros"


@pytest.mark.slow
def test_a_colcon_style_install_puts_every_program_where_ros2_run_looks(tmp_path):
    """What colcon's ament_python build runs (``setup.py install --prefix ... --single-version-externally-managed``),
    from a copy of the source: every console script lands in <prefix>/lib/lq_ros, the package in the ament index."""
    src, prefix = tmp_path / "src", tmp_path / "install"
    shutil.copytree(REPO, src, ignore=shutil.ignore_patterns(".*", "build", "bags", "__pycache__", "*.egg-info"))
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    result = subprocess.run(
        [sys.executable, "setup.py", "-q", "install", "--prefix", str(prefix), "--single-version-externally-managed",
         "--record", str(tmp_path / "record.txt")],
        cwd=src, env=env, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    setup_text = (REPO / "setup.py").read_text()
    programs = re.findall(r'"(\w+) = [\w.]+:\w+"', setup_text)
    assert {"lq", "sim_node", "policy_node", "executor_node", "metrics_node", "manager_node"} <= set(programs)
    for program in programs:
        script = prefix / "lib" / "lq_ros" / program
        assert script.is_file() and os.access(script, os.X_OK), program
        assert not (prefix / "bin" / program).exists(), program
    assert (prefix / "share" / "ament_index" / "resource_index" / "packages" / "lq_ros").is_file()
    assert (prefix / "share" / "lq_ros" / "package.xml").is_file()
