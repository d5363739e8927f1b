"""benchmarks/physics_gap.py's pure parts: the paired table of two physics and the open-loop divergence tick."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

_PATH = Path(__file__).resolve().parents[2] / "benchmarks" / "physics_gap.py"
_SPEC = importlib.util.spec_from_file_location("physics_gap", _PATH)
physics_gap = importlib.util.module_from_spec(_SPEC)
sys.modules.setdefault("physics_gap", physics_gap)
_SPEC.loader.exec_module(physics_gap)

OTHER = "mujoco-3.8.1"


def closed_rows(outcomes: dict[tuple[str, int, int], tuple[bool, bool]], policy: str = "scripted") -> list[dict]:
    """Rows of (suite, task, init) -> (success under the stack's physics, under OTHER)."""
    rows = []
    for (suite, task, init), pair in outcomes.items():
        for physics, success in zip((physics_gap.STACK, OTHER), pair):
            rows.append(
                {"kind": "closed", "physics": physics, "suite": suite, "task": task, "init": init, "policy": policy,
                 "success": success, "ticks": 100}
            )  # fmt: skip
    return rows


def test_paired_table_counts_pairs_and_differences():
    # 5 tasks x 2 inits; the other physics loses task 0 init 0 and gains task 1 init 1 and task 2 init 0.
    outcomes = {("libero_spatial", t, i): (True, True) for t in range(5) for i in range(2)}
    outcomes[("libero_spatial", 0, 0)] = (True, False)
    outcomes[("libero_spatial", 1, 1)] = (False, True)
    outcomes[("libero_spatial", 2, 0)] = (False, True)
    rows = pd.DataFrame(closed_rows(outcomes))
    (row,) = physics_gap.paired_table(rows, OTHER).to_dict("records")
    assert (row["n"], row["tasks"], row["only_other"], row["only_stack"]) == (10, 5, 2, 1)
    assert row[physics_gap.STACK] == pytest.approx(0.8) and row[OTHER] == pytest.approx(0.9)
    assert row["diff"] == pytest.approx(0.1)
    assert row["low"] < 0.0 < 0.1 < row["high"]


def test_paired_table_keeps_a_width_when_every_pair_agrees_and_leaves_unpaired_episodes_out():
    outcomes = {(s, t, 0): (t % 2 == 0, t % 2 == 0) for s in ("libero_spatial", "libero_object") for t in range(5)}
    rows = closed_rows(outcomes)
    rows.append({**rows[0], "init": 7})  # run under the stack's physics only: no pair
    table = physics_gap.paired_table(pd.DataFrame(rows), OTHER).set_index("suite")
    assert list(table.index) == ["libero_object", "libero_spatial", "all"]
    assert table.loc["all", "n"] == 10 and table.loc["libero_spatial", "n"] == 5
    assert (table["diff"] == 0).all()
    assert (table["low"] < 0).all() and (table["high"] > 0).all()  # Tango's interval: no zero width


def test_first_divergence_names_the_first_tick_beyond_the_threshold():
    a = np.zeros((6, 3))
    b = np.zeros((6, 3))
    b[2:, 0] = [0.0005, 0.002, 0.0, 0.003]  # 0.5 mm at tick 2, 2 mm at tick 3
    assert physics_gap.first_divergence(a, b) == (3, pytest.approx(0.003))
    assert physics_gap.first_divergence(a, a) == (None, 0.0)
    assert physics_gap.first_divergence(a[:3], b) == (None, pytest.approx(0.0005))  # the shorter one's ticks only
