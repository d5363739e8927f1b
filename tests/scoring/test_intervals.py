"""lq_ros.scoring.intervals: the small-n mean interval holds its coverage; the task-cluster interval widens with
clustering and is nothing for one task."""

import math

import numpy as np
import pytest

from lq_ros.scoring.intervals import bootstrap_ci, cluster_bootstrap_ci, design_effect, t_interval, wilson_interval


def coverage(interval, draw, true_mean: float, n: int, reps: int, seed: int) -> float:
    rng = np.random.default_rng(seed)
    hits = 0
    for _ in range(reps):
        lo, hi = interval(draw(rng, n))
        hits += lo <= true_mean <= hi
    return hits / reps


NORMAL = (lambda rng, n: rng.normal(10.0, 2.0, n), 10.0)
LOGNORMAL = (lambda rng, n: rng.lognormal(0.0, 0.5, n), math.exp(0.125))


@pytest.mark.parametrize("n", [5, 7, 9])
def test_t_interval_covers_95_percent_at_small_n(n):
    """Simulated, 4000 samples each: normal data 94-96% (measured 94.5-95.1%), lognormal (sigma 0.5) above 90%
    (measured 91.8-93.1%), where the percentile bootstrap the report used before covers well under 92%."""
    draw, mean = NORMAL
    assert 0.93 <= coverage(t_interval, draw, mean, n, 4000, n) <= 0.97
    draw, mean = LOGNORMAL
    assert coverage(t_interval, draw, mean, n, 4000, 100 + n) >= 0.90
    # The replaced interval, for contrast (this is why it was replaced): it undercovers the same normal data.
    boot = coverage(lambda x: bootstrap_ci(x, n_resamples=400, seed=1), *NORMAL, n, 1000, 200 + n)
    assert boot < 0.92


def test_t_interval_values():
    lo, hi = t_interval([1.0, 2.0, 3.0])
    assert lo == pytest.approx(2.0 - 4.302652729911275 / math.sqrt(3))
    assert hi == pytest.approx(2.0 + 4.302652729911275 / math.sqrt(3))
    assert t_interval([4.0, 4.0]) == (4.0, 4.0)
    with pytest.raises(ValueError, match="at least 2"):
        t_interval([1.0])


def test_cluster_bootstrap_widens_with_clustering_and_needs_two_clusters():
    independent = [np.array([1, 0] * 5, float) for _ in range(10)]  # every task 5/10
    clustered = [np.ones(10) if t % 2 else np.zeros(10) for t in range(10)]  # tasks 0/10 or 10/10
    lo_i, hi_i = cluster_bootstrap_ci(independent, seed=0)
    lo_c, hi_c = cluster_bootstrap_ci(clustered, seed=0)
    assert (lo_i, hi_i) == (0.5, 0.5)  # no task differs: resampling tasks moves nothing
    assert hi_c - lo_c > 0.4
    assert lo_c < 0.5 < hi_c
    assert all(math.isnan(v) for v in cluster_bootstrap_ci([np.ones(10)]))
    assert all(math.isnan(v) for v in cluster_bootstrap_ci([np.ones(10), np.array([])]))


def test_design_effect():
    clustered = [np.ones(10) if t % 2 else np.zeros(10) for t in range(10)]
    independent = [np.array([1, 0] * 5, float) for _ in range(10)]
    # All variance between tasks of 10: the pooled mean's variance is about 10x the independent one.
    assert design_effect(clustered) == pytest.approx(10.0 * 99 / 90 * 10 / 9 / 1.0, rel=0.2)
    assert design_effect(independent) == pytest.approx(0.0)
    assert math.isnan(design_effect([np.ones(5)]))


def test_wilson_interval_textbook():
    low, high = wilson_interval(8, 10)
    assert low == pytest.approx(0.4902, abs=1e-4)
    assert high == pytest.approx(0.9433, abs=1e-4)
    low0, high0 = wilson_interval(0, 10)
    assert low0 == 0.0 and 0.0 < high0 < 0.35
    with pytest.raises(ValueError):
        wilson_interval(11, 10)


def test_bootstrap_ci_deterministic_and_contains_mean():
    values = np.random.default_rng(3).normal(5.0, 2.0, 40)
    a = bootstrap_ci(values, seed=7)
    b = bootstrap_ci(values, seed=7)
    assert a == b
    assert bootstrap_ci(values, seed=8) != a
    low, high = a
    assert low < float(np.mean(values)) < high
    assert high - low < 2.0  # ~ 2 * 1.96 * 2 / sqrt(40) = 1.24
    assert bootstrap_ci([1.5]) == (1.5, 1.5)
    assert math.isclose(bootstrap_ci(np.full(10, 2.0))[0], 2.0)
