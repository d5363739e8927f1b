"""A built wheel, installed without the source tree, runs and scores episodes from anywhere.

The wheel is built from a copy of the source tree and installed (not editable) into a venv outside the checkout;
every command runs from a folder outside the checkout, so the message definitions and robot configurations can
only come from the installed package (lq_ros.core.shipped).

The venv's third-party packages are those of the project's own venv (``make setup``), as hard links: installing
requirements.lock afresh would fetch and unpack some 3.8 GB (torch, MuJoCo, LIBERO's assets, the ROS wheels), far
more than a test can take. It is still a venv of its own (its own prefix, site-packages and bin/), the checkout's
editable lq_ros is removed from it, and the wheel is installed with pip.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from lq_ros.core.shipped import SHIPPED

pytestmark = [pytest.mark.slow, pytest.mark.sim, pytest.mark.ros]

REPO = Path(__file__).resolve().parents[1]
#: Not part of the package (or built from it): left out of the copy the wheel is built from. ".*" covers the
#: venvs (``.venv``, ``.venv-lerobot``: some 14 GB), ``.git`` and the tool caches.
NOT_SOURCE = (".*", "build", "bags", "__pycache__", "*.egg-info", "dist")
RUN = ("--policy", "sine", "--max-steps", "10")


def run(*argv, cwd: Path, env: dict, timeout: float = 300) -> subprocess.CompletedProcess:
    result = subprocess.run([str(a) for a in argv], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert result.returncode == 0, (argv, result.stdout[-2000:], result.stderr[-3000:])
    return result


def scored(lq: Path, folder: str, cwd: Path, env: dict) -> list[dict]:
    """``lq score FOLDER --json``: one JSON row per episode."""
    out = run(lq, "score", folder, "--json", cwd=cwd, env=env).stdout
    return [json.loads(line) for line in out.splitlines() if line.startswith("{")]


def clone_venv(src: Path, dest: Path) -> None:
    """A venv at ``dest`` holding ``src``'s packages and libraries (hard links; a copy across file systems).

    ``src`` is resolved first: a venv that is a link (``.venv -> elsewhere``) would otherwise be copied as the
    link, and removing the copy's ``bin`` below would remove the real venv's."""
    src = Path(src).resolve()
    if subprocess.run(["cp", "-al", src, dest], capture_output=True).returncode != 0:
        shutil.rmtree(dest, ignore_errors=True)
        subprocess.run(["cp", "-a", src, dest], check=True)
    shutil.rmtree(dest / "bin")  # its scripts point at src's interpreter
    (dest / "pyvenv.cfg").unlink()
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", dest], check=True)


def test_installed_wheel_scores_and_runs_outside_the_checkout(tmp_path):
    assert sys.prefix != sys.base_prefix, "run inside the project's venv (make setup)"
    assert not tmp_path.is_relative_to(REPO), "the test must run outside the checkout"

    src, dist, venv, elsewhere = tmp_path / "src", tmp_path / "dist", tmp_path / "venv", tmp_path / "elsewhere"
    shutil.copytree(REPO, src, ignore=shutil.ignore_patterns(*NOT_SOURCE))
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env.update(ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PATH=f"{venv / 'bin'}{os.pathsep}{env.get('PATH', '')}")
    env.setdefault("MUJOCO_GL", "egl")

    run(sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", dist, src,
        cwd=tmp_path, env=env)  # fmt: skip
    (wheel,) = dist.glob("lq_ros-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    for folder, pattern in SHIPPED.items():
        shipped = {f"lq_ros/_shipped/{folder}/{p.name}" for p in (REPO / folder).glob(pattern)}
        assert shipped and shipped <= names, (folder, shipped - names)

    clone_venv(Path(sys.prefix), venv)
    python = venv / "bin" / "python"
    run(python, "-m", "pip", "uninstall", "-y", "-q", "lq_ros", cwd=tmp_path, env=env)  # the checkout's editable one
    run(python, "-m", "pip", "install", "--no-deps", "--no-index", "-q", wheel, cwd=tmp_path, env=env)
    elsewhere.mkdir()

    # The installed package, with its shipped folders, not the checkout.
    probe = run(python, "-c", "import json, sys, lq_ros, lq_ros_nodes, lq_ros.wire.messages as m; "
                "from lq_ros.robot.robot_config import ROBOTS_DIR, load_robot_config; load_robot_config('standin'); "
                "print(json.dumps([lq_ros.__file__, lq_ros_nodes.__file__, str(m.MSG_DIR), str(ROBOTS_DIR), sys.path,"
                " sorted(m.typestore().types)]))", cwd=elsewhere, env=env)  # fmt: skip
    package, nodes, msg_dir, robots_dir, path, types = json.loads(probe.stdout)
    site = venv / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / "site-packages"
    assert Path(package) == site / "lq_ros" / "__init__.py" and Path(nodes) == site / "lq_ros_nodes" / "__init__.py"
    assert Path(msg_dir) == site / "lq_ros" / "_shipped" / "msg_schemas" / "lq_msgs" / "msg"
    assert Path(robots_dir) == site / "lq_ros" / "_shipped" / "config" / "robots"
    assert not [p for p in path if p and Path(p).resolve().is_relative_to(REPO)], path
    assert "lq_msgs/msg/ActionChunk" in types
    for script in ("lq", "manager_node", "bridge_node", "robot_standin", "sim_node", "executor_node"):
        assert (venv / "bin" / script).is_file(), script

    # (a) an in-process episode into a bag, scored by the installed `lq score`
    run(venv / "bin" / "lq", "run", *RUN, "--transport", "inprocess", "--out", "local", cwd=elsewhere, env=env)
    (local,) = scored(venv / "bin" / "lq", "local", elsewhere, env)
    assert local["transport"] == "inprocess" and local["completion_steps"] == 10 and not local["partial"], local

    # (b) the same episode on the four-node ROS stack started by the installed `lq run`
    run(venv / "bin" / "lq", "run", *RUN, "--transport", "ros", "--out", "ros", cwd=elsewhere, env=env)
    (bag,) = [p for p in (elsewhere / "ros").iterdir() if p.is_dir()]
    assert (bag / "score.json").is_file() and (bag / "logs").is_dir()
    (ros,) = scored(venv / "bin" / "lq", "ros", elsewhere, env)
    assert ros["transport"] == "ros" and ros["status"] == local["status"], ros
    for key in ("completion_steps", "jerk_mean", "traj_length", "energy_total_j"):
        assert ros[key] == local[key], key  # lockstep: the ROS run is the in-process run
