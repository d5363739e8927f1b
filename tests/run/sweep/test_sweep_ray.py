"""The Ray backend on a private local Ray: loopback only, no dashboard, results in the same store, clean exit."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from lq_ros.core.run_config import openblas_core
from lq_ros.recording.episode_bag import read_run_metadata
from lq_ros.run import sweep as sw

# Serial (after make test's parallel part): one private Ray at a time (Ray's session folders, /tmp/ray, are the
# machine's).
pytestmark = [pytest.mark.slow, pytest.mark.sim, pytest.mark.serial]

LOOPBACK = {"127.0.0.1", "::1", "::ffff:127.0.0.1"}


def _descendants(pid: int) -> set[int]:
    out, todo = set(), [pid]
    while todo:
        p = todo.pop()
        for task in Path(f"/proc/{p}/task").glob("*"):
            with_children = task / "children"
            for c in map(int, with_children.read_text().split() if with_children.exists() else []):
                if c not in out:
                    out.add(c)
                    todo.append(c)
    return out


def _decode(addr_hex: str) -> str:
    """/proc/net/tcp{,6} address (little-endian hex words) -> text."""
    import ipaddress

    raw = bytes.fromhex(addr_hex)
    words = b"".join(raw[i : i + 4][::-1] for i in range(0, len(raw), 4))
    ip = ipaddress.ip_address(words)
    if ip.version == 6 and ip.ipv4_mapped:
        return f"::ffff:{ip.ipv4_mapped}"
    return str(ip)


def listening_addresses(pids: set[int]) -> dict[int, set[str]]:
    """pid -> addresses its TCP sockets listen on (from /proc, no external tool needed)."""
    inode_to_addr = {}
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        for line in Path(table).read_text().splitlines()[1:]:
            cols = line.split()
            if cols[3] == "0A":  # LISTEN
                inode_to_addr[cols[9]] = _decode(cols[1].split(":")[0])
    out: dict[int, set[str]] = {}
    for pid in pids:
        try:
            fds = list(Path(f"/proc/{pid}/fd").iterdir())
        except OSError:
            continue
        for fd in fds:
            try:
                target = os.readlink(fd)
            except OSError:
                continue
            if target.startswith("socket:["):
                addr = inode_to_addr.get(target[8:-1])
                if addr is not None:
                    out.setdefault(pid, set()).add(addr)
    return out


def test_ray_backend_on_loopback_gathers_results_and_shuts_down(tmp_path):
    # The second policy kills its Ray worker once: the actor is replaced and the episode retried.
    dies_once = {"name": "tests.run.sweep.test_sweep:ExitOncePolicy", "args": {"marker": str(tmp_path / "marker")}}
    raw = {"transport": "inprocess", "tasks": [0], "inits": [0], "policies": ["sine", dies_once]}
    spec = sw.expand_spec({**raw, "latencies_s": [0.1], "modes": ["async"], "max_steps": 6})
    seen: dict[int, set[str]] = {}

    def probe(summary, record) -> None:
        # While Ray runs: every server of every process it started listens on loopback only.
        for pid, addrs in listening_addresses(_descendants(os.getpid())).items():
            seen.setdefault(pid, set()).update(addrs)

    out = tmp_path / "out"
    summary = sw.run_sweep(spec, out, workers=2, backend="ray", on_progress=probe)
    assert summary.counts == {"failure": 2} and summary.retried == 1
    assert seen, "no Ray process was listening during the sweep"
    assert all(addrs <= LOOPBACK for addrs in seen.values()), seen
    records = sw.ResultStore(out).records()
    assert len(records) == 2
    for record in records:
        # Bags travelled back from the Ray worker's own folder into the sweep's store.
        assert (out / record["bag"] / "metadata.yaml").exists()
        assert all((out / a["log"]).exists() for a in record["attempts"])
        assert record["row"]["completion_steps"] == 6
    died = next(r for r in records if r["config"]["policy"] != "sine")
    assert [a["status"] for a in died["attempts"]] == ["error", "failure"]
    assert "Ray worker failed: ActorDiedError" in died["attempts"][0]["reason"]
    import ray

    assert not ray.is_initialized()
    deadline = time.monotonic() + 20
    while (left := _ray_processes()) and time.monotonic() < deadline:
        time.sleep(0.5)
    assert not left, left


def _ray_processes() -> list[bytes]:
    out = []
    for pid in _descendants(os.getpid()):
        try:
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ")
            state = Path(f"/proc/{pid}/status").read_text()
        except OSError:
            continue
        if "zombie" not in state and (b"ray" in cmd or b"gcs_server" in cmd):
            out.append(cmd[:120])
    return out


# -- a Ray cluster of two nodes with token authentication (what `ray start` builds), on loopback -----------------


@pytest.fixture
def two_node_cluster(tmp_path, monkeypatch):
    """A head and a second node (each its own GCS/raylet processes, 1 CPU), token authentication on.

    The token is a file of this test's (RAY_AUTH_TOKEN_PATH), never ~/.ray/auth_token; the cluster's
    processes and the driver (the sweep, in this process) read it from the environment.
    """
    import secrets

    token = tmp_path / "ray_token"
    token.write_text(secrets.token_hex(16))
    monkeypatch.setenv("RAY_AUTH_MODE", "token")
    monkeypatch.setenv("RAY_AUTH_TOKEN_PATH", str(token))
    monkeypatch.delenv("RAY_AUTH_TOKEN", raising=False)
    monkeypatch.setenv("RAY_USAGE_STATS_ENABLED", "0")
    # Nodes started by `ray start` from a plain shell know nothing of lq_ros's OpenBLAS pin.
    monkeypatch.delenv("OPENBLAS_CORETYPE", raising=False)
    from lq_ros.run.sweep.ray_pool import _loopback_only

    _loopback_only()  # both nodes on 127.0.0.1 only
    from ray.cluster_utils import Cluster

    from lq_ros.run.sweep.ray_pool import _reload_ray_auth

    _reload_ray_auth()  # this process's Ray reads the mode and token above (not an earlier test's)
    cluster = Cluster(
        initialize_head=True,
        head_node_args={"num_cpus": 1, "include_dashboard": False, "node_ip_address": "127.0.0.1"},
    )
    second = cluster.add_node(num_cpus=1, node_ip_address="127.0.0.1")
    try:
        yield cluster, {cluster.head_node.node_id, second.node_id}, token
    finally:
        cluster.shutdown()


@pytest.mark.ros
def test_ray_backend_on_a_two_node_cluster_spreads_episodes_and_gathers_bags(tmp_path, two_node_cluster):
    cluster, node_ids, _ = two_node_cluster
    spec = sw.expand_spec({"transport": "ros", "tasks": [0], "inits": [0], "policies": ["sine"], "modes": ["async"],
                           "latencies_s": [0.0, 0.1, 0.2, 0.3], "max_steps": 15})  # fmt: skip
    seen: dict[int, set[str]] = {}

    def probe(summary, record) -> None:
        for pid, addrs in listening_addresses(_descendants(os.getpid())).items():
            seen.setdefault(pid, set()).update(addrs)

    out = tmp_path / "out"
    summary = sw.run_sweep(spec, out, backend="ray", address=cluster.address, on_progress=probe)
    assert summary.counts == {"failure": 4} and summary.retried == 0
    records = sw.ResultStore(out).records()
    assert len(records) == 4
    # The actors were spread: episodes ran on both nodes.
    ran_on = {r["attempts"][-1]["node"]["ray_node_id"] for r in records}
    assert ran_on == node_ids
    for record in records:
        # Each four-node ROS episode ran on its Ray node; its bag and node logs came back to the driver's store.
        bag = out / record["bag"]
        assert (bag / "metadata.yaml").exists() and sorted(p.name for p in bag.glob("logs/*.log"))[:1] == [
            "executor.log"
        ]
        assert record["row"]["completion_steps"] == 15 and record["row"]["transport"] == "ros"
        assert record["row"]["partial"] is False
        assert (out / record["attempts"][-1]["log"]).exists()
        # A Ray worker imports lq_ros (which pins the kernels) before numpy: same kernels as a local run.
        assert read_run_metadata(bag)["versions"]["openblas_core"] == openblas_core()
    assert seen and all(addrs <= LOOPBACK for addrs in seen.values()), seen
    import ray

    assert not ray.is_initialized()  # the driver left; the cluster itself stays up for other drivers
    assert cluster.remaining_processes_alive()


def test_a_driver_without_the_clusters_token_is_refused_in_one_line(tmp_path, two_node_cluster):
    import subprocess
    import sys

    cluster, _, _ = two_node_cluster
    wrong = tmp_path / "wrong_token"
    wrong.write_text("0" * 32)
    spec = tmp_path / "spec.yaml"
    spec.write_text("transport: inprocess\ntasks: [0]\ninits: [0]\npolicies: [sine]\nlatencies_s: [0.1]\n")
    env = dict(os.environ, RAY_AUTH_TOKEN_PATH=str(wrong))
    result = subprocess.run(
        [sys.executable, "-m", "lq_ros.cli", "sweep", str(spec), "--backend", "ray", "--address", cluster.address,
         "--out", str(tmp_path / "out")],
        capture_output=True, text=True, timeout=300, env=env, cwd=Path(__file__).resolve().parents[3],
    )  # fmt: skip
    assert result.returncode == 2
    ours = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert len(ours) == 1 and f"cannot join the Ray cluster at {cluster.address}" in ours[0]
    assert f"RAY_AUTH_TOKEN_PATH={wrong}" in ours[0]
    assert "Traceback" not in result.stderr
    assert not list((tmp_path / "out").glob("bags/*"))
