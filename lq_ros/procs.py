"""Process-lifetime helpers shared by the launcher, the sweep workers and the CLI.

No rclpy here: these run in processes that must not initialise ROS (the CLI, a sweep worker) and in a
child between fork and exec (``preexec_fn``).
"""

from __future__ import annotations

import contextlib
import ctypes
import signal
from collections.abc import Callable
from types import FrameType

#: prctl option from <linux/prctl.h>.
_PR_SET_PDEATHSIG = 1


def die_with_parent() -> None:
    """Have the kernel send this process SIGTERM when its parent dies, even by kill -9.

    Called first thing in a child (a launched node via ``preexec_fn``, a sweep worker), so nothing
    outlives the program that started it. A no-op where prctl does not exist (not Linux).
    """
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)


def raise_keyboard_interrupt(*_) -> None:
    """Signal handler that unwinds like Ctrl-C, so ``finally`` blocks stop children cleanly."""
    raise KeyboardInterrupt


def sigterm_as_keyboard_interrupt() -> Callable[[int, FrameType | None], object] | int | None:
    """SIGTERM (a job runner, a parent stopping its workers) stops like Ctrl-C; returns the previous handler."""
    return signal.signal(signal.SIGTERM, raise_keyboard_interrupt)
