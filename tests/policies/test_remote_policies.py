"""Remote VLA clients (openpi websocket, OpenVLA REST) against stand-in servers on 127.0.0.1.

The stand-ins (tests/standin_servers.py) speak the real wire protocols and check every request;
here we check what the clients send (bit for bit against each reference evaluation's own
preprocessing of the same rendered frame, and against the images and states recorded in the bag),
what they return, the server timing they keep, and that every server failure ends the episode as an
*error* with its reason, quickly (never a hang, a success or a plain failure).
"""

import json
import os
import time
from pathlib import Path

import numpy as np
import pytest
import requests
from openpi_client import image_tools
from PIL import Image
from scipy.spatial.transform import Rotation

from lq_ros.core.run_config import RunConfig
from lq_ros.core.types import Observation, TaskInfo
from lq_ros.policies import PolicyError, make_policy
from lq_ros.policies.openpi_remote import libero_training_image, quat_xyzw_to_axis_angle
from lq_ros.policies.openvla_rest import (
    _lanczos3_spans,
    jpeg_round_trip,
    openvla_center_crop,
    openvla_resize,
    resize_lanczos3,
)
from lq_ros.recording.bag_compare import bag_messages
from lq_ros.run.episode import run_episode
from lq_ros.scoring.bag_scorer import score_bag
from lq_ros.sim.libero_env import LiberoEnv
from lq_ros.transport.inprocess import run_inprocess
from lq_ros.wire import messages as m
from tests.standin_servers import OpenPIStandin, OpenVLAStandin, free_port, standin_action, standin_observation

CAMERAS = ("agentview", "robot0_eye_in_hand")
TASK = TaskInfo("libero_spatial", 0, "t0", "pick up the black bowl", [], 220, 50)
FAST_TIMEOUT_S = 0.5  # client timeout used against the 'slow' stand-ins
#: What OpenVLA's and OFT's own LIBERO code (TensorFlow 2.15) made of real rendered frames; see make_reference.py.
VLA_REFERENCE = Path(__file__).parents[1] / "data" / "vla_reference" / "libero_frames.npz"


def synthetic_obs(size: int = 224, tick: int = 3) -> Observation:
    return standin_observation(size, tick)


def libero_example_image(upright: np.ndarray) -> np.ndarray:
    """What openpi's LIBERO example sends for a camera, from our upright image (rows flipped back)."""
    robosuite_obs = upright[::-1]
    return image_tools.convert_to_uint8(image_tools.resize_with_pad(robosuite_obs[::-1, ::-1], 224, 224))


def openvla_example_image(upright: np.ndarray, crop: bool = True) -> np.ndarray:
    """What OpenVLA's LIBERO evaluation gives its model (OFT's client sends it uncropped), from our upright
    image; the functions are those proven equal to TensorFlow in test_openvla_images_equal_tensorflow_reference."""
    resized = openvla_resize(np.ascontiguousarray(upright[::-1][::-1, ::-1]), 224)
    return openvla_center_crop(resized) if crop else resized


def decoded(bag: Path, topic: m.Topic) -> list:
    return [m.deserialize(raw, topic.msgtype) for _, raw in bag_messages(bag).get(topic.name, [])]


def assert_error_everywhere(outcome, reason: str) -> dict:
    """The episode is an error with ``reason`` in the outcome, the bag's events and the score."""
    assert outcome.status == "error", outcome
    assert reason in outcome.reason, outcome.reason
    row = score_bag(outcome.bag_path)
    assert row["status"] == "error" and row["success"] is None, row
    assert reason in row["error_reason"], row["error_reason"]
    return row


# -- conversions ----------------------------------------------------------------------------
def test_axis_angle_is_robosuite_convention():
    rng = np.random.default_rng(0)
    for q in rng.normal(size=(50, 4)):
        q /= np.linalg.norm(q)
        aa = quat_xyzw_to_axis_angle(q)
        # Same rotation; angle 2 acos(w) in [0, 2 pi] (scipy's rotvec picks the one <= pi).
        assert Rotation.from_rotvec(aa).approx_equal(Rotation.from_quat(q), atol=1e-9)
        assert np.linalg.norm(aa) == pytest.approx(2 * np.arccos(q[3]))
        if q[3] >= 0:
            assert np.allclose(aa, Rotation.from_quat(q).as_rotvec())
    assert np.array_equal(quat_xyzw_to_axis_angle(np.array([0.0, 0.0, 0.0, 1.0])), np.zeros(3))


