"""``lq run``: one episode, its scored row."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import sys
from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape

from lq_ros.cli.common import (
    _RUN,
    BUDGETS_HELP,
    MERGE_HELP,
    POLICY_ARG_HELP,
    POLICY_HELP,
    REPLAN_STEPS_HELP,
    SUITE_HELP,
    BudgetCounts,
    Budgets,
    Clock,
    LatencyRounding,
    Transport,
    _make_room,
    _out_folder,
    _parse_policy_args,
    _refuse,
    console,
    print_error_reasons,
    print_rows,
)
from lq_ros.core.executor_protocol import Hold, Mode
from lq_ros.core.merge import Merge
from lq_ros.core.run_config import DEFAULT_CAMERA_SIZE_PX, RunConfig
from lq_ros.run.episode_notes import warnings_of
from lq_ros.transport.ros.domain_choice import choose_domain


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
    replan_steps: Annotated[int | None, typer.Option(help=REPLAN_STEPS_HELP)] = None,
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
    max_steps: Annotated[int, typer.Option(help="Tick budget; 0: the suite's (see --budgets).")] = _RUN.max_steps,
    budgets: Annotated[Budgets, typer.Option(help=BUDGETS_HELP)] = Budgets(_RUN.budgets),
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
    domain_id: Annotated[
        int | None,
        typer.Option(
            help="ROS domain of the nodes; default: an exported ROS_DOMAIN_ID, else a free one (printed either way). "
            "Refused if another lq run of yours holds it."
        ),
    ] = None,
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
            seconds = float(latency if latency.isascii() else "not ASCII")  # digits 0-9 only
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
            replan_steps=_RUN.replan_steps if replan_steps is None else replan_steps, hold=hold.value,
            request_threshold=request_threshold, merge=merge.value,
            request_slack=request_slack, policy=policy, policy_args=_parse_policy_args(policy_arg),
            camera_size=camera_size, physics_rate=physics_rate, max_steps=max_steps, budgets=budgets.value,
            budget_counts=budget_counts.value, clock=clock.value, robot=robot,
            replan_steps_source=("policy" if replan_steps is None else "flag") if mode is Mode.SYNC else "",
        )  # fmt: skip
        if cfg.clock == "realtime" and transport is not Transport.ros:
            raise ValueError("--clock realtime runs through ROS only (--transport ros)")
        from lq_ros.run.sweep.spec import MAX_CAMERA_SIZE_PX

        if not 0 <= camera_size <= MAX_CAMERA_SIZE_PX:  # as a spec's camera_size
            raise ValueError(f"--camera-size: expected 0 (the policy's) or 1..{MAX_CAMERA_SIZE_PX} px, got "
                             f"{camera_size}")  # fmt: skip
        if timeout is not None and not 0 < timeout < float("inf"):
            raise ValueError(f"--timeout: expected a number of seconds > 0, got {timeout}")
        if cfg.robot:
            from lq_ros.robot.robot_config import load_robot_config

            load_robot_config(cfg.robot)  # a bad robot YAML: one line naming the entry
        validate.check_run(cfg)  # task and init ranges, the policy and its arguments: before anything starts
        from lq_ros.policies import declared_replan_steps, policy_class

        if replan_steps is None and cfg.mode == "sync":  # the policy's reference protocol (LeRobot: n_action_steps)
            cfg = dataclasses.replace(cfg, replan_steps=declared_replan_steps(cfg.policy, cfg.policy_args))

        policy_class(cfg.policy).check_merge(cfg.merge)  # rtc needs a policy that takes the executing prefix
        if cfg.robot:  # a policy that needs what the robot does not publish: refused before anything starts
            from lq_ros.policies import make_policy
            from lq_ros.robot.observation_builder import Requirements, check_robot

            probe = make_policy(cfg.policy, **cfg.policy_args)
            try:
                check_robot(cfg.robot, Requirements.of(probe), cfg.policy)
            finally:
                probe.close()
        # The nodes' ROS domain: --domain-id, else an exported ROS_DOMAIN_ID, else a free one.
        domain, source = choose_domain(domain_id) if transport is Transport.ros else (None, "")
    except ValueError as exc:  # validate.InputError included
        _refuse(str(exc))
    from lq_ros.transport.processes import ResourceBusy, claimed

    _out_folder(out)
    try:  # one run per bag folder (a second lq run of this configuration into this --out), a domain id held: one line
        with claimed(out / cfg.episode_name(), "bag folder"):
            _make_room(out / cfg.episode_name(), overwrite)
            # stdout holds the result alone: what LIBERO, robosuite or the policy print while it runs goes to stderr.
            with contextlib.ExitStack() as stack:
                launch: dict = {"timeout_s": timeout}
                if transport is Transport.ros:  # the nodes' domain, said so that ROS tools can join it
                    from lq_ros.transport.ros.stack import RosStack

                    launch["stack"] = stack.enter_context(RosStack(domain))
                    console.print(f"ROS_DOMAIN_ID={launch['stack'].domain.id} ({source})", highlight=False)
                with contextlib.redirect_stdout(sys.stderr):
                    row = run_episode(cfg, out, transport, **launch)
    except ResourceBusy as exc:
        _refuse(str(exc))
    if as_json:
        print(json.dumps(row, sort_keys=True, default=str))
        print_error_reasons([row])
    else:
        print_rows([row], title=f"{cfg.suite} task {cfg.task} init {cfg.init} · {cfg.policy} · {transport.value}",
                   where=f"run folder: {out}/ (the bag: {cfg.episode_name()}/)")  # fmt: skip
        console.print(f"bag: {out / cfg.episode_name()}", highlight=False)
    for warning in warnings_of(row, out / cfg.episode_name()):
        console.print(f"[yellow]warning:[/yellow] {escape(warning)}", highlight=False)
    if row.get("status") == "error":
        raise typer.Exit(1)


def run_episode(cfg, out: Path, transport: Transport, **launch_kwargs) -> dict:
    """One episode through the chosen transport; returns the scored row."""
    from lq_ros.run import episode
    from lq_ros.transport.processes import sigterm_as_keyboard_interrupt

    sigterm_as_keyboard_interrupt()  # e.g. from a job runner: the children are stopped cleanly, like on Ctrl-C
    _, row = episode.run_episode(cfg, out, transport.value, **launch_kwargs)
    return row
