"""Sweep throughput: episodes per wall second and per CPU-second for each worker count on the same spec.

Each run is a fresh sweep folder (nothing skipped) and includes everything a user waits for: worker
start-up, env creation (once per worker and task), episodes, scoring and the durable store. Episodes per
CPU-second (the workers' CPU, their node processes included) is what sizes a cluster: a paper-sized run's
episodes divided by it is the CPU-seconds it needs. The machine's load average is printed before and after,
since a shared machine changes the figures. Before and after: each worker count runs the spec first without the
fast tick (``LQ_FAST_TICK=off``: robosuite's own ``env.step``, the same episodes bit for bit) and then with it, and
prints both rates (``--no-before`` skips the first). The simulation floor puts the wall in the machine's own terms:
the sweep's ticks (each episode's, plus LIBERO's 10 wait steps per reset) times ``LiberoEnv.step`` on this machine
(CPU time; measured before and after the sweeps in the same run, bench_transport.floor_per_tick), divided by the
workers: no transport, bag, scoring or start-up can make a sweep faster than that. The same ticks through
robosuite's stock ``env.step`` are printed beside it. ``--spec FILE`` runs a spec file instead of the generated one
(e.g. benchmarks/specs/demo_sweep.yaml); ``--transport`` then overrides the spec's.

    .venv/bin/python benchmarks/bench_sweep.py [--transport inprocess] [--policy scripted] [--policy-arg K=V]
        [--tasks 2] [--inits 2] [--latencies 0 0.2] [--max-steps 0] [--workers 1 2] [--spec FILE] [--floor-ticks 200]
        [--no-before]
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

from bench_transport import floor_per_tick  # noqa: E402

from lq_ros.core.suite_constants import NUM_WAIT_STEPS  # noqa: E402
from lq_ros.run import sweep as sw  # noqa: E402


def _children_cpu_s() -> float:
    t = os.times()
    return t.children_user + t.children_system


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--transport", default="inprocess", choices=sw.TRANSPORTS)
    parser.add_argument("--policy", default="scripted")
    parser.add_argument("--tasks", type=int, default=2, help="LIBERO-Spatial tasks 0..N-1")
    parser.add_argument("--inits", type=int, default=2, help="init states 0..N-1")
    parser.add_argument("--latencies", type=float, nargs="+", default=[0.0, 0.2])
    parser.add_argument("--max-steps", type=int, default=0, help="0: the suite's budget (220)")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--policy-arg", action="append", default=[], help="K=V (a number or text), repeatable")
    parser.add_argument("--spec", type=Path, help="a sweep spec file instead of the generated spec")
    parser.add_argument("--floor-ticks", type=int, default=200, help="ticks of bare env.step for the floor (0: skip)")
    parser.add_argument("--no-before", action="store_true", help="skip the runs without the fast tick")
    args = parser.parse_args()
    if args.spec:
        spec = sw.load_spec(args.spec)
        spec = sw.SweepSpec(spec.name, spec.configs, args.transport, spec.timeout_s, spec.raw)
        print(f"spec: {args.spec} ({len(spec.configs)} episodes, {args.transport})")
        return measure(spec, args.workers, args.transport, args.floor_ticks, not args.no_before)
    policy_args = {k: _value(v) for k, _, v in (a.partition("=") for a in args.policy_arg)}
    raw = {
        "name": "bench",
        "transport": args.transport,
        "tasks": list(range(args.tasks)),
        "inits": list(range(args.inits)),
        "policies": [{"name": args.policy, "args": policy_args}],
        "latencies_s": args.latencies,
        "modes": ["sync", "async"],
        "max_steps": args.max_steps,
    }
    spec = sw.expand_spec(raw)
    steps = args.max_steps or "suite"
    print(f"spec: {len(spec.configs)} episodes ({args.policy} {policy_args}, {args.transport}, tasks {raw['tasks']}, "
          f"inits {raw['inits']}, latencies {args.latencies} s, sync+async, max_steps {steps})")  # fmt: skip
    measure(spec, args.workers, args.transport, args.floor_ticks, not args.no_before)


def _value(text: str) -> float | str:
    try:
        return float(text)
    except ValueError:
        return text


def _sweep_ticks(out: Path) -> int:
    """Every tick the sweep's episodes simulated: their executed ticks plus each reset's wait steps."""
    rows = [r["row"] for r in sw.ResultStore(out).records()]
    return sum(int(r.get("action_ticks") or 0) + int(r.get("hold_ticks") or 0) + NUM_WAIT_STEPS for r in rows)


def _run(spec: sw.SweepSpec, n: int, transport: str, fast_tick: str) -> tuple[float, float, int, int]:
    """One sweep in a fresh folder with ``LQ_FAST_TICK=fast_tick``: (wall s, workers' CPU s, episodes, ticks)."""
    out = Path(tempfile.mkdtemp(prefix=f"lq_bench_sweep_{n}w_"))
    saved = os.environ.get("LQ_FAST_TICK")
    os.environ["LQ_FAST_TICK"] = fast_tick  # read by every worker's LiberoEnv (and sim node)
    try:
        load_before = os.getloadavg()[0]
        cpu_before = _children_cpu_s()
        started = time.perf_counter()
        summary = sw.run_sweep(spec, out, workers=n)
        wall = time.perf_counter() - started
        cpu = _children_cpu_s() - cpu_before
        load_after = os.getloadavg()[0]
        ticks = _sweep_ticks(out)
    finally:
        if saved is None:
            os.environ.pop("LQ_FAST_TICK", None)
        else:
            os.environ["LQ_FAST_TICK"] = saved
        shutil.rmtree(out, ignore_errors=True)
    print(f"{n} worker(s), {transport}, fast tick {fast_tick}: {summary.ran} episodes in {wall:.1f} s = "
          f"{summary.ran / wall:.3f} episodes/s, {summary.ran / cpu:.3f} episodes per CPU-second "
          f"({dict(summary.counts)}; worker CPU {cpu:.0f} s; {ticks} ticks; load avg {load_before:.1f} -> "
          f"{load_after:.1f} on {os.cpu_count()} cores)")  # fmt: skip
    return wall, cpu, summary.ran, ticks


def measure(spec: sw.SweepSpec, workers: list[int], transport: str, floor_ticks: int, before: bool = True) -> None:
    """Each worker count's sweep; with ``before``, first without the fast tick (LQ_FAST_TICK=off), then with it."""
    rates: dict[int, float] = {}
    walls: dict[int, float] = {}
    ticks: dict[int, int] = {}  # per worker count: episodes may end differently from run to run
    floor_before = floor_per_tick(floor_ticks, repetitions=5) if floor_ticks else None
    for n in workers:
        if before:
            wall_off, cpu_off, ran_off, _ = _run(spec, n, transport, "off")
        wall, cpu, ran, ticks[n] = _run(spec, n, transport, "on")
        rates[n] = ran / wall
        walls[n] = wall
        if before:
            print(f"  episodes per CPU-second, {n} worker(s): before (fast tick off) {ran_off / cpu_off:.3f}, after "
                  f"{ran / cpu:.3f} ({cpu_off / ran_off / (cpu / ran):.2f}x); per wall second {ran_off / wall_off:.3f} "
                  f"-> {ran / wall:.3f}")  # fmt: skip
    if floor_before and ticks:
        floor_after = floor_per_tick(floor_ticks, repetitions=5)
        # the mean of before and after: the machine's speed drifts during a long run
        step_s = (floor_before.env_step_s + floor_after.env_step_s) / 2
        stock_s = (floor_before.robosuite_step_s + floor_after.robosuite_step_s) / 2
        per_workers = "; ".join(
            f"{n} worker(s): {ticks[n]} ticks, floor {ticks[n] * step_s / n:.1f} s, "
            f"wall / floor {walls[n] * n / (ticks[n] * step_s):.2f}, through robosuite's stock step "
            f"{ticks[n] * stock_s / n:.1f} s"
            for n in walls
        )
        print(f"simulation floor (ticks, wait steps included, x LiberoEnv.step {1000 * step_s:.2f} ms: the mean of "
              f"{1000 * floor_before.env_step_s:.2f} ms before the sweeps and {1000 * floor_after.env_step_s:.2f} ms "
              f"after / workers; robosuite's stock env.step {1000 * stock_s:.2f} ms): {per_workers}")  # fmt: skip
    if len(rates) >= 2:
        lo, hi = min(rates), max(rates)
        print(f"speed-up {hi} vs {lo} worker(s): {rates[hi] / rates[lo]:.2f}x")


if __name__ == "__main__":
    main()
