"""LIBERO-LQ on ROS 2: latency-aware evaluation of VLA policies.

Pure-Python cores live here (executor protocols, env wrapper, policies, metrics, bag I/O); the
rclpy node programs in ``nodes/`` only wire them to topics.
"""

__version__ = "0.1.0"
