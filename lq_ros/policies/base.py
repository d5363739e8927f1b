"""The Policy interface: an observation in, an H x 7 action chunk out."""

from __future__ import annotations

import abc
from dataclasses import dataclass

import numpy as np

from lq_ros.core.control import ControlMode
from lq_ros.core.merge import PREFIX_STRATEGIES, ActionPrefix, Merge
from lq_ros.core.run_config import PAPER_REPLAN_STEPS
from lq_ros.core.types import Observation, TaskInfo


class PolicyError(RuntimeError):
    """The policy could not produce a chunk (server down, timeout, garbage): the episode is an error."""


@dataclass(frozen=True)
class ReferenceProtocol:
    """How a policy's own reference evaluation runs it: ``lq run``, ``lq eval`` and sweeps default to it (an explicit
    ``--replan-steps`` or ``--camera-size`` wins, and the result row says which was used)."""

    #: Actions of each chunk the sync protocol executes before the next request.
    replan_steps: int = PAPER_REPLAN_STEPS
    #: Camera render size, px; None: the run's default (lq_ros.core.run_config.DEFAULT_CAMERA_SIZE_PX).
    camera_size: int | None = None
    #: The cameras rendered for it (none: no rendering).
    camera_names: tuple[str, ...] = ()


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
    #: True if ``infer`` accepts ``prefix`` (an :class:`ActionPrefix`: the actions that will execute while it
    #: infers and the delay d) and makes its chunk consistent with it: real-time chunking, ``--merge rtc``.
    supports_prefix: bool = False
    #: True if ``infer`` reads privileged object poses (``Observation.objects``): on a robot they must come from
    #: a tracker's pose topics, else the run is refused at configure time (lq_ros/robot/observation_builder.py).
    needs_object_poses: bool = False
    #: True if the policy's arguments name code it runs (a program, a checkpoint whose files name classes to
    #: import): like ``package.module:Class``, such a policy is built only with the arguments the launching user
    #: chose, never from a runtime parameter change (nodes/policy_node.py).
    args_run_code: bool = False
    #: Ticks of observations each ``infer`` conditions on: 1, the request's tick only; n > 1, also the n - 1 ticks
    #: before it, in ``Observation.history`` (captured by the simulator every tick, lq_ros.core.observation_history).
    observation_history_ticks: int = 1
    #: How the arm values of its actions are meant (lq_ros.core.control): relative steps in [-1, 1] (LIBERO's, every
    #: policy of the paper) or absolute EE poses (X-VLA's LIBERO checkpoints). The simulator switches its controller.
    control_mode: ControlMode = ControlMode.RELATIVE
    #: Whether two seeds can give two different episodes (benchmarks/seed_replication.py measures it; the simulator
    #: sets the init state after seeding, so the scene does not depend on the seed): False, measured identical (the
    #: policy ignores its seed), so a second seed repeats the first episode and a sweep refuses it; True, measured
    #: to differ; None, not known (a checkpoint's sampling decides, or a user's policy).
    seed_varies: bool | None = None

    @abc.abstractmethod
    def reset(self, task: TaskInfo, seed: int) -> None:
        """Start an episode of ``task``."""

    @abc.abstractmethod
    def infer(self, obs: Observation, prefix: ActionPrefix | None = None) -> np.ndarray:
        """Action chunk (H, 7) computed from ``obs``; row 0 is meant for tick ``obs.tick``.

        ``prefix`` is given only to a policy with ``supports_prefix`` (merge ``rtc``/``rtc_hard``): the
        executor's plan from tick ``obs.tick`` on, whose first ``prefix.delay`` rows execute while the
        policy infers; rows 0..d-1 of the result are dropped as stale, the rest replace the plan.
        """

    def params(self) -> dict:
        """Parameters recorded in the run metadata."""
        return {}

    def reference(self) -> ReferenceProtocol:
        """The protocol this policy's reference evaluation uses: the paper's actions per chunk, its render size and
        cameras. A policy whose reference depends on its arguments (a LeRobot checkpoint's ``n_action_steps``)
        overrides it."""
        return ReferenceProtocol(camera_size=self.render_size, camera_names=tuple(self.camera_names))

    @classmethod
    def check_merge(cls, merge: str) -> None:
        """Refuse (ValueError) a merge strategy this policy cannot serve: the prefix strategies need
        ``supports_prefix``. Called when a run is configured, before its episode starts."""
        if Merge(merge) in PREFIX_STRATEGIES and not cls.supports_prefix:
            raise ValueError(
                f"merge {merge!r} (real-time chunking) needs a policy that conditions its chunk on the executing "
                f"prefix; policy {cls.name!r} cannot (Policy.supports_prefix is False). Use another merge "
                "strategy, or a policy that supports a prefix (flow)"
            )

    def close(self) -> None:  # noqa: B027 - optional hook, most policies hold nothing
        """Release resources (connections, threads)."""
