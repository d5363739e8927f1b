"""A loaded LeRobot policy with its processors: what ``lerobot-eval`` hands the policy, and the chunk it answers.

Part of the LeRobot server (``lerobot_server.py``, whose docstring describes what is built and why); runs in
LeRobot's venv (lq_ros is not installed there).
"""

from __future__ import annotations

import contextlib
import importlib
import sys
import time
from pathlib import Path

# The server runs as a script in LeRobot's venv, where lq_ros is not installed: its sibling modules are imported by
# name from this folder (a script's own folder is on sys.path; added for an import by path).
if str(Path(__file__).resolve().parent) not in sys.path:
    sys.path.append(str(Path(__file__).resolve().parent))

from lerobot_checkpoint import (  # noqa: E402 - after the path
    check_config_fields,
    check_processors,
    check_weights_loaded,
    checkpoint_source,
    processor_configs,
)
from lerobot_request import (  # noqa: E402
    EEF_MAT_FIELD,
    EMPTY_CAMERA_PREFIX,
    ENV_CAMERAS,
    MAX_OBS_STEPS,
)

#: What the RTC prefix is: the model's own leftover actions of its previous chunk (LeRobot's RTC), or the executor's
#: plan (normalized with the checkpoint's action statistics).
RTC_PREFIXES = ("model", "executor")
#: Where a checkpoint's relative actions (``use_relative_actions``) are made absolute: ``tick``, each action with the
#: state of the tick that executes it (``lerobot-eval``: its post-processor runs every tick; the answer carries the
#: relative rows and the anchor weights, the executor adds the state), or ``chunk``, the whole chunk with the
#: request tick's state (LeRobot's RTC rollout engine, ``lerobot-rollout --inference.type=rtc``, post-processes each
#: chunk at once).
RELATIVE_ANCHORS = ("tick", "chunk")


def reads_eef_mat(step) -> bool:
    """Whether a LeRobot env processor step builds the state from ``robot_state.eef.mat`` (X-VLA's LIBERO step)."""
    from lerobot.policies.xvla.processor_xvla import LiberoProcessorStep as XVLALiberoStep

    return isinstance(step, XVLALiberoStep)


