"""The ``lq`` command line: run episodes, score bags."""

from __future__ import annotations

import atexit
import contextlib
import json
import os
import signal
import sys
from enum import StrEnum
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

from lq_ros.core.executor_protocol import Hold, Mode
from lq_ros.core.merge import Merge
from lq_ros.core.run_config import BUDGET_COUNTS, CLOCKS, DEFAULT_CAMERA_SIZE_PX, TRANSPORTS, RunConfig
from lq_ros.scoring.metrics import DEFAULT_OSC_WINDOW, ELEC_LOSS_COEFF_W_PER_NM2, OVERHEAD_POWER_W

# Before anything may initialise ROS: keep DDS discovery on this machine unless the user chose.
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

app = typer.Typer(add_completion=False, no_args_is_help=True, help="LIBERO-LQ: latency-aware VLA evaluation on ROS 2.")
#: Messages (stderr). soft_wrap: a long path stays on one line, whatever the terminal's width (or none, piped).
console = Console(stderr=True, soft_wrap=True)
#: Width of --help when the output is no terminal (a pipe, a file): wide enough for every option name.
PIPED_WIDTH = 160
#: Width of result tables when piped: wide enough for every column of a scored row, none cut short.
PIPED_TABLE_WIDTH = 240
#: Largest --n-boot of lq score: the bootstrap holds n_boot x episodes draws per cell in memory.
MAX_N_BOOT = 100_000

ROW_COLUMNS = [
    ("status", "status"),
    ("mode", "mode"),
    ("latency_s", "Δt_sim s"),
    ("latency_dist", "latency"),
    ("budget_counts", "budget"),
    ("completion_steps", "steps"),
    ("action_ticks", "action steps"),
    ("completion_time_s", "time s"),
    ("jerk_mean", "jerk m/s³"),
    ("jerk_p90", "jerk P90"),
    ("ee_osc", "EE-Osc m"),
    ("traj_length", "length m"),
    ("energy_total_j", "energy J"),
    ("energy_per_step_j", "J/step"),
    ("hold_ticks", "holds"),
    ("underrun_ticks", "underruns"),
    ("switch_executed_step_mean", "switch step"),
]


#: Defaults of `lq run` options: RunConfig's (the one source; node parameters derive from it too).
_RUN = RunConfig()


class LatencyRounding(StrEnum):
    exact = "exact"
    nearest = "nearest"


#: --budget-counts choices (lq_ros.core.run_config.BUDGET_COUNTS).
BudgetCounts = StrEnum("BudgetCounts", {v: v for v in BUDGET_COUNTS})


#: --transport choices (lq_ros.core.run_config.TRANSPORTS).
Transport = StrEnum("Transport", {v: v for v in TRANSPORTS})

#: --clock choices (lq_ros.core.run_config.CLOCKS).
Clock = StrEnum("Clock", {v: v for v in CLOCKS})

#: lq sweep --backend choices (lq_ros.run.sweep.BACKENDS; tests/test_cli_errors.py checks they agree).
Backend = StrEnum("Backend", {v: v for v in ("local", "ray")})

#: lq score --rate and --energy-rate choices (lq_ros.scoring.bag_scorer.TRAJECTORY_RATES / ENERGY_RATES; checked by
#: tests/test_cli_errors.py): literal here, so that ``lq --help`` does not import the scorer.
TrajectoryRate = StrEnum("TrajectoryRate", {v: v for v in ("auto", "control", "physics", "native")})
EnergyRate = StrEnum("EnergyRate", {v: v for v in ("auto", "substep", "physics", "control", "native")})

#: --merge's help: every strategy named (its choices are too many for the option's column).
MERGE_HELP = (
    "async: how a new chunk meets the buffered one: " + ", ".join(m.value for m in Merge) + " (docs/guide/async.md)."
)
#: --suite's help (lq_ros.core.suite_constants.STEP_BUDGETS; checked by tests/test_cli_errors.py).
SUITE_HELP = "LIBERO suite: libero_spatial, libero_object, libero_goal, libero_10, libero_90."
#: --policy's help, shared by lq run and lq eval.
POLICY_HELP = (
    "A registered policy (scripted, oft, flow, openpi, openvla, lerobot, sine, faulty; docs/guide/policies.md) or "
    "your own class as module:Class, a subclass of lq_ros.policies.Policy (examples/my_policy.py). Modules in the "
    "current directory are importable, as with python -m."
)
POLICY_ARG_HELP = (
    "A keyword argument of the policy's constructor, key=value (repeatable); values are JSON when they parse as JSON "
    "(5, 0.1, true, [1,2]), else text. In a spec: policies: [{name: P, args: {key: value}}]."
)


def _refuse(message: str) -> None:
    """A mistake in the user's input: one line on stderr, exit code 2, nothing started."""
    from rich.markup import escape

    console.print(f"[red]error:[/red] {escape(' '.join(message.split()))}", soft_wrap=True, highlight=False)
    raise typer.Exit(2)


def _make_room(bag: Path, overwrite: bool) -> None:
    """The episode's bag folder must be new: refuse a rerun into the same --out, or replace it on request."""
    import shutil

    from lq_ros.recording.episode_folder import episode_folders

    leftovers = [p for p in episode_folders(bag) if p.exists()]
    if leftovers and not overwrite:
        _refuse(f"bag folder {bag} already exists (this configuration already ran into this --out); "
                "pass --overwrite to replace it, or choose another --out")  # fmt: skip
    for path in leftovers:
        shutil.rmtree(path)


def _parse_policy_args(items: list[str]) -> dict:
    """``key=value`` pairs; values are JSON when they parse as JSON (numbers, lists), else strings."""
    args = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise typer.BadParameter(f"--policy-arg expects key=value, got {item!r}")
        try:
            args[key] = json.loads(value)
        except (ValueError, RecursionError):  # not JSON, a 5000-digit number, nested too deep: the text itself
            args[key] = value
    return args


