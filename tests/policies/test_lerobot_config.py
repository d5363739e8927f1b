"""What the LeRobot client reads from a checkpoint's config.json before anything starts (no LeRobot needed):
which of LIBERO's cameras feeds each image input, renames, empty cameras, and the one-line refusals."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from lq_ros.policies.lerobot_client import camera_mapping, check_config, parse_rename

IMAGE = {"type": "VISUAL", "shape": [3, 256, 256]}
STATE = {"observation.state": {"type": "STATE", "shape": [8]}}
ACTION = {"action": {"type": "ACTION", "shape": [7]}}


def config_file(tmp_path: Path, images: list[str], **fields) -> Path:
    inputs = {f"observation.images.{name}": IMAGE for name in images} | STATE
    path = tmp_path / "config.json"
    path.write_text(json.dumps({"type": "smolvla", "input_features": inputs, "output_features": ACTION, **fields}))
    return path


@pytest.mark.parametrize(
    ("names", "expected"),
    [
        (["image", "image2"], {"image": "image", "image2": "image2"}),
        (["image"], {"image": "image"}),
        (["camera1", "camera2"], {"camera1": "image", "camera2": "image2"}),  # lerobot/smolvla_libero
        (["cam_2", "cam_1"], {"cam_1": "image", "cam_2": "image2"}),
        (["front", "wrist"], {"front": "image", "wrist": "image2"}),
        (["agentview_rgb", "eye_in_hand_rgb"], {"agentview_rgb": "image", "eye_in_hand_rgb": "image2"}),
    ],
)
def test_unambiguous_cameras_map_automatically(names, expected):
    images = [f"observation.images.{name}" for name in names]
    mapping = camera_mapping(images, None, "ckpt")
    assert mapping == {f"observation.images.{key}": camera for key, camera in expected.items()}


@pytest.mark.parametrize("names", [["top", "side"], ["camera1"], ["wrist", "hand_cam"], ["base", "camera2"]])
def test_ambiguous_cameras_ask_for_rename(names):
    with pytest.raises(ValueError, match="--policy-arg rename=KEY:CAMERA") as refused:
        camera_mapping([f"observation.images.{name}" for name in names], None, "ckpt")
    assert "\n" not in str(refused.value)


def test_rename_names_the_cameras(tmp_path):
    rename = parse_rename("top:wrist, side:image")
    assert rename == {"observation.images.top": "image2", "observation.images.side": "image"}
    config = check_config(config_file(tmp_path, ["top", "side"]), "ckpt", rename)
    assert config["lq_cameras"] == rename
    assert parse_rename({"observation.images.top": "agentview"}) == {"observation.images.top": "image"}
    for bad, message in [
        ("top=image", "valid: KEY:CAMERA"),
        ("top:left", "camera 'left'; valid"),
        ({}, "valid: KEY:CAMERA"),
        (7, "valid: KEY:CAMERA"),
    ]:
        with pytest.raises(ValueError, match=message):
            parse_rename(bad)
    with pytest.raises(ValueError, match=r"not mapped: \['observation.images.side'\]"):
        check_config(config_file(tmp_path, ["top", "side"]), "ckpt", parse_rename("top:image"))


def test_empty_cameras_are_the_policys_and_newer_fields_pass(tmp_path):
    """smolvla_libero's config: camera1, camera2, an empty camera, and fields of LeRobot 0.6."""
    path = config_file(
        tmp_path, ["camera1", "camera2", "empty_camera_0"], empty_cameras=1, pretrained_revision=None,
        use_relative_actions=False,
    )  # fmt: skip
    config = check_config(path, "ckpt")
    assert config["lq_cameras"] == {"observation.images.camera1": "image", "observation.images.camera2": "image2"}


def test_inputs_beyond_libero_are_refused(tmp_path):
    with pytest.raises(ValueError, match="cannot tell which LIBERO camera .* or another LIBERO camera: frontview"):
        check_config(config_file(tmp_path, ["image", "image2", "image3"]), "ckpt")
    with pytest.raises(ValueError, match="not LIBERO's"):
        check_config(config_file(tmp_path, ["empty_camera_0"]), "ckpt")


@pytest.mark.parametrize("n_obs_steps", [None, 1, 2, 5, 10])
def test_an_observation_history_of_up_to_ten_ticks_is_accepted(tmp_path, n_obs_steps):
    config = check_config(config_file(tmp_path, ["image", "image2"], type="diffusion", n_obs_steps=n_obs_steps), "d")
    assert config["n_obs_steps"] == n_obs_steps


@pytest.mark.parametrize("n_obs_steps", [0, 11, 2.5, True, "2"])
def test_an_observation_history_beyond_ten_ticks_is_one_line(tmp_path, n_obs_steps):
    path = config_file(tmp_path, ["image", "image2"], type="vqbet", n_obs_steps=n_obs_steps)
    with pytest.raises(ValueError, match=r"n_obs_steps is .*; valid: 1 to 10") as refused:
        check_config(path, "d")
    assert "\n" not in str(refused.value)


def test_empty_cameras_let_the_policy_pad_inputs_libero_does_not_render(tmp_path):
    """As lerobot-eval --policy.empty_cameras=1: a third numbered camera stays unfed (the policy pads it); the
    config's own empty_cameras is the default, the argument overrides it."""
    path = config_file(tmp_path, ["camera1", "camera2", "camera3"])
    with pytest.raises(ValueError, match="cannot tell which LIBERO camera"):
        check_config(path, "ckpt")
    config = check_config(path, "ckpt", empty_cameras=1)
    assert config["lq_cameras"] == {"observation.images.camera1": "image", "observation.images.camera2": "image2"}
    assert config["lq_empty_cameras"] == 1
    (tmp_path / "own").mkdir()
    padded = config_file(tmp_path / "own", ["camera1", "camera2", "camera3"], empty_cameras=1)
    assert check_config(padded, "ckpt")["lq_empty_cameras"] == 1
    with pytest.raises(ValueError, match="cannot tell which LIBERO camera"):
        check_config(padded, "ckpt", empty_cameras=0)


def test_a_camera_libero_renders_feeds_an_input_rename_names_it_for(tmp_path):
    """As lerobot-eval --env.camera_name=...,frontview_image: a third input gets LIBERO's frontview camera."""
    path = config_file(tmp_path, ["image", "image2", "image3"])
    config = check_config(path, "ckpt", parse_rename("image:image,image2:wrist,image3:frontview"))
    assert config["lq_cameras"]["observation.images.image3"] == "frontview"
    with pytest.raises(ValueError, match="camera 'kitchen'; valid"):
        parse_rename("image3:kitchen")


def test_libero_has_the_cameras_we_render():
    """The client's LIBERO cameras are MuJoCo cameras of LIBERO's scene (its model, loaded by our simulator)."""
    from lq_ros.policies.lerobot_client import ENV_CAMERAS
    from lq_ros.sim.libero_env import LiberoEnv

    env = LiberoEnv("libero_spatial", 0, camera_names=("frontview",), camera_size=32)
    try:
        env.reset(0, seed=0)
        model = env._sim.model
        cameras = {model.camera_id2name(i) for i in range(model.ncam)}
        assert env.observe().images["frontview"].shape == (32, 32, 3)
    finally:
        env.close()
    assert set(ENV_CAMERAS.values()) <= cameras, sorted(set(ENV_CAMERAS.values()) - cameras)