def test_axis_angle_is_bitwise_robosuites_quat2axisangle():
    """openpi's and OpenVLA's LIBERO clients copy robosuite's quat2axisangle; same bits, clipping included."""
    from robosuite.utils.transform_utils import quat2axisangle

    rng = np.random.default_rng(1)
    quats = rng.normal(size=(200, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    quats[:3] = [[0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 1e-9, 1.0], [0.0, 0.0, 0.0, 1.0000000000000002]]  # edge cases
    for q in quats:
        assert np.array_equal(quat_xyzw_to_axis_angle(q.copy()), quat2axisangle(q.copy())), q


# -- clients against the stand-ins, no simulator ----------------------------------------------
def test_openpi_payload_chunk_and_timing():
    obs = synthetic_obs(size=256)  # openpi's example renders 256 px and resizes with padding
    with OpenPIStandin(prompt=TASK.instruction) as server:
        policy = make_policy("openpi", port=server.port, timeout_s=5.0)
        policy.reset(TASK, 7)
        first, second = policy.infer(obs), policy.infer(obs)
        policy.close()
    assert server.check_failures == [] and server.requests == 2
    sent = server.received[0]
    for key, cam in (("observation/image", "agentview"), ("observation/wrist_image", "robot0_eye_in_hand")):
        assert np.array_equal(sent[key], libero_example_image(obs.images[cam]))
    assert sent["observation/state"].dtype == np.float64
    assert np.array_equal(sent["observation/state"][:3], obs.eef_pos)
    assert np.array_equal(sent["observation/state"][6:], obs.gripper_qpos)
    assert sent["prompt"] == TASK.instruction
    assert policy.server_metadata["policy"] == "openpi-standin"
    expected = np.tile(standin_action(sent["observation/state"]), (10, 1))
    assert np.array_equal(first, expected) and np.array_equal(second, expected)
    first_t, second_t = policy.timings
    assert first_t["policy_infer_ms"] == 1.5 and first_t["server_infer_ms"] >= 0.0
    assert first_t["server_prev_total_ms"] is None and second_t["server_prev_total_ms"] > 0.0
    assert second_t["round_trip_ms"] >= second_t["server_infer_ms"] and policy.last_timing is second_t


def test_openpi_healthz_and_api_key(monkeypatch):
    with OpenPIStandin(api_key="s3cret") as server:
        health = requests.get(f"http://127.0.0.1:{server.port}/healthz", timeout=5)
        assert health.status_code == 200 and health.text == "OK\n"
        monkeypatch.delenv("OPENPI_API_KEY", raising=False)
        no_key = make_policy("openpi", port=server.port, timeout_s=5.0)
        no_key.reset(TASK, 7)
        with pytest.raises(PolicyError, match="unreachable.*401"):
            no_key.infer(synthetic_obs())
        monkeypatch.setenv("OPENPI_API_KEY", "s3cret")
        from_env = make_policy("openpi", port=server.port, timeout_s=5.0)
        from_env.reset(TASK, 7)
        assert from_env.infer(synthetic_obs()).shape == (10, 7)
        assert from_env.params()["api_key"] == "set"  # the key itself never reaches a bag
        from_env.close()


OPENPI_FAULTS = [
    ("down", "unreachable: ConnectionRefusedError"),
    ("slow", f"no response within {FAST_TIMEOUT_S} s"),
    ("nan", "non-finite action nan at row 1, column 2"),
    ("shape", "shape (10, 5)"),
    ("nonnumeric", "not numeric"),
    ("missing", "no 'actions'"),
    ("error", "openpi server error: RuntimeError: stand-in model failed (injected error)"),
    ("close", "closed the connection (close code 1001"),
    ("garbage", "not msgpack-numpy"),
]
OPENVLA_FAULTS = [
    ("down", "request failed ([Errno 111] Connection refused)"),
    ("slow", f"no response within {FAST_TIMEOUT_S} s"),
    ("nan", "non-finite action nan at row 0, column 0"),
    ("shape", "shape (6,)"),
    ("nonnumeric", "not numeric"),
    ("error", "answered 'error'"),
    ("http500", "HTTP 500"),
    ("close", "request failed"),
    ("garbage", "not json-numpy"),
]


def _serve(kind: str, fault: str, **kwargs):
    """A stand-in with ``fault`` (None when the fault is 'down': nothing listens) and its port."""
    if fault == "down":
        return None, free_port()
    kwargs.setdefault("slow_s", FAST_TIMEOUT_S + 1.0)  # late enough to time out, short enough not to linger
    server = (OpenPIStandin if kind == "openpi" else OpenVLAStandin)(fault=fault, **kwargs)
    return server, server.port


@pytest.mark.parametrize(
    "kind, fault, reason", [("openpi", *f) for f in OPENPI_FAULTS] + [("openvla", *f) for f in OPENVLA_FAULTS]
)
def test_every_fault_raises_policy_error_quickly(kind, fault, reason):
    server, port = _serve(kind, fault)
    policy = make_policy(kind, port=port, timeout_s=FAST_TIMEOUT_S)
    policy.reset(TASK, 7)
    try:
        if server is not None:
            server.__enter__()
        started = time.monotonic()
        with pytest.raises(PolicyError) as err:
            policy.infer(synthetic_obs())
        elapsed_s = time.monotonic() - started
    finally:
        policy.close()
        if server is not None:
            server.__exit__(None, None, None)
    assert reason in str(err.value)
    assert elapsed_s < FAST_TIMEOUT_S + 1.0  # bounded by the timeout, never a hang
    assert server is None or server.check_failures == []  # the request itself was well-formed


def test_openvla_payload_styles_and_gripper_convention():
    obs = synthetic_obs(size=256)
    with OpenVLAStandin(prompt=TASK.instruction) as server:
        policy = make_policy("openvla", port=server.port, timeout_s=5.0)
        policy.reset(TASK, 7)
        chunk = policy.infer(obs)
        raw = make_policy("openvla", url=server.url, gripper="raw", timeout_s=5.0)
        raw.reset(TASK, 7)
        raw_chunk = raw.infer(obs)
    assert server.check_failures == []
    sent = server.received[0]
    assert sent["unnorm_key"] == "libero_spatial" and sent["image"].shape == (224, 224, 3)
    assert policy.camera_names == ("agentview",)
    assert chunk.shape == (1, 7) and chunk[0, 6] == -1.0  # server's 1 (open) -> LIBERO's -1 (open)
    assert raw_chunk[0, 6] == 1.0 and np.array_equal(chunk[0, :6], server.action_for(sent)[:6])
    assert policy.last_timing["round_trip_ms"] > 0
    with OpenVLAStandin(style="oft", horizon=8, prompt=TASK.instruction) as server:
        oft = make_policy("openvla", port=server.port, style="oft", timeout_s=5.0)
        oft.reset(TASK, 7)
        chunk = oft.infer(synthetic_obs())
    assert server.check_failures == [] and oft.camera_names == CAMERAS
    state = server.received[0]["state"]
    assert chunk.shape == (8, 7) and np.allclose(chunk[:, :6], standin_action(state)[:6]) and np.all(chunk[:, 6] == -1)


@pytest.mark.parametrize("kind", ["openpi", "openvla"])
@pytest.mark.parametrize(
    "args, message",
    [
        ({"timeout_s": "soon"}, "timeout_s must be a positive number"),
        ({"timeout_s": 0}, "timeout_s must be a positive number"),
        ({"resize": 2.5}, "resize must be a positive integer"),
        ({"port": "http"}, "port must be a positive integer"),
        ({"clip": "no"}, "clip must be true or false"),
    ],
)
def test_bad_parameters_are_refused_at_construction(kind, args, message):
    with pytest.raises(ValueError, match=message):
        make_policy(kind, **args)


def test_openvla_center_crop_keeps_central_90_percent_of_the_area():
    columns = np.ascontiguousarray(np.broadcast_to(np.arange(224, dtype=np.uint8)[None, :, None], (224, 224, 3)))
    cropped = openvla_center_crop(columns)
    # crop_and_resize samples the box [lo, lo + s] (normalised, s = sqrt(0.9)) corner to corner: column j of
    # the output reads input column 223 (lo + j s / 223), linearly interpolated, then x 255.5 / 255, truncated.
    side = np.sqrt(0.9)
    expected = 223 * ((1 - side) / 2 + np.arange(224) * side / 223)
    assert cropped.shape == (224, 224, 3) and np.all(cropped == cropped[:1])  # rows identical
    assert np.abs(cropped[0, :, 0] - expected).max() <= 1.0
    assert cropped[0, 0, 0] == 5 and cropped[0, -1, 0] == 217  # (1 - sqrt(0.9)) / 2 = 2.6 % of each side gone


@pytest.mark.parametrize(
    "style, crop, cropped",
    [("openvla", None, True), ("openvla", False, False), ("oft", None, False)],
)
def test_openvla_center_crop_defaults_follow_the_reference(style, crop, cropped):
    """OpenVLA crops client-side (its deploy.py passes the image through); OFT's deploy.py crops itself."""
    args = {} if crop is None else {"center_crop": crop}
    policy = make_policy("openvla", style=style, **args)
    policy.reset(TASK, 7)
    obs = synthetic_obs(size=256)
    sent = policy.request_payload(obs)["image" if style == "openvla" else "full_image"]
    assert policy.center_crop is cropped and policy.params()["center_crop"] is cropped
    assert np.array_equal(sent, openvla_example_image(obs.images["agentview"], crop=cropped))


def test_oft_refuses_a_second_center_crop():
    with pytest.raises(ValueError, match="crops server-side"):
        make_policy("openvla", style="oft", center_crop=True)


# -- the pixels and states sent equal each reference evaluation's own preprocessing ------------
@pytest.fixture(scope="module")
def vla_reference() -> dict:
    data = np.load(VLA_REFERENCE)
    return {key: data[key] for key in data.files}


def reference_observation(ref: dict, i: int) -> Observation:
    """Observation ``i`` of the recorded LIBERO frames, as our env would hand it over (images upright)."""
    return Observation(
        tick=0,
        sim_time_s=0.5,
        eef_pos=np.array(ref["robot0_eef_pos"][i]),
        eef_quat_xyzw=np.array(ref["robot0_eef_quat"][i]),
        gripper_qpos=np.array(ref["robot0_gripper_qpos"][i]),
        joint_pos=np.zeros(7),
        joint_vel=np.zeros(7),
        # robosuite's images are bottom row first (macros.IMAGE_CONVENTION "opengl"); ours are upright.
        images={cam: ref[f"{cam}_image"][i][::-1] for cam in CAMERAS},
    )


def test_openvla_images_equal_tensorflow_reference(vla_reference):
    """Both styles send, bit for bit, what OpenVLA's / OFT's LIBERO code (TensorFlow 2.15) made of the same frames."""
    meta = json.loads(str(vla_reference["meta"]))
    assert meta["tensorflow"] == "2.15.0" and len(meta["scenes"]) == len(vla_reference["openvla_image"]) == 2
    openvla = make_policy("openvla")
    oft = make_policy("openvla", style="oft")
    for i, scene in enumerate(meta["scenes"]):
        task = TaskInfo(scene["suite"], scene["task"], "t", scene["instruction"], [], 300, 50)
        openvla.reset(task, 7)
        oft.reset(task, 7)
        obs = reference_observation(vla_reference, i)
        sent = openvla.request_payload(obs)
        assert sent["image"].dtype == np.uint8 and np.array_equal(sent["image"], vla_reference["openvla_image"][i])
        assert sent["instruction"] == scene["instruction"] and sent["unnorm_key"] == scene["suite"]
        sent = oft.request_payload(obs)
        assert np.array_equal(sent["full_image"], vla_reference["oft_full_image"][i])
        assert np.array_equal(sent["wrist_image"], vla_reference["oft_wrist_image"][i])
        assert sent["state"].dtype == np.float64 and np.array_equal(sent["state"], vla_reference["oft_state"][i])


def test_openvla_reference_pixels_survive_the_wire(vla_reference):
    """json-numpy over HTTP changes nothing: the OFT stand-in receives the reference's arrays."""
    scene = json.loads(str(vla_reference["meta"]))["scenes"][1]
    task = TaskInfo(scene["suite"], scene["task"], "t", scene["instruction"], [], 300, 50)
    with OpenVLAStandin(style="oft", horizon=8, prompt=scene["instruction"]) as server:
        policy = make_policy("openvla", port=server.port, style="oft", timeout_s=5.0)
        policy.reset(task, 7)
        policy.infer(reference_observation(vla_reference, 1))
        policy.close()
    assert server.check_failures == []
    received = server.received[0]
    for key in ("full_image", "wrist_image", "state"):
        assert received[key].dtype == vla_reference[f"oft_{key}"][1].dtype
        assert np.array_equal(received[key], vla_reference[f"oft_{key}"][1]), key


def test_openvla_reference_steps_one_by_one(vla_reference):
    """The resize and the crop each on their own (a failure names the stage), and controls: Pillow's own
    Lanczos (what this client sent before) and our Lanczos-3 without the JPEG round trip are far off."""
    for i in range(len(vla_reference["openvla_image"])):
        rotated = np.ascontiguousarray(vla_reference["agentview_image"][i][::-1, ::-1])
        resized = openvla_resize(rotated, 224)
        assert np.array_equal(resized, vla_reference["oft_full_image"][i]), "JPEG round trip + Lanczos-3"
        assert np.array_equal(openvla_center_crop(resized), vla_reference["openvla_image"][i]), "center crop"
        pil = np.asarray(Image.fromarray(rotated).resize((224, 224), Image.LANCZOS))
        no_jpeg = np.clip(np.round(resize_lanczos3(rotated, 224, 224)), 0, 255).astype(np.uint8)
        for other in (pil, no_jpeg):
            diff = np.abs(other.astype(int) - resized.astype(int))
            assert diff.max() >= 5 and (diff > 0).mean() > 0.2
    # The reference has no shortcut for a frame already at 224: the lossy JPEG round trip still applies.
    at_size = vla_reference["oft_full_image"][0]
    assert np.array_equal(openvla_resize(at_size, 224), jpeg_round_trip(at_size))
    assert not np.array_equal(jpeg_round_trip(at_size), at_size)


def test_lanczos3_spans_are_normalised_and_antialiased():
    starts, weights = _lanczos3_spans(224, 256)
    assert weights.dtype == np.float32 and weights.shape == (224, 9)  # radius 3 widened by 256/224: 9 taps
    assert np.allclose(weights.sum(axis=1), 1.0, atol=1e-6)
    assert starts[0] == 0 and starts[-1] + 9 > 255 and np.all(np.diff(starts) >= 0)
    same_starts, same = _lanczos3_spans(224, 224)  # no scaling: the identity
    assert np.array_equal(same[np.arange(224), np.arange(224) - same_starts], np.ones(224, dtype=np.float32))


# -- whole episodes, in-process (real MuJoCo, real rendering) ---------------------------------
@pytest.fixture(scope="module")
def env():
    e = LiberoEnv("libero_spatial", 0, camera_names=CAMERAS)
    yield e
    e.close()


@pytest.fixture(scope="module")
def scene_256() -> tuple[Observation, dict, dict]:
    """LIBERO-Spatial task 0, init 0, seed 7 at 256 px: our observation, robosuite's own camera observation
    of our env's state at that moment, and the observation of the env class openpi's and OpenVLA's
    evaluations use (OffScreenRenderEnv at 256 px, set_init_state, 10 no-op steps)."""
    from libero.libero import benchmark, get_libero_path
    from libero.libero.envs import OffScreenRenderEnv

    os.environ.setdefault("MUJOCO_GL", "egl")
    ours = LiberoEnv("libero_spatial", 0, camera_names=CAMERAS, camera_size=256)
    try:
        ours.reset(0, 7)
        obs = ours.observe()
        robosuite_now = {}
        # robosuite's camera sensor (its image convention included) at the state the observation was
        # sampled at (inside robosuite's substep loop; LiberoEnv keeps that MjData for rendering).
        live, ours._sim.data._data = ours._sim.data._data, ours._observed_data
        try:
            for cam in CAMERAS:
                sensors, _ = ours._env.env._create_camera_sensors(cam, 256, 256, False, None)
                robosuite_now[cam] = sensors[0]({})
        finally:
            ours._sim.data._data = live
    finally:
        ours.close()
    bench = benchmark.get_benchmark_dict()["libero_spatial"]()
    task = bench.get_task(0)
    bddl = Path(get_libero_path("bddl_files")) / task.problem_folder / task.bddl_file
    ref_env = OffScreenRenderEnv(bddl_file_name=str(bddl), camera_heights=256, camera_widths=256)
    try:
        ref_env.seed(7)
        ref_env.reset()
        ref = ref_env.set_init_state(bench.get_task_init_states(0)[0])
        for _ in range(10):
            ref, *_ = ref_env.step([0.0] * 6 + [-1.0])
    finally:
        ref_env.close()
    return obs, robosuite_now, {key: np.array(value) for key, value in ref.items()}


@pytest.mark.slow
@pytest.mark.sim
def test_real_frames_at_256_are_sent_as_each_reference_preprocesses_them(scene_256):
    """openpi: openpi_client.image_tools on the raw frame, exactly as examples/libero/main.py; OpenVLA / OFT:
    their rotation + JPEG + Lanczos (+ crop); the 8-D state equals the reference env's, bit for bit."""
    from robosuite.utils.transform_utils import quat2axisangle

    obs, robosuite_now, ref = scene_256
    openpi, openvla, oft = make_policy("openpi"), make_policy("openvla"), make_policy("openvla", style="oft")
    assert openpi.render_size == openvla.render_size == oft.render_size == 256 == obs.images["agentview"].shape[0]
    for policy in (openpi, openvla, oft):
        policy.reset(TASK, 7)
    sent_pi, sent_vla, sent_oft = (
        openpi.observation_payload(obs),
        openvla.request_payload(obs),
        oft.request_payload(obs),
    )
    raw = {}
    for cam in CAMERAS:
        # Our upright image is robosuite's camera observation (bottom row first) with its rows flipped back.
        assert np.array_equal(obs.images[cam][::-1], robosuite_now[cam]), cam
        raw[cam] = np.ascontiguousarray(robosuite_now[cam][::-1, ::-1])  # openpi's and OpenVLA's 180-degree turn
    for key, cam in (("observation/image", "agentview"), ("observation/wrist_image", "robot0_eye_in_hand")):
        expected = image_tools.convert_to_uint8(image_tools.resize_with_pad(raw[cam], 224, 224))
        assert sent_pi[key].dtype == np.uint8 and np.array_equal(sent_pi[key], expected), key
    assert np.array_equal(sent_vla["image"], openvla_center_crop(openvla_resize(raw["agentview"], 224)))
    assert np.array_equal(sent_oft["full_image"], openvla_resize(raw["agentview"], 224))
    assert np.array_equal(sent_oft["wrist_image"], openvla_resize(raw["robot0_eye_in_hand"], 224))
    quat = ref["robot0_eef_quat"].copy()  # quat2axisangle clips in place
    state = np.concatenate((ref["robot0_eef_pos"], quat2axisangle(quat), ref["robot0_gripper_qpos"]))
    assert state.dtype == sent_pi["observation/state"].dtype == np.float64
    assert np.array_equal(sent_pi["observation/state"], state) and np.array_equal(sent_oft["state"], state)


@pytest.mark.slow
@pytest.mark.sim
def test_rendered_frame_equals_the_reference_envs_frame(scene_256):
    """robosuite samples its observations inside the substep loop; LiberoEnv renders that instant."""
    obs, _, ref = scene_256
    for cam in CAMERAS:
        assert np.array_equal(obs.images[cam], ref[f"{cam}_image"][::-1]), cam


@pytest.mark.slow
@pytest.mark.sim
def test_openpi_episode_sends_libero_example_payload(tmp_path, env):
    with OpenPIStandin(prompt=env.task.instruction) as server:
        cfg = RunConfig(policy="openpi", policy_args={"port": server.port}, max_steps=12, replan_steps=5)
        policy = make_policy(cfg.policy, **cfg.policy_args)
        outcome = run_inprocess(cfg, tmp_path, env=env, policy=policy)
    assert outcome.status == "failure" and outcome.reason == "timeout"  # the stand-in does not solve tasks
    assert server.check_failures == []
    bag = outcome.bag_path
    observations = decoded(bag, m.OBSERVATION)
    chunks = decoded(bag, m.ACTION_CHUNK)
    images = {cam: [m.image_from_msg(i) for i in decoded(bag, m.camera_topic(cam))] for cam in CAMERAS}
    assert len(observations) == len(chunks) == len(server.received) == len(policy.timings) == 3  # ticks 0, 5, 10
    for k, sent in enumerate(server.received):
        # Cameras rendered only at inference ticks, and exactly what openpi's LIBERO example would send.
        assert np.array_equal(sent["observation/image"], libero_example_image(images["agentview"][k]))
        assert np.array_equal(sent["observation/wrist_image"], libero_example_image(images["robot0_eye_in_hand"][k]))
        obs = m.observation_from_msg(observations[k])
        assert np.array_equal(sent["observation/state"][:3], obs.eef_pos)
        assert np.allclose(sent["observation/state"][3:6], quat_xyzw_to_axis_angle(obs.eef_quat_xyzw))
        assert np.array_equal(m.chunk_actions(chunks[k]), np.tile(standin_action(sent["observation/state"]), (10, 1)))
        assert policy.timings[k]["tick"] == obs.tick == 5 * k
        assert policy.timings[k]["server_infer_ms"] is not None
        # The server's timing travels with its chunk into the bag ...
        assert json.loads(chunks[k].timing_json) == policy.timings[k]
    assert outcome.ticks == 12
    # ... and the scorer reports it.
    row = score_bag(bag)
    server_ms = [t["server_infer_ms"] for t in policy.timings]
    assert row["policy_timing_server_infer_ms_mean"] == pytest.approx(np.mean(server_ms))
    assert row["policy_timing_round_trip_ms_mean"] >= row["policy_timing_server_infer_ms_mean"]
    # The image convention itself, against robosuite's own camera observation (what openpi's example
    # rotates) of the state the observation was sampled at (robosuite samples inside its substep loop).
    sensors, _ = env._env.env._create_camera_sensors("agentview", 224, 224, False, None)
    live, env._sim.data._data = env._sim.data._data, env._observed_data
    try:
        robosuite_image = sensors[0]({})
    finally:
        env._sim.data._data = live
    assert np.array_equal(libero_training_image(env.observe().images["agentview"]), robosuite_image[::-1, ::-1])


@pytest.mark.slow
@pytest.mark.sim
def test_openvla_oft_chunks_run_then_error_answer_ends_episode(tmp_path, env):
    """OFT style: a chunk of 8 runs open-loop (replan 4); the second request gets OpenVLA's 'error'."""
    with OpenVLAStandin(style="oft", horizon=8, prompt=env.task.instruction, fault="error", at_request=2) as server:
        cfg = RunConfig(
            policy="openvla", policy_args={"port": server.port, "style": "oft"}, max_steps=20, replan_steps=4
        )
        outcome = run_inprocess(cfg, tmp_path, env=env)
    assert_error_everywhere(outcome, "answered 'error'")
    assert server.check_failures == [] and len(server.received) == 2 and outcome.ticks == 4
    commands = decoded(outcome.bag_path, m.COMMAND)
    assert len(commands) == 4 and np.allclose([c.action for c in commands], standin_action(server.received[0]["state"]))
    events = decoded(outcome.bag_path, m.EPISODE_EVENTS)
    assert events[-1].kind == m.EventKind.ERROR and "answered 'error'" in events[-1].reason


# Every fault is detected by the clients (test_every_fault_raises_policy_error_quickly); the runner
# turns any PolicyError into an ERROR event the same way, so whole episodes cover one failure per
# stage: no connection at all, a timeout mid-episode (plus the error answer above and, through
# ROS, an error frame and a server that is down).
@pytest.mark.slow
@pytest.mark.parametrize("fault, reason, ticks", [("down", "unreachable", 0), ("slow", "no response within", 4)])
@pytest.mark.sim
def test_openpi_server_failure_ends_episode_as_error(tmp_path, env, fault, reason, ticks):
    server, port = _serve("openpi", fault, at_request=2)
    cfg = RunConfig(
        policy="openpi", policy_args={"port": port, "timeout_s": FAST_TIMEOUT_S}, max_steps=20, replan_steps=4
    )
    started = time.monotonic()
    if server is None:
        outcome = run_inprocess(cfg, tmp_path, env=env)
    else:
        with server:
            outcome = run_inprocess(cfg, tmp_path, env=env)
    assert time.monotonic() - started < 60.0  # a reset and a few ticks; the timeout bounds the wait
    assert_error_everywhere(outcome, reason)
    assert outcome.ticks == ticks
    events = decoded(outcome.bag_path, m.EPISODE_EVENTS)
    assert events[-1].kind == m.EventKind.ERROR and reason in events[-1].reason


# -- through the four ROS processes ------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.sim
@pytest.mark.ros
def test_openpi_through_ros_images_then_server_error(tmp_path):
    """Camera images cross ROS as sensor_msgs/Image and still reach the server exactly as openpi's example."""
    with OpenPIStandin(fault="error", at_request=3) as server:
        cfg = RunConfig(
            policy="openpi", policy_args={"port": server.port, "timeout_s": 10.0}, max_steps=20, replan_steps=4
        )
        outcome, row = run_episode(cfg, tmp_path, "ros")
    assert outcome.status == "error" and row["success"] is None
    assert "openpi server error: RuntimeError: stand-in model failed (injected error)" in row["error_reason"]
    assert server.check_failures == [] and server.requests == 3
    bag = outcome.bag_path
    images = [m.image_from_msg(i) for i in decoded(bag, m.camera_topic("agentview"))]
    wrist = [m.image_from_msg(i) for i in decoded(bag, m.camera_topic("robot0_eye_in_hand"))]
    assert len(images) == len(wrist) == 3  # rendered at the three inference ticks only
    for k, sent in enumerate(server.received):
        assert np.array_equal(sent["observation/image"], libero_example_image(images[k]))
        assert np.array_equal(sent["observation/wrist_image"], libero_example_image(wrist[k]))
    commands = decoded(bag, m.COMMAND)
    assert len(commands) == 8  # two chunks of 4 executed; the third request failed
    assert np.allclose(commands[0].action, standin_action(server.received[0]["observation/state"]))


@pytest.mark.slow
@pytest.mark.sim
@pytest.mark.ros
def test_openvla_server_dies_mid_episode_through_ros(tmp_path):
    """One action per query (OpenVLA); after two answers the server is gone: connection refused -> error."""
    with OpenVLAStandin(fault="crash", at_request=3) as server:
        cfg = RunConfig(policy="openvla", policy_args={"port": server.port, "timeout_s": 5.0}, max_steps=20)
        started = time.monotonic()
        outcome, row = run_episode(cfg, tmp_path, "ros")
    assert time.monotonic() - started < 90.0
    assert outcome.status == "error" and row["success"] is None
    assert "request failed ([Errno 111] Connection refused)" in row["error_reason"]
    assert server.check_failures == [] and server.requests == 2
    bag = outcome.bag_path
    images = [m.image_from_msg(i) for i in decoded(bag, m.camera_topic("agentview"))]
    assert len(images) == 3 and not bag_messages(bag).get(m.camera_topic("robot0_eye_in_hand").name)
    for k, sent in enumerate(server.received):
        assert np.array_equal(sent["image"], openvla_example_image(images[k]))
    commands = decoded(bag, m.COMMAND)
    assert len(commands) == 2  # chunks of one action; the third request found no server
    for sent, command in zip(server.received, commands, strict=True):
        expected = server.action_for(sent)
        expected[6] = -1.0  # OpenVLA's 1 = open -> LIBERO's -1
        assert np.allclose(command.action, expected)
