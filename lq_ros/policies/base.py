"""The Policy interface: an observation in, an H x 7 action chunk out."""

from __future__ import annotations

import abc

import numpy as np

from lq_ros.env import Observation, TaskInfo


class PolicyError(RuntimeError):
    """The policy could not produce a chunk (server down, timeout, garbage): the episode is an error."""


class Policy(abc.ABC):
    """A chunking policy. Implementations must be deterministic given (task, seed, observations)."""

    #: Registry name, recorded with every result.
    name: str = "policy"
    #: Cameras the policy needs rendered at inference ticks (none: no rendering at all).
    camera_names: tuple[str, ...] = ()
    #: Camera render size in px this policy's reference evaluation uses (e.g. 256 for openpi's and
    #: OpenVLA's LIBERO clients, which render 256 and resize themselves); None: the run's default.
    render_size: int | None = None
    #: Timing the policy measured or was told for its last ``infer`` (e.g. a remote server's times, ms);
    #: recorded with that chunk in the bag. None: nothing beyond the wall-clock latency measured outside.
    last_timing: dict | None = None

    @abc.abstractmethod
    def reset(self, task: TaskInfo, seed: int) -> None:
        """Start an episode of ``task``."""

    @abc.abstractmethod
    def infer(self, obs: Observation) -> np.ndarray:
        """Action chunk (H, 7) computed from ``obs``; row 0 is meant for tick ``obs.tick``."""

    def params(self) -> dict:
        """Parameters recorded in the run metadata."""
        return {}

    def close(self) -> None:  # noqa: B027 - optional hook, most policies hold nothing
        """Release resources (connections, threads)."""
