"""The rebuild pipeline (config/training/shipped_weights.yaml) is what the shipped weight files record."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from lq_ros.policies.learned.chunk_policy import WEIGHTS_DIR
from lq_ros.training.collect import CollectConfig
from lq_ros.training.pipeline import load_pipeline, main

DATASETS, WEIGHTS = load_pipeline()


def test_every_shipped_weight_file_has_a_stage():
    assert set(WEIGHTS) == {p.stem for p in WEIGHTS_DIR.glob("*.json")}


@pytest.mark.parametrize("name", sorted(WEIGHTS))
def test_stage_configuration_equals_what_the_weights_record(name):
    meta = json.loads((WEIGHTS_DIR / f"{name}.json").read_text())
    stage = WEIGHTS[name]
    assert stage.config().to_dict() == meta["train_config"]
    recorded = meta["dataset"]
    assert [Path(p).name for p in recorded["paths"]] == list(stage.data)
    defaults = CollectConfig().to_dict()
    for dataset, source in zip(stage.data, recorded["sources"], strict=True):
        ours, theirs = DATASETS[dataset].config().to_dict(), source["collect_config"]
        # Options added to `lq collect` after a dataset was collected are absent from its record: they must be
        # at their defaults (the behaviour it was collected with); every recorded one must be equal.
        assert {k: ours[k] for k in ours.keys() - theirs.keys()} == {
            k: defaults[k] for k in ours.keys() - theirs.keys()
        }
        assert {k: ours[k] for k in theirs} == theirs, dataset


def test_plan_prints_every_command_and_the_recorded_times(capsys, tmp_path):
    assert main(["--out", str(tmp_path), "--plan"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == len(DATASETS) + len(WEIGHTS)
    assert lines[0].startswith("collect spatial_a: lq collect --out ") and "--tasks 4,6 --inits 10-49" in lines[0]
    assert any(line.startswith("train flow_c10_libero_object: lq train --policy flow --chunk 10") for line in lines)
    assert all("(recorded: " in line for line in lines)
    assert main(["--out", str(tmp_path), "--plan", "--only", "nope"]) == 2
