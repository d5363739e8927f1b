"""The rclpy node programs (installed as ``lq_ros_nodes``).

lq_ros is imported first so its process-wide settings (OpenBLAS kernel pinning) precede the numpy
that ROS message modules load.
"""

import lq_ros  # noqa: F401
