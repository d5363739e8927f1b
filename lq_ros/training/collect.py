"""Collect expert demonstrations with DART-style action noise (no ROS, one LiberoEnv per task).

At every tick the expert labels the observation with its clean action (and its open-loop plan of
``chunk_rows`` actions); the simulator executes the label plus Gaussian noise on the six arm
dimensions (the gripper command is never perturbed). The noisy execution drives the robot off the
expert's path, so the labels cover recoveries. Only successful episodes are kept; the others are
counted in info.json. Each init state can be run ``repeats`` times (different noise draws and levels).
With ``fresh`` the episodes start from new random object placements (LIBERO's own placement sampler,
seeded) instead of the shipped init states: more distinct scenes than the 40 shipped ones outside the
evaluation set. A task's episodes run in one env in a fixed order, deterministic given the configuration.

DAgger under latency (``latency_ticks`` non-empty): each episode draws a driver from ``latency_drivers``, a
protocol from ``modes`` and a latency N from ``latency_ticks``; the driver's chunks go through the executor's
protocol core (lq_ros/core/executor_protocol.py, the same ``ExecutorCore``/``TickDriver`` every transport runs:
sync holds, async drops the N stale rows and replaces the buffer), so the robot visits the states evaluation
produces (held robot, stale-dropped plans, late chunks). The expert labels every tick closed loop; the
simulator gets the executor's command plus arm noise and, with ``gripper_noise``, bursts of a wrong gripper
command.
"""

from __future__ import annotations

import multiprocessing as mp
import pickle
import shutil
import sys
import time
from dataclasses import MISSING, dataclass, field, fields
from pathlib import Path

import numpy as np

from lq_ros.core.safe_write import replacing
from lq_ros.core.suite_constants import ACTION_DIM, ACTION_HIGH, ACTION_LOW, NUM_INIT_STATES, NUM_TASKS
from lq_ros.policies.learned.features import layout_for, raw_from_observation
from lq_ros.training.dataset import Episode, write_dataset


