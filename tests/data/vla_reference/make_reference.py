"""Record what OpenVLA's and OpenVLA-OFT's own LIBERO code hands the model, for real rendered frames.

tests/policies/test_remote_policies.py checks that our OpenVLA client sends exactly these images and states.
The reference code needs TensorFlow, which this project does not install, so the recording is made
in two steps and committed (``libero_frames.npz``, ~1 MB):

1. ``frames`` (this project's venv): LIBERO observations exactly as those evaluations get them
   (``OffScreenRenderEnv`` at 256 px, seed 7, ``set_init_state``, 10 no-op steps, then a few moves):
   the raw robosuite camera images and the proprioception.

       MUJOCO_GL=egl .venv/bin/python tests/data/vla_reference/make_reference.py frames /tmp/frames.npz

2. ``reference`` (a separate venv with ``tensorflow-cpu==2.15.0``, the version both repositories pin,
   plus numpy 1.26 and Pillow): runs the *unmodified* reference functions, read from checkouts of
   github.com/openvla/openvla and github.com/moojink/openvla-oft (their modules import torch,
   transformers and prismatic, so the functions are taken out of the source files and executed
   with stand-ins only for the model and its processor), and stores their outputs.

       python -m venv /tmp/tfref && /tmp/tfref/bin/pip install tensorflow-cpu==2.15.0 numpy==1.26.4 pillow
       /tmp/tfref/bin/python tests/data/vla_reference/make_reference.py reference /tmp/frames.npz \\
           --openvla OPENVLA_CHECKOUT --oft OFT_CHECKOUT --out tests/data/vla_reference/libero_frames.npz
"""

from __future__ import annotations

import argparse
import ast
import json
import os
from pathlib import Path

import numpy as np

#: (suite, task, init state, steps of MOVE after the 10 no-op steps): one still scene, one with the arm moved.
SCENES = (("libero_spatial", 0, 0, 0), ("libero_goal", 5, 2, 15))
MOVE = [0.6, -0.3, -0.5, 0.0, 0.0, 0.2, 1.0]  # towards the table, gripper closing: the wrist view changes
NOOP = [0.0] * 6 + [-1.0]
RENDER_SIZE = 256
OBS_KEYS = ("agentview_image", "robot0_eye_in_hand_image", "robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos")


def record_frames(out: Path) -> None:
    os.environ.setdefault("MUJOCO_GL", "egl")
    from libero.libero import benchmark, get_libero_path
    from libero.libero.envs import OffScreenRenderEnv

    arrays: dict[str, list] = {key: [] for key in OBS_KEYS}
    scenes = []
    for suite, task_id, init, moves in SCENES:
        bench = benchmark.get_benchmark_dict()[suite]()
        task = bench.get_task(task_id)
        bddl = Path(get_libero_path("bddl_files")) / task.problem_folder / task.bddl_file
        env = OffScreenRenderEnv(bddl_file_name=str(bddl), camera_heights=RENDER_SIZE, camera_widths=RENDER_SIZE)
        try:
            env.seed(7)
            env.reset()
            obs = env.set_init_state(bench.get_task_init_states(task_id)[init])
            for step in range(10 + moves):
                obs, *_ = env.step(NOOP if step < 10 else MOVE)
        finally:
            env.close()
        for key in OBS_KEYS:
            arrays[key].append(np.array(obs[key]))
        scenes.append({"suite": suite, "task": task_id, "init": init, "moves": moves, "instruction": task.language})
    np.savez_compressed(out, scenes=json.dumps(scenes), **{k: np.stack(v) for k, v in arrays.items()})


def _functions(path: Path, names: tuple[str, ...], namespace: dict) -> dict:
    """Execute the named top-level functions of a reference source file in ``namespace`` (not its imports)."""
    source = path.read_text()
    for node in ast.parse(source).body:
        if isinstance(node, ast.FunctionDef) and node.name in names:
            exec(compile(ast.get_source_segment(source, node), str(path), "exec"), namespace)  # noqa: S102
    missing = [n for n in names if n not in namespace]
    if missing:
        raise SystemExit(f"{path}: no function {missing}")
    return namespace


class _CropCfg:
    """The one field of OFT's deploy config that ``prepare_images_for_vla`` reads (deploy.py's default)."""

    center_crop = True


class _Captured(Exception):
    """Raised by the processor stand-in: carries the image the model would have been given."""


def _capture_processor(prompt: str, image) -> None:
    raise _Captured(np.asarray(image))


