"""The rebuild pipeline (config/training/shipped_weights.yaml) is what the shipped weight files record."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from lq_ros.policies.learned.chunk_policy import WEIGHTS_DIR
from lq_ros.training.collect import CollectConfig
from lq_ros.training.pipeline import load_pipeline, main

DATASETS, STAGES = load_pipeline()
WEIGHTS = {n: w for n, w in STAGES.items() if w.shipped}
CANDIDATES = {n: w for n, w in STAGES.items() if not w.shipped}


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
    shipped_data = {d for w in WEIGHTS.values() for d in w.data}
    assert len(lines) == len(shipped_data) + len(WEIGHTS)
    assert lines[0].startswith("collect spatial_a: lq collect --out ") and "--tasks 4,6 --inits 10-49" in lines[0]
    assert any(line.startswith("train flow_c10_libero_object: lq train --policy flow --chunk 10") for line in lines)
    assert all("(recorded: " in line for line in lines)
    assert main(["--out", str(tmp_path), "--plan", "--only", "nope"]) == 2


def test_delay_aware_candidates_start_from_shipped_weights_and_are_built_when_named(capsys, tmp_path):
    """The candidates (built and evaluated, not shipped) are valid configurations that fine-tune a shipped file;
    naming one builds its datasets and the weights it starts from first."""
    assert set(CANDIDATES) == {"oft_c8_delay_libero_object", "flow_c10_delay_libero_object"}
    for name, stage in CANDIDATES.items():
        cfg = stage.config()
        assert cfg.run_name("libero_object") == name and cfg.delay_max >= 1 and cfg.freeze_base
        assert WEIGHTS[cfg.init_from].policy == stage.policy and WEIGHTS[cfg.init_from].chunk == stage.chunk
        for dataset in stage.data:
            collect = DATASETS[dataset].config()
            assert collect.latency_ticks and collect.suite == "libero_object"
    assert main(["--out", str(tmp_path), "--plan", "--only", "flow_c10_delay_libero_object"]) == 0
    lines = capsys.readouterr().out.splitlines()
    order = [line.split(":")[0] for line in lines]
    assert order == ["collect object", "collect object_expert_latency", "train flow_c10_libero_object",
                     "train flow_c10_delay_libero_object"]  # fmt: skip
    assert "--freeze-base" in lines[-1] and "--init-from flow_c10_libero_object" in lines[-1]
    assert "--latency-ticks 0-8 --latency-driver scripted" in lines[1] and lines[-1].endswith("(not shipped)")