@dataclass(frozen=True)
class CollectConfig:
    suite: str = "libero_spatial"
    tasks: tuple[int, ...] = tuple(range(10))
    #: Init states used per task; the default leaves 0-9 (the evaluation set) out of the training data.
    inits: tuple[int, ...] = tuple(range(10, 30))
    #: Noise std (action units, arm dims) of each episode, cycled over the episodes.
    noise_levels: tuple[float, ...] = (0.0, 0.1, 0.2)
    #: Episodes per init state (each with its own noise draw; the level cycles over all episodes).
    repeats: int = 1
    #: ``inits`` are seeds of fresh random placements (sampled by LIBERO's placement initializer), not
    #: indices of the shipped init states.
    fresh: bool = False
    seed: int = 7
    expert: str = "scripted"
    #: Rows of the expert's open-loop plan stored per frame (the chunk targets, H <= chunk_rows).
    chunk_rows: int = 16
    #: Tick budget per episode; 0: the suite's.
    max_steps: int = 0
    workers: int = 2
    expert_args: dict = field(default_factory=dict)
    #: DAgger: a policy that drives the robot instead of the expert (registry name + keyword arguments,
    #: executing ``driver_replan`` actions of each of its chunks open loop); the expert still labels every
    #: tick. None: the expert drives (plain demonstrations).
    driver: str | None = None
    driver_args: dict = field(default_factory=dict)
    driver_replan: int = 8
    #: Keep unsuccessful episodes too (DAgger: the expert's labels of the states a learner got stuck in).
    keep_failures: bool = False
    #: DAgger under latency: latency ticks N drawn per episode (empty: off, the loops above).
    latency_ticks: tuple[int, ...] = ()
    #: Protocols drawn per episode ("sync", "async"; merge replace) with ``latency_ticks``.
    modes: tuple[str, ...] = ("sync", "async")
    #: Drivers drawn per episode with ``latency_ticks`` (``name[:key=value,...]``, e.g. "scripted", "oft", "flow").
    latency_drivers: tuple[str, ...] = ("scripted",)
    #: Per tick, probability that a burst (2-7 ticks) of a wrong gripper command starts (0: never).
    gripper_noise: float = 0.0

    def __post_init__(self) -> None:
        if not self.tasks or not self.inits:
            raise ValueError("need at least one task and one init state")
        if any(s < 0 for s in self.noise_levels) or not self.noise_levels:
            raise ValueError(f"noise levels must be >= 0 and non-empty, got {self.noise_levels}")
        if self.chunk_rows < 1 or self.workers < 1 or self.repeats < 1:
            raise ValueError("chunk_rows, workers and repeats must be >= 1")
        layout_for(self.suite)  # fails early for a suite without a feature layout
        n_tasks = NUM_TASKS.get(self.suite, 0)
        if bad := [t for t in self.tasks if not 0 <= t < n_tasks]:
            raise ValueError(f"task {bad[0]} is out of range: {self.suite} has tasks 0..{n_tasks - 1}")
        if not self.fresh and (bad := [i for i in self.inits if not 0 <= i < NUM_INIT_STATES]):
            raise ValueError(
                f"init state {bad[0]} is out of range: every task has init states 0..{NUM_INIT_STATES - 1}"
                " (--fresh takes any seed)"
            )
        if any(n < 0 for n in self.latency_ticks) or any(m not in ("sync", "async") for m in self.modes):
            raise ValueError(f"latency ticks must be >= 0 and modes sync/async, got {self.latency_ticks} {self.modes}")
        if self.latency_ticks and (not self.modes or not self.latency_drivers):
            raise ValueError("DAgger under latency needs at least one mode and one driver")
        if not 0.0 <= self.gripper_noise < 1.0:
            raise ValueError(f"gripper_noise is a probability per tick in [0, 1), got {self.gripper_noise}")

    def to_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.__dict__.items()}


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def collect_task(cfg: CollectConfig, task_id: int) -> tuple[list[Episode], dict, str]:
    """All episodes of one task with one env; returns (kept episodes, stats, instruction)."""
    from lq_ros.policies import make_policy
    from lq_ros.sim.libero_env import LiberoEnv

    layout = layout_for(cfg.suite)
    env = LiberoEnv(cfg.suite, task_id)
    expert = make_policy(cfg.expert, chunk_size=cfg.chunk_rows, **cfg.expert_args)
    driver = make_policy(cfg.driver, **cfg.driver_args) if cfg.driver else None
    pool = [parse_spec(spec) for spec in cfg.latency_drivers] if cfg.latency_ticks else []
    made: dict[tuple[int, str], object] = {}

    def pooled(k: int, mode: str):
        """Driver k for an episode in ``mode`` (a delay-aware learned policy is told the protocol it runs under)."""
        name, args = pool[k]
        key = (k, mode if args.get("variant") == "delay" else "")
        if key not in made:
            made[key] = make_policy(name, **({**args, "mode": mode} if key[1] else args))
        return made[key]

    budget = cfg.max_steps or env.task.step_budget
    kept: list[Episode] = []
    stats = {"attempts": 0, "successes": 0, "failures": 0, "errors": 0, "frames": 0, "wall_s": 0.0}
    by_noise: dict[str, list[int]] = {}
    try:
        for k, (init, rep) in enumerate((i, r) for i in cfg.inits for r in range(cfg.repeats)):
            noise = float(cfg.noise_levels[k % len(cfg.noise_levels)])
            seed = cfg.seed + init + 1000 * rep
            rng = np.random.default_rng([cfg.seed, task_id, init, rep, int(round(noise * 1000))])
            t0 = time.perf_counter()
            stats["attempts"] += 1
            try:
                if pool:
                    pick = np.random.default_rng([cfg.seed, task_id, init, rep, 99])
                    k_driver = int(pick.integers(len(pool)))
                    mode = str(cfg.modes[int(pick.integers(len(cfg.modes)))])
                    ep = _latency_episode(
                        env, expert, layout, task_id, init, seed, noise, rng, budget, cfg.chunk_rows,
                        pooled(k_driver, mode), mode,
                        int(cfg.latency_ticks[int(pick.integers(len(cfg.latency_ticks)))]),
                        cfg.gripper_noise, cfg.fresh,
                    )  # fmt: skip
                    ep.extra["driver"] = cfg.latency_drivers[k_driver]
                else:
                    ep = _episode(
                        env, expert, layout, task_id, init, seed, noise, rng, budget, cfg.chunk_rows, driver,
                        cfg.driver_replan, cfg.fresh,
                    )  # fmt: skip
            except Exception as exc:  # noqa: BLE001 - an expert crash loses one demo, it is counted
                stats["errors"] += 1
                _log(f"task {task_id} init {init}: error {type(exc).__name__}: {exc}")
                continue
            wall = time.perf_counter() - t0
            stats["wall_s"] += wall
            ok = bool(ep.success[-1])
            stats["successes" if ok else "failures"] += 1
            if pool:
                label = f"{ep.extra['driver']} {ep.extra['mode']} N={ep.extra['latency_ticks']}"
                stats.setdefault("by_setting", {}).setdefault(label, [0, 0])
                stats["by_setting"][label][0] += ok
                stats["by_setting"][label][1] += 1
            tally = by_noise.setdefault(f"{noise:g}", [0, 0])
            tally[0] += ok
            tally[1] += 1
            stats["kept_by_noise"] = {lvl: f"{a}/{n}" for lvl, (a, n) in by_noise.items()}
            if ok or cfg.keep_failures:
                kept.append(ep)
                stats["frames"] += len(ep)
            how = " ".join(f"{k}={v}" for k, v in ep.extra.items())
            outcome = "ok" if ok else "--"
            _log(f"task {task_id} init {init} noise {noise:.2f} {how}: {outcome} {len(ep)} ticks {wall:.1f} s")
    finally:
        env.close()
    return kept, stats, env.task.instruction


