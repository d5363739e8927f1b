"""The streaming reader's bulk CDR decoding agrees with rosbags' generic deserializer, layout by layout."""

from __future__ import annotations

import numpy as np
import pytest

from lq_ros.recording.mcap_reader import StreamingMcapReader, decode
from lq_ros.wire import messages as m
from tests.scoring.test_bag_scorer import write_with_mcap_library


def _variants(rng: np.random.Generator) -> list[tuple[str, str, int, bytes]]:
    """Messages whose layouts differ within one topic: frame ids, joint names and array lengths vary."""
    store = m.typestore()
    types = store.types
    header = types["std_msgs/msg/Header"]
    stamp = types["builtin_interfaces/msg/Time"]
    out = []
    for i in range(60):
        t_ns = 10**9 + i * 50_000_000
        hdr = header(stamp=stamp(sec=t_ns // 10**9, nanosec=t_ns % 10**9), frame_id="w" * (i % 9))
        little = i % 7 != 3  # a few big-endian payloads too
        pose = types["geometry_msgs/msg/Pose"](
            position=types["geometry_msgs/msg/Point"](*rng.normal(size=3)),
            orientation=types["geometry_msgs/msg/Quaternion"](0.0, 0.0, 0.0, 1.0),
        )
        msg = types["geometry_msgs/msg/PoseStamped"](header=hdr, pose=pose)
        out.append(("/ee", m.EE_POSE.msgtype, t_ns, store.serialize_cdr(msg, m.EE_POSE.msgtype, little_endian=little)))
        n = 7 if i % 5 else 3  # joint count changes now and then
        names = [f"j{k}" * (1 + (i + k) % 3) for k in range(n)]
        effort = rng.normal(size=n) if i % 11 else np.zeros(0)  # some without effort
        joint = types["sensor_msgs/msg/JointState"](
            header=hdr, name=names, position=rng.normal(size=n), velocity=rng.normal(size=n), effort=effort
        )
        out.append(("/joints", m.JOINT_STATES.msgtype, t_ns, store.serialize_cdr(joint, m.JOINT_STATES.msgtype)))
        command = types[m.COMMAND.msgtype](
            header=hdr, tick=i, action=rng.normal(size=i % 8), source=i % 5, request_id=i, chunk_index=0
        )
        out.append(("/cmd", m.COMMAND.msgtype, t_ns, store.serialize_cdr(command, m.COMMAND.msgtype)))
    return out


@pytest.mark.parametrize("chunk_size", [300, 1 << 20])
def test_bulk_decoding_matches_rosbags(tmp_path, chunk_size):
    messages = _variants(np.random.default_rng(0))
    bag = write_with_mcap_library(tmp_path / "variants", messages, chunk_size=chunk_size)
    reader = StreamingMcapReader(next(bag.glob("*.mcap")), {"/ee", "/joints", "/cmd"})
    decoded: dict[str, list] = {"/ee": [], "/joints": [], "/cmd": []}
    for batch in reader.batches():
        for group in decode(batch):
            for row, i in enumerate(group["index"]):
                payload = bytes(batch.payload(int(i)))
                decoded[batch.channel.topic].append((payload, {k: v[row] for k, v in group.items()}))
    assert not reader.damage and reader.complete
    assert [len(v) for v in decoded.values()] == [60, 60, 60]
    for topic, items in decoded.items():
        msgtype = {"/ee": m.EE_POSE.msgtype, "/joints": m.JOINT_STATES.msgtype, "/cmd": m.COMMAND.msgtype}[topic]
        for payload, fields in items:
            ref = m.deserialize(payload, msgtype)
            if topic == "/cmd":
                assert fields["source"] == ref.source
                continue
            assert fields["stamp_ns"] == m.stamp_ns(ref)
            if topic == "/ee":
                p = ref.pose.position
                assert fields["position"].tolist() == [p.x, p.y, p.z]
            else:
                assert fields["velocity"].tolist() == ref.velocity.tolist()
                assert fields["effort"].tolist() == ref.effort.tolist()


def test_payload_shorter_than_its_layout_is_rejected(tmp_path):
    good = m.ee_pose_msg(10**9, [0.1, 0.2, 0.3], [0, 0, 0, 1])
    bag = write_with_mcap_library(tmp_path / "short", [("/ee", m.EE_POSE.msgtype, 10**9, good[:30])])
    reader = StreamingMcapReader(next(bag.glob("*.mcap")), {"/ee"})
    (batch,) = list(reader.batches())
    with pytest.raises(ValueError, match="shorter than its layout"):
        decode(batch)
