"""Greenwood's variance and the log-log band of a Kaplan-Meier curve, against a hand-computed example."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lq_ros.scoring import aggregate as agg
from lq_ros.scoring import survival

#: Six episodes: successes at 1, 2, 3 and 5; censored (timed out) at 2 and 4.
TIMES = [1, 2, 2, 3, 4, 5]
EVENTS = [True, True, False, True, False, True]


def test_greenwood_by_hand():
    # t=1: n=6, d=1: S = 5/6,           V = 1/(6*5)          = 1/30
    # t=2: n=5, d=1 (the censored 2 is still at risk): S = 5/6*4/5 = 2/3, V = 1/30 + 1/(5*4) = 1/12
    # t=3: n=3, d=1: S = 2/3*2/3 = 4/9, V = 1/12 + 1/(3*2)     = 1/4
    # t=5: n=1, d=1: S = 0,             V = inf (every episode at risk succeeded)
    t, s, v = survival.greenwood(TIMES, EVENTS)
    assert t.tolist() == [0, 1, 2, 3, 5]
    assert s == pytest.approx([1, 5 / 6, 2 / 3, 4 / 9, 0])
    assert v[:4] == pytest.approx([0, 1 / 30, 1 / 12, 1 / 4]) and math.isinf(v[4])
    _, var = survival.greenwood_variance(TIMES, EVENTS)
    # Var S(3) = (4/9)^2 * 1/4 = 4/81: a standard error of 2/9.
    assert var == pytest.approx([0, (5 / 6) ** 2 / 30, (2 / 3) ** 2 / 12, 4 / 81, 0])


def test_the_steps_are_kaplan_meiers():
    t, s, _ = survival.greenwood(TIMES, EVENTS)
    km_t, km_s = agg.kaplan_meier(TIMES, EVENTS)
    assert np.array_equal(t, km_t) and np.allclose(s, km_s)


def test_log_log_band_by_hand():
    t, s, lo, hi = survival.kaplan_meier_band(TIMES, EVENTS, 0.95)
    # At t=2: S = 2/3, V = 1/12; sigma of log(-log S) = sqrt(1/12) / |log(2/3)| = 0.711960;
    # spread = exp(1.959964 * 0.711960) = 4.03666; band = [S^spread, S^(1/spread)] = [0.19462, 0.90443].
    assert lo[2] == pytest.approx(0.19462, abs=5e-5) and hi[2] == pytest.approx(0.90443, abs=5e-5)
    # Before the first success S = 1 and Greenwood gives [1, 1]; the band is the exact bound over the 6 at risk.
    assert hi[0] == 1.0 and lo[0] == pytest.approx(0.025 ** (1 / 6))
    assert np.isnan(lo[-1]) and np.isnan(hi[-1])  # S = 0: the log-log band is undefined (as R's survfit)
    inside = np.isfinite(lo) & (s < 1)
    assert np.all((lo[inside] <= s[inside]) & (s[inside] <= hi[inside]))
    assert np.all((lo[inside] >= 0) & (hi[inside] <= 1))
    # A wider confidence gives a wider band.
    _, _, lo80, hi80 = survival.kaplan_meier_band(TIMES, EVENTS, 0.80)
    assert lo80[2] > lo[2] and hi80[2] < hi[2]


def test_bad_input_names_the_problem():
    with pytest.raises(ValueError, match="one event flag per time"):
        survival.greenwood([1, 2], [True])
    with pytest.raises(ValueError, match="finite and >= 0"):
        survival.greenwood([-1.0], [True])
    with pytest.raises(ValueError, match="confidence must be in"):
        survival.kaplan_meier_band(TIMES, EVENTS, 1.5)


def test_an_all_fail_cell_has_the_exact_band_not_a_point():
    """0 of 10 succeeded: Greenwood's band is [1, 1] (the figure drew no band); the exact one-sided bound says at most
    30.8% succeed, never narrower than the cell's Wilson interval of 0/10 (27.8%)."""
    from lq_ros.scoring.intervals import wilson_interval

    t, s, lo, hi = survival.kaplan_meier_band(np.full(10, 11.0), np.zeros(10, bool))
    assert t.tolist() == [0.0] and s.tolist() == [1.0] and hi[0] == 1.0
    assert 1 - lo[0] == pytest.approx(0.3085, abs=1e-4)
    assert 1 - lo[0] >= wilson_interval(0, 10)[1]
    # Censoring before the first success leaves fewer at risk at its end: a wider band there.
    _, _, lo_early, _ = survival.kaplan_meier_band([3.0, 3.0, 8.0, 9.0, 11.0, 11.0], [False] * 4 + [False, True])
    assert lo_early[0] == pytest.approx(0.025 ** (1 / 2))


