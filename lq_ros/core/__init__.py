"""The pure core: types, suite constants, run configuration, latency draws, merge strategies and the
execution protocols. No simulator, no ROS, no I/O; every other layer builds on it."""