class LeRobotServer:
    """A loaded LeRobot policy with its processors, answering observation dicts with action chunks.

    ``cameras``: the policy's image key -> the LIBERO env camera (``image`` agentview, ``image2`` wrist) that feeds
    it (default: the keys ``observation.images.image``/``image2`` themselves); ``n_action_steps`` overrides the
    checkpoint's; ``full_chunk`` answers with ``predict_action_chunk``'s whole chunk.
    """

    def __init__(
        self,
        path: str,
        device: str = "cpu",
        suite: str = "libero_spatial",
        trust_processors: bool = False,
        cameras: dict[str, str] | None = None,
        n_action_steps: int | None = None,
        full_chunk: bool = False,
        rtc: dict | None = None,
        rtc_prefix: str = "model",
        empty_cameras: int | None = None,
        relative_anchor: str = "tick",
    ) -> None:
        import torch
        from lerobot.configs.policies import PreTrainedConfig
        from lerobot.envs.configs import LiberoEnv as LiberoEnvConfig
        from lerobot.envs.factory import make_env_pre_post_processors
        from lerobot.policies.factory import get_policy_class, make_pre_post_processors

        self.torch = torch
        #: RTCConfig fields the user set (execution_horizon, prefix_attention_schedule, max_guidance_weight), and what
        #: the RTC prefix is: the model's own leftover (LeRobot's) or the executor's plan.
        self.rtc = dict(rtc or {})
        if rtc_prefix not in RTC_PREFIXES:
            raise ValueError(f"rtc_prefix {rtc_prefix!r}: valid: {', '.join(RTC_PREFIXES)}")
        self.rtc_prefix = rtc_prefix
        #: The model's last chunk (its original actions, before post-processing): LeRobot's RTC prefix comes from it.
        self._last_chunk = None
        self._rtc_ready = False
        path, local = checkpoint_source(path)
        if local:  # offline: the server's main set the switches before LeRobot was imported (go_offline)
            check_config_fields(Path(path) / "config.json")
        else:
            from huggingface_hub import hf_hub_download

            check_config_fields(Path(hf_hub_download(path, "config.json")))
        config = PreTrainedConfig.from_pretrained(path)
        config.device = device
        #: Observations the policy conditions on: each request carries the n_obs_steps - 1 ticks before its own.
        self.n_obs_steps = int(getattr(config, "n_obs_steps", 1) or 1)
        #: What the action queue holds while a past tick goes through select_action (popped, never executed).
        self.past_tick = torch.full((1, 7), float("nan"))
        if not 1 <= self.n_obs_steps <= MAX_OBS_STEPS:
            raise ValueError(f"n_obs_steps is {self.n_obs_steps}: valid: 1 to {MAX_OBS_STEPS}")
        self.chunk_size = int(getattr(config, "chunk_size", None) or getattr(config, "horizon", None) or 1)
        if n_action_steps is not None:
            if not 1 <= n_action_steps <= self.chunk_size:
                raise ValueError(f"n_action_steps {n_action_steps}: valid: 1 to the chunk size, {self.chunk_size}")
            config.n_action_steps = int(n_action_steps)
        if empty_cameras is not None and hasattr(config, "empty_cameras"):  # as lerobot-eval --policy.empty_cameras
            config.empty_cameras = int(empty_cameras)
            config.validate_features()  # the policy's padded inputs (observation.images.empty_camera_<i>)
        self.cameras = self._camera_map(config, cameras)
        self.config = config
        self.policy = get_policy_class(config.type).from_pretrained(path, config=config)
        self.policy.eval()
        check_weights_loaded(self.policy, path, local)
        self.full_chunk = bool(full_chunk) or self._action_queue() is None
        if self.full_chunk and config.type in ("diffusion", "vqbet"):
            raise ValueError(
                f"full_chunk: a {config.type} policy's chunk is its n_action_steps from the current step; "
                "set n_action_steps instead"
            )
        if self.full_chunk and self.n_obs_steps > 1:
            raise ValueError(
                f"full_chunk with n_obs_steps {self.n_obs_steps}: the past ticks are queued by select_action, which a "
                "whole-chunk answer does not call; leave full_chunk off"
            )
        # The policy type's own processor steps register when its processor module is imported: import it (LeRobot's
        # code) before checking that every saved step is a registered one.
        with contextlib.suppress(ImportError):
            importlib.import_module(f"lerobot.policies.{config.type}.processor_{config.type}")
        check_processors(processor_configs(path, local), trust_processors)
        device_override = {"device": device}
        # As lerobot-eval: the saved pipelines, on the chosen device.
        self.preprocessor, self.postprocessor = make_pre_post_processors(
            policy_cfg=config,
            pretrained_path=path,
            preprocessor_overrides={"device_processor": device_override},
            postprocessor_overrides={"device_processor": device_override},
        )
        self.env_preprocessor, self.env_postprocessor = make_env_pre_post_processors(
            env_cfg=LiberoEnvConfig(task=suite), policy_cfg=config
        )
        #: The request's image keys, in LeRobot's env names (``observation.images.image``/``image2``).
        self.image_keys = sorted({f"observation.images.{camera}" for camera in self.cameras.values()})
        #: LeRobot's env processor for this policy reads the EE rotation matrix (X-VLA's LIBERO state is built from it).
        self.needs_eef_mat = any(reads_eef_mat(step) for step in self.env_preprocessor.steps)
        #: The post-processor's enabled AbsoluteActionsProcessorStep (a checkpoint with use_relative_actions), if any.
        self.absolute_step = next(
            (s for s in self.postprocessor.steps if type(s).__name__ == "AbsoluteActionsProcessorStep" and s.enabled),
            None,
        )
        if relative_anchor not in RELATIVE_ANCHORS:
            raise ValueError(f"relative_anchor {relative_anchor!r}: valid: {', '.join(RELATIVE_ANCHORS)}")
        self.relative_anchor = relative_anchor
        #: Answers carry relative rows and the anchor weights: the executor adds each tick's state (lerobot-eval's).
        self.anchor_per_tick = self.absolute_step is not None and relative_anchor == "tick"
        if self.anchor_per_tick and self.env_postprocessor.steps:
            raise ValueError(
                "relative actions: LeRobot's env post-processor acts on the absolute action, after the state is "
                "added, so the executor cannot add it per tick; use relative_anchor=chunk"
            )
        if self.supports_rtc():
            self._rtc_schedule = self.rtc_config().prefix_attention_schedule  # checks the user's values early

    @staticmethod
    def _camera_map(config, cameras: dict[str, str] | None) -> dict[str, str]:
        """The policy's image key -> env camera, every non-empty image key fed (ValueError, one line)."""
        images = [key for key in config.input_features if key.startswith("observation.images.")]
        wanted = [key for key in images if not key.startswith(EMPTY_CAMERA_PREFIX)]
        if cameras is None:
            cameras = {key: key.removeprefix("observation.images.") for key in wanted}
        unfed = sorted(set(wanted) - set(cameras))
        stray = sorted(set(cameras) - set(wanted))
        bad = sorted(key for key, camera in cameras.items() if camera not in ENV_CAMERAS)
        padded = int(getattr(config, "empty_cameras", 0) or 0)  # inputs the policy pads when they are missing
        if len(unfed) > padded or stray or bad:
            raise ValueError(
                f"cameras {cameras}: every image input {wanted} needs one of LIBERO's cameras {list(ENV_CAMERAS)} "
                f"(not fed: {unfed}; not an input: {stray}; not a camera: {bad})"
            )
        return dict(cameras)

    # -- metadata ---------------------------------------------------------------------------
    def metadata(self) -> dict:
        import huggingface_hub.constants
        import lerobot

        return {
            "server": "lq-lerobot",
            "lerobot_version": lerobot.__version__,
            "torch_version": self.torch.__version__,
            "policy_type": self.config.type,
            "n_action_steps": int(getattr(self.config, "n_action_steps", 1) or 1),
            "chunk_size": self.chunk_size,
            "image_keys": self.image_keys,
            "cameras": self.cameras,
            "full_chunk": self.full_chunk,
            "action_queue": self._action_queue() is not None,
            "rtc": self.supports_rtc(),
            "rtc_config": self._rtc_description() if self.supports_rtc() else None,
            "state_from_eef_mat": self.needs_eef_mat,
            "relative_actions": self.absolute_step is not None,
            "relative_anchor": self.relative_anchor if self.absolute_step is not None else None,
            # What the hub library itself reads (it takes the switch once, when imported): True for a local checkpoint.
            "hub_offline": bool(huggingface_hub.constants.HF_HUB_OFFLINE),
        }

    # -- one request --------------------------------------------------------------------------
    def raw_observation(self, request: dict) -> dict:
        """The dict ``lerobot.envs.libero.LiberoEnv`` returns (``obs_type=pixels_agent_pos``), batch of one, its
        pixel keys renamed as ``--env.camera_name_mapping`` renames them."""
        import numpy as np

        def batched(name: str) -> np.ndarray:
            return np.asarray(request[f"observation/{name}"])[None]

        pixels = {}
        for key, camera in self.cameras.items():
            pixels[key.removeprefix("observation.images.")] = np.asarray(request[f"observation/images/{camera}"])[None]
        eef = {"pos": batched("eef_pos"), "quat": batched("eef_quat")}
        if EEF_MAT_FIELD in request:  # (1, 3, 3), as LeRobot 0.6's env stacks the controller's matrix
            eef["mat"] = np.asarray(request[EEF_MAT_FIELD], dtype=np.float64).reshape(1, 3, 3)
        elif self.needs_eef_mat:
            raise ValueError(
                f"{self.config.type}: LeRobot's LIBERO processor for it builds the state from the end-effector "
                f"rotation matrix ({EEF_MAT_FIELD}), which this observation does not carry (a robot reports none)"
            )
        return {
            "pixels": pixels,
            "robot_state": {
                "eef": eef,
                "gripper": {"qpos": batched("gripper_qpos")},
                "joints": {"pos": batched("joint_pos"), "vel": batched("joint_vel")},
            },
        }

    def policy_batch(self, request: dict) -> dict:
        """What the policy is handed: lerobot-eval's steps from the env's observation to ``select_action``."""
        from lerobot.envs.utils import preprocess_observation

        observation = preprocess_observation(self.raw_observation(request))
        observation["task"] = [str(request.get("prompt", ""))]  # lerobot-eval: the env's task_description
        observation = self.env_preprocessor(observation)
        return self.preprocessor(observation)

    def postprocessed(self, actions):
        """(n, 7) float32: each (1, A) action through the saved post-processor and the env post-processor. Relative
        actions anchored per tick: without the post-processor's absolute step (the executor adds each tick's state,
        with :meth:`anchor_weights`)."""
        import numpy as np
        from lerobot.utils.constants import ACTION

        out = []
        skip = self.absolute_step if self.anchor_per_tick else None
        if skip is not None:
            skip.enabled = False
        try:
            for action in actions:
                action = self.postprocessor(action)
                action = self.env_postprocessor({ACTION: action})[ACTION]
                out.append(action.to("cpu").numpy()[0])
        finally:
            if skip is not None:
                skip.enabled = True
        return np.stack(out).astype(np.float32)

    def anchor_weights(self, action_dim: int):
        """(A,) float32: 1 where the absolute step adds the state's value of the same index (LeRobot's mask, 0 for a
        dimension ``relative_exclude_joints`` names), 0 elsewhere."""
        import numpy as np

        return np.asarray(self.absolute_step.relative_step._build_mask(action_dim), dtype=np.float32)

    def chunk(self, batch: dict, prefix: dict | None = None, history: list[dict] = ()):
        """(n, 7) float32 actions from one observation, post-processed as lerobot-eval does each tick.

        ``history``: the policy's input for each of the n_obs_steps - 1 ticks before, oldest first. Each goes through
        ``select_action`` as lerobot-eval hands it every tick, with a placeholder in the action queue for it to pop
        instead of inferring: the policy's own code queues it (populate_queues, after the policy's own batch
        preparation), so its observation queue then holds exactly what lerobot-eval's would at this tick.
        """
        if len(history) != self.n_obs_steps - 1:
            raise ValueError(
                f"history: n_obs_steps is {self.n_obs_steps}, so a request carries the {self.n_obs_steps - 1} tick(s) "
                f"before its own; this one carries {len(history)}"
            )
        if prefix is not None:
            if history:
                raise ValueError("merge rtc: LeRobot's RTC is wired into policies of one observation (n_obs_steps 1)")
            return self.rtc_chunk(batch, prefix)
        self._enable_rtc(False)  # LeRobot's select_action refuses to run with RTC on
        queue = self._action_queue()
        with self.torch.inference_mode():
            if self.full_chunk:
                chunk = self.policy.predict_action_chunk(batch)  # (1, H, A)
                return self.postprocessed(chunk.transpose(0, 1))
            for past in history:
                queue.clear()
                queue.append(self.past_tick)
                if self.policy.select_action(past) is not self.past_tick:
                    raise RuntimeError(f"{self.config.type}'s select_action did not take from its action queue")
            queue.clear()
            actions = [self.policy.select_action(batch)]
            actions += list(queue)
            queue.clear()
            return self.postprocessed(actions)

    # -- real-time chunking ----------------------------------------------------------------------
    def supports_rtc(self) -> bool:
        """LeRobot wires its RTC processor into this policy (SmolVLA, pi0, pi0.5) and the env adds no action step."""
        supports = getattr(self.policy, "supports_rtc", None)
        relative = bool(getattr(self.config, "use_relative_actions", False))
        return callable(supports) and bool(supports()) and not relative and not self.env_postprocessor.steps

    def rtc_config(self):
        """The RTC configuration the policy runs with: the checkpoint's ``rtc_config`` if it has one, else LeRobot's
        ``RTCConfig`` defaults (0.6.1: LINEAR schedule, execution horizon 10, maximum guidance weight 10), with the
        user's overrides (``rtc`` argument of the constructor) on top."""
        import dataclasses

        from lerobot.configs.types import RTCAttentionSchedule
        from lerobot.policies.rtc.configuration_rtc import RTCConfig

        saved = getattr(self.config, "rtc_config", None)
        config = dataclasses.replace(saved) if saved is not None else RTCConfig()
        config.enabled = True
        for key, value in self.rtc.items():
            if key == "prefix_attention_schedule":
                value = RTCAttentionSchedule[str(value).upper()]
            setattr(config, key, value)
        return config

    def rtc_chunk(self, batch: dict, prefix: dict):
        """The whole chunk, guided by LeRobot's RTC processor as LeRobot's RTC runs it: the prefix is the model's own
        leftover of its previous chunk (the original actions not yet executed: its last L rows, where L is the length
        of the executor's plan from the request tick on), weighted by the RTC configuration's schedule over its
        execution horizon; ``rtc_hard`` uses the ZEROS schedule (the d executing rows only). With ``rtc_prefix``
        ``executor`` (or no previous chunk of this episode) the executor's plan, normalized with the checkpoint's own
        action statistics (the inverse of its post-processor), is the prefix instead."""
        if not self.supports_rtc():
            raise ValueError(
                f"merge rtc: LeRobot's RTC is wired into SmolVLA, pi0 and pi0.5 (absolute actions); this checkpoint is "
                f"{self.config.type}; use another merge strategy"
            )
        from lerobot.configs.types import RTCAttentionSchedule

        torch = self.torch
        if not self._rtc_ready:  # the configuration in force (a saved rtc_config made a processor without ours)
            self.policy.config.rtc_config = self.rtc_config()
            self.policy.init_rtc_processor()
            self._rtc_ready = True
        self._enable_rtc(True)
        config = self.policy.rtc_processor.rtc_config
        hard = prefix["schedule"] == "hard"
        config.prefix_attention_schedule = RTCAttentionSchedule.ZEROS if hard else self._rtc_schedule
        rows = prefix["actions"]
        left_over = None
        last = self._last_chunk
        if len(rows) and self.rtc_prefix == "model" and last is not None and len(rows) <= last.shape[1]:
            left_over = last[:, last.shape[1] - len(rows) :].clone()  # noqa: E203 - the model's unexecuted rows
        elif len(rows):
            actions = torch.as_tensor(rows, dtype=torch.float32)[None].to(self.config.device)
            left_over = self._action_normalizer()._normalize_action(actions, inverse=False)
        # No inference_mode: RTC's guidance differentiates through the denoiser (it enables grad itself).
        with torch.no_grad():
            chunk = self.policy.predict_action_chunk(
                batch, inference_delay=prefix["delay"], prev_chunk_left_over=left_over
            )
        self._last_chunk = chunk.detach().clone()
        return self.postprocessed(chunk.transpose(0, 1))

    def _rtc_description(self) -> dict:
        """The RTC configuration in force (as recorded with the run)."""
        config = self.rtc_config()
        return {
            "execution_horizon": int(config.execution_horizon),
            "prefix_attention_schedule": config.prefix_attention_schedule.name,
            "max_guidance_weight": float(config.max_guidance_weight),
            "prefix": self.rtc_prefix,
        }

    def _enable_rtc(self, enabled: bool) -> None:
        """Switch the policy's RTC on (a request with a prefix) or off (one without) if it has an RTC config."""
        rtc_config = getattr(self.policy.config, "rtc_config", None)
        if rtc_config is not None:
            rtc_config.enabled = enabled

    def _action_normalizer(self):
        """The post-processor's unnormalizer step (its statistics turn the model's actions into the env's)."""
        for step in self.postprocessor.steps:
            if hasattr(step, "_normalize_action"):
                return step
        raise ValueError("the checkpoint's post-processor has no unnormalizer step: the prefix cannot be normalized")

    def reset(self, seed: int | None) -> None:
        """A new episode: the policy's queues and the processors reset; torch, numpy and random seeded as
        ``lerobot-eval`` seeds them (``set_seed``), so a sampling policy (diffusion) repeats its episode."""
        from lerobot.utils.random_utils import set_seed

        self.policy.reset()
        self._last_chunk = None
        if seed is not None:
            set_seed(int(seed))
        for pipeline in (self.preprocessor, self.postprocessor, self.env_preprocessor, self.env_postprocessor):
            pipeline.reset()

    def answer(self, request: dict) -> dict:
        """One chunk for a request :func:`checked_request` has checked."""
        if request.get("reset"):
            self.reset(request.get("seed"))
        started = time.perf_counter()
        prompt = request.get("prompt", "")
        history = [self.policy_batch({**past, "prompt": prompt}) for past in request.get("history", [])]
        actions = self.chunk(self.policy_batch(request), request.get("prefix"), history)
        reply = {"actions": actions, "policy_timing": {"infer_ms": (time.perf_counter() - started) * 1000.0}}
        if self.anchor_per_tick:
            reply["anchor_weights"] = self.anchor_weights(actions.shape[1])
        return reply

    def _action_queue(self):
        """The deque ``select_action`` pops from, or None for a policy that infers every call."""
        from lerobot.utils.constants import ACTION

        if getattr(self.config, "temporal_ensemble_coeff", None) is not None:
            return None
        queue = getattr(self.policy, "_action_queue", None)
        if queue is not None:
            return queue
        queues = getattr(self.policy, "_queues", None)
        if isinstance(queues, dict) and ACTION in queues:
            return queues[ACTION]
        return None
