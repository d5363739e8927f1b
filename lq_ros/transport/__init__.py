"""Transports that run one episode: in process (no ROS) or through the ROS node stack."""
