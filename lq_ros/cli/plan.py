"""``lq plan``: how many episodes a difference in success needs, paired and unpaired, with task clustering."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Annotated

import typer

from lq_ros.cli.common import _refuse

if TYPE_CHECKING:
    from lq_ros.scoring.power import Plan


def _lines(p: Plan) -> list[str]:
    from lq_ros.scoring.power import independent_discordance

    sign = "+" if p.effect > 0 else ""
    head = (
        f"Difference in success {sign}{100 * p.effect:g} points ({100 * p.baseline:g}% -> "
        f"{100 * (p.baseline + p.effect):g}%), two-sided alpha {p.alpha:g}, power {100 * p.power:g}%."
    )
    clustered = p.per_task > 1 and p.icc > 0
    lines = [head, "", "Unpaired (separate episodes per arm; z test of two proportions):"]
    lines.append(f"  {p.unpaired} independent episodes per arm")
    if p.per_task > 1:
        total = p.unpaired * p.unpaired_design_effect
        lines.append(
            f"  {_per_task_text(total, p.per_task)} with {p.per_task} episodes per task at ICC {p.icc:.3g} "
            f"(design effect {p.unpaired_design_effect:.2f})"
        )
    lines += ["", "Paired (both arms on the same task, init and seed; McNemar's test):"]
    for i, d in enumerate(p.discordances):
        lines.append(f"  discordance {d:g}: {p.paired[i]} independent pairs")
        if p.per_task > 1:
            total = p.paired[i] * p.paired_design_effect[i]
            icc = (p.paired_design_effect[i] - 1) / (p.per_task - 1)
            lines.append(
                f"    {_per_task_text(total, p.per_task)} at ICC {icc:.3g} (design effect "
                f"{p.paired_design_effect[i]:.2f})"
            )
            lines.append(f"    task-level test (the task as the unit, t over task means): {p.paired_tasks[i]} tasks "
                         f"x {p.per_task} pairs")  # fmt: skip
    if p.tasks is not None:
        n = p.tasks * p.per_task
        lines += ["", f"Power at {p.tasks} tasks x {p.per_task} episodes per arm ({n} per arm):"]
        lines.append(f"  unpaired {100 * p.power_unpaired:.0f}%")
        for i, d in enumerate(p.discordances):
            lines.append(f"  paired at discordance {d:g}: McNemar {100 * p.power_paired[i]:.0f}%, task-level "
                         f"{100 * p.power_paired_tasks[i]:.0f}%")  # fmt: skip
        if p.tasks < 5:
            lines.append("  (fewer than 5 tasks: the report gives no task-clustered interval)")
    lines += [
        "",
        "Assumptions:",
        "  - normal approximations (McNemar: Connor 1987; unpaired: pooled-variance z test, no continuity correction);",
        "  - discordance = the share of pairs where exactly one arm succeeds; arms that fail on the same scenes have",
        "    a small one, arms that succeed independently of each other "
        f"{independent_discordance(p.baseline, p.effect):.3g};",
    ]
    if clustered:
        lines += [
            "  - episodes of a task correlate: the design effect 1 + (m - 1) ICC multiplies the episodes (arms drawn",
            "    on separate tasks: conservative for arms on the same tasks); the paired design takes the ICC of the",
            "    task effects from --effect-sd, else the same ICC as success;",
        ]
    else:
        lines += [
            "  - episodes independent (ICC 0 or one episode per task): optimistic when success clusters by task;",
            "    give --inits and --icc or --task-sd (lq report prints each cell's design effect);",
        ]
    lines.append("  - the discordance and the ICC are guesses until a pilot sweep measures them.")
    return lines


def _per_task_text(total: float, per_task: int) -> str:
    tasks = math.ceil(total / per_task - 1e-9)
    return f"{tasks} tasks x {per_task} = {tasks * per_task} episodes per arm"


def plan(
    effect: Annotated[float, typer.Option(help="Difference in success to detect, as a fraction (0.10: 10 points).")],
    baseline: Annotated[float, typer.Option(help="Success rate of the reference arm, as a fraction.")],
    alpha: Annotated[float, typer.Option(help="Two-sided significance level.")] = 0.05,
    power: Annotated[float, typer.Option(help="Power to reach.")] = 0.8,
    discordance: Annotated[
        list[float] | None,
        typer.Option(help="Share of pairs where exactly one arm succeeds (repeatable); default 0.2 and independence."),
    ] = None,
    inits: Annotated[int, typer.Option(help="Episodes per task and arm (init states x seeds).", min=1)] = 1,
    icc: Annotated[float, typer.Option(help="Intra-task correlation of success (0: independent episodes).")] = 0.0,
    task_sd: Annotated[float | None, typer.Option(help="SD of the tasks' success rates (instead of --icc).")] = None,
    effect_sd: Annotated[
        float | None, typer.Option(help="SD of the per-task effect, for the paired design (default: --icc's).")
    ] = None,
    tasks: Annotated[int | None, typer.Option(help="Tasks you can run: print the power at tasks x inits.")] = None,
) -> None:
    """Sample size and power for a difference in success: unpaired, paired (McNemar, by discordance) and with task
    clustering (design effect, task-level test), with the assumptions. E.g. lq plan --effect 0.10 --baseline 0.5."""
    from lq_ros.scoring.power import plan as make_plan

    try:
        result = make_plan(baseline, effect, alpha=alpha, power=power, discordances=tuple(discordance or ()),
                           per_task=inits, icc=icc, task_sd=task_sd, effect_sd=effect_sd, tasks=tasks)  # fmt: skip
    except ValueError as exc:
        _refuse(str(exc))
    typer.echo("\n".join(_lines(result)))
