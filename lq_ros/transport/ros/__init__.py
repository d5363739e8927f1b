"""The ROS transport: rclpy helpers, the protocol endpoints the nodes share, the wall clock, the
process stack and the launcher. Only node programs and stack children import rclpy."""