def _fmt(value) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def stdout_console() -> Console:
    """The console for results on stdout: the terminal's width, or PIPED_TABLE_WIDTH when piped (nothing cut)."""
    return Console(width=None if sys.stdout.isatty() else PIPED_TABLE_WIDTH, soft_wrap=True)


def print_rows(rows: list[dict], title: str = "") -> None:
    """Scored rows as a table on stdout; under it, on stderr, the reason of every error row."""
    table = Table(title=title or None, caption="bags and episode names: see the run folder")
    for _, header in ROW_COLUMNS:
        table.add_column(header, justify="right")
    for row in rows:
        table.add_row(*(_fmt(row.get(k)) for k, _ in ROW_COLUMNS))
    stdout_console().print(table)
    print_error_reasons(rows)


def print_error_reasons(rows: list[dict], limit: int = 20) -> None:
    """One line per error row: its episode and why (the table shows only ``error``); at most ``limit`` lines."""
    from rich.markup import escape

    errors = [r for r in rows if r.get("status") == "error"]
    for row in errors[:limit]:
        reason = " ".join(str(row.get("error_reason") or "no reason recorded").split())
        console.print(f"[red]error:[/red] {escape(str(row.get('episode', '')))}: {escape(reason)}", highlight=False)
    if len(errors) > limit:
        console.print(f"... and {len(errors) - limit} more errors (episodes.csv has every reason)")


