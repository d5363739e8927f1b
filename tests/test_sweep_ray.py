"""The Ray backend on a private local Ray: loopback only, no dashboard, results in the same store, clean exit."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from lq_ros import sweep as sw

pytestmark = pytest.mark.slow

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
    dies_once = {"name": "tests.test_sweep:ExitOncePolicy", "args": {"marker": str(tmp_path / "marker")}}
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
