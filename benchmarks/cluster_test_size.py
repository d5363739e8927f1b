"""How often a paired test rejects a true zero mean effect when episodes cluster in tasks: the pooled exact McNemar
test (pairs as independent draws) against the within-task sign-flip test (the task as the unit, ``cluster_p``).

    python benchmarks/cluster_test_size.py [--samples 2000] [--tasks 10] [--pairs 12] [--seed 0]

Model: each task t has a success rate p_t ~ Uniform(0.2, 0.8) and a true difference d_t ~ Normal(0, SD): no
effect on average over the suite's tasks, though the tasks drawn have one. Arm A succeeds with p_t + d_t / 2, arm B
with p_t - d_t / 2 (clipped to [0.02, 0.98]), independently per pair. A test at nominal 5% that speaks for other
tasks of the suite should reject in about 5% of samples. Prints the rejection rate of each test per SD with its
Wilson 95% interval.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import lq_ros  # noqa: F401 - first: it pins OpenBLAS's kernels before numpy loads them (lq_ros/__init__.py)

# isort: split

import numpy as np  # noqa: E402

from lq_ros.scoring.decisions import sign_flip_p  # noqa: E402
from lq_ros.scoring.intervals import wilson_interval  # noqa: E402
from lq_ros.scoring.paired_tests import mcnemar_exact_p  # noqa: E402

ALPHA = 0.05


def rejection_rates(sd: float, samples: int, tasks: int, pairs: int, seed: int) -> tuple[int, int]:
    """(McNemar rejections, sign-flip rejections) over ``samples`` simulated comparisons."""
    rng = np.random.default_rng(seed)
    mcnemar = flips = 0
    for _ in range(samples):
        base = rng.uniform(0.2, 0.8, tasks)
        diff = rng.normal(0.0, sd, tasks)  # mean 0 over the suite's tasks, not over the 10 drawn
        pa = np.clip(base + diff / 2, 0.02, 0.98)
        pb = np.clip(base - diff / 2, 0.02, 0.98)
        a = rng.random((tasks, pairs)) < pa[:, None]
        b = rng.random((tasks, pairs)) < pb[:, None]
        a_only, b_only = int((a & ~b).sum()), int((~a & b).sum())
        mcnemar += mcnemar_exact_p(a_only, b_only) < ALPHA
        flips += sign_flip_p((a.astype(float) - b.astype(float)).mean(axis=1)) < ALPHA
    return mcnemar, flips


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=2000)
    parser.add_argument("--tasks", type=int, default=10)
    parser.add_argument("--pairs", type=int, default=12, help="pairs per task")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--sds", type=float, nargs="+", default=[0.0, 0.2, 0.4])
    ns = parser.parse_args(argv)
    print(f"{ns.tasks} tasks x {ns.pairs} pairs, no mean effect, {ns.samples} samples; rejections at nominal 5%")
    print("| task-to-task SD of the true difference | pooled McNemar | task-level sign-flip |")
    print("|---|---|---|")
    for sd in ns.sds:
        mcnemar, flips = rejection_rates(sd, ns.samples, ns.tasks, ns.pairs, ns.seed)

        def rate(k: int) -> str:
            lo, hi = wilson_interval(k, ns.samples)
            return f"{100 * k / ns.samples:.1f}% [{100 * lo:.1f}, {100 * hi:.1f}]"

        print(f"| {sd:g} | {rate(mcnemar)} | {rate(flips)} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
