"""Simulated coverage of the report's 95% intervals at the sizes the report uses them (lq_ros/scoring/intervals.py).

Usage: python benchmarks/interval_coverage.py [--reps 2000] [--seed 0]

Prints one markdown table per interval family, each cell the fraction of simulated samples whose interval holds the
true value:
- the mean of n = 5..9 values (normal, and lognormal with sigma 0.5): the Student t interval, the t interval with a
  bootstrap standard error, and the plain percentile bootstrap it replaced;
- a success rate pooled over k tasks of m episodes, each task's success probability drawn from a Beta distribution
  (Beta(0.6, 0.4): most tasks nearly always fail or nearly always succeed, as in the demo sweep; Beta(3, 2): milder;
  Beta(8, 2): an easy suite), true value the Beta mean: the interval the report gives (the hull of the task-cluster
  bootstrap, expanded percentile, and Wilson), the cluster bootstrap alone, the plain percentile cluster bootstrap,
  and the Wilson interval that counts episodes as independent;
- the paired difference of two arms' success on the same k x m scenes: the interval the report gives (the hull of
  the cluster bootstrap of per-pair differences and Newcombe's paired score interval) and each part alone.
tests/scoring/test_intervals.py checks the same coverages with fewer samples. Deterministic for a given seed.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import lq_ros  # noqa: F401 - first: it pins OpenBLAS's kernels before numpy loads them (lq_ros/__init__.py)

# isort: split

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from lq_ros.scoring.intervals import (  # noqa: E402
    bootstrap_ci,
    bootstrap_t_interval,
    cluster_bootstrap_ci,
    clustered_success_ci,
    newcombe_paired_ci,
    paired_success_ci,
    t_interval,
    wilson_interval,
)

N_BOOT = 1000
MEAN_SIZES = (5, 6, 7, 8, 9)
DISTRIBUTIONS = {
    "normal(10, 2)": (lambda rng, n: rng.normal(10.0, 2.0, n), 10.0),
    "lognormal(0, 0.5)": (lambda rng, n: rng.lognormal(0.0, 0.5, n), math.exp(0.125)),
}
#: (tasks, episodes per task) of the suites: the demo's 5 x 2 and 10 x 1, the attribution sweep's 10 x 1, 10 x 10.
CLUSTER_SHAPES = ((5, 2), (5, 10), (10, 1), (10, 10))
BETAS = ((0.6, 0.4), (3.0, 2.0), (8.0, 2.0))


def _boot_t(x: np.ndarray, seed: int) -> tuple[float, float]:
    rng = np.random.default_rng(seed)
    means = x[rng.integers(0, x.size, size=(N_BOOT, x.size))].mean(axis=1)
    return bootstrap_t_interval(float(x.mean()), means, x.size)


def mean_coverage(reps: int, seed: int) -> pd.DataFrame:
    rows = []
    for name, (draw, truth) in DISTRIBUTIONS.items():
        for n in MEAN_SIZES:
            rng = np.random.default_rng([seed, n, len(name)])
            hits = {"t": 0, "bootstrap SE t": 0, "percentile bootstrap": 0}
            for rep in range(reps):
                x = draw(rng, n)
                for label, (lo, hi) in (("t", t_interval(x)), ("bootstrap SE t", _boot_t(x, rep)),
                                        ("percentile bootstrap", bootstrap_ci(x, 0.95, N_BOOT, rep))):  # fmt: skip
                    hits[label] += lo <= truth <= hi
            rows.append({"data": name, "n": n} | {k: f"{100 * v / reps:.1f}%" for k, v in hits.items()})
    return pd.DataFrame(rows)


def cluster_coverage(reps: int, seed: int) -> pd.DataFrame:
    rows = []
    for k, m in CLUSTER_SHAPES:
        for a, b in BETAS:
            rng = np.random.default_rng([seed, k, m, int(10 * a)])
            truth = a / (a + b)
            hits = dict.fromkeys(("reported", "cluster bootstrap", "plain percentile", "Wilson"), 0)
            for rep in range(reps):
                tasks = [rng.random(m) < p for p in rng.beta(a, b, k)]
                successes = int(sum(t.sum() for t in tasks))
                for label, (lo, hi) in (
                    ("reported", clustered_success_ci(tasks, n_boot=N_BOOT, seed=rep)),
                    ("cluster bootstrap", cluster_bootstrap_ci(tasks, n_boot=N_BOOT, seed=rep)),
                    ("plain percentile", cluster_bootstrap_ci(tasks, N_BOOT, rep, expanded=False)),
                    ("Wilson", wilson_interval(successes, k * m)),
                ):
                    hits[label] += lo <= truth <= hi
            rows.append({"tasks x episodes": f"{k} x {m}", "task success ~": f"Beta({a:g}, {b:g})"}
                        | {key: f"{100 * v / reps:.1f}%" for key, v in hits.items()})  # fmt: skip
    return pd.DataFrame(rows)


#: Arm B succeeds where A does with probability SHARE of A's (comonotone: the pairs share their scene), so the true
#: paired difference is (1 - SHARE) x the Beta mean.
SHARE = 0.6


def paired_coverage(reps: int, seed: int) -> pd.DataFrame:
    rows = []
    for k, m in CLUSTER_SHAPES:
        for a, b in BETAS:
            rng = np.random.default_rng([seed, k, m, int(10 * a), 1])
            truth = (1 - SHARE) * a / (a + b)
            hits = dict.fromkeys(("reported", "cluster bootstrap", "Newcombe"), 0)
            tasks = np.repeat(np.arange(k), m)
            for rep in range(reps):
                q = rng.beta(a, b, k)[:, None]
                u = rng.random((k, m))
                arm_a, arm_b = (u < q).ravel(), (u < SHARE * q).ravel()
                diff = arm_a.astype(float) - arm_b.astype(float)
                counts = [int(x.sum()) for x in (arm_a & arm_b, arm_a & ~arm_b, ~arm_a & arm_b, ~arm_a & ~arm_b)]
                for label, (lo, hi) in (
                    ("reported", paired_success_ci(arm_a, arm_b, tasks, n_boot=N_BOOT, seed=rep)),
                    ("cluster bootstrap", cluster_bootstrap_ci([diff[tasks == t] for t in range(k)], N_BOOT, rep)),
                    ("Newcombe", newcombe_paired_ci(*counts)),
                ):
                    hits[label] += lo <= truth <= hi
            rows.append({"tasks x pairs": f"{k} x {m}", "task success of A ~": f"Beta({a:g}, {b:g})"}
                        | {key: f"{100 * v / reps:.1f}%" for key, v in hits.items()})  # fmt: skip
    return pd.DataFrame(rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reps", type=int, default=2000, help="simulated samples per cell (default 2000)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if args.reps < 100:
        parser.error(f"--reps must be at least 100 samples, got {args.reps}")
    print(f"Coverage of nominal 95% intervals, {args.reps} simulated samples per cell (seed {args.seed}).\n")
    print("Mean of n values:\n")
    print(mean_coverage(args.reps, args.seed).to_markdown(index=False))
    print("\nSuccess rate pooled over tasks (reported: the hull of the cluster bootstrap and Wilson):\n")
    print(cluster_coverage(args.reps, args.seed).to_markdown(index=False))
    print(
        f"\nPaired success difference, B succeeding with {SHARE:g} x A's probability on the same scenes (reported: the"
    )
    print("hull of the cluster bootstrap and Newcombe's paired score interval):\n")
    print(paired_coverage(args.reps, args.seed).to_markdown(index=False))


if __name__ == "__main__":
    main()
