"""The stack's Fast DDS profile (config/dds/fastdds_participant.xml, lq_ros.transport.ros.stack.FASTDDS_PROFILE):
the launcher hands it to its processes unless the user names their own, and a participant that loads it
announces itself every 0.25 s instead of every 3 s (counted on the loopback port of an unused participant id,
where the announcements of a participant that has discovered nobody arrive)."""

from __future__ import annotations

import socket
import subprocess
import sys
import time

from lq_ros.transport.ros.stack import FASTDDS_PROFILE, FASTDDS_PROFILES_ENV, child_environment, reserved_domain

#: Seconds the probe participant lives; announcements are counted over WINDOW_S from the first.
PROBE_S, WINDOW_S = 3.0, 2.0
PROBE = (
    "import time, rclpy; rclpy.init(); node = rclpy.create_node('lq_discovery_probe'); "
    f"time.sleep({PROBE_S}); node.destroy_node(); rclpy.shutdown()"
)
#: The highest participant id the localhost discovery range announces to (7400 + 250 * domain + 10 + 2 * id).
LAST_PARTICIPANT_ID = 31


def announcements(env: dict[str, str], domain_id: int) -> int:
    """Discovery datagrams one fresh participant sends to an unused participant's port within WINDOW_S."""
    port = 7400 + 250 * domain_id + 10 + 2 * LAST_PARTICIPANT_ID
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", port))
        sock.settimeout(0.1)
        probe = subprocess.Popen([sys.executable, "-c", PROBE], env=env, stderr=subprocess.PIPE)
        first, count = None, 0
        deadline = time.monotonic() + PROBE_S + 20.0
        while time.monotonic() < deadline and (first is None or time.monotonic() < first + WINDOW_S):
            try:
                data = sock.recv(65536)
            except TimeoutError:
                continue
            if data.startswith(b"RTPS"):
                first = first if first is not None else time.monotonic()
                count += 1
        _, stderr = probe.communicate(timeout=PROBE_S + 30.0)
    assert probe.returncode == 0, stderr.decode(errors="replace")[-2000:]
    assert b"XMLPARSER" not in stderr, stderr.decode(errors="replace")[-2000:]  # the profile loaded cleanly
    return count


def test_the_launcher_hands_its_profile_to_the_nodes_unless_the_user_names_one(tmp_path, monkeypatch):
    monkeypatch.delenv(FASTDDS_PROFILES_ENV, raising=False)
    assert child_environment(42, tmp_path)[FASTDDS_PROFILES_ENV] == str(FASTDDS_PROFILE)
    assert FASTDDS_PROFILE.is_file()
    own = tmp_path / "mine.xml"
    monkeypatch.setenv(FASTDDS_PROFILES_ENV, str(own))
    assert child_environment(42, tmp_path)[FASTDDS_PROFILES_ENV] == str(own)


def test_a_participant_with_the_profile_announces_itself_every_quarter_second(tmp_path):
    with reserved_domain() as domain:
        env = child_environment(domain.id, tmp_path / "ros_logs")
        env[FASTDDS_PROFILES_ENV] = str(FASTDDS_PROFILE)
        with_profile = announcements(env, domain.id)
        env.pop(FASTDDS_PROFILES_ENV)  # Fast DDS's defaults: the first announcements 0.1 s apart, then every 3 s
        default = announcements(env, domain.id)
    assert default <= 7, default  # (6 seen)
    assert with_profile >= 9, with_profile  # the same first ones, then about one per 0.25 s (12 seen)
