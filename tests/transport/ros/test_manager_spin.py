"""The manage_nodes spin thread ends quietly when a signal shuts ROS down under it, and only then."""

from __future__ import annotations

import pytest
import rclpy
from lq_ros_nodes.manager_node import _spin_quietly
from rclpy.context import Context
from rclpy.impl.implementation_singleton import rclpy_implementation


class RacingExecutor:
    """spin() as rclpy's when a signal's shutdown lands between its check of the context and its next wait set:
    rcl refuses the wait set of the now invalid context."""

    def __init__(self, context: Context, shut_down: bool) -> None:
        self.context, self.shut_down = context, shut_down

    def spin(self) -> None:
        if self.shut_down:
            rclpy.shutdown(context=self.context)
        raise rclpy_implementation.RCLError("failed to initialize wait set: the given context is not valid")


@pytest.mark.parametrize("shut_down", [True, False])
def test_a_wait_set_refused_by_a_shut_down_context_ends_the_thread_quietly(shut_down):
    context = Context()
    rclpy.init(context=context)
    try:
        if shut_down:
            _spin_quietly(RacingExecutor(context, shut_down=True))  # before: the thread's traceback on stderr
        else:  # the context still valid: a real failure, not hidden
            with pytest.raises(rclpy_implementation.RCLError):
                _spin_quietly(RacingExecutor(context, shut_down=False))
    finally:
        rclpy.try_shutdown(context=context)
