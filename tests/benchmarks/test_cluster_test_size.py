"""benchmarks/cluster_test_size.py: with tasks that differ and no effect on average over the suite, the pooled McNemar
test over-rejects and the task-level sign-flip test keeps its level (a reduced run of the committed command)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

_PATH = Path(__file__).resolve().parents[2] / "benchmarks" / "cluster_test_size.py"
_SPEC = importlib.util.spec_from_file_location("cluster_test_size", _PATH)
size = importlib.util.module_from_spec(_SPEC)
sys.modules.setdefault("cluster_test_size", size)
_SPEC.loader.exec_module(size)


def test_mcnemar_over_rejects_and_the_sign_flip_test_keeps_its_level():
    samples = 400
    mcnemar, flips = size.rejection_rates(0.4, samples, tasks=10, pairs=12, seed=1)
    assert mcnemar / samples > 0.2  # 30% at 2,000 samples
    assert flips / samples < 0.06  # 3.4% at 2,000 samples
    mcnemar0, flips0 = size.rejection_rates(0.0, samples, tasks=10, pairs=12, seed=1)
    assert mcnemar0 / samples < 0.07 and flips0 / samples < 0.06  # no task spread: both keep it
