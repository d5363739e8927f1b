"""Zero-latency success under this stack's LIBERO on MuJoCo 2.3.7 and under LeRobot 0.6's hf-libero on MuJoCo 3.x.

LeRobot 0.6's ``lerobot[libero]`` installs hf-libero 0.1.4 with MuJoCo 3.8.1 (as pip resolves it beside LeRobot
0.6.1); this stack, like LIBERO, openpi and OpenVLA, runs MuJoCo 2.3.7. This runs the same policies on the same
tasks, init states and seed under both, closed loop at zero latency (``run_conventional``: infer, execute the
policy's actions per chunk, repeat; the paper's step budgets), and prints per suite and policy the success under
each, the paired difference (3.x minus 2.3.7) with its 95% interval (``paired_success_ci``: the hull of the
task-clustered t interval and Tango's score interval, which keeps a width when every pair agrees) and n.

MuJoCo 2.3.7 is the stack's own LiberoEnv, in this process. MuJoCo 3.x is benchmarks/physics_gap_driver.py run by
the other venv's Python (``make setup-hflibero``), one process per task, stepped over a pipe: the policy, the task
and the init states stay here, only the simulator is the other one. ``--check-driver`` first runs one episode
through the same driver under this venv's Python and requires it to equal LiberoEnv's tick for tick, so a
difference under 3.x is the other simulator's, not the driver's. The BDDL files are byte-compared between the two
packages, and the init states array-compared (hf-libero's torch files against the stack's).

Open loop (``--open-loop-inits N``, the scripted expert only): the actions of its 2.3.7 episode on the first N init
states are replayed under 3.x; printed per suite: the first tick at which the two exact EE positions are more than
1 mm apart (none: never, within the episode) and the largest distance.

Usage: python benchmarks/physics_gap.py [--suite libero_spatial --suite libero_object] [--tasks 0 ... 9]
       [--inits 0 1 2] [--policy scripted --policy oft ...] [--open-loop-inits 1] [--check-driver]
       [--out rows.jsonl]   (appends one row per episode; episodes already there are skipped)
       python benchmarks/physics_gap.py --table rows.jsonl   (the tables from rows; nothing is run)
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import lq_ros  # noqa: F401 - first: it pins OpenBLAS's kernels before numpy loads them (lq_ros/__init__.py)

# isort: split

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lq_ros.core.control import ControlMode  # noqa: E402
from lq_ros.core.suite_constants import DUMMY_ACTION, NUM_WAIT_STEPS, sim_time_of_tick  # noqa: E402
from lq_ros.core.types import Observation  # noqa: E402
from lq_ros.scoring.intervals import paired_success_ci  # noqa: E402

DRIVER = ROOT / "benchmarks" / "physics_gap_driver.py"
HF_PYTHON = ROOT / ".venv-hflibero" / "bin" / "python"
SEED = 7
#: Distance between the two physics' EE positions that counts as diverged, m.
DIVERGED_M = 1e-3
STACK = "mujoco-2.3.7"


class DriverState:
    """What ``run_conventional`` reads of a tick's state: the exact EE position and LIBERO's success."""

    def __init__(self, tick: int, answer: dict) -> None:
        self.tick = tick
        self.eef_pos = np.asarray(answer["eef_pos_exact"], dtype=np.float64)
        self.success = bool(answer["success"])


class DriverEnv:
    """LiberoEnv's interface as ``run_conventional`` uses it, over physics_gap_driver.py run by ``python``.

    The task, its BDDL file and its init states are the stack's (:func:`lq_ros.sim.libero_env.load_task`); the
    driver builds the scene from its own package's copy of the same BDDL file (byte-compared by
    :func:`check_same_task`).
    """

    def __init__(self, python: Path, suite: str, task_id: int, assets: Path) -> None:
        from lq_ros.sim.libero_env import load_task

        self.task, bddl, self._init_states = load_task(suite, task_id)
        self._log = tempfile.TemporaryFile(mode="w+")  # noqa: SIM115 - the driver's stderr while it lives
        self._proc = subprocess.Popen(
            [str(python), str(DRIVER)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self._log, text=True
        )
        self.versions = self._ask(op="open", bddl=f"{Path(bddl).parent.name}/{Path(bddl).name}", assets=str(assets))
        self._answer: dict | None = None
        self._tick = 0

    def _ask(self, **request) -> dict:
        try:
            self._proc.stdin.write(json.dumps(request) + "\n")
            self._proc.stdin.flush()
            line = self._proc.stdout.readline()
        except BrokenPipeError:
            line = ""
        if not line:
            self._log.seek(0)
            tail = self._log.read()[-2000:]
            raise RuntimeError(f"physics driver exited (code {self._proc.wait()}) at {request['op']}:\n{tail}")
        answer = json.loads(line)
        if "error" in answer:
            raise RuntimeError(f"physics driver, {request['op']}: {answer['error']}\n{answer['traceback']}")
        return answer

    @property
    def init_states(self) -> np.ndarray:
        return self._init_states

    def reset(self, init_index: int, seed: int, *, control_mode: ControlMode = ControlMode.RELATIVE) -> DriverState:
        if ControlMode(control_mode) is not ControlMode.RELATIVE:
            raise ValueError(f"the physics driver runs relative control only, not {control_mode}")
        self._answer = self._ask(
            op="reset",
            state=self._init_states[init_index].tolist(),
            seed=int(seed),
            wait_action=list(DUMMY_ACTION),
            wait_steps=NUM_WAIT_STEPS,
        )
        self._tick = 0
        return DriverState(0, self._answer)

    def step(self, action: np.ndarray) -> DriverState:
        self._answer = self._ask(op="step", action=np.asarray(action, dtype=np.float64).tolist())
        self._tick += 1
        return DriverState(self._tick, self._answer)

    def observe(self, with_images: bool = False) -> Observation:
        a = self._answer
        assert a is not None, "reset() first"
        arr = lambda key: np.asarray(a[key], dtype=np.float64)  # noqa: E731
        objects = {
            name: (np.asarray(p, dtype=np.float64), np.asarray(q, dtype=np.float64))
            for name, (p, q) in a["objects"].items()
        }
        return Observation(
            tick=self._tick,
            sim_time_s=sim_time_of_tick(self._tick),
            eef_pos=arr("eef_pos"),
            eef_quat_xyzw=arr("eef_quat_xyzw"),
            gripper_qpos=arr("gripper_qpos"),
            joint_pos=arr("joint_pos"),
            joint_vel=arr("joint_vel"),
            objects=objects,
            eef_rot_mat=arr("eef_rot_mat"),
        )

    def close(self) -> None:
        try:
            self._ask(op="close")
        finally:
            self._proc.wait(timeout=60)
            self._log.close()


class Recording:
    """An env whose ``reset``/``step`` record the commands and the exact EE positions of the episode."""

    def __init__(self, env) -> None:
        self.env = env
        self.actions: list[np.ndarray] = []
        self.eef: list[np.ndarray] = []

    def reset(self, *args, **kwargs):
        state = self.env.reset(*args, **kwargs)
        self.actions, self.eef = [], [np.array(state.eef_pos)]
        return state

    def step(self, action):
        self.actions.append(np.array(action, dtype=np.float64))
        state = self.env.step(action)
        self.eef.append(np.array(state.eef_pos))
        return state

    def __getattr__(self, name):
        return getattr(self.env, name)


def first_divergence(a: np.ndarray, b: np.ndarray, threshold_m: float = DIVERGED_M) -> tuple[int | None, float]:
    """First tick at which two EE trajectories ((T, 3), m, tick 0 first) are more than ``threshold_m`` apart (None:
    never within the shorter one), and their largest distance, m."""
    n = min(len(a), len(b))
    dist = np.linalg.norm(np.asarray(a[:n]) - np.asarray(b[:n]), axis=1)
    over = np.flatnonzero(dist > threshold_m)
    return (int(over[0]) if over.size else None), float(dist.max()) if n else 0.0


def paired_table(rows: pd.DataFrame, other: str) -> pd.DataFrame:
    """Per suite and policy (and all suites): successes under the stack's physics and ``other``, the paired
    difference ``other`` minus the stack's, its 95% interval, the discordant pairs and n (pairs: the same suite,
    task, init state and policy under both). Episodes run under one physics only are left out."""
    closed = rows[rows["kind"] == "closed"]
    wide = closed.pivot_table(
        index=["suite", "policy", "task", "init"], columns="physics", values="success", aggfunc="first"
    )
    wide = wide.dropna(subset=[STACK, other]).reset_index()
    out = []
    groups = [((s, p), g) for (s, p), g in wide.groupby(["suite", "policy"], sort=True)]
    groups += [(("all", p), g) for p, g in wide.groupby("policy", sort=True) if g["suite"].nunique() > 1]
    for (suite, policy), g in groups:
        a, b = g[other].astype(bool).to_numpy(), g[STACK].astype(bool).to_numpy()
        tasks = (g["suite"] + ":" + g["task"].astype(str)).to_numpy()
        low, high = paired_success_ci(a, b, tasks)
        out.append(
            {
                "suite": suite, "policy": policy, "n": len(g), "tasks": len(set(tasks)),
                STACK: b.mean(), other: a.mean(), "diff": a.mean() - b.mean(), "low": low, "high": high,
                "only_other": int((a & ~b).sum()), "only_stack": int((~a & b).sum()),
            }
        )  # fmt: skip
    return pd.DataFrame(out)


def print_tables(rows: pd.DataFrame) -> None:
    physics = sorted(set(rows["physics"]) - {STACK})
    for other in physics:
        table = paired_table(rows, other)
        print(f"\nclosed loop, zero latency, seed {SEED}: success under {STACK} (this stack) and {other} (hf-libero)")
        print(f"| suite | policy | n (tasks) | {STACK} | {other} | difference, 95% CI | only {other} / only {STACK} |")
        print("|---|---|---|---|---|---|---|")
        for d in table.to_dict("records"):
            print(
                f"| {d['suite']} | {d['policy']} | {d['n']} ({d['tasks']}) | {100 * d[STACK]:.0f}% "
                f"| {100 * d[other]:.0f}% | {100 * d['diff']:+.0f} pp [{100 * d['low']:+.0f}, {100 * d['high']:+.0f}] "
                f"| {d['only_other']} / {d['only_stack']} |"
            )
        loop = rows[(rows["kind"] == "open") & (rows["physics"] == other)]
        if len(loop):
            print(f"\nopen loop (the 2.3.7 episode's commands replayed under {other}): EE divergence > 1 mm")
            print("| suite | episodes | diverged | first tick > 1 mm (median, min) | largest distance (median, max) |")
            print("|---|---|---|---|---|")
            for suite, g in loop.groupby("suite"):
                ticks = g["first_tick_over_1mm"].dropna()
                first = f"{ticks.median():.0f}, {ticks.min():.0f}" if len(ticks) else "none"
                print(
                    f"| {suite} | {len(g)} | {len(ticks)} | {first} "
                    f"| {1e3 * g['max_dist_m'].median():.3g} mm, {1e3 * g['max_dist_m'].max():.3g} mm |"
                )


def check_same_task(hf_python: Path, suite: str, task_id: int) -> None:
    """The BDDL file of the task is byte-identical in both packages, and so are the init states' arrays (hf-libero's
    torch file, read here with the stack's torch, against the stack's npz). Raises RuntimeError naming the file."""
    from libero.libero import benchmark, get_libero_path

    task = benchmark.get_benchmark_dict()[suite]().get_task(task_id)
    site = subprocess.run(
        [str(hf_python), "-c", "import importlib.util as u; print(*u.find_spec('libero').submodule_search_locations)"],
        capture_output=True, text=True, check=True,
    ).stdout.strip()  # fmt: skip
    hf_root = Path(site) / "libero"
    ours = Path(get_libero_path("bddl_files")) / task.problem_folder / task.bddl_file
    theirs = hf_root / "bddl_files" / task.problem_folder / task.bddl_file
    if hashlib.sha256(ours.read_bytes()).digest() != hashlib.sha256(theirs.read_bytes()).digest():
        raise RuntimeError(f"BDDL files differ: {ours} and {theirs}")
    import torch

    from lq_ros.sim.libero_env import load_task

    _, _, init_states = load_task(suite, task_id)
    theirs_init = hf_root / "init_files" / task.problem_folder / task.init_states_file
    hf_states = np.asarray(torch.load(theirs_init, weights_only=False))
    if hf_states.shape != init_states.shape or not np.array_equal(hf_states, init_states):
        raise RuntimeError(f"init states differ: {theirs_init} and the stack's")


def run_episode(env, policy_spec: str, init: int) -> tuple[dict, Recording]:
    """One closed-loop zero-latency episode; (row fields, the recording of its commands and EE positions)."""
    from lq_ros.policies import make_policy
    from lq_ros.transport.inprocess import run_conventional

    name, _, args = policy_spec.partition(":")
    kwargs = dict(kv.split("=", 1) for kv in args.split(",") if kv)
    policy = make_policy(name, **kwargs)
    try:
        policy.reset(env.task.for_init(init), SEED)  # a learned policy loads its suite's weights here
        replan = int(getattr(policy, "replan_steps", 0) or policy.reference().replan_steps)
        recording = Recording(env)
        result = run_conventional(recording, policy, init, SEED, replan)
    finally:
        policy.close()
    return {"success": bool(result.success), "ticks": int(result.ticks), "replan_steps": replan}, recording


def replay(env: DriverEnv, init: int, actions: list[np.ndarray]) -> np.ndarray:
    """The exact EE positions (T + 1, 3) of ``actions`` executed open loop from ``init``."""
    eef = [env.reset(init, SEED).eef_pos]
    eef += [env.step(a).eef_pos for a in actions]
    return np.asarray(eef)


def check_driver(suite: str, task_id: int, assets: Path) -> None:
    """The driver under this venv's Python must give LiberoEnv's episode exactly (scripted expert, init 0)."""
    from lq_ros.sim.libero_env import LiberoEnv

    env = LiberoEnv(suite, task_id)
    ours, rec_ours = run_episode(env, "scripted", 0)
    env.close()
    driver = DriverEnv(Path(sys.executable), suite, task_id, assets)
    theirs, rec_theirs = run_episode(driver, "scripted", 0)
    driver.close()
    same = len(rec_ours.eef) == len(rec_theirs.eef) and np.array_equal(
        np.asarray(rec_ours.eef), np.asarray(rec_theirs.eef)
    )
    _, dist = first_divergence(np.asarray(rec_ours.eef), np.asarray(rec_theirs.eef))
    print(
        f"driver check ({suite} task {task_id} init 0, MuJoCo {driver.versions['mujoco']}): LiberoEnv {ours}, "
        f"driver {theirs}; "
        f"EE trajectories {'identical' if same else f'differ (largest distance {dist:.3g} m)'}",
        flush=True,
    )
    if not same or ours != theirs:
        raise SystemExit(
            "the driver does not reproduce LiberoEnv under the same MuJoCo: its results would not be the physics'"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--suite", action="append", dest="suites", help="default: libero_spatial and libero_object")
    ap.add_argument("--tasks", type=int, nargs="+", default=list(range(10)))
    ap.add_argument("--inits", type=int, nargs="+", default=[0, 1, 2], help="init-state indices")
    ap.add_argument("--policy", action="append", dest="policies", help="name[:key=value,...]; default: scripted")
    ap.add_argument("--open-loop-inits", type=int, default=1, help="replay the scripted expert's first N inits")
    ap.add_argument("--hf-python", type=Path, default=HF_PYTHON, help="the Python of make setup-hflibero's venv")
    ap.add_argument("--check-driver", action="store_true", help="first check the driver against LiberoEnv")
    ap.add_argument("--out", type=Path, help="append one JSON row per episode; episodes already there are skipped")
    ap.add_argument("--table", type=Path, help="print the tables of these rows and exit")
    args = ap.parse_args()
    if args.table:
        if not args.table.is_file():
            raise SystemExit(f"--table: no such file {args.table}")
        print_tables(pd.read_json(args.table, lines=True))
        return
    if not args.hf_python.is_file():
        raise SystemExit(f"no hf-libero venv at {args.hf_python}: run `make setup-hflibero` (or pass --hf-python)")
    suites, policies = args.suites or ["libero_spatial", "libero_object"], args.policies or ["scripted"]

    from lq_ros.sim.libero_env import LiberoEnv

    assets = Path(__import__("libero.libero", fromlist=["get_libero_path"]).get_libero_path("assets")).resolve()
    if args.check_driver:
        check_driver(suites[0], args.tasks[0], assets)
    rows: list[dict] = []
    if args.out and args.out.is_file():
        rows = [json.loads(line) for line in args.out.read_text().splitlines() if line.strip()]
    done = {(r["kind"], r["physics"], r["suite"], r["task"], r["init"], r["policy"]) for r in rows}

    def record(row: dict) -> None:
        rows.append(row)
        done.add((row["kind"], row["physics"], row["suite"], row["task"], row["init"], row["policy"]))
        if args.out:
            with args.out.open("a") as f:
                f.write(json.dumps(row) + "\n")

    hf_physics = "mujoco-" + subprocess.run(
        [str(args.hf_python), "-c", "import importlib.metadata as m; print(m.version('mujoco'))"],
        capture_output=True, text=True, check=True,
    ).stdout.strip()  # fmt: skip
    for suite in suites:
        for task in args.tasks:
            check_same_task(args.hf_python, suite, task)
            stack_env, hf_env = None, None
            for init in args.inits:
                for spec in policies:
                    open_loop = spec == "scripted" and init < args.open_loop_inits
                    kinds = [("closed", STACK), ("closed", hf_physics)] + [("open", hf_physics)] * open_loop
                    if all((k, p, suite, task, init, spec) in done for k, p in kinds):
                        continue
                    stack_env = stack_env or LiberoEnv(suite, task)
                    hf_env = hf_env or DriverEnv(args.hf_python, suite, task, assets)
                    if f"mujoco-{hf_env.versions['mujoco']}" != hf_physics:
                        raise SystemExit(f"the driver runs MuJoCo {hf_env.versions['mujoco']}, not {hf_physics}")
                    base = {"suite": suite, "task": task, "init": init, "policy": spec, "seed": SEED}
                    t0 = time.perf_counter()
                    ours, rec = run_episode(stack_env, spec, init)
                    theirs, _ = run_episode(hf_env, spec, init)
                    for physics, result in ((STACK, ours), (hf_physics, theirs)):
                        if ("closed", physics, suite, task, init, spec) not in done:
                            record({**base, "kind": "closed", "physics": physics, **result})
                    line = f"{suite} task {task} init {init} {spec}: 2.3.7 {ours['success']:d}/{ours['ticks']}"
                    line += f"  {hf_env.versions['mujoco']} {theirs['success']:d}/{theirs['ticks']}"
                    if open_loop and ("open", hf_physics, suite, task, init, spec) not in done:
                        first, dist = first_divergence(np.asarray(rec.eef), replay(hf_env, init, rec.actions))
                        record({**base, "kind": "open", "physics": hf_physics, "ticks": len(rec.actions),
                                "first_tick_over_1mm": first, "max_dist_m": dist})  # fmt: skip
                        line += f"  open loop: >1 mm at tick {first}, max {1e3 * dist:.3g} mm"
                    print(f"{line}  ({time.perf_counter() - t0:.0f} s)", flush=True)
            if hf_env:
                hf_env.close()
            if stack_env:
                stack_env.close()
    print_tables(pd.DataFrame(rows))


if __name__ == "__main__":
    main()
