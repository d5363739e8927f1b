"""benchmarks/interval_coverage.py, reduced: a few hundred simulated samples of the cells where the replaced
intervals failed, with loose bounds that a broken method would miss (the full table: run the benchmark)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

_PATH = Path(__file__).resolve().parents[2] / "benchmarks" / "interval_coverage.py"
_SPEC = importlib.util.spec_from_file_location("interval_coverage", _PATH)
interval_coverage = importlib.util.module_from_spec(_SPEC)
sys.modules.setdefault("interval_coverage", interval_coverage)
_SPEC.loader.exec_module(interval_coverage)

REPS = 300


def test_a_small_one_way_effect_at_five_tasks_of_two():
    """+10 points, one way, 5 tasks x 2 inits: a quarter of the samples have no discordant pair. The replaced
    interval (task bootstrap hull Newcombe) covered about 82%, the cluster t alone about 70%; the reported one holds."""
    cell = interval_coverage.paired_cell(5, 2, "+10 points one way, B ~ 0.9 Beta(3, 2)", REPS)
    assert cell["no discordant pair"] > 0.15
    assert cell["reported"] >= 0.93 and cell["reported, none discordant"] == 1.0
    assert cell["replaced"] < 0.90 and cell["cluster t"] < 0.85


def test_the_stated_coverage_range_is_the_benchmarks():
    """intervals.CLUSTER_COVERAGE is the range the full benchmark printed; a reduced run of its lowest cells (success:
    5 tasks x 10, Beta(0.6, 0.4), 91.5%; paired: 5 x 10, task effects +-0.3, 92.3%) lands near it."""
    from lq_ros.scoring.intervals import CLUSTER_COVERAGE

    low = interval_coverage.success_cell(5, 10, 0.6, 0.4, REPS)["reported"]
    assert abs(low - CLUSTER_COVERAGE["success"][0]) < 0.05
    low = interval_coverage.paired_cell(5, 10, "no mean effect, task effects +-0.3", REPS)["reported"]
    assert abs(low - CLUSTER_COVERAGE["paired"][0]) < 0.05


def test_task_effects_without_a_mean_effect_need_the_task_as_the_unit():
    """Task effects of +-0.3 around no mean effect, 10 tasks x 10 pairs: pairs as units (Tango alone) cover about
    two thirds; the reported hull, which has the task as the unit, stays near nominal."""
    cell = interval_coverage.paired_cell(10, 10, "no mean effect, task effects +-0.3", REPS)
    assert cell["reported"] >= 0.86 and cell["Tango"] < 0.80


def test_a_clustered_success_rate():
    """Beta(0.6, 0.4) tasks of 10 episodes: Wilson (episodes as units) covers under 60%; the reported interval
    stays near nominal."""
    cell = interval_coverage.success_cell(10, 10, 0.6, 0.4, REPS)
    assert cell["reported"] >= 0.86 and cell["Wilson"] < 0.70