@app.command()
def run(
    suite: Annotated[str, typer.Option(help=SUITE_HELP)] = _RUN.suite,
    task: Annotated[int, typer.Option(help="Task index in the suite: 0..9 (libero_90: 0..89).")] = _RUN.task,
    init: Annotated[int, typer.Option(help="Init state index, 0..49 (the object layout the episode starts from).")] = (
        _RUN.init
    ),
    seed: Annotated[
        int,
        typer.Option(help="Seed of the scene's reset and of the policy's (a rerun with the same seed is identical)."),
    ] = _RUN.seed,
    mode: Annotated[
        Mode, typer.Option(help="sync: the robot holds while the policy infers; async: it executes buffered actions.")
    ] = Mode(_RUN.mode),
    latency: Annotated[
        str,
        typer.Option(
            help="Injected inference latency Δt_sim: seconds (a whole number of 0.05 s ticks), or a distribution "
            "drawn per inference: uniform:LO:HI, normal:MEAN:STD, lognormal:MEDIAN:SIGMA, trace:FILE "
            "(docs/design/async.md)."
        ),
    ] = f"{_RUN.latency_s:g}",
    latency_rounding: Annotated[
        LatencyRounding, typer.Option(help="exact: refuse a latency between ticks; nearest: round it to N·0.05 s.")
    ] = LatencyRounding.exact,
    replan_steps: Annotated[int, typer.Option(help="sync: actions of each chunk executed.")] = _RUN.replan_steps,
    hold: Annotated[
        Hold,
        typer.Option(
            help="sync: what the robot does while it waits: stop (zero arm delta) or repeat the last "
            "(a policy of absolute poses always keeps its last target)."
        ),
    ] = Hold(_RUN.hold),
    request_threshold: Annotated[
        int, typer.Option(help="async: request at this buffer size; -1: the merge strategy's default (replace: N).")
    ] = _RUN.request_threshold,
    request_slack: Annotated[
        int,
        typer.Option(
            help="async: request K actions earlier than the threshold (replace: at N + K). 0, the default, is the "
            "lockstep best case: a chunk lands exactly as the buffer empties (docs/design/async.md)."
        ),
    ] = _RUN.request_slack,
    merge: Annotated[Merge, typer.Option(help=MERGE_HELP, metavar="STRATEGY")] = Merge(_RUN.merge),
    policy: Annotated[str, typer.Option(help=POLICY_HELP)] = _RUN.policy,
    policy_arg: Annotated[list[str], typer.Option(help=POLICY_ARG_HELP, metavar="KEY=VALUE")] = [],  # noqa: B006
    camera_size: Annotated[
        int,
        typer.Option(help=f"Camera render size, px; 0: the policy's reference size, else {DEFAULT_CAMERA_SIZE_PX}."),
    ] = _RUN.camera_size,
    physics_rate: Annotated[bool, typer.Option(help="Also record 500 Hz poses and joint states.")] = _RUN.physics_rate,
    max_steps: Annotated[int, typer.Option(help="Tick budget; 0: the suite's.")] = _RUN.max_steps,
    budget_counts: Annotated[
        BudgetCounts,
        typer.Option(
            help="What the tick budget counts: all ticks (the paper's: holds count) or action ticks only (those "
            "whose command came from a chunk; the episode still stops at 4x the budget; docs/guide/scoring.md)."
        ),
    ] = BudgetCounts(_RUN.budget_counts),
    clock: Annotated[
        Clock,
        typer.Option(
            help="lockstep (deterministic) or realtime (wall-clock ticks, real inference time + Δt_sim; "
            "not bit-reproducible; docs/guide/real_robot.md)."
        ),
    ] = Clock(_RUN.clock),
    robot: Annotated[
        str,
        typer.Option(
            help="Run against a robot's standard topics through the bridge: a robot YAML or a shipped name "
            "(standin: the LIBERO stand-in, started with the run; franka_ros2). Needs --clock realtime."
        ),
    ] = _RUN.robot,
    out: Annotated[Path, typer.Option(help="Folder for the episode's bag (OUT/<episode name>).")] = Path("bags"),
    overwrite: Annotated[
        bool, typer.Option(help="Replace the episode's bag folder if the same configuration already ran into --out.")
    ] = False,
    transport: Annotated[
        Transport,
        typer.Option(help="ros: the four ROS 2 nodes; inprocess: one process, no ROS (the same episode, faster)."),
    ] = Transport.ros,
    domain_id: Annotated[int | None, typer.Option(help="ROS_DOMAIN_ID; default: a free one.")] = None,
    timeout: Annotated[float | None, typer.Option(help="Wall-clock limit of the run, seconds.")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print the scored row as JSON.")] = False,
) -> None:
    """Run one episode and print its scored row. Exits 1 when the *run* failed (not the task).

    Your own policy: lq run --transport inprocess --policy my_policy:MyPolicy, from the folder that holds my_policy.py
    (a template: examples/my_policy.py)."""
    from lq_ros.core.latency import MAX_LATENCY_S
    from lq_ros.core.suite_constants import round_latency

    latency_fields: dict = {"latency_dist": latency}  # a distribution (RunConfig parses and checks it)
    if ":" not in latency:
        try:
            seconds = float(latency)
        except ValueError:
            _refuse(f"--latency {latency!r}: expected seconds or a distribution (docs/design/async.md)")
        bounded = 0 <= seconds <= MAX_LATENCY_S  # else RunConfig refuses it in one line
        if latency_rounding is LatencyRounding.nearest and bounded and round_latency(seconds) != seconds:
            console.print(f"latency {seconds:g} s rounded to {round_latency(seconds):g} s (--latency-rounding nearest)")
            seconds = round_latency(seconds)
        latency_fields = {"latency_s": seconds}
    try:
        from lq_ros.run import validation as validate

        validate.check_suite(suite)  # before RunConfig, whose own message has no suggestion
        cfg = RunConfig(
            suite=suite, task=task, init=init, seed=seed, mode=mode.value, **latency_fields,
            replan_steps=replan_steps, hold=hold.value, request_threshold=request_threshold, merge=merge.value,
            request_slack=request_slack, policy=policy, policy_args=_parse_policy_args(policy_arg),
            camera_size=camera_size, physics_rate=physics_rate, max_steps=max_steps,
            budget_counts=budget_counts.value, clock=clock.value, robot=robot,
        )  # fmt: skip
        if cfg.clock == "realtime" and transport is not Transport.ros:
            raise ValueError("--clock realtime runs through ROS only (--transport ros)")
        if cfg.robot:
            from lq_ros.robot.robot_config import load_robot_config

            load_robot_config(cfg.robot)  # a bad robot YAML: one line naming the entry
        validate.check_run(cfg)  # task and init ranges, the policy and its arguments: before anything starts
        from lq_ros.policies import policy_class

        policy_class(cfg.policy).check_merge(cfg.merge)  # rtc needs a policy that takes the executing prefix
        if cfg.robot:  # a policy that needs what the robot does not publish: refused before anything starts
            from lq_ros.policies import make_policy
            from lq_ros.robot.observation_builder import Requirements, check_robot

            probe = make_policy(cfg.policy, **cfg.policy_args)
            try:
                check_robot(cfg.robot, Requirements.of(probe), cfg.policy)
            finally:
                probe.close()
    except ValueError as exc:  # validate.InputError included
        _refuse(str(exc))
    from lq_ros.transport.processes import ResourceBusy, claimed

    try:  # one run per bag folder (a second lq run of this configuration into this --out), a domain id held: one line
        with claimed(out / cfg.episode_name(), "bag folder"):
            _make_room(out / cfg.episode_name(), overwrite)
            # stdout holds the result alone: what LIBERO, robosuite or the policy print while it runs goes to stderr.
            with contextlib.redirect_stdout(sys.stderr):
                row = run_episode(cfg, out, transport, domain_id=domain_id, timeout_s=timeout)
    except ResourceBusy as exc:
        _refuse(str(exc))
    if as_json:
        print(json.dumps(row, sort_keys=True, default=str))
        print_error_reasons([row])
    else:
        print_rows([row], title=f"{cfg.suite} task {cfg.task} init {cfg.init} · {cfg.policy} · {transport.value}")
        console.print(f"bag: {out / cfg.episode_name()}", highlight=False)
    if row.get("status") == "error":
        raise typer.Exit(1)


def run_episode(cfg, out: Path, transport: Transport, **launch_kwargs) -> dict:
    """One episode through the chosen transport; returns the scored row."""
    from lq_ros.run import episode
    from lq_ros.transport.processes import sigterm_as_keyboard_interrupt

    sigterm_as_keyboard_interrupt()  # e.g. from a job runner: the children are stopped cleanly, like on Ctrl-C
    _, row = episode.run_episode(cfg, out, transport.value, **launch_kwargs)
    return row


@app.command()
def demo(
    out: Annotated[Path, typer.Option(help="Folder for the four episodes' bags.")] = Path("bags/demo"),
    policy: Annotated[str, typer.Option(help=POLICY_HELP)] = "scripted",
    task: Annotated[int, typer.Option(help="LIBERO-Spatial task index, 0..9.")] = 0,
    transport: Annotated[
        Transport, typer.Option(help="ros: the four ROS 2 nodes, kept up for the four episodes; inprocess: no ROS.")
    ] = Transport.ros,
) -> None:
    """LIBERO-Spatial task 0 through one four-node stack: sync and async at 0 and 0.2 s latency (a rerun
    replaces the demo's episodes in OUT)."""
    from lq_ros.run import validation as validate

    configs = [RunConfig(suite="libero_spatial", task=task, mode=mode, latency_s=latency, policy=policy)
               for mode in ("sync", "async") for latency in (0.0, 0.2)]  # fmt: skip
    try:
        validate.check_run(configs[0])
    except ValueError as exc:
        _refuse(str(exc))
    rows = []
    with contextlib.ExitStack() as keep:
        # One long-lived node stack for the four episodes (docs/design/lifecycle.md), as a sweep worker keeps one.
        stack = None
        if transport is Transport.ros:
            from lq_ros.transport.ros.stack import RosStack

            stack = keep.enter_context(RosStack())
        for cfg in configs:
            console.print(f"running {cfg.mode} Δt_sim={cfg.latency_s} s ...")
            _make_room(out / cfg.episode_name(), overwrite=True)
            with contextlib.redirect_stdout(sys.stderr):  # stdout: the table alone
                rows.append(run_episode(cfg, out, transport, **({"stack": stack} if stack else {})))
    print_rows(rows, title=f"LIBERO-LQ demo · libero_spatial task {task} · {policy} · {transport.value}")
    console.print(f"bags: {out}/  (score again with: lq score {out})", highlight=False)
    if any(r.get("status") == "error" for r in rows):
        raise typer.Exit(1)


@app.command()
def score(
    path: Annotated[Path, typer.Argument(help="A bag folder, an .mcap file, or a directory of bags.")],
    ee_topic: Annotated[str, typer.Option(help="geometry_msgs/PoseStamped topic of the end effector.")] = "/ee_pose",
    joint_topic: Annotated[str, typer.Option(help="sensor_msgs/JointState topic (with effort).")] = "/joint_states",
    osc_window: Annotated[int, typer.Option(help="EE-Osc window K in samples.")] = DEFAULT_OSC_WINDOW,
    rate: Annotated[
        TrajectoryRate,
        typer.Option(
            help="Trajectory sampling: auto (control for our bags, the topic's own rate for others), "
            "control (20 Hz), physics (500 Hz), native (the topic's own)."
        ),
    ] = TrajectoryRate.auto,
    energy_rate: Annotated[
        EnergyRate,
        typer.Option(
            help="Energy sampling: auto (substep integrals when present), substep, physics (500 Hz joint states), "
            "control (the paper's 20 Hz estimate), native."
        ),
    ] = EnergyRate.auto,
    efficiency_reference: Annotated[
        Path | None,
        typer.Option(help="episodes.csv/.parquet of an earlier scoring: pin the relative-efficiency reference paths."),
    ] = None,
    elec_coeff: Annotated[float, typer.Option(help="Electrical loss R/Kt², W/(N m)².")] = ELEC_LOSS_COEFF_W_PER_NM2,
    overhead_w: Annotated[float, typer.Option(help="Constant overhead power, W.")] = OVERHEAD_POWER_W,
    out: Annotated[Path | None, typer.Option(help="Where tables go (directory input: default PATH).")] = None,
    jobs: Annotated[int, typer.Option(help="Scoring processes.")] = 1,
    n_boot: Annotated[int, typer.Option(help="Bootstrap resamples per confidence interval, 1..100000.")] = 2000,
    seed: Annotated[int, typer.Option(help="Bootstrap seed.")] = 0,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON object per episode on stdout.")] = False,
) -> None:
    """Score bags. A folder of bags (even of one) also gets per (policy, mode, Δt_sim, suite, task) aggregates with
    95% CIs, written as CSV + Parquet, and a markdown table on stdout. Exits 1 if any bag is damaged."""
    from lq_ros.scoring.aggregate import aggregate, markdown_table, score_directory, write_tables
    from lq_ros.scoring.bag_scorer import find_bags

    # Options are checked before any bag is read: a bad one would otherwise surface per bag, or after scoring.
    if osc_window < 1:
        _refuse(f"--osc-window must be >= 1 (EE-Osc window K in samples), got {osc_window}")
    if not 1 <= n_boot <= MAX_N_BOOT:
        _refuse(f"--n-boot must be 1..{MAX_N_BOOT} bootstrap resamples, got {n_boot}")
    if seed < 0:
        _refuse(f"--seed must be >= 0, got {seed}")
    if jobs < 1:
        _refuse(f"--jobs must be >= 1 scoring processes, got {jobs}")
    for name, value in (("--elec-coeff", elec_coeff), ("--overhead-w", overhead_w)):
        if not 0 <= value < float("inf"):
            _refuse(f"{name} must be a finite number >= 0, got {value}")
    if path.exists() and not path.is_dir() and not path.is_file():  # a FIFO would block the read forever
        _refuse(f"{path}: not a regular file or folder (a FIFO or device is never read as a bag)")
    bags = find_bags(path)
    if not bags:
        _refuse(f"no rosbag2 MCAP bag at or below {path}")
    references = _read_references(efficiency_reference) if efficiency_reference else None
    kwargs = dict(ee_topic=ee_topic, joint_topic=joint_topic, osc_window=osc_window, rate=rate.value,
                  energy_rate=energy_rate.value, elec_coeff=elec_coeff, overhead_w=overhead_w)  # fmt: skip
    episodes = score_directory(path, jobs=jobs, references=references, **kwargs)
    rows = [{k: v for k, v in r.items() if not (isinstance(v, float) and v != v)} for r in episodes.to_dict("records")]
    # Partial: the bag was damaged or unreadable (a run error recorded in an intact bag is not).
    damaged = any(row.get("partial") for row in rows)
    for row in rows:
        for warning in json.loads(row.get("warnings") or "[]"):
            console.print(f"[yellow]warning:[/yellow] {warning}", soft_wrap=True)
    # One bag given as such: its row. A folder of bags, even of one: the aggregates too.
    single_bag = bags == [path] and out is None
    if as_json:
        from lq_ros.scoring.bag_scorer import to_json

        for row in rows:
            nested = {k: json.loads(v) for k, v in row.items() if k in ("versions", "null_reasons", "warnings") and v}
            print(to_json(row | nested))
    elif single_bag:
        print_rows(rows)
    if as_json or not single_bag:
        print_error_reasons(rows)
    if not single_bag:
        aggregates = aggregate(episodes, n_boot=n_boot, seed=seed)
        out_dir = out or (path if path.is_dir() else path.parent)
        written = write_tables(episodes, aggregates, out_dir)
        if not as_json:
            print(markdown_table(aggregates))
        console.print("wrote " + ", ".join(str(p) for p in written.values()), soft_wrap=True)
    if damaged:
        raise typer.Exit(1)


def _read_references(path: Path):
    """Relative-efficiency references from an earlier episodes table (one line naming a bad file)."""
    import pandas as pd

    from lq_ros.scoring.aggregate import REFERENCE_KEYS, efficiency_references

    try:
        table = pd.read_parquet(path) if path.suffix == ".parquet" else pd.read_csv(path)
    except (OSError, ValueError) as exc:
        raise typer.BadParameter(f"--efficiency-reference {path}: unreadable ({exc})") from exc
    if "traj_ref_length" in table:
        return table[[*REFERENCE_KEYS, "traj_ref_length", "traj_ref_episode"]].drop_duplicates(list(REFERENCE_KEYS))
    missing = [c for c in (*REFERENCE_KEYS, "status", "traj_length", "episode") if c not in table]
    if missing:
        raise typer.BadParameter(f"--efficiency-reference {path}: not an episodes table (missing {', '.join(missing)})")
    return efficiency_references(table)


@app.command()
def sweep(
    spec: Annotated[Path, typer.Argument(help="The sweep spec, a YAML file (docs/guide/sweeps.md).")],
    workers: Annotated[int | None, typer.Option(help="Parallel workers; default: CPU cores.")] = None,
    transport: Annotated[Transport | None, typer.Option(help="Default: the spec's, else ros.")] = None,
    backend: Annotated[
        Backend, typer.Option(help="local: worker processes on this machine; ray: Ray actors (--address).")
    ] = Backend.local,
    address: Annotated[str | None, typer.Option(help="Ray cluster address; none: a private local Ray.")] = None,
    out: Annotated[Path | None, typer.Option(help="Sweep folder; default: bags/sweeps/<spec name>.")] = None,
    retry_errors: Annotated[bool, typer.Option(help="Run episodes recorded as error again.")] = False,
) -> None:
    """Run a latency sweep (docs/guide/sweeps.md); resumable: finished episodes are skipped. Exits 1 on any error."""
    from lq_ros.run import sweep as sw

    if address and backend is not Backend.ray:
        raise typer.BadParameter("--address is the Ray cluster address: use it with --backend ray")
    if workers is not None and workers < 1:
        raise typer.BadParameter(f"--workers must be >= 1, got {workers}")
    try:
        sweep_spec = sw.load_spec(spec)
        sw.check_policies(sweep_spec.configs)
    except sw.SpecError as exc:
        _refuse(str(exc) if str(exc).startswith(str(spec)) else f"{spec}: {exc}")
    out = out or Path("bags/sweeps") / sweep_spec.name
    try:
        summary = _run_sweep_with_progress(
            sweep_spec, out, workers=workers, transport=transport.value if transport else None,
            backend=backend.value, address=address, retry_errors=retry_errors,
        )  # fmt: skip
    except (sw.RayConnectError, sw.StoreError) as exc:  # a wrong --address or token; --out busy or unusable
        _refuse(str(exc))
    c = summary.counts
    console.print(
        f"{summary.ran} episodes run in {summary.wall_s:.0f} s ({c['success']} success, {c['failure']} failure, "
        f"{c['error']} error; {summary.retried} retried), {summary.skipped} skipped. Results: {out}  "
        f"(report: lq report {out})"
    )
    if c["error"]:
        raise typer.Exit(1)


#: ``lq eval``'s flags that set what runs, each named as the spec key it sets or mapped to it in
#: lq_ros.run.sweep.spec.FLAG_TO_SPEC_KEY (tests/test_cli_eval.py checks both). --workers and --out say how it runs.
EVAL_SPEC_FLAGS = (
    "--policy", "--policy-arg", "--suite", "--tasks", "--inits", "--latencies", "--modes", "--merge", "--replan-steps",
    "--seeds", "--camera-size", "--max-steps", "--transport",
)  # fmt: skip
#: The file ``lq eval`` writes the spec it runs to, in OUT (``lq sweep OUT/eval_spec.yaml --out OUT`` runs it again).
EVAL_SPEC_FILE = "eval_spec.yaml"
#: What the printed table's brackets and columns mean (the report says more: docs/guide/scoring.md).
EVAL_CAPTION = (
    "[lo, hi]: 95% interval (success: Wilson); success 95% (tasks): clustered by task, from {n} tasks on; "
    "(succ.): over successful episodes; (n=k): fewer than {n} values, no interval"
)
#: Columns of the report's summary table (lq_ros.report.tables.summary_table) that ``lq eval`` prints.
EVAL_COLUMNS = (
    "mode", "latency", "n", "errors", "success %", "success 95% (tasks)", "time s (succ.)", "jerk m/s³ (succ.)",
    "EE-Osc mm (succ.)", "J/step (succ.)",
)  # fmt: skip


def _csv(text: str, flag: str, kind=str) -> list:
    """``a,b,c`` -> [a, b, c] converted by ``kind``; a bad item is one line naming the flag."""
    items = [t for t in (x.strip() for x in text.split(",")) if t]
    try:
        return [kind(t) for t in items]
    except ValueError:
        _refuse(f"{flag}: expected a comma-separated list of {kind.__name__}s, got {text!r}")
    return []


def _number_or_text(text: str) -> float | str:
    """A latency as YAML should hold it: seconds as a number, a distribution as its text."""
    try:
        return float(text)
    except ValueError:
        return text


def eval_spec(policy: str, policy_args: dict, suite: str, tasks: str, inits: str, latencies: list, modes: list[str],
              merge: str, replan_steps: int, seeds: list[int], camera_size: int, max_steps: int, transport: str,
              name: str) -> dict:  # fmt: skip
    """The sweep spec ``lq eval`` runs: its flags under their spec keys (docs/guide/sweeps.md)."""
    protocol = {
        "sync": {"replan_steps": replan_steps, "hold": "stop"},
        "async": {"merge": merge, "request_threshold": -1},
    }
    raw = {
        "name": name, "transport": transport, "suite": suite, "tasks": tasks, "inits": inits,
        "policies": [{"name": policy, "args": policy_args} if policy_args else policy], "latencies_s": latencies,
        "modes": {m: protocol[m] for m in modes}, "seeds": seeds,
    }  # fmt: skip
    raw |= {"camera_size": camera_size} if camera_size else {}
    return raw | ({"max_steps": max_steps} if max_steps else {})


@app.command(name="eval")
def eval_(
    policy: Annotated[str, typer.Option(help=POLICY_HELP)],
    out: Annotated[
        Path,
        typer.Option(help="Folder for the spec, the episodes and the report. Run the same command again to resume."),
    ],
    policy_arg: Annotated[list[str], typer.Option(help=POLICY_ARG_HELP, metavar="KEY=VALUE")] = [],  # noqa: B006
    suite: Annotated[str, typer.Option(help=SUITE_HELP)] = "libero_spatial",
    tasks: Annotated[str, typer.Option(help="Task indices: all, or ranges and indices like 0-9 or 0-4,7.")] = "all",
    inits: Annotated[
        str, typer.Option(help="Init states: all (0-49, the paper's 50 per task), or ranges like 0-9.")
    ] = "all",
    latencies: Annotated[
        str,
        typer.Option(
            help="Injected latencies Δt_sim, comma-separated: seconds (whole 0.05 s ticks) or distributions "
            "(uniform:0.1:0.3). Spec key: latencies_s."
        ),
    ] = "0,0.1,0.2,0.4",
    modes: Annotated[
        str, typer.Option(help="Protocols, comma-separated: sync, async, or sync,async (both, paired).")
    ] = "sync,async",
    merge: Annotated[Merge, typer.Option(help=MERGE_HELP, metavar="STRATEGY")] = Merge.REPLACE,
    replan_steps: Annotated[int, typer.Option(help="sync: actions of each chunk executed before the next.")] = 5,
    seeds: Annotated[str, typer.Option(help="Seeds, comma-separated: every episode once per seed (7 or 7,8,9).")] = "7",
    camera_size: Annotated[
        int,
        typer.Option(help=f"Camera render size, px; 0: the policy's reference size, else {DEFAULT_CAMERA_SIZE_PX}."),
    ] = 0,
    max_steps: Annotated[int, typer.Option(help="Tick budget per episode; 0: the suite's (the paper's).")] = 0,
    workers: Annotated[int | None, typer.Option(help="Episodes run in parallel; default: CPU cores.")] = None,
    transport: Annotated[
        Transport,
        typer.Option(
            help="inprocess: one process per worker, no ROS (fastest; the same episodes); ros: the ROS nodes."
        ),
    ] = Transport.inprocess,
) -> None:
    """Evaluate one policy with the paper's protocol, without a YAML file: tasks x init states x latencies x
    protocols (sync and async), paired.

    Writes the spec it runs to OUT/eval_spec.yaml, runs it as a resumable sweep with a progress bar (run the same
    command again after any stop: finished episodes are skipped), writes the report (OUT/report: report.html,
    report.md, figures, CSV tables) and prints the success table. Exits 1 if any episode was a run error; their
    reasons are printed under the table.

    Every flag is a spec key (docs/guide/sweeps.md): --suite, --tasks, --inits, --seeds, --modes, --camera-size,
    --max-steps and --transport by the same name; --latencies is latencies_s, --policy and --policy-arg are
    policies: [{name: P, args: {key: value}}], --merge is modes: {async: {merge: M}}, --replan-steps is
    modes: {sync: {replan_steps: K}}.
    """
    import yaml

    from lq_ros.report.sweep_report import build_report
    from lq_ros.run import sweep as sw
    from lq_ros.run.validation import did_you_mean

    if workers is not None and workers < 1:
        _refuse(f"--workers must be >= 1, got {workers}")
    mode_list = _csv(modes, "--modes")
    bad = [m for m in mode_list if m not in ("sync", "async")]
    if not mode_list or bad or len(set(mode_list)) != len(mode_list):
        hint = did_you_mean(bad[0], ("sync", "async")) if bad else ""
        _refuse(f"--modes {modes!r}: expected sync, async or sync,async{hint}")
    raw = eval_spec(
        policy, _parse_policy_args(policy_arg), suite, tasks, inits,
        [_number_or_text(v) for v in _csv(latencies, "--latencies")], mode_list, merge.value, replan_steps,
        _csv(seeds, "--seeds", int), camera_size, max_steps, transport.value, out.resolve().name or "eval",
    )  # fmt: skip
    try:
        spec = sw.expand_spec(raw, default_name="eval")
        sw.check_policies(spec.configs)
    except sw.SpecError as exc:
        _refuse(str(exc))
    out.mkdir(parents=True, exist_ok=True)
    (out / EVAL_SPEC_FILE).write_text(yaml.safe_dump(raw, sort_keys=False, allow_unicode=True))
    console.print(f"{len(spec.configs)} episodes; the spec: {out / EVAL_SPEC_FILE}", highlight=False)
    try:
        summary = _run_sweep_with_progress(spec, out, workers=workers, transport=transport.value)
    except (sw.RayConnectError, sw.StoreError) as exc:
        _refuse(str(exc))
    with contextlib.redirect_stdout(sys.stderr):
        result = build_report(out)
    print_eval_table(result, f"{policy} on {suite}")
    print_error_reasons(result.episodes.to_dict("records"))
    console.print(
        f"report: {result.files['report.html']}  (markdown: {result.files['report.md'].name})", highlight=False
    )
    if summary.counts["error"]:
        raise typer.Exit(1)


def print_eval_table(result, title: str) -> None:
    """The report's summary table, the columns of EVAL_COLUMNS, on stdout: each metric with its 95% interval."""
    from lq_ros.report.tables import summary_table
    from lq_ros.scoring.intervals import MIN_N_INTERVAL

    summary = summary_table(result.pooled)
    columns = [c for c in EVAL_COLUMNS if c in summary.columns]
    from rich.markup import escape

    table = Table(title=escape(title), caption=escape(EVAL_CAPTION.format(n=MIN_N_INTERVAL)))
    for column in columns:
        table.add_column(column, justify="left" if column in ("mode", "latency") else "right")
    for _, r in summary.iterrows():
        table.add_row(*(str(r[c]) for c in columns))
    stdout_console().print(table)


def _run_sweep_with_progress(spec, out_dir: Path, **kwargs):
    """run_sweep with a rich progress bar: episodes done, successes, failures, errors, ETA."""
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    from lq_ros.run.sweep import SweepSummary, run_sweep
    from lq_ros.transport.processes import sigterm_as_keyboard_interrupt

    progress = Progress(
        TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
        TextColumn("[green]✓ {task.fields[ok]}[/] [yellow]✗ {task.fields[fail]}[/] [red]! {task.fields[err]}[/]"
                   " [dim]retried {task.fields[retried]}[/]"),
        TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(), console=console, transient=False,
    )  # fmt: skip
    state: dict = {}

    def update(summary: SweepSummary, record: dict | None) -> None:
        if "task" not in state:
            pending = summary.total - summary.skipped
            state["task"] = progress.add_task(spec.name, total=pending, ok=0, fail=0, err=0, retried=0)
            if summary.skipped:
                console.print(f"{summary.skipped} of {summary.total} episodes already finished in {out_dir}: skipped")
        c = summary.counts
        progress.update(state["task"], completed=summary.ran, ok=c["success"], fail=c["failure"], err=c["error"],
                        retried=summary.retried)  # fmt: skip
        if record is not None and record["status"] == "error":
            progress.console.print(f"[red]error[/red] {record['episode']}: {record['row'].get('error_reason')}")

    previous = sigterm_as_keyboard_interrupt()  # SIGTERM stops the sweep (and its workers) like Ctrl-C
    try:
        with progress:
            return run_sweep(spec, out_dir, on_progress=update, **kwargs)
    finally:
        signal.signal(signal.SIGTERM, previous)


@app.command()
def report(
    results_dir: Path,
    out: Annotated[Path | None, typer.Option(help="Output folder; default: RESULTS_DIR/report.")] = None,
    all_episodes: Annotated[bool, typer.Option(help="Every finished episode, not only the spec's.")] = False,
    videos: Annotated[
        int, typer.Option(help="Replay videos per (policy, protocol, Δt_sim) cell (re-simulated: costs CPU).")
    ] = 0,
) -> None:
    """Figures (paper Figs. 4-7, 95% CIs), tables, report.html and report.md of a sweep or bag folder, a figure
    per episode and, with --videos K, up to K replay videos per cell (successes and failures)."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from lq_ros.report.sweep_report import build_report

    if videos < 0:
        raise typer.BadParameter(f"--videos must be >= 0, got {videos}")
    bar = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                   console=console)  # fmt: skip
    stages: dict[str, int] = {}

    def progress(stage: str, done: int, total: int) -> None:
        if stage not in stages:
            stages[stage] = bar.add_task(stage + (" (ticks)" if stage == "replay videos" else ""), total=total)
        bar.update(stages[stage], completed=done, total=total)

    try:
        with bar, contextlib.redirect_stdout(sys.stderr):  # --videos re-simulates: LIBERO prints as it loads
            result = build_report(results_dir, out, all_episodes=all_episodes, videos=videos, progress=progress)
    except FileNotFoundError as exc:
        console.print(f"[red]{exc}[/red]")
        raise typer.Exit(2) from exc
    for warning in result.media_warnings or []:
        console.print(f"[yellow]warning:[/yellow] {warning}", soft_wrap=True)
    console.print(f"{len(result.episodes)} episodes -> {result.files['report.html']}", soft_wrap=True)
    console.print(f"markdown: {result.files['report.md']}", soft_wrap=True)


@app.command()
def replay(
    bag: Annotated[Path, typer.Argument(help="An episode bag folder (or its .mcap) recorded by lq run / lq sweep.")],
    video: Annotated[Path | None, typer.Option(help="Also render the episode into this MP4.")] = None,
    cameras: Annotated[str, typer.Option(help="Cameras, side by side.")] = "agentview,robot0_eye_in_hand",
    size: Annotated[int, typer.Option(help="Pixels per camera image (square).")] = 256,
    as_json: Annotated[bool, typer.Option("--json", help="Print the verdict as JSON.")] = False,
) -> None:
    """Re-simulate a recorded lockstep episode from its bag's configuration and commands; check that the EE
    trajectory equals the recorded one. Exits 1 if it differs, 2 if the bag cannot be replayed (reason given)."""
    from lq_ros.report.replay import ReplayRefused
    from lq_ros.report.replay import replay as replay_bag

    names = tuple(c.strip() for c in cameras.split(",") if c.strip())
    if video is not None and not names:
        raise typer.BadParameter("--cameras names no camera")
    if not 16 <= size <= 2048:
        raise typer.BadParameter(f"--size must be 16..2048 pixels, got {size}")
    try:
        with contextlib.redirect_stdout(sys.stderr):  # stdout: the verdict alone (LIBERO prints as it loads)
            result = replay_bag(bag, video=video, cameras=names, size_px=size)
    except ReplayRefused as exc:
        from rich.markup import escape

        reason = escape(" ".join(f"{bag}: {exc}".split()))  # one line, brackets in a file's text kept
        console.print(f"[red]cannot replay[/red] {reason}", soft_wrap=True, highlight=False)
        raise typer.Exit(2) from None
    if as_json:
        print(json.dumps(result.to_dict(), sort_keys=True))
    else:
        print(result.summary())
    if not result.equal:
        raise typer.Exit(1)


@app.command()
def reindex(
    bags: Annotated[list[Path], typer.Argument(help="Bag folders whose metadata.yaml is rebuilt from the .mcap.")],
) -> None:
    """Rebuild the metadata.yaml of bags from their .mcap (like ros2 bag reindex), e.g. after the recorder was
    killed; the run metadata is kept, the .mcap is not modified. Exits 1 if any .mcap is damaged."""
    from lq_ros.recording.episode_bag import BagRefused
    from lq_ros.recording.episode_bag import reindex as reindex_bag

    damaged = False
    for bag in bags:
        try:
            result = reindex_bag(bag)
        except (FileNotFoundError, BagRefused) as exc:  # no .mcap, a FIFO, a metadata.yaml directory
            _refuse(str(exc))
        except OSError as exc:  # e.g. a read-only bag folder
            _refuse(f"{bag}: cannot rebuild metadata.yaml ({exc})")
        state = "; ".join(result.damage) if result.damage else "complete"
        console.print(f"{bag}: {result.messages} messages ({state})", soft_wrap=True, highlight=False, markup=False)
        damaged |= bool(result.damage)
    if damaged:
        raise typer.Exit(1)


# Learned policies: demonstrations and training (lq_ros/training/cli.py).
from lq_ros.training import cli as _learned_cli  # noqa: E402

app.command()(_learned_cli.collect)
app.command()(_learned_cli.train)


def main() -> int:
    """``lq``: a usage mistake is one line on stderr and exit code 2 (no usage panel, no traceback)."""
    try:
        from typer._click import exceptions  # typer vendors click (0.2x)
    except ImportError:  # pragma: no cover - an older typer on click
        from click import exceptions

    try:
        from lq_ros.transport.processes import executor_choice, node_forks_choice, sim_cpu_choice

        executor_choice(dict(os.environ))  # the node processes' executor: refused before anything starts
        sim_cpu_choice(dict(os.environ))  # whether the stack pins its sim to a CPU
        node_forks_choice(dict(os.environ))  # whether the stack forks its nodes from a process that imported them
        from lq_ros.sim import model_cache

        model_cache.settings(os.environ)  # the compiled-model cache's variables
    except ValueError as exc:
        console.print(f"[red]error:[/red] {exc}", soft_wrap=True, highlight=False)
        return 2
    _importable_current_directory()
    if not sys.stdout.isatty() and "TERMINAL_WIDTH" not in os.environ and may_print_help(sys.argv[1:]):
        import typer.rich_utils  # (with rich's markdown renderer: imported only for help, not for every command)

        typer.rich_utils.MAX_WIDTH = PIPED_WIDTH  # --help piped: no option name cut short
    from lq_ros.run.quiet import quiet_simulator_banners

    quiet_simulator_banners()
    try:
        return app(standalone_mode=False) or 0
    except exceptions.NoArgsIsHelpError as exc:
        exc.show()
        return exc.exit_code
    except exceptions.UsageError as exc:
        from rich.markup import escape

        where = exc.ctx.command_path if exc.ctx is not None else "lq"
        message = _choice_hint(" ".join(exc.format_message().split()))
        console.print(f"[red]error:[/red] {escape(f'{where}: {message} (see {where} --help)')}", soft_wrap=True,
                      highlight=False)  # fmt: skip
        return exc.exit_code
    except exceptions.ClickException as exc:
        exc.show()
        return exc.exit_code
    except typer.Abort:
        console.print("Aborted!")
        return 1


def may_print_help(args: list[str]) -> bool:
    """Whether ``lq ARGS`` may print a help text: ``--help`` anywhere, or no command (``lq`` alone shows it)."""
    return not args or "--help" in args


def _importable_current_directory() -> None:
    """``--policy module:Class`` finds a module in the current directory, as ``python -m`` would (after installed
    packages, so a file there never hides one lq itself uses); PYTHONSAFEPATH / ``python -P`` turn it off."""
    if not sys.flags.safe_path and os.getcwd() not in sys.path and "" not in sys.path:
        sys.path.append(os.getcwd())


def _choice_hint(message: str) -> str:
    """Click's message for a value outside an option's choices, plainer and with the closest choice:
    "Invalid value for '--mode': 'asynch' is not one of 'sync', 'async'. (did you mean 'async'?)"."""
    import re

    from lq_ros.run.validation import did_you_mean

    message = message.replace("Value error, ", "")
    found = re.search(r"'([^']*)' is not one of ((?:'[^']*'(?:, )?)+)", message)
    if found:
        message += did_you_mean(found.group(1), re.findall(r"'([^']*)'", found.group(2)))
    return message


def entry() -> None:
    """The ``lq`` command: :func:`main`, then leave without tearing the interpreter down when nothing needs it.

    Once every file is closed and everything printed, tearing down the modules of an in-process run (MuJoCo,
    robosuite, numba and the rest) takes 0.1-0.2 s. The exit handlers still run; the teardown is skipped only
    when ROS was never loaded in this process (DDS removes its shared-memory files in its destructors) and no
    non-daemon thread is still running.
    """
    import threading

    code = main()
    run_exit_handlers = getattr(atexit, "_run_exitfuncs", None)
    others = [t for t in threading.enumerate() if t is not threading.main_thread() and not t.daemon]
    if "rclpy" in sys.modules or others or run_exit_handlers is None:
        sys.exit(code)
    run_exit_handlers()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


if __name__ == "__main__":
    entry()
