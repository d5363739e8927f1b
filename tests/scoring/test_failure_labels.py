"""The failure-mode classifier against the labelled sets, labelled from replay contact sheets by a reader of the
taxonomy, not the code (benchmarks/failure_labels.py made and checks them):

- tests/data/failure_labels: 48 failed episodes of the failure-mode study, stratified by suite, protocol, latency
  and policy;
- tests/data/failure_labels_by_mode: 24 more, 6 of each rare mode as the classifier calls it (its precision).

The agreement documented in docs/design/failure_modes.md is what the scorer gives on these bags today: a
classifier change that moves it fails here, and the page must say the new figure."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from lq_ros.scoring.bag_scorer import score_bag
from lq_ros.scoring.failure_aggregate import label_agreement

DATA = Path(__file__).resolve().parents[1] / "data/failure_labels"
#: docs/design/failure_modes.md: 39 of 48 agree, Cohen's kappa 0.68.
AGREED, N, KAPPA = 39, 48, 0.68


@pytest.fixture(scope="module")
def labelled() -> tuple[dict[str, str], dict[str, str]]:
    with (DATA / "labels.csv").open() as f:
        labels = {row["episode"]: row["label"] for row in csv.DictReader(f)}
    predicted = {name: score_bag(DATA / "bags" / name)["failure_mode"] for name in labels}
    return labels, predicted


def test_the_labelled_set_is_the_selected_one(labelled):
    labels, predicted = labelled
    assert sorted(labels) == json.loads((DATA / "episodes.json").read_text())["episodes"]
    rows = [score_bag(DATA / "bags" / name) for name in sorted(labels)[:3]]
    assert all(r["status"] == "failure" for r in rows)


def test_the_documented_agreement(labelled):
    out = label_agreement(*labelled)
    assert (out["agreed"], out["n"]) == (AGREED, N)
    assert round(out["kappa"], 2) == KAPPA


BY_MODE = Path(__file__).resolve().parents[1] / "data/failure_labels_by_mode"
#: docs/design/failure_modes.md: of 6 episodes the classifier puts in each mode, how many the labeller does.
BY_MODE_AGREED = {"wrong_object_disturbed": 1, "dropped_in_transit": 1, "placed_off_target": 3, "stalled": 1}


def test_the_documented_precision_of_the_rare_modes():
    with (BY_MODE / "labels.csv").open() as f:
        labels = {row["episode"]: row["label"] for row in csv.DictReader(f)}
    assert sorted(labels) == json.loads((BY_MODE / "episodes.json").read_text())["episodes"]
    assert not set(labels) & set(json.loads((DATA / "episodes.json").read_text())["episodes"])
    predicted = {name: score_bag(BY_MODE / "bags" / name)["failure_mode"] for name in labels}
    called = {mode: [n for n in labels if predicted[n] == mode] for mode in BY_MODE_AGREED}
    assert {mode: len(names) for mode, names in called.items()} == dict.fromkeys(BY_MODE_AGREED, 6)
    assert {mode: sum(labels[n] == mode for n in names) for mode, names in called.items()} == BY_MODE_AGREED
