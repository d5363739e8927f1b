"""``lq collect`` and ``lq train`` (registered in lq_ros/cli.py)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Annotated

import typer

from lq_ros.core.safe_write import output_folder
from lq_ros.training.dataset import NoEpisodes
from lq_ros.training.recipe import KIND_RECIPE, TrainConfig, parse_ids

#: TrainConfig's defaults (the shipped recipe): `lq train`'s option defaults, so the two cannot drift apart.
_D = TrainConfig
#: "oft 8, flow 10" per kind-dependent field, for the help texts.
_RECIPE_HELP = {
    key: ", ".join(f"{kind} {values[key]:g}" for kind, values in KIND_RECIPE.items())
    for key in ("horizon", "steps", "ema")
}


def _ints(spec: str) -> tuple[int, ...]:
    """``"0-9"``, ``"0,2,5"`` or ``"10-29,40"`` -> integers (recipe.parse_ids), as a command-line error."""
    try:
        return parse_ids(spec)
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from None


def _noise_levels(spec: str) -> tuple[float, ...]:
    """``"0,0.1,0.2"`` -> action-noise std values (finite, >= 0, ASCII digits), else one line naming the bad value
    and what is valid."""
    levels = []
    for item in spec.split(","):
        try:
            value = float(item) if item.strip().isascii() else math.nan  # "٠.١" is not taken as 0.1
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and value >= 0.0):
            raise typer.BadParameter(
                f"{item.strip()!r}{f' (in {spec!r})' if ',' in spec else ''} is not a noise std; expected numbers"
                " >= 0 separated by commas, e.g. '0,0.1,0.2'",
                param_hint="'--noise'",
            )
        levels.append(value)
    return tuple(levels)


def _driver(spec: str) -> dict:
    """``name[:key=value,...]`` -> CollectConfig driver fields; values parsed as JSON when possible."""
    if not spec:
        return {}
    name, _, rest = spec.partition(":")
    args = {}
    for item in filter(None, rest.split(",")):
        key, sep, value = item.partition("=")
        if not sep:
            raise typer.BadParameter(f"bad driver {spec!r}: expected name:key=value,...")
        try:
            args[key] = json.loads(value)
        except json.JSONDecodeError:
            args[key] = value
    return {"driver": name, "driver_args": args}


def collect(
    out: Annotated[Path, typer.Option(help="Dataset folder (data/frames.parquet + meta/).")],
    suite: str = "libero_spatial",
    tasks: Annotated[str, typer.Option(help="Task ids, e.g. '0-9' or '0,3'.")] = "0-9",
    inits: Annotated[str, typer.Option(help="Init states (one episode each); 0-9 are the evaluation set.")] = "10-29",
    noise: Annotated[str, typer.Option(help="Arm action-noise std per episode, cycled, e.g. '0,0.1,0.2'.")] = (
        "0,0.1,0.2"
    ),
    repeats: Annotated[int, typer.Option(help="Episodes per init state (own noise draw each).")] = 1,
    fresh: Annotated[
        bool, typer.Option(help="--inits are seeds of new random object placements, not shipped init states.")
    ] = False,
    seed: int = 7,
    expert: str = "scripted",
    chunk_rows: Annotated[int, typer.Option(help="Rows of the expert's plan stored per frame.")] = 16,
    max_steps: Annotated[int, typer.Option(help="Tick budget per episode; 0: the suite's.")] = 0,
    workers: Annotated[int, typer.Option(help="Processes (one task each at a time).")] = 2,
    driver: Annotated[
        str, typer.Option(help="DAgger: policy driving the robot, 'name[:key=value,...]'; the expert labels.")
    ] = "",
    driver_replan: Annotated[int, typer.Option(help="Actions of each driver chunk run open loop.")] = 8,
    keep_failures: Annotated[bool, typer.Option(help="Keep unsuccessful episodes too (DAgger).")] = False,
    latency_ticks: Annotated[
        str, typer.Option(help="DAgger under latency: latency ticks drawn per episode, e.g. '0-8' (empty: off).")
    ] = "",
    modes: Annotated[str, typer.Option(help="With --latency-ticks: protocols drawn per episode.")] = "sync,async",
    latency_driver: Annotated[
        list[str] | None,
        typer.Option(help="With --latency-ticks: a driver 'name[:key=value,...]' (repeatable; drawn per episode)."),
    ] = None,
    gripper_noise: Annotated[
        float, typer.Option(help="Per-tick probability of a 2-7 tick burst of a wrong gripper command.")
    ] = 0.0,
) -> None:
    """Collect expert demonstrations with DART-style action noise; keeps the successful episodes."""
    from lq_ros.training.collect import CollectConfig
    from lq_ros.training.collect import collect as run_collect

    try:
        levels = _noise_levels(noise)
        cfg = CollectConfig(
            suite=suite, tasks=_ints(tasks), inits=_ints(inits), noise_levels=levels, repeats=repeats, fresh=fresh,
            seed=seed, expert=expert, chunk_rows=chunk_rows, max_steps=max_steps, workers=workers,
            driver_replan=driver_replan, keep_failures=keep_failures, **_driver(driver),
            latency_ticks=_ints(latency_ticks) if latency_ticks else (), modes=tuple(modes.split(",")),
            latency_drivers=tuple(latency_driver or ("scripted",)), gripper_noise=gripper_noise,
        )  # fmt: skip
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from exc
    output_folder(out)  # not a file, a dangling link or another user's folder (one line)
    try:
        info = run_collect(cfg, out)
    except NoEpisodes as exc:
        typer.echo(f"error: {exc}: nothing written to {out}; more --repeats, other --tasks or less --noise", err=True)
        raise typer.Exit(1) from None
    stats = info["collection"]["per_task"]
    for task, s in stats.items():
        print(
            f"task {task}: {s['successes']}/{s['attempts']} successful ({s['frames']} frames kept,"
            f" {s['errors']} errors;"
            f" successes by noise std {s.get('kept_by_noise', {})})"
        )
    wall_s = info["collection"]["wall_s"]
    print(f"{out}: {info['total_episodes']} episodes, {info['total_frames']} frames, {wall_s:.0f} s")


def train(
    policy: Annotated[str, typer.Option(help="oft | flow")],
    data: Annotated[list[Path], typer.Option(help="Dataset folder from `lq collect` (repeatable).")],
    out: Annotated[Path, typer.Option(help="Folder for <name>.pt + <name>.json.")],
    chunk: Annotated[int, typer.Option(help=f"Chunk length H; 0: the recipe's ({_RECIPE_HELP['horizon']}).")] = (
        _D.horizon
    ),
    steps: Annotated[int, typer.Option(help=f"Optimiser steps; 0: the recipe's ({_RECIPE_HELP['steps']}).")] = (
        _D.steps
    ),
    batch_size: int = _D.batch_size,
    lr: float = _D.lr,
    width: int = _D.width,
    depth: int = _D.depth,
    seed: int = _D.seed,
    dropout: float = _D.dropout,
    feature_noise: Annotated[float, typer.Option(help="Input noise std (normalised units) in training.")] = (
        _D.feature_noise
    ),
    ema: Annotated[
        float | None,
        typer.Option(
            help=f"EMA decay of the saved weights per step (0: off); default the recipe's ({_RECIPE_HELP['ema']})."
        ),
    ] = _D.ema,
    joint_velocity: Annotated[bool, typer.Option(help="Joint velocities as inputs (off: see the docs).")] = (
        _D.joint_velocity
    ),
    target: Annotated[str, typer.Option(help="future (next H labels) | plan (expert's plan per frame).")] = _D.target,
    replan_steps: Annotated[int, typer.Option(help="Actions run per chunk (default); 0: H oft, H//2 flow.")] = (
        _D.replan_steps
    ),
    flow_steps: Annotated[int, typer.Option(help="Euler steps of the flow sampler.")] = _D.flow_steps,
    threads: Annotated[int, typer.Option(help="torch threads.")] = _D.threads,
    name: Annotated[str, typer.Option(help="Checkpoint name; default <policy>_c<H>_<suite>.")] = _D.name,
    delay_max: Annotated[
        int, typer.Option(help="Delay-aware variant: condition on d in 0..DELAY_MAX and the d executing actions.")
    ] = _D.delay_max,
    init_from: Annotated[
        str, typer.Option(help="Fine-tune from a checkpoint (name: --out folder, then shipped; or a path).")
    ] = _D.init_from,
    freeze_base: Annotated[
        bool, typer.Option(help="With --init-from: train only the conditioning inputs (d = 0 stays the initial model).")
    ] = _D.freeze_base,
    successful_only: Annotated[
        bool, typer.Option(help="Only the frames of successful episodes (of a dataset that kept failures).")
    ] = _D.successful_only,
) -> None:
    """Train a chunk policy on collected demonstrations (seeded; logs losses as JSON lines on stderr).

    Every default is the shipped weights' recipe (lq_ros/training/recipe.py): with no other option,
    `lq train --policy oft --chunk 8` trains with the configuration the shipped oft_c8 weights record.
    """
    from lq_ros.training.train import train as run_train

    try:
        cfg = TrainConfig(
            policy=policy, horizon=chunk, width=width, depth=depth, steps=steps, batch_size=batch_size, lr=lr,
            seed=seed, dropout=dropout, feature_noise=feature_noise, ema=ema, joint_velocity=joint_velocity,
            target=target, replan_steps=replan_steps, flow_steps=flow_steps, threads=threads, name=name,
            delay_max=delay_max, init_from=init_from, freeze_base=freeze_base,
            successful_only=successful_only,
        )  # fmt: skip
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from exc
    output_folder(out)  # not a file, a dangling link or another user's folder (one line)
    try:
        meta = run_train(cfg, data, out)
    except FileNotFoundError as exc:  # no dataset at --data (the message says how to make one)
        raise typer.BadParameter(str(exc)) from None
    m = meta["metrics"]
    print(json.dumps({k: m[k] for k in ("params", "train_wall_s", "final_train_loss", "final_val_loss")}))
