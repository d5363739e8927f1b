"""Soak test: hundreds of episodes through the four-node ROS stack with faults injected; nothing may be lost.

A sweep (``lq_ros.run.sweep.run_sweep``, local workers, ros transport) of short episodes: mostly the sine policy,
plus a policy that raises (``faulty``, fault ``raise``) and a remote policy slower than its timeout (the
``openvla`` client against a stand-in server that answers after 1.5 s, ``timeout_s`` 0.5). About every
``--kill-every`` finished episodes a random node (sim, policy, executor or metrics) of a running episode is
killed with SIGKILL. At the end it prints episodes completed / errored / lost (lost: neither a result
record nor a kept failed attempt; must be 0), the injected kills, and RSS, open file descriptors and
/dev/shm files of every long-lived process (the sweep itself, its workers, multiprocessing's resource
tracker) after the first episode, after ``--warmup`` episodes and at the end, plus any Fast DDS file left
orphaned in /dev/shm.

    .venv/bin/python benchmarks/soak.py [--episodes 200] [--max-steps 30] [--workers 2] [--kill-every 20]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import random
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
os.environ.setdefault("MUJOCO_GL", "egl")
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # tests.standin_servers: the stand-in OpenVLA server

from lq_ros.core.run_config import RunConfig  # noqa: E402
from lq_ros.run.sweep import ResultStore, SweepSpec, SweepSummary, run_sweep  # noqa: E402
from lq_ros.transport.processes import SHM_DIR  # noqa: E402

NODE_NAMES = ("sim", "policy", "executor", "metrics")


# -- processes ---------------------------------------------------------------------------------------------


def children(pid: int) -> list[int]:
    out = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        with contextlib.suppress(OSError):
            out += [int(c) for c in (task / "children").read_text().split()]
    return out


def descendants(pid: int) -> list[int]:
    out, todo = [], [pid]
    while todo:
        kids = children(todo.pop())
        out += kids
        todo += kids
    return out


def cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def age_s(pid: int) -> float:
    """Seconds since the process started."""
    try:
        start_ticks = int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19])
        uptime = float(Path("/proc/uptime").read_text().split()[0])
    except (OSError, IndexError, ValueError):
        return 0.0
    return uptime - start_ticks / os.sysconf("SC_CLK_TCK")


def process_stats(pid: int) -> dict:
    """RSS (MiB), open file descriptors and /dev/shm files (mapped or open) of one process."""
    stats = {"pid": pid, "rss_mib": None, "fds": None, "shm": None}
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                stats["rss_mib"] = int(line.split()[1]) / 1024
        fds = list(Path(f"/proc/{pid}/fd").iterdir())
        stats["fds"] = len(fds)
        shm = set()
        for fd in fds:
            try:
                target = os.readlink(fd)
            except OSError:
                continue
            if target.startswith(f"{SHM_DIR}/"):
                shm.add(target)
        for line in Path(f"/proc/{pid}/maps").read_text().splitlines():
            if f" {SHM_DIR}/" in line:
                shm.add(line[line.index(f"{SHM_DIR}/") :].split()[0])
        stats["shm"] = len(shm)
    except OSError:
        pass
    return stats


def long_lived() -> dict[str, int]:
    """The sweep's long-lived processes: this one, its workers, multiprocessing's resource tracker, and each
    worker's ROS stack (four nodes, the lifecycle manager and the fork server they are started from; a node restarted
    after a kill shows a new PID)."""
    out = {"sweep": os.getpid()}
    for pid in children(os.getpid()):
        cmd = cmdline(pid)
        if "resource_tracker" in cmd:
            out["resource tracker"] = pid
        elif "spawn_main" in cmd:
            out[f"worker {pid}"] = pid
            for node in descendants(pid):
                cmd = cmdline(node)
                name = next((n for n in (*NODE_NAMES, "manager") if f"lq_ros_nodes.{n}_node" in cmd), None)
                name = "fork server" if "lq_ros.transport.ros.fork_server" in cmd else name
                if name:
                    out[f" {name} {node}"] = node
    return out


def fastdds_orphans(before: set[str]) -> list[str]:
    """Fast DDS files in /dev/shm, new since ``before``, whose owner lock nobody holds."""
    import fcntl

    out = []
    for name in sorted(set(os.listdir(SHM_DIR)) - before):
        base = name.removeprefix("sem.").removesuffix("_mutex").removesuffix("_el")
        if not base.startswith(("fastrtps_", "fastdds_")):
            continue
        try:
            fd = os.open(SHM_DIR / f"{base}_el", os.O_RDWR)
        except FileNotFoundError:
            out.append(name)
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            out.append(name)
        except OSError:
            pass
        finally:
            os.close(fd)
    return out


# -- fault injection ---------------------------------------------------------------------------------------


class Killer(threading.Thread):
    """Kills a random node of a running episode with SIGKILL about every ``every`` finished episodes."""

    def __init__(self, every: int, seed: int) -> None:
        super().__init__(daemon=True)
        self.every, self.rng = every, random.Random(seed)
        self.finished = 0
        self.next_at = self.rng.randint(every // 2, every)
        self.kills: list[str] = []
        self.stop = threading.Event()

    def run(self) -> None:
        while not self.stop.wait(0.2):
            if self.finished < self.next_at:
                continue
            # A node of an episode that is well under way (its sim node up for 3 s or more).
            nodes = [(name, pid) for pid in descendants(os.getpid()) for name in NODE_NAMES
                     if f"lq_ros_nodes.{name}_node" in cmdline(pid)]  # fmt: skip
            sims = [pid for name, pid in nodes if name == "sim" and age_s(pid) > 3.0]
            if not sims:
                continue
            name, pid = self.rng.choice(nodes)
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                continue
            self.kills.append(f"{name} node at {self.finished} episodes")
            self.next_at = self.finished + self.rng.randint(self.every // 2, self.every * 3 // 2)


# -- the soak ----------------------------------------------------------------------------------------------


def soak_configs(n: int, max_steps: int, openvla_port: int) -> list[RunConfig]:
    """``n`` short episodes: one in ten raises in its policy, one in ten is a remote policy slower than its timeout."""
    configs, i = [], 0
    while len(configs) < n:
        task, init, mode, latency = i % 10, (i // 10) % 5, ("sync", "async")[i % 2], (0.0, 0.1, 0.2)[i % 3]
        common = dict(task=task, init=init, seed=7 + i // 50, mode=mode, latency_s=latency, max_steps=max_steps)
        if i % 10 == 3:
            cfg = RunConfig(policy="faulty", policy_args={"fault": "raise", "at_requests": [2]}, **common)
        elif i % 10 == 7:
            cfg = RunConfig(policy="openvla", policy_args={"port": openvla_port, "timeout_s": 0.5}, **common)
        else:
            cfg = RunConfig(policy="sine", **common)
        if cfg.key() not in {c.key() for c in configs}:
            configs.append(cfg)
        i += 1
    return configs


def print_stats(snapshots: dict[str, dict[str, dict]]) -> None:
    print(f"\n{'process':<18} {'when':<22} {'RSS MiB':>9} {'open fds':>9} {'/dev/shm':>9}")
    for proc in dict.fromkeys(k for snap in snapshots.values() for k in snap):
        for when, snap in snapshots.items():
            s = snap.get(proc)
            if s is None:
                continue
            rss = f"{s['rss_mib']:.1f}" if s["rss_mib"] is not None else "-"
            print(f"{proc:<18} {when:<22} {rss:>9} {s['fds'] if s['fds'] is not None else '-':>9} "
                  f"{s['shm'] if s['shm'] is not None else '-':>9}")  # fmt: skip


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--max-steps", type=int, default=30)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--kill-every", type=int, default=20)
    parser.add_argument("--warmup", type=int, default=20, help="episodes before the 'warm' snapshot")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None, help="sweep folder (default: a new temp dir)")
    args = parser.parse_args()
    from tests.standin_servers import OpenVLAStandin

    out = args.out or Path(tempfile.mkdtemp(prefix="lq_soak_"))
    shm_before = set(os.listdir(SHM_DIR))
    snapshots: dict[str, dict[str, dict]] = {}
    killer = Killer(args.kill_every, args.seed)

    def on_progress(summary: SweepSummary, record: dict | None) -> None:
        if record is None:
            return
        killer.finished = summary.ran
        if summary.ran == 1:
            snapshots["after 1 episode"] = {k: process_stats(p) for k, p in long_lived().items()}
        if summary.ran == args.warmup:
            snapshots[f"after {args.warmup} episodes"] = {k: process_stats(p) for k, p in long_lived().items()}
        if summary.ran == summary.total - summary.skipped:  # the last episode: workers still up
            snapshots["end"] = {k: process_stats(p) for k, p in long_lived().items()}
        if summary.ran % 10 == 0:
            c = summary.counts
            print(f"[{time.strftime('%H:%M:%S')}] {summary.ran} finished ({c['success']} success, "
                  f"{c['failure']} failure, {c['error']} error), {summary.retried} retried, {len(killer.kills)} "
                  f"kills", flush=True)  # fmt: skip

    started = time.monotonic()
    with OpenVLAStandin(fault="slow", at_request=1, slow_s=1.5) as server:
        configs = soak_configs(args.episodes, args.max_steps, server.port)
        spec = SweepSpec("soak", tuple(configs), "ros", None, {"name": "soak", "episodes": len(configs)})
        print(f"soak: {len(configs)} episodes (max_steps {args.max_steps}, ros transport, {args.workers} workers) "
              f"into {out}", flush=True)  # fmt: skip
        killer.start()
        summary = run_sweep(spec, out, workers=args.workers, transport="ros", on_progress=on_progress)
        killer.stop.set()
    wall = time.monotonic() - started

    store = ResultStore(out)
    records = {r["key"]: r for r in store.records()}
    kept = list(store.attempts.glob("*.json"))
    lost = [c.episode_name() for c in configs if c.key() not in records and not store.failed_attempts(c.key())]
    final = {s: sum(r["status"] == s for r in records.values()) for s in ("success", "failure", "error")}
    attempts = sum(len(r["attempts"]) for r in records.values())
    killed_episodes = [r for r in records.values() if any("exited with code -9" in a["reason"] for a in r["attempts"])]
    print(
        f"\nepisodes: {len(configs)}  completed: {final['success'] + final['failure']} "
        f"({final['success']} success, {final['failure']} failure)  errored: {final['error']}  lost: {len(lost)}"
    )
    print(f"attempts: {attempts} ({summary.retried} retried; {len(kept)} failed attempts kept with their bags)")
    print(
        f"injected: {len(killer.kills)} kill -9 ({', '.join(killer.kills) or 'none'}); episodes with a killed "
        f"node: {len(killed_episodes)}, final status {sorted(r['status'] for r in killed_episodes)}"
    )
    reasons: dict[str, int] = {}
    for r in records.values():
        if r["status"] == "error":
            reason = r["row"].get("error_reason") or r["attempts"][-1]["reason"]
            key = (
                "policy raised"
                if "injected failure" in reason
                else "slower than timeout"
                if "within" in reason
                else reason
            )
            reasons[key] = reasons.get(key, 0) + 1
    print(f"errors by cause: {json.dumps(reasons)}")
    print(f"wall time: {wall / 60:.1f} min ({wall / max(1, attempts):.1f} s per attempt)")
    print_stats(snapshots)
    orphans = fastdds_orphans(shm_before)
    print(f"\norphaned Fast DDS files in /dev/shm at the end: {len(orphans)} {orphans[:8]}")
    print(f"results: {out}")
    return 0 if not lost and not orphans else 1


if __name__ == "__main__":
    sys.exit(main())
