"""A template for your own policy: copy this file, fill in ``infer``, and evaluate it.

Run it from the folder that holds this file (``lq`` imports modules from the current directory):

    lq run --transport inprocess --policy my_policy:MyPolicy --policy-arg lift_m=0.05
    lq eval --policy my_policy:MyPolicy --tasks 0 --inits 0-4 --latencies 0,0.2 --out results/my_policy

or from Python, with an object you built yourself (a notebook, a debugger):

    import lq_ros
    from my_policy import MyPolicy

    row = lq_ros.run_episode(MyPolicy(), suite="libero_spatial", task=0, init=0, mode="async", latency_s=0.2)
    print(row["status"], row["completion_steps"], row["bag"])

What this template does is trivial on purpose: it lifts the hand a few centimetres above where the episode
started and holds it there, with the gripper open. It never solves a task. Everything a real policy needs is
shown: the observation's fields and units, the image orientation a LIBERO-trained model expects, LIBERO's
standard 8-D state, the action convention, the chunk shape, and ``reset``.

Observation (``lq_ros.core.types.Observation``), one per inference:

    tick            control tick of this observation (0 = the first the policy controls; one tick = 0.05 s)
    sim_time_s      simulated time, s
    eef_pos         (3,) end-effector position, m, in the world frame (LIBERO's MuJoCo world; z up)
    eef_quat_xyzw   (4,) end-effector orientation, quaternion x, y, z, w (robosuite's order), world frame
    gripper_qpos    (2,) finger joint positions, m (open ~ +-0.04, closed ~ 0)
    joint_pos       (7,) arm joint angles, rad
    joint_vel       (7,) arm joint velocities, rad/s
    objects         name -> (position (3,) m, quaternion xyzw (4,)), world frame: privileged state, which a
                    real robot does not have (set ``needs_object_poses = True`` if you read it)
    images          camera name -> (H, W, 3) uint8 RGB, UPRIGHT (row 0 is the top of the picture); only the
                    cameras in ``camera_names``, square, ``--camera-size`` px (else ``render_size``, else 224)

Image orientation: LIBERO's datasets, and so every model trained on them (openpi's pi0 family, OpenVLA,
OpenVLA-OFT), hold robosuite's raw images rotated by 180 degrees, as their LIBERO clients do: that is the upright
picture mirrored left to right. Give such a model ``libero_training_image(image)``, not the upright image: the
wrong orientation costs success silently, with no error anywhere.

Action chunk: ``infer`` returns an (H, 7) float array, H >= 1. Row i is the action for tick ``obs.tick + i``.
Columns, each in [-1, 1] (robosuite's OSC_POSE controller, as LIBERO trains and evaluates):

    0-2  dx, dy, dz      end-effector position goal offset, world frame: 1.0 = 0.05 m
    3-5  dax, day, daz   end-effector rotation goal, axis-angle in the world frame: 1.0 = 0.5 rad
    6    gripper         -1 open, +1 close

A chunk with any value outside [-1, 1], a NaN, or another shape is rejected and never executed (the run
records why): clip your output. In sync mode the first ``--replan-steps`` rows run, then the policy is asked
again; in async mode a chunk that arrives N ticks late (N = latency / 0.05 s) loses its first N rows, so
return more than N.
"""

from __future__ import annotations

import numpy as np

from lq_ros.core.types import Observation, TaskInfo
from lq_ros.policies import Policy, libero_state_8d, libero_training_image

#: OSC_POSE scale: one unit of action moves the position goal by this much, m.
POSITION_SCALE_M = 0.05


class MyPolicy(Policy):
    """Lift the hand ``lift_m`` above where the episode started and hold it there, gripper open.

    Constructor arguments are the policy's arguments: ``--policy-arg lift_m=0.1`` on the command line,
    ``args: {lift_m: 0.1}`` in a sweep spec, ``policy_args.lift_m`` as a ROS parameter of the policy node. Give
    them type hints: a value of the wrong type is refused before anything runs.
    """

    #: Recorded with every result.
    name = "my_policy"
    #: Cameras rendered at inference ticks: agentview (third person) and robot0_eye_in_hand (wrist). Each costs
    #: render time, so ask only for what the model uses; () renders nothing.
    camera_names = ("agentview",)
    #: The camera size your model's LIBERO evaluation renders at, px (openpi and OpenVLA: 256); None: 224.
    render_size: int | None = None

    def __init__(self, lift_m: float = 0.05, chunk_size: int = 10) -> None:
        if not 0.0 <= lift_m <= 0.3:
            raise ValueError(f"lift_m must be in [0, 0.3] m, got {lift_m}")
        if chunk_size < 1:
            raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
        self.lift_m = float(lift_m)
        self.chunk_size = int(chunk_size)
        self.target_m: np.ndarray | None = None

    def reset(self, task: TaskInfo, seed: int) -> None:
        """A new episode: forget the last one. ``task.instruction`` is the language goal ("pick up the black
        bowl ... and place it on the plate"); ``seed`` seeds anything random, so that reruns are identical."""
        self.instruction = task.instruction
        self.rng = np.random.default_rng(seed)
        self.target_m = None

    def infer(self, obs: Observation, prefix=None) -> np.ndarray:
        image = libero_training_image(obs.images["agentview"])  # what a LIBERO-trained model saw in training
        state = libero_state_8d(obs)  # EE position (3, m), axis-angle (3, rad), finger positions (2, m)
        assert image.shape[2] == 3 and state.shape == (8,)  # a real policy feeds these to its model
        if self.target_m is None:
            self.target_m = obs.eef_pos + np.array([0.0, 0.0, self.lift_m])
        # Spread the remaining offset over the chunk: each row asks for 1/H of it.
        per_tick_m = (self.target_m - obs.eef_pos) / self.chunk_size
        chunk = np.zeros((self.chunk_size, 7))
        chunk[:, 0:3] = per_tick_m / POSITION_SCALE_M
        chunk[:, 6] = -1.0  # gripper open
        return np.clip(chunk, -1.0, 1.0)

    def params(self) -> dict:
        """What is recorded with every result (the bag's run metadata): the arguments that shaped it."""
        return {"lift_m": self.lift_m, "chunk_size": self.chunk_size}

    def close(self) -> None:
        """Release what the policy holds (a connection, a GPU model). Called once, after its last episode."""
