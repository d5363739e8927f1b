"""The Ray token is a credential: a private Ray's token is a 0600 file of its own (Ray wrote ~/.ray/auth_token
0644), the programs the workers launch (ROS nodes, the LeRobot server) are not given it, and it is never sent in
clear to a cluster on another machine (the rule the openpi and OpenVLA clients follow)."""

from __future__ import annotations

import os
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from lq_ros.run import sweep as sw
from lq_ros.run.sweep.ray_pool import ALLOW_INSECURE_ENV, RayConnectError, refuse_token_in_clear
from lq_ros.transport.processes import SECRET_ENV

REPO = Path(__file__).resolve().parents[3]


@pytest.fixture
def token_env(monkeypatch, tmp_path):
    for key in ("RAY_AUTH_MODE", "RAY_USE_TLS", ALLOW_INSECURE_ENV, "RAY_AUTH_TOKEN_PATH"):
        monkeypatch.delenv(key, raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))  # no ~/.ray/auth_token of the real user's
    monkeypatch.setenv("RAY_AUTH_TOKEN", "0123456789abcdef")


def test_a_token_is_not_sent_in_clear_to_another_machine(token_env, monkeypatch):
    with pytest.raises(RayConnectError, match="would travel unencrypted to another machine") as refused:
        refuse_token_in_clear("10.1.2.3:6379")
    assert "RAY_USE_TLS=1" in str(refused.value) and "\n" not in str(refused.value)
    assert "0123456789abcdef" not in str(refused.value)  # named by where it comes from, never shown
    refuse_token_in_clear("127.0.0.1:6379")  # loopback: never leaves the machine
    refuse_token_in_clear("localhost:6379")
    monkeypatch.setenv("RAY_USE_TLS", "1")
    refuse_token_in_clear("10.1.2.3:6379")  # encrypted
    monkeypatch.delenv("RAY_USE_TLS")
    monkeypatch.setenv(ALLOW_INSECURE_ENV, "1")
    refuse_token_in_clear("10.1.2.3:6379")  # allowed explicitly
    monkeypatch.delenv(ALLOW_INSECURE_ENV)
    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    refuse_token_in_clear("10.1.2.3:6379")  # no token is sent


def test_lq_sweep_refuses_in_one_line_before_connecting(token_env, tmp_path):
    spec = tmp_path / "spec.yaml"
    spec.write_text("transport: inprocess\ntasks: [0]\ninits: [0]\npolicies: [sine]\nlatencies_s: [0.1]\n")
    result = subprocess.run(
        [sys.executable, "-m", "lq_ros.cli", "sweep", str(spec), "--backend", "ray", "--address", "192.0.2.1:6379",
         "--out", str(tmp_path / "out")],
        capture_output=True, text=True, timeout=120, cwd=REPO,
    )  # fmt: skip
    ours = [line for line in result.stderr.splitlines() if line.strip()]
    assert result.returncode == 2 and len(ours) == 1, result.stderr[-2000:]
    assert not (tmp_path / "out").exists()
    assert "would travel unencrypted" in ours[0] and "Traceback" not in result.stderr


def test_launched_programs_are_not_given_the_token(monkeypatch, tmp_path):
    from lq_ros.policies.lerobot_client import venv_environment
    from lq_ros.transport.ros.stack import child_environment

    monkeypatch.setenv("RAY_AUTH_TOKEN", "secret")
    monkeypatch.setenv("RAY_AUTH_TOKEN_PATH", str(tmp_path / "token"))
    for env in (child_environment(42, tmp_path), venv_environment()):
        assert not set(SECRET_ENV) & set(env)
    assert "OPENPI_API_KEY" not in venv_environment() or "OPENPI_API_KEY" not in os.environ


def _environ(pid: int) -> dict[str, str]:
    try:
        raw = Path(f"/proc/{pid}/environ").read_bytes()
    except OSError:
        return {}
    return dict(item.split("=", 1) for item in raw.decode(errors="replace").split("\0") if "=" in item)


@pytest.mark.slow
@pytest.mark.sim
@pytest.mark.ros
@pytest.mark.serial  # one private Ray at a time (Ray's session folders, /tmp/ray, are the machine's)
def test_a_private_ray_has_a_private_token_its_nodes_never_see(tmp_path, monkeypatch):
    from tests.run.sweep.test_sweep_ray import _descendants

    monkeypatch.setenv("HOME", str(tmp_path / "home"))  # where Ray would write ~/.ray/auth_token
    for key in ("RAY_AUTH_MODE", "RAY_AUTH_TOKEN", "RAY_AUTH_TOKEN_PATH"):
        monkeypatch.delenv(key, raising=False)
    spec = sw.expand_spec({"transport": "ros", "tasks": [0], "inits": [0], "policies": ["sine"], "modes": ["sync"],
                           "latencies_s": [0.0], "max_steps": 30})  # fmt: skip
    seen: dict = {"nodes": {}, "token": None}

    def probe(summary, record) -> None:
        path = os.environ.get("RAY_AUTH_TOKEN_PATH")
        if path and seen["token"] is None:
            seen["token"] = (
                path,
                stat.S_IMODE(os.stat(path).st_mode),
                stat.S_IMODE(os.stat(Path(path).parent).st_mode),
            )
        for pid in _descendants(os.getpid()):
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes() if Path(f"/proc/{pid}/cmdline").exists() else b""
            if b"lq_ros_nodes" in cmd:
                seen["nodes"][pid] = _environ(pid)

    summary = sw.run_sweep(spec, tmp_path / "out", workers=1, backend="ray", on_progress=probe)
    assert summary.counts == {"failure": 1}
    path, mode, folder_mode = seen["token"]
    assert mode == 0o600 and folder_mode == 0o700
    assert not Path(path).exists() and "RAY_AUTH_TOKEN_PATH" not in os.environ  # removed, environment restored
    assert not (tmp_path / "home" / ".ray" / "auth_token").exists()
    assert seen["nodes"], "no node process was seen"
    assert all(not set(SECRET_ENV) & set(env) for env in seen["nodes"].values())
