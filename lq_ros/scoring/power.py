"""Sample size and power for a difference in success rates, before a sweep is run (``lq plan``).

Three analyses, two-sided at level alpha, each with the normal approximation its test is planned with:

- **Unpaired**: two arms on separate episodes, the z test of two proportions (pooled variance under the null;
  Fleiss, Levin and Paik 2003, 4.2, without continuity correction):
  n per arm = (z_{1-a/2} sqrt(2 pbar qbar) + z_{1-b} sqrt(p1 q1 + p2 q2))^2 / delta^2.
- **Paired**: both arms on the same (task, init, seed) episodes, McNemar's test (Connor 1987, Biometrics 43:207):
  pairs = (z_{1-a/2} sqrt(psi) + z_{1-b} sqrt(psi - delta^2))^2 / delta^2, psi the discordance (the share of
  pairs where exactly one arm succeeds; arms that fail on the same scenes have a small psi, independent arms
  psi = p1 q2 + p2 q1).
- **Task clustering**: episodes of one task are not independent (one task 0/10, another 10/10). With m episodes
  per task and intra-task correlation ICC the variance grows by the design effect 1 + (m - 1) ICC (Kish 1965), so
  the episodes above are multiplied by it. A task SD (of the task success rates, or of the task effects for the
  paired design) gives the ICC: SD^2 / (the per-episode variance: p (1 - p), or psi - delta^2 for a pair's
  difference). The task-level test (the task as the unit, as the report's task-clustered interval) is a t test
  over k task means with k - 1 degrees of freedom: its power is the noncentral t's.

The design effect assumes every arm's tasks are drawn apart; arms on the same tasks share them, which makes the
unpaired numbers conservative. These are plans, not guarantees: the discordance and the ICC are guesses until a
pilot sweep measures them (``lq report`` prints each cell's design effect).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from scipy import stats

#: Fewest tasks the report gives a task-clustered interval for (lq_ros/scoring/intervals.py MIN_N_INTERVAL).
MIN_TASKS = 5


def _z(p: float) -> float:
    return float(stats.norm.ppf(p))


def _check(alpha: float, power: float | None = None) -> None:
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must be in (0, 1), got {alpha}")
    if power is not None and not 0.0 < power < 1.0:
        raise ValueError(f"power must be in (0, 1), got {power}")


def _rates(baseline: float, effect: float) -> tuple[float, float]:
    p2, p1 = float(baseline), float(baseline) + float(effect)
    if not 0.0 < p2 < 1.0:
        raise ValueError(f"baseline success must be in (0, 1), got {baseline}")
    if effect == 0 or not 0.0 < p1 < 1.0:
        raise ValueError(f"effect must be non-zero with baseline + effect in (0, 1), got {baseline} + {effect}")
    return p1, p2


def independent_discordance(baseline: float, effect: float) -> float:
    """The discordance of two arms that succeed independently of each other on a scene: p1 q2 + p2 q1."""
    p1, p2 = _rates(baseline, effect)
    return p1 * (1 - p2) + p2 * (1 - p1)


def check_discordance(baseline: float, effect: float, discordance: float) -> None:
    """Raise ValueError unless |effect| < discordance <= the most two arms at these rates can disagree."""
    p1, p2 = _rates(baseline, effect)
    most = min(p1 + p2, 2.0 - p1 - p2)
    if not abs(effect) < discordance <= most + 1e-12:
        raise ValueError(
            f"discordance must be above |effect| = {abs(effect):g} and at most {most:g} at {p2:g} vs {p1:g}, "
            f"got {discordance}"
        )


def unpaired_episodes(baseline: float, effect: float, alpha: float = 0.05, power: float = 0.8) -> int:
    """Independent episodes per arm for the z test of two proportions (50% vs 60%: 388)."""
    _check(alpha, power)
    p1, p2 = _rates(baseline, effect)
    pbar = (p1 + p2) / 2
    root = _z(1 - alpha / 2) * math.sqrt(2 * pbar * (1 - pbar)) + _z(power) * math.sqrt(p1 * (1 - p1) + p2 * (1 - p2))
    return math.ceil(root**2 / effect**2 - 1e-9)


def unpaired_power(baseline: float, effect: float, episodes: float, alpha: float = 0.05) -> float:
    """Power of the z test of two proportions with ``episodes`` independent episodes per arm."""
    _check(alpha)
    p1, p2 = _rates(baseline, effect)
    if episodes <= 0:
        return 0.0
    pbar = (p1 + p2) / 2
    spread = math.sqrt(p1 * (1 - p1) + p2 * (1 - p2))
    shift = abs(effect) * math.sqrt(episodes) - _z(1 - alpha / 2) * math.sqrt(2 * pbar * (1 - pbar))
    return float(stats.norm.cdf(shift / spread))


def mcnemar_pairs(effect: float, discordance: float, alpha: float = 0.05, power: float = 0.8) -> int:
    """Independent pairs for McNemar's test of a paired difference ``effect`` at ``discordance`` (0.10 at 0.2: 155)."""
    _check(alpha, power)
    if not abs(effect) < discordance <= 1.0:
        raise ValueError(f"discordance must be in (|effect|, 1], got {discordance} for effect {effect}")
    root = _z(1 - alpha / 2) * math.sqrt(discordance) + _z(power) * math.sqrt(discordance - effect**2)
    return math.ceil(root**2 / effect**2 - 1e-9)


