"""Remote VLA clients (openpi websocket, OpenVLA REST) against stand-in servers on 127.0.0.1.

The stand-ins (tests/standin_servers.py) speak the real wire protocols and check every request;
here we check what the clients send (against the images and states recorded in the bag), what
they return, the server timing they keep, and that every server failure ends the episode as an
*error* with its reason, quickly (never a hang, a success or a plain failure).
"""

import json
import time
from pathlib import Path

import numpy as np
import pytest
import requests
from openpi_client import image_tools
from scipy.spatial.transform import Rotation

from lq_ros import messages as m
from lq_ros.config import RunConfig
from lq_ros.env import LiberoEnv, Observation, TaskInfo
from lq_ros.episode import run_episode
from lq_ros.policies import PolicyError, make_policy
from lq_ros.policies.openpi_remote import libero_training_image, quat_xyzw_to_axis_angle
from lq_ros.runner import run_inprocess
from lq_ros.scoring import score_bag
from tests.bag_compare import bag_messages
from tests.standin_servers import OpenPIStandin, OpenVLAStandin, free_port, standin_action

CAMERAS = ("agentview", "robot0_eye_in_hand")
TASK = TaskInfo("libero_spatial", 0, "t0", "pick up the black bowl", [], 220, 50)
FAST_TIMEOUT_S = 0.5  # client timeout used against the 'slow' stand-ins


def synthetic_obs(size: int = 224, tick: int = 3) -> Observation:
    rng = np.random.default_rng(tick)
    quat = np.array([0.99, 0.05, 0.1, 0.02])
    return Observation(
        tick=tick,
        sim_time_s=(10 + tick) * 0.05,
        eef_pos=np.array([-0.2, 0.01, 1.17]),
        eef_quat_xyzw=quat / np.linalg.norm(quat),
        gripper_qpos=np.array([0.039, -0.039]),
        joint_pos=np.zeros(7),
        joint_vel=np.zeros(7),
        images={cam: rng.integers(0, 256, (size, size, 3), dtype=np.uint8) for cam in CAMERAS},
    )


def libero_example_image(upright: np.ndarray) -> np.ndarray:
    """What openpi's LIBERO example sends for a camera, from our upright image (rows flipped back)."""
    robosuite_obs = upright[::-1]
    return image_tools.convert_to_uint8(image_tools.resize_with_pad(robosuite_obs[::-1, ::-1], 224, 224))


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
    obs = synthetic_obs()
    columns = np.broadcast_to(np.arange(224, dtype=np.uint8)[None, :, None], (224, 224, 3))
    obs.images["agentview"] = np.ascontiguousarray(columns[:, ::-1])  # the 180-degree rotation undoes the mirror
    with OpenVLAStandin() as server:
        for crop in (False, True):
            policy = make_policy("openvla", port=server.port, center_crop=crop, timeout_s=5.0)
            policy.reset(TASK, 7)
            policy.infer(obs)
    plain, cropped = server.received[0]["image"], server.received[1]["image"]
    assert np.array_equal(plain, columns)
    # Column j of the crop samples column (224 - s) / 2 + (j + 0.5) s / 224 - 0.5, s = 224 sqrt(0.9).
    side = 224 * np.sqrt(0.9)
    expected = (224 - side) / 2 + (np.arange(224) + 0.5) * side / 224 - 0.5
    assert cropped.shape == (224, 224, 3) and np.abs(cropped[112, :, 0] - expected).max() <= 1.0


# -- whole episodes, in-process (real MuJoCo, real rendering) ---------------------------------
@pytest.fixture(scope="module")
def env():
    e = LiberoEnv("libero_spatial", 0, camera_names=CAMERAS)
    yield e
    e.close()


@pytest.mark.slow
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
    # rotates) of the env's current state.
    sensors, _ = env._env.env._create_camera_sensors("agentview", 224, 224, False, None)
    robosuite_image = sensors[0]({})
    assert np.array_equal(libero_training_image(env.observe().images["agentview"]), robosuite_image[::-1, ::-1])


@pytest.mark.slow
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
        assert np.array_equal(sent["image"], libero_example_image(images[k]))
    commands = decoded(bag, m.COMMAND)
    assert len(commands) == 2  # chunks of one action; the third request found no server
    for sent, command in zip(server.received, commands, strict=True):
        expected = server.action_for(sent)
        expected[6] = -1.0  # OpenVLA's 1 = open -> LIBERO's -1
        assert np.allclose(command.action, expected)