def test_restricted_mean_of_an_all_fail_cell_is_bounded_by_the_success_bound():
    """0 of 10 at an 11 s horizon: printed 11.00 [11.00, 11.00] before; the time is at most 11 s, and at least
    11 s x the exact lower bound of S (7.61 s)."""
    estimate, low, high, note = survival.restricted_mean_interval(np.full(10, 11.0), np.zeros(10, bool), 11.0)
    assert (estimate, high, note) == (11.0, 11.0, "")
    assert low == pytest.approx(11.0 * 0.025 ** (1 / 10)) and low < high
    # Failures that end early never reached the horizon: fewer episodes bound S there.
    times = np.array([11.0] * 5 + [4.0] * 5)
    _, low5, _, _ = survival.restricted_mean_interval(times, np.zeros(10, bool), 11.0)
    assert low5 == pytest.approx(11.0 * 0.025 ** (1 / 5))


def test_restricted_mean_interval_is_the_t_interval_when_failures_end_at_the_horizon():
    from lq_ros.scoring.intervals import t_interval

    rng = np.random.default_rng(2)
    times = np.where(rng.random(12) < 0.6, rng.uniform(2, 10, 12), 11.0)
    estimate, low, high, _ = survival.restricted_mean_interval(times, times < 11.0, 11.0)
    assert estimate == pytest.approx(times.mean())
    assert (low, high) == pytest.approx(t_interval(times))


def test_restricted_mean_standard_error_matches_the_bootstrap_with_early_censoring():
    """Failures that end before the horizon (the action budget's): the analytic Kaplan-Meier variance against the
    standard deviation of 20,000 bootstrap estimates (agree within 10%); the estimate against metrics'."""
    from scipy import stats

    from lq_ros.scoring.metrics import restricted_mean_time

    rng = np.random.default_rng(5)
    n, horizon = 40, 11.0
    success = rng.random(n) < 0.6
    times = np.where(success, rng.uniform(2, 10, n), rng.uniform(3, 11, n))
    estimate, low, high, _ = survival.restricted_mean_interval(times, success, horizon)
    assert estimate == pytest.approx(restricted_mean_time(times, success, horizon))
    se = (high - low) / 2 / stats.t.ppf(0.975, n - 1) / math.sqrt(n / (n - 1))
    picks = rng.integers(0, n, size=(20_000, n))
    boot = np.array([restricted_mean_time(times[i], success[i], horizon) for i in picks])
    assert se == pytest.approx(boot.std(ddof=1), rel=0.1)


def test_restricted_mean_without_an_interval_says_why():
    _, low, high, note = survival.restricted_mean_interval([2.0, 3.0, 11.0], [True, True, False], 11.0)
    assert math.isnan(low) and math.isnan(high) and note == "fewer than 5 episodes"
    _, low, _, note = survival.restricted_mean_interval(np.full(6, 4.0), np.ones(6, bool), 11.0)
    assert math.isnan(low) and note == "every episode took the same time"
    with pytest.raises(ValueError, match="horizon must be positive"):
        survival.restricted_mean_interval([1.0], [True], 0.0)