def mcnemar_power(effect: float, discordance: float, pairs: float, alpha: float = 0.05) -> float:
    """Power of McNemar's test with ``pairs`` independent pairs."""
    _check(alpha)
    if not abs(effect) < discordance <= 1.0:
        raise ValueError(f"discordance must be in (|effect|, 1], got {discordance} for effect {effect}")
    if pairs <= 0:
        return 0.0
    shift = abs(effect) * math.sqrt(pairs) - _z(1 - alpha / 2) * math.sqrt(discordance)
    return float(stats.norm.cdf(shift / math.sqrt(discordance - effect**2)))


def design_effect(per_task: int, icc: float) -> float:
    """1 + (m - 1) ICC: how much m correlated episodes of a task inflate the variance of a mean over them."""
    if per_task < 1:
        raise ValueError(f"episodes per task must be >= 1, got {per_task}")
    if not 0.0 <= icc <= 1.0:
        raise ValueError(f"ICC must be in [0, 1], got {icc}")
    return 1.0 + (per_task - 1) * icc


def icc_from_task_sd(task_sd: float, unit_variance: float) -> float:
    """The ICC that a between-task SD implies for units of variance ``unit_variance`` (p (1 - p) for a success,
    psi - delta^2 for a pair's difference): SD^2 / unit variance, at most 1."""
    if task_sd < 0 or unit_variance <= 0:
        raise ValueError(f"task SD must be >= 0 and the unit variance > 0, got {task_sd} and {unit_variance}")
    icc = task_sd**2 / unit_variance
    if icc > 1.0:
        raise ValueError(f"a task SD of {task_sd:g} exceeds the SD of one episode ({math.sqrt(unit_variance):.3g})")
    return icc


def task_level_power(
    effect: float, unit_variance: float, icc: float, tasks: int, per_task: int, alpha: float = 0.05
) -> float:
    """Power of the two-sided t test over ``tasks`` task means of ``per_task`` units each (k - 1 degrees of
    freedom; a task mean's variance is unit_variance (ICC + (1 - ICC) / m)). 0 below 2 tasks."""
    _check(alpha)
    if tasks < 2:
        return 0.0
    task_variance = unit_variance * (icc + (1.0 - icc) / per_task)
    df = tasks - 1
    ncp = abs(effect) / math.sqrt(task_variance / tasks)
    crit = float(stats.t.ppf(1 - alpha / 2, df))
    return float(stats.nct.sf(crit, df, ncp) + stats.nct.cdf(-crit, df, ncp))


