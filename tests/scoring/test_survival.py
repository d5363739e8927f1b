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
    assert lo[0] == hi[0] == 1.0  # before any success: S = 1 exactly
    assert np.isnan(lo[-1]) and np.isnan(hi[-1])  # S = 0: the log-log band is undefined (as R's survfit)
    inside = np.isfinite(lo)
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
