"""Simulated coverage of the report's 95% intervals at the sizes the report uses them (lq_ros/scoring/intervals.py).

Usage: python benchmarks/interval_coverage.py [--reps 2000] [--seed 0]

Prints one markdown table per interval family, each cell the fraction of simulated samples whose interval holds the
true value, then the range over the task-clustered cells (intervals.CLUSTER_COVERAGE holds it for the report):
- the mean of n = 5..9 values (normal, and lognormal with sigma 0.5): the Student t interval the report gives and
  the plain percentile bootstrap it replaced;
- a success rate pooled over k = 5 or 10 tasks of m = 1-10 episodes, each task's success probability drawn from a
  Beta distribution (Beta(0.6, 0.4): most tasks nearly always fail or nearly always succeed, as in the demo sweep;
  Beta(3, 2): milder; Beta(8, 2): an easy suite; Beta(1, 9): a hard one), true value the Beta mean: the interval the
  report gives (the hull of the cluster-robust t interval over tasks and Wilson), the cluster t alone, the interval
  it replaced (the hull of a 2,000-draw expanded percentile task bootstrap and Wilson), and Wilson alone;
- the paired difference of two arms' success on the same k x m scenes (PAIRED_SCENARIOS: a large effect, a small
  one-directional effect of 10 points where many samples have no discordant pair, and no mean effect with task
  effects of +-0.2 or +-0.3): the interval the report gives (the hull of the cluster t over tasks and Tango's score
  interval), each part alone, the interval it replaced (the hull of the task bootstrap and Newcombe's interval), the
  share of samples without a discordant pair and the reported interval's coverage among them.
tests/benchmarks/test_interval_coverage.py runs a reduced simulation of the same cells. Deterministic for a seed.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import lq_ros  # noqa: F401 - first: it pins OpenBLAS's kernels before numpy loads them (lq_ros/__init__.py)

# isort: split

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from lq_ros.scoring.intervals import (  # noqa: E402
    bootstrap_ci,
    cluster_bootstrap_ci,
    cluster_t_ci,
    clustered_success_ci,
    newcombe_paired_ci,
    paired_success_ci,
    t_interval,
    tango_paired_ci,
    wilson_interval,
)

#: Draws of the replaced bootstrap intervals (their shipped default).
N_BOOT = 2000
MEAN_SIZES = (5, 6, 7, 8, 9)
DISTRIBUTIONS = {
    "normal(10, 2)": (lambda rng, n: rng.normal(10.0, 2.0, n), 10.0),
    "lognormal(0, 0.5)": (lambda rng, n: rng.lognormal(0.0, 0.5, n), math.exp(0.125)),
}
#: (tasks, episodes per task) of the success-rate cells.
SUCCESS_SHAPES = ((5, 2), (5, 10), (10, 1), (10, 2), (10, 10))
BETAS = ((0.6, 0.4), (3.0, 2.0), (8.0, 2.0), (1.0, 9.0))
#: (tasks, pairs per task) of the paired cells: 5 or 10 tasks x 2 or 10 init states.
PAIRED_SHAPES = ((5, 2), (5, 10), (10, 2), (10, 10))


def _share(rng: np.random.Generator, k: int) -> tuple[np.ndarray, np.ndarray]:
    q = rng.beta(0.6, 0.4, k)
    return q, 0.6 * q


def _plus_ten(a: float, b: float) -> Callable[[np.random.Generator, int], tuple[np.ndarray, np.ndarray]]:
    def draw(rng: np.random.Generator, k: int) -> tuple[np.ndarray, np.ndarray]:
        base = 0.9 * rng.beta(a, b, k)
        return base + 0.1, base

    return draw


def _task_effects(spread: float) -> Callable[[np.random.Generator, int], tuple[np.ndarray, np.ndarray]]:
    def draw(rng: np.random.Generator, k: int) -> tuple[np.ndarray, np.ndarray]:
        base = rng.uniform(0.3, 0.7, k)
        return base + rng.choice([-spread, spread], k), base

    return draw


#: name -> (each task's success probability of arm A and of arm B, the true mean difference). Within a task the two
#: arms share their scene (one uniform draw per pair), so a pair is discordant only one way where qA > qB.
PAIRED_SCENARIOS = {
    "B = 0.6 x A, A ~ Beta(0.6, 0.4)": (_share, 0.4 * 0.6),
    "+10 points one way, B ~ 0.9 Beta(3, 2)": (_plus_ten(3.0, 2.0), 0.1),
    "+10 points one way, B ~ 0.9 Beta(8, 2)": (_plus_ten(8.0, 2.0), 0.1),
    "+10 points one way, B ~ 0.9 Beta(0.6, 0.4)": (_plus_ten(0.6, 0.4), 0.1),
    "no mean effect, task effects +-0.2": (_task_effects(0.2), 0.0),
    "no mean effect, task effects +-0.3": (_task_effects(0.3), 0.0),
}


def _hull(*intervals: tuple[float, float]) -> tuple[float, float]:
    return min(i[0] for i in intervals), max(i[1] for i in intervals)


def mean_coverage(reps: int, seed: int) -> pd.DataFrame:
    rows = []
    for name, (draw, truth) in DISTRIBUTIONS.items():
        for n in MEAN_SIZES:
            rng = np.random.default_rng([seed, n, len(name)])
            hits = {"t (reported)": 0, "percentile bootstrap": 0}
            for rep in range(reps):
                x = draw(rng, n)
                for label, (lo, hi) in (("t (reported)", t_interval(x)),
                                        ("percentile bootstrap", bootstrap_ci(x, 0.95, N_BOOT, rep))):  # fmt: skip
                    hits[label] += lo <= truth <= hi
            rows.append({"data": name, "n": n} | {k: f"{100 * v / reps:.1f}%" for k, v in hits.items()})
    return pd.DataFrame(rows)


def success_cell(k: int, m: int, a: float, b: float, reps: int, seed: int = 0) -> dict[str, float]:
    """Coverage of each success-rate interval for k tasks of m episodes, task success ~ Beta(a, b)."""
    rng = np.random.default_rng([seed, k, m, int(10 * a), int(10 * b)])
    truth = a / (a + b)
    hits = dict.fromkeys(("reported", "cluster t", "replaced", "Wilson"), 0)
    for rep in range(reps):
        tasks = [rng.random(m) < p for p in rng.beta(a, b, k)]
        wilson = wilson_interval(int(sum(t.sum() for t in tasks)), k * m)
        for label, (lo, hi) in (
            ("reported", clustered_success_ci(tasks)),
            ("cluster t", cluster_t_ci(tasks)),
            ("replaced", _hull(cluster_bootstrap_ci(tasks, n_boot=N_BOOT, seed=rep), wilson)),
            ("Wilson", wilson),
        ):
            hits[label] += lo <= truth <= hi
    return {key: v / reps for key, v in hits.items()}


def paired_cell(k: int, m: int, scenario: str, reps: int, seed: int = 0) -> dict[str, float]:
    """Coverage of each paired-difference interval for k tasks of m pairs under PAIRED_SCENARIOS[scenario], with
    ``no discordant pair`` (the share of samples without one) and ``reported, none discordant`` (the reported
    interval's coverage among those; NaN without such a sample)."""
    draw, truth = PAIRED_SCENARIOS[scenario]
    rng = np.random.default_rng([seed, k, m, sum(map(ord, scenario))])
    task = np.repeat(np.arange(k), m)
    labels = ("reported", "cluster t", "Tango", "replaced")
    hits = dict.fromkeys(labels, 0)
    none_discordant = none_hits = 0
    for rep in range(reps):
        qa, qb = draw(rng, k)
        u = rng.random((k, m))
        a, b = (u < qa[:, None]).ravel(), (u < qb[:, None]).ravel()
        diff = a.astype(float) - b.astype(float)
        clusters = [diff[task == t] for t in range(k)]
        counts = [int(x.sum()) for x in (a & b, a & ~b, ~a & b, ~a & ~b)]
        intervals = (
            paired_success_ci(a, b, task),
            cluster_t_ci(clusters),
            tango_paired_ci(*counts),
            _hull(cluster_bootstrap_ci(clusters, n_boot=N_BOOT, seed=rep), newcombe_paired_ci(*counts)),
        )
        # 1e-12: the truth 0.1 is not exactly representable; a bound at it holds it.
        covered = [lo - 1e-12 <= truth <= hi + 1e-12 for lo, hi in intervals]
        for label, hit in zip(labels, covered, strict=True):
            hits[label] += hit
        if counts[1] + counts[2] == 0:
            none_discordant += 1
            none_hits += covered[0]
    out = {key: v / reps for key, v in hits.items()}
    out["no discordant pair"] = none_discordant / reps
    out["reported, none discordant"] = none_hits / none_discordant if none_discordant else math.nan
    return out


def _percent(value: float) -> str:
    return "-" if math.isnan(value) else f"{100 * value:.1f}%"


def success_coverage(reps: int, seed: int) -> pd.DataFrame:
    rows = []
    for k, m in SUCCESS_SHAPES:
        for a, b in BETAS:
            cell = success_cell(k, m, a, b, reps, seed)
            rows.append({"tasks x episodes": f"{k} x {m}", "task success ~": f"Beta({a:g}, {b:g})"}
                        | {key: _percent(v) for key, v in cell.items()})  # fmt: skip
    return pd.DataFrame(rows)


def paired_coverage(reps: int, seed: int) -> pd.DataFrame:
    rows = []
    for scenario in PAIRED_SCENARIOS:
        for k, m in PAIRED_SHAPES:
            cell = paired_cell(k, m, scenario, reps, seed)
            rows.append({"scenario": scenario, "tasks x pairs": f"{k} x {m}"}
                        | {key: _percent(v) for key, v in cell.items()})  # fmt: skip
    return pd.DataFrame(rows)


def _range(column: pd.Series) -> str:
    values = column.str.rstrip("%").astype(float)
    return f"{values.min():.1f}-{values.max():.1f}%"


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
    print("\nSuccess rate pooled over tasks (reported: the hull of the cluster t over tasks and Wilson):\n")
    success = success_coverage(args.reps, args.seed)
    print(success.to_markdown(index=False))
    print("\nPaired success difference on the same scenes (reported: the hull of the cluster t and Tango):\n")
    paired = paired_coverage(args.reps, args.seed)
    print(paired.to_markdown(index=False))
    print(f"\nReported task-clustered intervals at 5-10 tasks: the success rate covers {_range(success['reported'])},")
    print(f"the paired difference {_range(paired['reported'])} (nominal 95%).")


if __name__ == "__main__":
    main()
