"""What two launcher settings are worth, each against its alternative in the same run, alternated round by round.

discovery   fresh stacks (one `lq run` episode each, as ``lq_ros.run.episode.run_episode`` through ROS): the nodes
            with the stack's Fast DDS profile (config/dds/fastdds_participant.xml: discovery announced every 0.25 s)
            against Fast DDS's defaults (every 3 s after the first announcements); wall per episode, and how many
            took over 2 s longer than the median (a discovery that waited for the next 3 s announcement)
sim CPU     a long-lived stack (as a sweep worker keeps) with the sim pinned to a CPU of its own during lockstep
            episodes (LQ_SIM_CPU=auto) against the scheduler's choice (off): (b)/(a) over episodes 2.., each (b)
            episode right after the same episode in process (a)

Default episode: the scripted expert, async, Δt_sim 0.2 s, LIBERO-Spatial task 0 (init states cycle over 0..9).

    .venv/bin/python benchmarks/bench_stack_options.py [--fresh 10] [--rounds 2] [--episodes 7]
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import tempfile
import time
from pathlib import Path

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

from lq_ros.core.run_config import RunConfig  # noqa: E402
from lq_ros.run.episode import run_episode  # noqa: E402
from lq_ros.run.sweep.worker import EpisodeWorker  # noqa: E402
from lq_ros.transport.processes import SIM_CPU_ENV  # noqa: E402
from lq_ros.transport.ros.stack import FASTDDS_PROFILES_ENV, RosStack  # noqa: E402

#: Fast DDS's defaults: a default participant profile that sets nothing.
PLAIN_PROFILE = """<?xml version="1.0" encoding="UTF-8"?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <participant profile_name="fastdds_defaults" is_default_profile="true"><rtps/></participant>
</profiles>
"""


def config(init: int) -> RunConfig:
    return RunConfig(policy="scripted", mode="async", latency_s=0.2, max_steps=220, init=init % 10)


def checked(outcome, what: str):
    assert outcome.status != "error", f"{what}: {outcome.reason}"
    return outcome


def discovery(rounds: int, out: Path) -> None:
    plain = out / "fastdds_defaults.xml"
    plain.write_text(PLAIN_PROFILE)
    variants = {"the stack's profile": None, "Fast DDS's defaults": str(plain)}
    walls: dict[str, list[float]] = {name: [] for name in variants}
    for r in range(rounds):
        for v, (name, profile) in enumerate(variants.items()):
            if profile is None:
                os.environ.pop(FASTDDS_PROFILES_ENV, None)  # the launcher hands its own
            else:
                os.environ[FASTDDS_PROFILES_ENV] = profile
            start = time.perf_counter()
            checked(run_episode(config(0), out / "fresh" / f"{r}_{v}", "ros")[0], name)
            walls[name].append(time.perf_counter() - start)
    os.environ.pop(FASTDDS_PROFILES_ENV, None)
    print(f"discovery: {rounds} fresh stacks each, one 164-tick episode per stack, alternated")
    for name, w in walls.items():
        median = statistics.median(w)
        late = sum(t > median + 2.0 for t in w)
        print(f"  {name:20s} wall per episode median {median:.2f} s, mean {statistics.mean(w):.2f} s, "
              f"longest {max(w):.2f} s; {late} of {len(w)} over the median + 2 s")  # fmt: skip


def sim_cpu(rounds: int, episodes: int, out: Path) -> None:
    ratios: dict[str, list[float]] = {"auto": [], "off": []}
    worker = EpisodeWorker("inprocess", out / "inprocess")
    try:
        for r in range(rounds):
            for choice in ratios:
                os.environ[SIM_CPU_ENV] = choice
                a_later, b_later = [], []
                with RosStack() as stack:
                    for i in range(episodes):
                        cfg = config(i)
                        start = time.perf_counter()
                        env, policy = worker._env_policy(cfg)
                        checked(run_episode(cfg, out / f"a{r}{choice}", "inprocess", env=env, policy=policy)[0], "a")
                        a = time.perf_counter() - start
                        start = time.perf_counter()
                        checked(run_episode(cfg, out / f"b{r}{choice}", "ros", stack=stack)[0], f"b {choice}")
                        if i:  # (the first builds the env, and starts the stack's processes)
                            a_later.append(a)
                            b_later.append(time.perf_counter() - start)
                ratios[choice].append(sum(b_later) / sum(a_later))
    finally:
        worker.close()
        os.environ.pop(SIM_CPU_ENV, None)
    print(f"sim CPU: {rounds} long-lived stacks each, {episodes} episodes per stack, (b)/(a) summed over episodes 2..")
    for choice, r in ratios.items():
        print(f"  {SIM_CPU_ENV}={choice:4s} (b)/(a) " + ", ".join(f"{x:.3f}" for x in r)
              + f"  (mean {statistics.mean(r):.3f})")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fresh", type=int, default=10, help="fresh stacks per discovery variant (0: skip)")
    parser.add_argument("--rounds", type=int, default=2, help="long-lived stacks per sim CPU choice (0: skip)")
    parser.add_argument("--episodes", type=int, default=7, help="episodes per long-lived stack")
    args = parser.parse_args()
    print(f"load average before: {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    out = Path(tempfile.mkdtemp(prefix="lq_bench_"))
    try:
        if args.fresh:
            discovery(args.fresh, out)
        if args.rounds:
            sim_cpu(args.rounds, args.episodes, out)
    finally:
        shutil.rmtree(out, ignore_errors=True)  # the episodes' bags
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
