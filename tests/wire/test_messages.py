"""The shared codec agrees with rclpy's own serialization (real rclpy, real message classes)."""

import numpy as np
import pytest

from lq_ros.core.executor_protocol import Command, Source
from lq_ros.wire import messages as m

rclpy_serialization = pytest.importorskip("rclpy.serialization")


def test_codec_bytes_decode_with_rclpy_and_back():
    from lq_ros.transport.ros.rclpy_helpers import msg_class

    data = m.command_msg(1_500_000_000, Command(tick=20, action=np.arange(7) / 10, source=Source.CHUNK, request_id=3))
    msg = rclpy_serialization.deserialize_message(data, msg_class(m.COMMAND.msgtype))
    assert msg.tick == 20 and list(msg.action) == pytest.approx(list(np.arange(7) / 10)) and msg.request_id == 3
    # rclpy leaves CDR padding bytes uninitialised, so compare decoded content, not bytes.
    back = m.deserialize(bytes(rclpy_serialization.serialize_message(msg)), m.COMMAND.msgtype)
    assert back.tick == 20 and back.request_id == 3 and list(back.action) == list(msg.action)


def test_joint_state_and_chunk_roundtrip():
    from lq_ros.transport.ros.rclpy_helpers import msg_class

    data = m.joint_state_msg(10, np.ones(7), np.zeros(7), np.full(7, 2.5))
    js = rclpy_serialization.deserialize_message(data, msg_class(m.JOINT_STATES.msgtype))
    assert list(js.effort) == [2.5] * 7 and js.name[0] == "robot0_joint1"
    chunk = np.random.default_rng(0).uniform(-1, 1, (8, 7))
    raw = m.chunk_msg(10, 1, 0, 0.2, 0.01, chunk, "x")
    assert np.array_equal(m.chunk_actions(m.deserialize(raw, m.ACTION_CHUNK.msgtype)), chunk)


def test_chunk_with_lying_shape_is_kept_for_rejection():
    raw = m.chunk_msg(10, 1, 0, 0.0, 0.0, np.zeros((2, 7)), "x")
    msg = m.deserialize(raw, m.ACTION_CHUNK.msgtype)
    msg.horizon = 5  # declared shape does not match the data
    assert m.chunk_actions(msg).shape == (1, 14)


def test_leading_stamp_matches_decoded_stamp():
    for data, msgtype in [
        (m.clock_msg(12_345_000_000), m.CLOCK.msgtype),
        (m.joint_state_msg(1_550_000_000, np.ones(7), np.zeros(7), np.ones(7)), m.JOINT_STATES.msgtype),
        (m.event_msg(700_000_000, m.EventKind.STARTED, 4, "x"), m.EPISODE_EVENTS.msgtype),
    ]:
        assert m.leading_stamp_ns(data) == m.stamp_ns(m.deserialize(data, msgtype))


@pytest.mark.parametrize("with_matrix", [True, False])
def test_observation_carries_the_controller_rotation_matrix_when_there_is_one(with_matrix):
    from lq_ros.core.types import Observation
    from lq_ros.transport.ros.rclpy_helpers import msg_class

    rot = np.arange(9, dtype=np.float64).reshape(3, 3) / 7 if with_matrix else None
    obs = Observation(3, 0.15, np.ones(3), np.array([0, 0, 0, 1.0]), np.zeros(2), np.zeros(7), np.zeros(7))
    obs.eef_rot_mat = rot
    data = m.observation_msg(obs, request_id=4)
    via_rclpy = rclpy_serialization.deserialize_message(data, msg_class(m.OBSERVATION.msgtype))
    assert len(via_rclpy.eef_rot_mat) == (9 if with_matrix else 0)
    back = m.observation_from_msg(m.deserialize(data, m.OBSERVATION.msgtype))
    if with_matrix:
        assert back.eef_rot_mat.shape == (3, 3) and np.array_equal(back.eef_rot_mat, rot)  # row-major, bit for bit
    else:
        assert back.eef_rot_mat is None


def _task_sample(**fields):
    from lq_ros.core.types import TaskStateSample

    return TaskStateSample(
        object_names=("drawer_region", "bowl"),
        object_pos=np.zeros((2, 3)),
        object_quat_xyzw=np.tile([0.0, 0.0, 0.0, 1.0], (2, 1)),
        gripper_contact=np.array([True, False]),
        grasped=np.array([False, False]),
        predicate_names=("(open drawer_region)",),
        predicate_values=np.array([False]),
        **fields,
    )


def test_task_state_carries_joints_and_surface_distances():
    from lq_ros.core.types import JOINT_NONE, JOINT_SLIDE

    sample = _task_sample(joint_type=np.array([JOINT_SLIDE, JOINT_NONE]), joint_position=np.array([-0.04, np.nan]),
                          ee_distance=np.array([0.01, 0.2]))  # fmt: skip
    (_, _, raw) = m.task_state_msgs(0, 3, sample)[1]
    joint_pos, kinds, distance = m.task_state_fields(m.deserialize(raw, m.TASK_STATE.msgtype))
    assert kinds.tolist() == [JOINT_SLIDE, JOINT_NONE] and joint_pos[0] == -0.04 and np.isnan(joint_pos[1])
    assert distance.tolist() == [0.01, 0.2]
    # A sample without them (a robot's own task state): no joint, distances unknown.
    (_, _, raw) = m.task_state_msgs(0, 3, _task_sample())[1]
    joint_pos, kinds, distance = m.task_state_fields(m.deserialize(raw, m.TASK_STATE.msgtype))
    assert kinds.tolist() == [JOINT_NONE] * 2 and np.isnan(joint_pos).all() and np.isnan(distance).all()


def test_a_task_state_recorded_before_joints_still_decodes():
    """Older bags hold TaskState without its last three fields: decoded by that definition, without them."""
    legacy = m._legacy_typestore()
    cls = legacy.types[m.TASK_STATE.msgtype]
    assert not hasattr(cls(**_old_fields()), "joint_type")
    raw = bytes(legacy.serialize_cdr(cls(**_old_fields()), m.TASK_STATE.msgtype))
    raw += bytes(-len(raw) % 4)  # padded as Fast DDS delivers it
    msg = m.deserialize(raw, m.TASK_STATE.msgtype)
    assert list(msg.object_names) == ["drawer_region", "bowl"] and m.task_state_fields(msg) is None
    with pytest.raises(Exception, match="TaskState"):  # damaged under either definition: still damage
        m.deserialize(raw[:-8], m.TASK_STATE.msgtype)


def _old_fields() -> dict:
    from rosbags.typesys.stores.ros2_jazzy import builtin_interfaces__msg__Time as Time
    from rosbags.typesys.stores.ros2_jazzy import std_msgs__msg__Header as Header

    return {"header": Header(stamp=Time(sec=0, nanosec=0), frame_id=""), "tick": 3,
            "object_names": ["drawer_region", "bowl"], "gripper_contact": np.array([True, False]),
            "grasped": np.array([False, False]), "predicate_names": ["(open drawer_region)"],
            "predicate_values": np.array([False])}  # fmt: skip
