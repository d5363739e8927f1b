"""Test setup. DDS discovery must stay on this machine: set before anything imports rclpy."""

import os
import shutil
import signal
import tempfile
from pathlib import Path

import pytest

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
# Every run a test starts takes a free ROS domain of its own (lq_ros.transport.ros.reservations): an exported one
# (.ci/run exports ROS_DOMAIN_ID for its own processes) would be shared by the runs of make test's parallel workers,
# and a run refuses a domain another run holds. A test that checks an exported domain sets it itself.
os.environ.pop("ROS_DOMAIN_ID", None)
# The nodes' ROS logs go to a folder of the session's own, removed at the end (a user's ROS_LOG_DIR is kept).
_ROS_LOG_DIR = None if "ROS_LOG_DIR" in os.environ else tempfile.mkdtemp(prefix="lq_test_roslog_")
if _ROS_LOG_DIR:
    os.environ["ROS_LOG_DIR"] = _ROS_LOG_DIR
os.environ.setdefault("MUJOCO_GL", "egl")
# The session's processes share their compiled scenes (lq_ros.sim.model_cache) in a folder of their own, removed
# at the end, not in the user's cache.
_MODEL_CACHE = tempfile.mkdtemp(prefix="lq_test_models_")
os.environ.setdefault("LQ_MODEL_CACHE", _MODEL_CACHE)

import lq_ros  # noqa: E402,F401 - its OpenBLAS kernel pinning must precede numpy, as in every entry point
from lq_ros.transport.ros.stack import FASTDDS_PROFILE, FASTDDS_PROFILES_ENV  # noqa: E402 - (imports no rclpy)

# The test's own rclpy participants discover the nodes as fast as the nodes discover each other.
os.environ.setdefault(FASTDDS_PROFILES_ENV, str(FASTDDS_PROFILE))

#: Every test below this folder starts ROS nodes or imports rclpy: marked ``ros`` (pyproject.toml's markers).
ROS_TESTS = Path(__file__).resolve().parent / "transport" / "ros"


def pytest_sessionfinish(session, exitstatus) -> None:
    for folder in (_MODEL_CACHE, _ROS_LOG_DIR):
        if folder:
            shutil.rmtree(folder, ignore_errors=True)


def pytest_collection_modifyitems(items) -> None:
    for item in items:
        if item.path.is_relative_to(ROS_TESTS):
            item.add_marker(pytest.mark.ros)


@pytest.fixture
def no_hang():
    """Fail a test that blocks (a FIFO read) after 120 s instead of hanging the run."""

    def hung(*_):
        raise TimeoutError("blocked for 120 s")

    old = signal.signal(signal.SIGALRM, hung)
    signal.alarm(120)
    yield
    signal.alarm(0)
    signal.signal(signal.SIGALRM, old)


@pytest.fixture(scope="session")
def spatial_env():
    """One LIBERO-Spatial task 0 scene without cameras for the whole session.

    For tests that need a scene and reset it before use (a soft reset gives the episode of a fresh env:
    tests/transport/test_inprocess.py checks it), instead of building one each. Do not close it.
    """
    from lq_ros.sim.libero_env import LiberoEnv

    env = LiberoEnv("libero_spatial", 0)
    yield env
    env.close()
