"""Wall time per episode: in process (a), a long-lived ROS stack (b), a fresh ROS stack per episode (c).

Same task, policy, latency and steps, no cameras, in one run, so the ratios compare like with like.
(a) reuses one env and policy across its episodes, as a sweep worker does; (b) keeps one RosStack (four
managed nodes + lifecycle manager) for all its episodes, as `lq sweep --transport ros` does per worker;
(c) starts and stops the processes for every episode, as `lq run` does. Every figure includes writing and
scoring the bag; (a) and (b) pay the env creation once, in their first episode, (c) in every one. The init
state cycles over 0..9 so consecutive episodes differ. Then the reset of one env: hard (robosuite rebuilds
the MjSim) against soft (LiberoEnv's default after the first reset), both including LIBERO's 10 wait
steps, alternated in the same process.

The floor (CPU time per tick, loops interleaved, median of 15 rounds; benchmarks/tick_floor.py): the same scene's
stock robosuite ``env.step`` and its MuJoCo calls; the same calls with repeated stages skipped (StageReuse);
robosuite's numba controller maths alone; the bit-identical floor (StageReuse's calls and the controller maths in one
loop replaying a real tick, bit for bit); ``LiberoEnv.step`` as a ratio of that floor (the median of the rounds'
paired ratios; target <= 1.2), with and without the fast tick (``LQ_FAST_TICK=off``); raw ``mj_step`` x 25 (the
physics alone). Then a paper cell as a whole in-process sweep (scripted, async 0.2 s, LIBERO-Spatial task 0, 8 init
states, one worker; start-up, resets, bags, scoring included), without and with the fast tick, against the same ticks
through LIBERO's stock ``env.step`` (each bag's commands replayed, its joint positions checked bit for bit; the
CPU of the steps alone; target <= 0.55x). Where an in-process episode's time goes (``--where N``): each
part's CPU time, exclusive of the parts it calls, from timers around MuJoCo's calls, robosuite's numba maths,
LiberoEnv's step, reset and tick state, the task state, robosuite's observables, its policy-step substep, LIBERO's
success check, bag writing, scoring and the policy. Where (b)'s time goes: the CPU seconds each
of its node processes used per episode (episodes 2.., from /proc), against (a)'s wall per episode. A slow policy: with
``--slow-policy S`` the scripted expert sleeps S wall seconds per inference at Δt_sim 0.2 s, in process and
through the long-lived stack, where the policy node's inference overlaps the simulation of the ticks that do not
wait for it.

    .venv/bin/python benchmarks/bench_transport.py [--policy scripted] [--episodes 10] [--resets 5]
        [--floor-ticks 600] [--sweep-inits 8] [--where 3] [--slow-policy 0.15]

``--episodes 0 --resets 0 --slow-policy 0`` prints the floor, the sweep and the time breakdown only.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

from tick_floor import Floor, floor_lines, floor_per_tick  # noqa: E402

from lq_ros.core.run_config import RunConfig  # noqa: E402
from lq_ros.run.episode import run_episode  # noqa: E402
from lq_ros.run.sweep.worker import EpisodeWorker  # noqa: E402
from lq_ros.transport.ros.stack import RosStack  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy", default="scripted")
    parser.add_argument("--episodes", type=int, default=10, help="episodes of (a), (b), (c) each (0: skip)")
    parser.add_argument("--mode", default="async")
    parser.add_argument("--latency", type=float, default=0.2)
    parser.add_argument("--max-steps", type=int, default=220)
    parser.add_argument("--resets", type=int, default=5, help="hard and soft resets each (0: skip)")
    parser.add_argument("--floor-ticks", type=int, default=600, help="ticks of each floor loop, 15 rounds (0: skip)")
    parser.add_argument("--slow-policy", type=float, default=0.15, help="sleep per inference, s (0: skip)")
    parser.add_argument("--sweep-inits", type=int, default=8, help="init states of the sweep vs stock (0: skip)")
    parser.add_argument("--where", type=int, default=3, help="episodes of the time breakdown (0: skip)")
    args = parser.parse_args()
    out = Path(tempfile.mkdtemp(prefix="lq_bench_"))
    try:
        measure(args, out)
    finally:
        shutil.rmtree(out, ignore_errors=True)  # the episodes' bags


def measure(args: argparse.Namespace, out: Path) -> None:
    """Run and print every figure; ``out`` holds the episodes' bags."""
    print(f"load average before: {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    times: dict[str, list[float]] = {"inprocess": []}
    ticks: dict[str, list[int]] = {"inprocess": []}
    if args.episodes:
        times, ticks = compare_transports(args, out)
    if args.floor_ticks:
        # The in-process tick over the episodes after the first (which builds the env): wall per tick.
        floor = floor_per_tick(args.floor_ticks)
        step_s = floor.robosuite_step_s
        print("\n".join(floor_lines(floor)))
        if len(times["inprocess"]) > 1:
            tick_s = statistics.median(
                t / n for t, n in zip(times["inprocess"][1:], ticks["inprocess"][1:], strict=True)
            )
            print(f"  in-process tick {1000 * tick_s:.2f} ms wall (median, episodes 2..) = {tick_s / step_s:.2f}x "
                  f"robosuite's env.step, {tick_s / floor.env_step_s:.2f}x LiberoEnv.step")  # fmt: skip
        if args.sweep_inits:
            sweep_against_stock(floor, args.sweep_inits)
    if args.where:
        where_the_time_goes(args.where, out)
    if args.slow_policy:
        slow(args.slow_policy, out)
    print(f"load average after: {os.getloadavg()[0]:.2f}")
    if args.resets:
        hard, soft = reset_times(args.resets)
        print(f"reset of one env (10 wait steps included): hard {hard:.3f} s, soft {soft:.3f} s, "
              f"hard / soft {hard / soft:.1f}  (target soft <= 0.3 s)")  # fmt: skip


def compare_transports(args: argparse.Namespace, out: Path) -> tuple[dict[str, list[float]], dict[str, list[int]]]:
    """(a), (b) and (c): wall seconds and ticks of each episode, printed with their ratios."""
    cfgs = [
        RunConfig(policy=args.policy, mode=args.mode, latency_s=args.latency, max_steps=args.max_steps, init=i % 10)
        for i in range(args.episodes)
    ]
    names = ("inprocess", "ros_stack", "ros_fresh")
    times: dict[str, list[float]] = {n: [] for n in names}
    ticks: dict[str, list[int]] = {n: [] for n in names}
    worker = EpisodeWorker("inprocess", out / "inprocess")
    stack = RosStack()
    stack_cpu: dict[str, float] = {}  # node -> CPU seconds at the end of (b)'s first episode
    try:
        # Interleaved, so a change of machine load hits the three alike.
        for i, cfg in enumerate(cfgs):
            for name in names:
                start = time.perf_counter()
                if name == "inprocess":
                    env, policy = worker._env_policy(cfg)
                    outcome, _ = run_episode(cfg, out / name, "inprocess", env=env, policy=policy)
                else:
                    outcome, _ = run_episode(cfg, out / name, "ros", stack=stack if name == "ros_stack" else None)
                times[name].append(time.perf_counter() - start)
                ticks[name].append(outcome.ticks)
                assert outcome.status != "error", f"{name} episode {i}: {outcome.reason}"
                if name == "ros_stack" and i == 0:
                    stack_cpu = {node: cpu_seconds(p.pid) for node, p in stack.procs.items()}
        stack_cpu = {node: cpu_seconds(stack.procs[node].pid) - s for node, s in stack_cpu.items()}
    finally:
        stack.close()
        worker.close()
    assert ticks["inprocess"] == ticks["ros_stack"] == ticks["ros_fresh"], ticks  # lockstep: the same episodes
    print(f"config: {args.policy} {args.mode} latency {args.latency} s, {args.episodes} episodes each, no cameras")
    labels = {"inprocess": "(a) in process", "ros_stack": "(b) ROS, long-lived", "ros_fresh": "(c) ROS, fresh"}
    for name in names:
        t = statistics.mean(times[name])
        steps = statistics.mean(ticks[name])
        print(f"{labels[name]:22s} wall per episode {t:6.2f} s  ({steps:.0f} ticks, {1000 * t / steps:.1f} ms per tick;"
              f" first {times[name][0]:.2f} s, median {statistics.median(times[name]):.2f} s)")  # fmt: skip
        print(f"{'':22s} each: {' '.join(f'{t:.2f}' for t in times[name])} s")
    base, base_median = statistics.mean(times["inprocess"]), statistics.median(times["inprocess"])
    print(f"(b)/(a): {statistics.mean(times['ros_stack']) / base:.2f} on means, "
          f"{statistics.median(times['ros_stack']) / base_median:.2f} on medians  (target <= 1.1)")  # fmt: skip
    if len(cfgs) > 2:  # without the first episodes: (a) builds its env there, (b) starts its five processes
        a_later, b_later = times["inprocess"][1:], times["ros_stack"][1:]
        print(f"(b)/(a) over episodes 2..: {statistics.mean(b_later) / statistics.mean(a_later):.2f} on means, "
              f"{statistics.median(b_later) / statistics.median(a_later):.2f} on medians")  # fmt: skip
    print(f"(c)/(a): {statistics.mean(times['ros_fresh']) / base:.2f}")
    if len(cfgs) > 1:
        later = len(cfgs) - 1
        base_later = statistics.mean(times["inprocess"][1:])
        per_node = ", ".join(f"{node} {s / later:.2f} s" for node, s in sorted(stack_cpu.items(), key=lambda x: -x[1]))
        print(f"(b) CPU per episode (episodes 2..): {per_node}; all nodes {sum(stack_cpu.values()) / later:.2f} s, "
              f"the sim alone {stack_cpu['sim'] / later / base_later:.2f}x (a)'s wall per episode "
              f"({base_later:.2f} s)")  # fmt: skip
    return times, ticks


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds a live process has used (/proc/PID/stat, fields 14 and 15)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def sweep_against_stock(floor: Floor, inits: int = 8) -> None:
    """The whole in-process sweep of a paper cell (scripted, async 0.2 s, LIBERO-Spatial task 0, ``inits`` init
    states, one worker: start-up, env creation, resets, bags, scoring and the store included), with the fast tick
    and without it (LQ_FAST_TICK=off), against its ticks through robosuite's stock env.step (``floor``, measured in
    the same run): the worker's CPU seconds and the sweep's wall seconds over ticks x stock step."""
    from lq_ros.core.suite_constants import NUM_WAIT_STEPS
    from lq_ros.run import sweep as sw

    raw = {
        "name": "bench_cell",
        "transport": "inprocess",
        "tasks": [0],
        "inits": list(range(inits)),
        "policies": [{"name": "scripted", "args": {}}],
        "latencies_s": [0.2],
        "modes": ["async"],
    }
    spec = sw.expand_spec(raw)
    saved = os.environ.get("LQ_FAST_TICK")
    results: dict[str, tuple[float, float, int]] = {}
    try:
        for setting in ("off", "on"):
            os.environ["LQ_FAST_TICK"] = setting  # read by the worker's LiberoEnv
            out = Path(tempfile.mkdtemp(prefix="lq_bench_cell_"))
            cpu_before = sum(os.times()[2:4])
            start = time.perf_counter()
            summary = sw.run_sweep(spec, out, workers=1)
            wall = time.perf_counter() - start
            cpu = sum(os.times()[2:4]) - cpu_before
            records = sw.ResultStore(out).records()
            rows = [r["row"] for r in records]
            ticks = sum(int(r.get("action_ticks") or 0) + int(r.get("hold_ticks") or 0) + NUM_WAIT_STEPS for r in rows)
            assert summary.ran == inits, summary
            results[setting] = (cpu, wall, ticks)
            if setting == "on":
                stock_cpu, stock_ticks = replay_through_stock([out / r["bag"] for r in records])
            shutil.rmtree(out, ignore_errors=True)
    finally:
        if saved is None:
            os.environ.pop("LQ_FAST_TICK", None)
        else:
            os.environ["LQ_FAST_TICK"] = saved
    assert results["on"][2] == results["off"][2] == stock_ticks, (results, stock_ticks)  # the same ticks
    print(f"  the cell's ticks replayed through LIBERO's stock env.step (each bag's commands, its joint positions "
          f"checked bit for bit): {stock_ticks} ticks, CPU {stock_cpu:.1f} s ({1000 * stock_cpu / stock_ticks:.2f} ms "
          f"per tick; the floor's static scene: {1000 * floor.robosuite_step_s:.2f} ms)")  # fmt: skip
    for setting, label in (("off", "without the fast tick"), ("on", "with it")):
        cpu, wall, ticks = results[setting]
        print(f"  in-process sweep, {label}: {inits} episodes, {ticks} ticks (wait steps included): worker CPU "
              f"{cpu:.1f} s = {cpu / stock_cpu:.2f}x, wall {wall:.1f} s = {wall / stock_cpu:.2f}x the stock steps' "
              f"CPU (target <= 0.55)")  # fmt: skip


def replay_through_stock(bags: list[Path]) -> tuple[float, int]:
    """Each bag's commands through LIBERO's own env (ControlEnv without a renderer, plus the one forward pass a
    renderer adds at each new MjSim: lq_ros.sim.renderer_passes; reset as LIBERO's evaluations reset it, then the
    10 wait steps): the CPU seconds of its env.step calls alone and their count. Every tick's joint positions must
    equal the bag's (else AssertionError)."""
    import numpy as np
    from libero.libero.envs.env_wrapper import ControlEnv

    from lq_ros.core.suite_constants import DUMMY_ACTION, NUM_WAIT_STEPS
    from lq_ros.recording.bag_compare import bag_messages
    from lq_ros.recording.episode_bag import read_run_metadata
    from lq_ros.sim.libero_env import load_task
    from lq_ros.sim.renderer_passes import take_renderer_passes
    from lq_ros.wire import messages as m

    cpu, ticks = 0.0, 0
    stock, scene = None, None
    try:
        for bag in bags:
            config = read_run_metadata(bag)["config"]
            _, bddl, init_states = load_task(config["suite"], config["task"])
            if scene != (config["suite"], config["task"]):
                if stock is not None:
                    stock.close()
                stock = ControlEnv(bddl_file_name=str(bddl), has_offscreen_renderer=False, use_camera_obs=False)
                take_renderer_passes(stock.env)
                scene = (config["suite"], config["task"])
            msgs = bag_messages(bag)
            commands = [m.deserialize(raw, m.COMMAND.msgtype) for _, raw in msgs[m.COMMAND.name]]
            joints = [m.deserialize(raw, m.JOINT_STATES.msgtype) for _, raw in msgs[m.JOINT_STATES.name]]
            stock.seed(config["seed"])
            np.random.seed(config["seed"])
            stock.reset()
            stock.set_init_state(init_states[config["init"]])
            actions = [np.asarray(DUMMY_ACTION)] * NUM_WAIT_STEPS + [
                np.asarray(c.action, dtype=np.float64) for c in commands
            ]
            arm = np.asarray(stock.env.robots[0]._ref_joint_pos_indexes)
            qpos = stock.env.sim.data._data.qpos
            for i, action in enumerate(actions):
                start = time.process_time()
                stock.step(action)
                cpu += time.process_time() - start
                if i >= NUM_WAIT_STEPS:
                    position = np.asarray(joints[i - NUM_WAIT_STEPS + 1].position)
                    assert np.array_equal(position, qpos[arm]), f"{bag.name}: tick {i - NUM_WAIT_STEPS + 1}"
            ticks += len(actions)
    finally:
        if stock is not None:
            stock.close()
    return cpu, ticks


def where_the_time_goes(episodes: int, out: Path) -> None:
    """Where an in-process episode's time goes (scripted, async 0.2 s, LIBERO-Spatial task 0, init states 1..N after
    one that builds the env): CPU seconds of each part, exclusive of the parts it calls, from timers wrapped around
    the functions below (each adds about a microsecond per call, counted in its caller)."""
    import mujoco
    import robosuite.utils.control_utils as control

    from lq_ros.recording.episode_bag import EpisodeBagWriter
    from lq_ros.run import episode as episode_module
    from lq_ros.sim.libero_env import LiberoEnv
    from lq_ros.sim.task_state import TaskStateProbe

    totals: dict[str, float] = {}
    calls: dict[str, int] = {}
    stack: list[list[float]] = []  # per open timer: [start, time spent in timed callees]

    def timed(label: str, function: Callable) -> Callable:
        def wrapper(*args, **kwargs):
            stack.append([time.process_time(), 0.0])
            try:
                return function(*args, **kwargs)
            finally:
                start, inner = stack.pop()
                spent = time.process_time() - start
                totals[label] = totals.get(label, 0.0) + spent - inner
                calls[label] = calls.get(label, 0) + 1
                if stack:
                    stack[-1][1] += spent

        return wrapper

    patches: list[tuple[object, str, object]] = []

    def patch(owner: object, name: str, label: str) -> None:
        patches.append((owner, name, getattr(owner, name)))
        setattr(owner, name, timed(label, getattr(owner, name)))

    for name in ("mj_forward", "mj_forwardSkip", "mj_step", "mj_step2", "mj_checkPos", "mj_checkVel", "mj_kinematics"):
        patch(mujoco, name, "MuJoCo")
    for name in ("opspace_matrices", "nullspace_torques", "orientation_error"):
        patch(control, name, "robosuite's numba maths (LAPACK)")
    patch(LiberoEnv, "step", "LiberoEnv.step: the fast tick's Python, StageReuse, energy")
    patch(LiberoEnv, "reset", "resets (the 10 wait steps' Python)")
    patch(LiberoEnv, "_tick_state", "tick state (exact EE pose)")
    patch(TaskStateProbe, "sample", "task state (object poses, contacts, predicates)")
    patch(EpisodeBagWriter, "write", "bag writing")
    patch(EpisodeBagWriter, "close", "bag writing")
    patch(episode_module, "scored_row", "scoring")
    patch(episode_module, "run_episode", "episode: executor, messages, the rest")
    worker = EpisodeWorker("inprocess", out / "where")
    try:
        cfgs = [RunConfig(policy="scripted", mode="async", latency_s=0.2, init=i) for i in range(episodes + 1)]
        env, policy = worker._env_policy(cfgs[0])
        episode_module.run_episode(cfgs[0], out / "where", "inprocess", env=env, policy=policy)
        inner = env._env.env
        for name, label in (
            ("_update_observables", "robosuite observables (sampled once per tick)"),
            ("_pre_action", "robosuite's own policy-step substep (a reset's first tick)"),
            ("_check_success", "LIBERO's success check"),
        ):
            setattr(inner, name, timed(label, getattr(inner, name)))
        policy.infer = timed("policy (scripted expert)", policy.infer)
        totals.clear()
        calls.clear()
        ticks = 0
        cpu = time.process_time()
        for cfg in cfgs[1:]:
            outcome, _ = episode_module.run_episode(cfg, out / "where", "inprocess", env=env, policy=policy)
            ticks += outcome.ticks
        cpu = time.process_time() - cpu
        for name in ("_update_observables", "_pre_action", "_check_success"):
            delattr(inner, name)
        del policy.infer
    finally:
        for owner, name, original in reversed(patches):
            setattr(owner, name, original)
        worker.close()
    total = sum(totals.values())
    print(f"where the time goes: {episodes} in-process episodes (scripted, async 0.2 s, Spatial task 0), {ticks} "
          f"ticks, CPU {total:.2f} s ({1000 * total / ticks:.2f} ms per tick; the process: {cpu:.2f} s); per part, "
          f"exclusive of the parts it calls:")  # fmt: skip
    for label, seconds in sorted(totals.items(), key=lambda item: -item[1]):
        print(f"  {100 * seconds / total:5.1f} %  {1000 * seconds / ticks:6.2f} ms per tick  {label} "
              f"({calls[label]} calls)")  # fmt: skip


def slow(sleep_s: float, out: Path, episodes: int = 3) -> None:
    """A policy whose inference takes ``sleep_s`` of wall time, at Δt_sim 0.2 s: in process every inference is
    waited for; through ROS the sim runs on while the policy node computes (lockstep only waits at the due tick)."""
    cfgs = [
        RunConfig(policy="lq_ros.policies.sleepy:SleepyPolicy", policy_args={"sleep_s": sleep_s}, mode="async",
                  latency_s=0.2, init=i)
        for i in range(episodes)
    ]  # fmt: skip
    walls: dict[str, list[float]] = {"inprocess": [], "ros": []}
    stack, worker = RosStack(), EpisodeWorker("inprocess", out / "slow_inprocess")
    try:
        for cfg in cfgs:
            for name in walls:
                start = time.perf_counter()
                if name == "inprocess":
                    env, policy = worker._env_policy(cfg)
                    outcome, _ = run_episode(cfg, out / "slow_inprocess", name, env=env, policy=policy)
                else:
                    outcome, _ = run_episode(cfg, out / "slow_ros", name, stack=stack)
                walls[name].append(time.perf_counter() - start)
                assert outcome.status != "error", f"slow {name}: {outcome.reason}"
    finally:
        stack.close()
        worker.close()
    a, b = statistics.mean(walls["inprocess"]), statistics.mean(walls["ros"])
    print(f"slow policy ({sleep_s} s per inference, async Δt_sim 0.2 s, {episodes} episodes each): in process "
          f"{a:.2f} s, ROS long-lived {b:.2f} s per episode (ROS/in-process {b / a:.2f}; the first ROS episode "
          f"configures the stack)")  # fmt: skip


def reset_times(n: int, suite: str = "libero_spatial", task: int = 0) -> tuple[float, float]:
    """Mean wall seconds of a hard and of a soft reset of one env, alternated (same process, same load)."""
    from lq_ros.sim.libero_env import LiberoEnv

    env = LiberoEnv(suite, task)
    env.reset(0, 7)  # the first reset builds everything once; not counted
    times: dict[bool, list[float]] = {True: [], False: []}
    for i in range(2 * n):
        hard = i % 2 == 0
        start = time.perf_counter()
        env.reset(i % 10, 7, hard=hard)
        times[hard].append(time.perf_counter() - start)
    env.close()
    return statistics.mean(times[True]), statistics.mean(times[False])


if __name__ == "__main__":
    main()