def _closed_loop(expert) -> None:
    """Make an expert label every tick from the observation of that tick.

    Experts for asynchronous execution (``commit_inflight``) replay the rows of their last chunk that
    are still queued; queried every tick with a 16-row plan, that would replay 15 stale rows and the
    labels would not react to the injected noise. Turned off on the policy and on the expert the
    ``scripted`` facade runs for the task (its ``expert``, chosen at reset). For ``scripted`` a missing
    switch is an error (a refactor must not silently turn the labels open loop).
    """
    found = False
    for p in (expert, getattr(expert, "expert", None)):
        if p is not None and hasattr(p, "commit_inflight"):
            p.commit_inflight = False
            found = True
    if not found and expert.name == "scripted":
        raise TypeError("the scripted expert has no commit_inflight switch: cannot collect closed-loop labels")


def fresh_init_state(env, placement_seed: int) -> int:
    """Sample a new random object placement with LIBERO's initializer; returns its init-state index.

    The state is appended to the env's init states (LiberoEnv has no public way to reset to a given
    state), so ``env.reset(index, seed)`` runs it like a shipped one. Indices >= 50 never collide with
    the evaluation set (0-9) nor any shipped state.
    """
    from robosuite.utils.errors import RandomizationError

    np.random.seed(placement_seed)  # robosuite samples placements from numpy's global generator
    while True:
        try:
            env._env.env.reset()
            break
        except RandomizationError:
            continue
    state = np.asarray(env._env.get_sim_state(), dtype=np.float64)
    env._init_states = np.concatenate([np.asarray(env._init_states), state[None]])
    return len(env._init_states) - 1


