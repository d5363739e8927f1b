"""Test setup. DDS discovery must stay on this machine: set before anything imports rclpy."""

import os
import tempfile

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
os.environ.setdefault("ROS_LOG_DIR", tempfile.mkdtemp(prefix="lq_test_roslog_"))
os.environ.setdefault("MUJOCO_GL", "egl")

import lq_ros  # noqa: E402,F401 - its OpenBLAS kernel pinning must precede numpy, as in every entry point
