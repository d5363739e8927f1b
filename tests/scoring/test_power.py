"""lq_ros.scoring.power: the textbook sample sizes, checked against published values and by simulation."""

from __future__ import annotations

import numpy as np
import pytest

from lq_ros.scoring import power as pw


def test_the_reference_sample_sizes():
    """50% vs 60%, alpha 0.05 two-sided, 80% power: 388 episodes per arm unpaired (the pooled-variance z test,
    Fleiss' formula without continuity correction), 155 pairs for McNemar at discordance 0.2 (Connor 1987)."""
    assert pw.unpaired_episodes(0.5, 0.10) == 388
    assert pw.mcnemar_pairs(0.10, 0.2) == 155
    assert pw.unpaired_power(0.5, 0.10, 388) == pytest.approx(0.80, abs=0.005)
    assert pw.mcnemar_power(0.10, 0.2, 155) == pytest.approx(0.80, abs=0.005)
    # A negative effect needs the same episodes as its mirror; independent arms give little gain from pairing.
    assert pw.unpaired_episodes(0.6, -0.10) == 388
    assert pw.mcnemar_pairs(0.10, pw.independent_discordance(0.5, 0.10)) > 380


def test_mcnemar_power_by_simulation():
    """4,000 simulated studies of 155 pairs at discordance 0.2 and a difference of 0.10 (15% of pairs only A
    succeeds, 5% only B): the McNemar z test rejects in about 80% of them, as planned."""
    rng = np.random.default_rng(3)
    counts = rng.multinomial(155, [0.15, 0.05, 0.80], size=4000)
    b, c = counts[:, 0], counts[:, 1]
    z = (b - c) / np.sqrt(np.maximum(b + c, 1))
    assert np.mean(np.abs(z) > 1.959964) == pytest.approx(0.80, abs=0.03)


def test_task_level_power_is_the_t_tests():
    """The one-sample t test at effect size d = 0.5 needs 34 units for 80% power (Cohen 1988, Table 2.4.1)."""
    assert pw.task_level_power(0.5, 1.0, 0.0, 34, 1) == pytest.approx(0.80, abs=0.01)
    assert pw.task_level_power(0.5, 1.0, 0.0, 33, 1) < 0.80 <= pw.task_level_power(0.5, 1.0, 0.0, 34, 1)
    assert pw.task_level_tasks(0.5, 1.0, 0.0, 1) == 34
    # Ten episodes of a task that agree fully (ICC 1) say no more than one.
    assert pw.task_level_power(0.5, 1.0, 1.0, 34, 10) == pytest.approx(pw.task_level_power(0.5, 1.0, 1.0, 34, 1))
    assert pw.task_level_tasks(0.1, 0.19, 0.0, 1) >= pw.MIN_TASKS


def test_clustering_inflates_the_episodes():
    assert pw.design_effect(10, 0.1) == pytest.approx(1.9)
    assert pw.design_effect(1, 0.9) == 1.0
    # A task SD of 0.2 around 55% success: ICC 0.04 / 0.2475.
    assert pw.icc_from_task_sd(0.2, 0.55 * 0.45) == pytest.approx(0.04 / 0.2475)
    planned = pw.plan(0.5, 0.10, per_task=10, task_sd=0.2, tasks=10)
    assert planned.unpaired_design_effect == pytest.approx(1 + 9 * 0.04 / 0.2475)
    assert planned.discordances == (0.2, 0.5)
    assert planned.paired == (155, 391)
    # 10 tasks x 10 inits is far from enough at this clustering: power well under the planned 80%.
    assert planned.power_unpaired < 0.3 and planned.power_paired[0] < 0.5 and planned.power_paired_tasks[0] < 0.5
    assert pw.plan(0.5, 0.10, per_task=10, icc=0.0, tasks=40).power_unpaired == pytest.approx(
        pw.unpaired_power(0.5, 0.10, 400)
    )


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"baseline": 1.2, "effect": 0.1}, "baseline success must be in"),
        ({"baseline": 0.95, "effect": 0.1}, "baseline \\+ effect in"),
        ({"baseline": 0.5, "effect": 0.1, "discordances": (0.05,)}, "discordance must be above"),
        ({"baseline": 0.5, "effect": 0.1, "alpha": 1.5}, "alpha must be in"),
        ({"baseline": 0.5, "effect": 0.1, "task_sd": 0.6}, "exceeds the SD of one episode"),
        ({"baseline": 0.5, "effect": 0.1, "icc": 2.0}, "ICC must be in"),
    ],
)
def test_bad_values_name_the_valid_range(kwargs, message):
    with pytest.raises(ValueError, match=message):
        pw.plan(**kwargs)