def task_level_tasks(
    effect: float, unit_variance: float, icc: float, per_task: int, alpha: float = 0.05, power: float = 0.8
) -> int:
    """Fewest tasks (at least MIN_TASKS) whose task-level t test reaches ``power``; raises ValueError past 10,000."""
    _check(alpha, power)
    for tasks in range(MIN_TASKS, 10_001):
        if task_level_power(effect, unit_variance, icc, tasks, per_task, alpha) >= power:
            return tasks
    raise ValueError("more than 10,000 tasks would be needed")


@dataclass(frozen=True)
class Plan:
    """Everything ``lq plan`` prints, from :func:`plan`."""

    baseline: float
    effect: float
    alpha: float
    power: float
    per_task: int
    icc: float
    icc_paired: float
    discordances: tuple[float, ...]
    unpaired: int
    unpaired_design_effect: float
    paired: tuple[int, ...]
    paired_design_effect: tuple[float, ...]
    paired_tasks: tuple[int, ...]
    tasks: int | None
    power_unpaired: float | None
    power_paired: tuple[float, ...] | None
    power_paired_tasks: tuple[float, ...] | None


def plan(
    baseline: float,
    effect: float,
    *,
    alpha: float = 0.05,
    power: float = 0.8,
    discordances: tuple[float, ...] = (),
    per_task: int = 1,
    icc: float = 0.0,
    task_sd: float | None = None,
    effect_sd: float | None = None,
    tasks: int | None = None,
) -> Plan:
    """Sample sizes (and, with ``tasks``, the power at tasks x per_task episodes per arm) of the three analyses.

    ``discordances``: the paired designs' psi (default: 0.2, if possible, and the independent arms' value);
    ``icc`` or ``task_sd``: the clustering of success (``task_sd``, the SD of the task success rates, wins);
    ``effect_sd``: the SD of the task effects for the paired design (default: the same ICC as success).

    Raises:
        ValueError: a value out of range (the message names it and the valid range).
    """
    _check(alpha, power)
    p1, p2 = _rates(baseline, effect)
    if tasks is not None and tasks < 1:
        raise ValueError(f"tasks must be >= 1, got {tasks}")
    if not discordances:
        candidates = (0.2, round(independent_discordance(baseline, effect), 4))
        discordances = tuple(sorted({d for d in candidates if abs(effect) < d <= min(p1 + p2, 2 - p1 - p2)}))
    for d in discordances:
        check_discordance(baseline, effect, d)
    pbar = (p1 + p2) / 2
    if task_sd is not None:
        icc = icc_from_task_sd(task_sd, pbar * (1 - pbar))
    deff = design_effect(per_task, icc)
    unpaired = unpaired_episodes(baseline, effect, alpha, power)
    paired, paired_deff, paired_tasks, iccs = [], [], [], []
    for d in discordances:
        icc_d = icc if effect_sd is None else icc_from_task_sd(effect_sd, d - effect**2)
        iccs.append(icc_d)
        paired.append(mcnemar_pairs(effect, d, alpha, power))
        paired_deff.append(design_effect(per_task, icc_d))
        paired_tasks.append(task_level_tasks(effect, d - effect**2, icc_d, per_task, alpha, power))
    power_unpaired = power_paired = power_tasks = None
    if tasks is not None:
        n = tasks * per_task
        power_unpaired = unpaired_power(baseline, effect, n / deff, alpha)
        power_paired = tuple(
            mcnemar_power(effect, d, n / f, alpha) for d, f in zip(discordances, paired_deff, strict=True)
        )
        power_tasks = tuple(
            task_level_power(effect, d - effect**2, i, tasks, per_task, alpha)
            for d, i in zip(discordances, iccs, strict=True)
        )
    return Plan(
        baseline=baseline, effect=effect, alpha=alpha, power=power, per_task=per_task, icc=icc,
        icc_paired=iccs[0] if iccs else icc, discordances=tuple(discordances), unpaired=unpaired,
        unpaired_design_effect=deff, paired=tuple(paired), paired_design_effect=tuple(paired_deff),
        paired_tasks=tuple(paired_tasks), tasks=tasks, power_unpaired=power_unpaired, power_paired=power_paired,
        power_paired_tasks=power_tasks,
    )  # fmt: skip