def _episode(
    env, expert, layout, task_id, init, seed, noise, rng, budget, chunk_rows, driver=None, driver_replan=8,
    fresh=False,
) -> Episode:  # fmt: skip
    if fresh:
        init = fresh_init_state(env, 1_000_003 * task_id + init)
    env.reset(init, seed)
    expert.reset(env.task, seed)
    _closed_loop(expert)
    if driver is not None:
        driver.reset(env.task, seed)
    driven: np.ndarray | None = None  # the driver's current chunk, executed open loop
    row = 0
    states, envs, labels, executed, chunks, success = [], [], [], [], [], []
    for _ in range(budget):
        obs = env.observe(with_images=False)
        plan = np.asarray(expert.infer(obs), dtype=np.float64)
        if plan.shape != (chunk_rows, ACTION_DIM):
            raise ValueError(f"expert returned {plan.shape}, expected ({chunk_rows}, {ACTION_DIM})")
        action = plan[0].copy()
        if driver is not None:
            if driven is None or row >= min(driver_replan, len(driven)):
                driven, row = np.asarray(driver.infer(obs), dtype=np.float64), 0
            applied = driven[row].copy()
            row += 1
        else:
            applied = action.copy()
        if noise > 0:
            applied[:6] = np.clip(applied[:6] + rng.normal(0.0, noise, 6), ACTION_LOW, ACTION_HIGH)
        s, e = raw_from_observation(layout, obs)
        states.append(s)
        envs.append(e)
        labels.append(action)
        executed.append(applied)
        chunks.append(plan)
        state = env.step(applied)
        success.append(state.success)
        if state.success:
            break
    return Episode(
        task_index=task_id, init_index=init, seed=seed, noise_std=noise,
        state=np.array(states), env_state=np.array(envs), action=np.array(labels, np.float32),
        action_executed=np.array(executed, np.float32), action_chunk=np.array(chunks, np.float32),
        success=np.array(success, bool),
    )  # fmt: skip


def parse_spec(spec: str) -> tuple[str, dict]:
    """``name[:key=value,...]`` -> (policy name, keyword arguments); values parsed as JSON when possible."""
    import json

    name, _, rest = spec.partition(":")
    args: dict = {}
    for item in filter(None, rest.split(",")):
        key, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"bad policy spec {spec!r}: expected name:key=value,...")
        try:
            args[key] = json.loads(value)
        except json.JSONDecodeError:
            args[key] = value
    return name, args


def _latency_episode(
    env, expert, layout, task_id, init, seed, noise, rng, budget, chunk_rows, driver, mode, latency_ticks,
    gripper_noise, fresh=False,
) -> Episode:  # fmt: skip
    """One DAgger episode: ``driver``'s chunks executed by the protocol core (``mode``, N = ``latency_ticks``,
    merge replace, hold stop), the expert labelling every tick closed loop, arm and gripper noise on top."""
    from lq_ros.core.executor_protocol import ExecutorConfig, ExecutorCore, TickDriver

    if fresh:
        init = fresh_init_state(env, 1_000_003 * task_id + init)
    env.reset(init, seed)
    expert.reset(env.task, seed)
    _closed_loop(expert)
    driver.reset(env.task, seed)
    replan = int(getattr(driver, "replan_steps", 8))
    core = ExecutorCore(ExecutorConfig(mode=mode, latency_ticks=latency_ticks, replan_steps=replan))
    rec: dict[str, list] = {k: [] for k in ("state", "env", "label", "executed", "chunk", "success")}
    pending: dict[int, np.ndarray] = {}
    burst = {"left": 0, "value": 0.0}

    class Handlers:
        done = False

        def ready(self) -> bool:
            return not self.done

        def request(self, req) -> bool:
            pending[req.request_id] = np.asarray(driver.infer(env.observe(with_images=False)), dtype=np.float64)
            return True

        def chunk_due(self, req) -> bool:
            core.deliver(req.request_id, pending.pop(req.request_id))
            return True

        def failed(self, reason: str) -> None:
            raise RuntimeError(reason)

        def command(self, cmd) -> bool:
            obs = env.observe(with_images=False)
            plan = np.asarray(expert.infer(obs), dtype=np.float64)
            if plan.shape != (chunk_rows, ACTION_DIM):
                raise ValueError(f"expert returned {plan.shape}, expected ({chunk_rows}, {ACTION_DIM})")
            applied = np.array(cmd.action, dtype=np.float64)
            if noise > 0:
                applied[:6] = np.clip(applied[:6] + rng.normal(0.0, noise, 6), ACTION_LOW, ACTION_HIGH)
            if gripper_noise > 0 and burst["left"] == 0 and rng.random() < gripper_noise:
                g = applied[-1]
                burst["left"] = int(rng.integers(2, 8))
                burst["value"] = -np.sign(g) if g != 0 else float(rng.choice([-1.0, 1.0]))
            if burst["left"] > 0:
                applied[-1] = burst["value"]
                burst["left"] -= 1
            s, e = raw_from_observation(layout, obs)
            for key, value in zip(rec, (s, e, plan[0].copy(), applied, plan)):
                rec[key].append(value)
            state = env.step(applied)
            rec["success"].append(state.success)
            self.done = bool(state.success) or len(rec["state"]) >= budget
            return not self.done

    TickDriver(core, Handlers()).drive()
    return Episode(
        task_index=task_id, init_index=init, seed=seed, noise_std=noise,
        state=np.array(rec["state"]), env_state=np.array(rec["env"]), action=np.array(rec["label"], np.float32),
        action_executed=np.array(rec["executed"], np.float32), action_chunk=np.array(rec["chunk"], np.float32),
        success=np.array(rec["success"], bool),
        extra={"mode": mode, "latency_ticks": latency_ticks},
    )  # fmt: skip