def record_reference(frames: Path, openvla: Path, oft: Path, out: Path) -> None:
    import math
    import typing

    import tensorflow as tf
    from PIL import Image

    # Names the reference functions use (annotations included); nothing else of their modules.
    common = {"np": np, "tf": tf, "Image": Image, "math": math}
    common.update({name: getattr(typing, name) for name in ("Any", "Dict", "List", "Optional", "Tuple", "Union")})
    robot = "experiments/robot"
    # OpenVLA: client-side get_libero_image (rotate + resize_image), then get_vla_action's centre crop;
    # the processor stand-in stops it where the real processor would receive the image.
    ovla = _functions(openvla / robot / "libero/libero_utils.py", ("get_libero_image", "resize_image"), dict(common))
    ovla.update({"OPENVLA_V01_SYSTEM_PROMPT": "", "DEVICE": None})
    _functions(openvla / robot / "openvla_utils.py", ("crop_and_resize", "get_vla_action"), ovla)
    # OFT: run_libero_eval.prepare_observation is what the client sends to deploy.py; the server's
    # prepare_images_for_vla then makes the model input (no resize at 224, centre crop).
    oft_ns = _functions(
        oft / robot / "libero/libero_utils.py",
        ("get_libero_image", "get_libero_wrist_image", "quat2axisangle"),
        dict(common, OPENVLA_IMAGE_SIZE=224),
    )
    _functions(
        oft / robot / "openvla_utils.py",
        ("resize_image_for_policy", "crop_and_resize", "center_crop_image", "check_image_format"),
        oft_ns,
    )
    _functions(oft / robot / "openvla_utils.py", ("prepare_images_for_vla",), oft_ns)
    _functions(oft / robot / "libero/run_libero_eval.py", ("prepare_observation",), oft_ns)

    data = np.load(frames)
    n = len(data["agentview_image"])
    results: dict[str, list] = {k: [] for k in ("openvla_image", "oft_full_image", "oft_wrist_image", "oft_state")}
    for i in range(n):
        obs = {key: np.array(data[key][i]) for key in OBS_KEYS}
        full_image = ovla["get_libero_image"](obs, 224)
        try:
            ovla["get_vla_action"](
                None, _capture_processor, "openvla-7b", {"full_image": full_image}, "task", "libero_spatial", True
            )
        except _Captured as captured:
            results["openvla_image"].append(captured.args[0])
        observation, _ = oft_ns["prepare_observation"]({k: np.array(v) for k, v in obs.items()}, 224)
        results["oft_full_image"].append(observation["full_image"])
        results["oft_wrist_image"].append(observation["wrist_image"])
        results["oft_state"].append(observation["state"])
        # Same model input from both repositories: OFT's server crop of what its client sends.
        served = oft_ns["prepare_images_for_vla"]([observation["full_image"]], _CropCfg())[0]
        if not np.array_equal(np.asarray(served), results["openvla_image"][-1]):
            raise SystemExit(f"frame {i}: OFT's server-side crop differs from OpenVLA's client-side crop")
    if len(results["openvla_image"]) != n:
        raise SystemExit("get_vla_action never reached the processor")
    meta = {
        "tensorflow": tf.__version__,
        "openvla": _revision(openvla),
        "openvla_oft": _revision(oft),
        "scenes": json.loads(str(data["scenes"])),
    }
    arrays = {k: np.stack(v) for k, v in results.items()}
    np.savez_compressed(out, meta=json.dumps(meta), **{k: data[k] for k in OBS_KEYS}, **arrays)


def _revision(checkout: Path) -> str:
    """The checkout's git commit, or the content of a REVISION file (an exported tree), or 'unknown'."""
    import subprocess

    try:
        return subprocess.run(
            ["git", "-C", str(checkout), "rev-parse", "HEAD"], capture_output=True, text=True, check=True
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        marker = checkout / "REVISION"
        return marker.read_text().strip() if marker.exists() else "unknown"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="step", required=True)
    frames = sub.add_parser("frames")
    frames.add_argument("out", type=Path)
    ref = sub.add_parser("reference")
    ref.add_argument("frames", type=Path)
    ref.add_argument("--openvla", type=Path, required=True, help="checkout of openvla/openvla")
    ref.add_argument("--oft", type=Path, required=True, help="checkout of moojink/openvla-oft")
    ref.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    if args.step == "frames":
        record_frames(args.out)
    else:
        record_reference(args.frames, args.openvla, args.oft, args.out)


if __name__ == "__main__":
    main()