def _shard_path(out: Path, task_id: int) -> Path:
    return Path(out) / "shards" / f"task_{task_id:03d}.pkl"


def _shard_key(cfg: dict) -> dict:
    """What a task's episodes depend on (not which other tasks ran, nor how many workers).

    A setting missing from ``cfg`` takes its default: a shard written before the setting existed was
    collected as the default does it, so it stays reusable.
    """
    defaults = {
        f.name: f.default if f.default is not MISSING else f.default_factory()  # type: ignore[misc]
        for f in fields(CollectConfig)
        if f.default is not MISSING or f.default_factory is not MISSING
    }
    full = {k: (list(v) if isinstance(v, tuple) else v) for k, v in {**defaults, **cfg}.items()}
    return {k: v for k, v in full.items() if k not in ("tasks", "workers")}


def _collect_task_star(args: tuple[CollectConfig, int, Path]):
    """Collect one task into its shard file (kept if the run is interrupted; reused on a rerun)."""
    cfg, task_id, out = args
    shard = _shard_path(out, task_id)
    if shard.is_file():
        with open(shard, "rb") as f:
            saved_cfg, result = pickle.load(f)
        if _shard_key(saved_cfg) == _shard_key(cfg.to_dict()):
            _log(f"task {task_id}: reusing {shard}")
            return result
    result = collect_task(cfg, task_id)
    shard.parent.mkdir(parents=True, exist_ok=True)
    with replacing(shard, binary=True) as f:  # never through a link (as every file written in --out)
        pickle.dump((cfg.to_dict(), result), f)
    return result


def collect(cfg: CollectConfig, out: Path) -> dict:
    """Collect every task (``cfg.workers`` processes, one task each at a time) and write the dataset.

    Each finished task is saved under ``out/shards/``; a rerun with the same configuration reuses them.
    """
    from lq_ros.core.run_config import versions

    t0 = time.perf_counter()
    jobs = [(cfg, t, Path(out)) for t in cfg.tasks]
    if cfg.workers == 1 or len(jobs) == 1:
        results = [_collect_task_star(j) for j in jobs]
    else:
        # spawn: a fresh interpreter per worker (MuJoCo/EGL state must not be forked).
        with mp.get_context("spawn").Pool(min(cfg.workers, len(jobs))) as pool:
            results = pool.map(_collect_task_star, jobs, chunksize=1)
    episodes, per_task, tasks = [], {}, {}
    for task_id, (kept, stats, instruction) in zip(cfg.tasks, results):
        episodes += kept
        per_task[str(task_id)] = stats
        tasks[task_id] = instruction
    from lq_ros.sim.libero_env import load_task

    goals = {str(t): load_task(cfg.suite, t)[0].goal for t in cfg.tasks}
    info_extra = {
        "suite": cfg.suite,
        "layout": layout_for(cfg.suite).to_dict(),
        "goals": goals,
        "collect_config": cfg.to_dict(),
        "collection": {"per_task": per_task, "wall_s": time.perf_counter() - t0},
        "versions": versions(),
    }
    info = write_dataset(out, episodes, info_extra, tasks)
    shutil.rmtree(Path(out) / "shards", ignore_errors=True)
    return info
