"""The shipped weights' training recipe has one source (lq_ros/training/recipe.py): TrainConfig's defaults and
``lq train``'s defaults both reproduce the configuration every shipped checkpoint records (pure Python)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from lq_ros.training.recipe import KIND_RECIPE, TrainConfig, default_replan_steps

WEIGHTS_DIR = Path(__file__).resolve().parents[2] / "lq_ros" / "policies" / "weights"
SHIPPED = sorted(WEIGHTS_DIR.glob("*.json"))


def _meta(path: Path) -> dict:
    return json.loads(path.read_text())


def test_every_shipped_checkpoint_records_its_recipe():
    assert len(SHIPPED) == 6, [p.name for p in SHIPPED]  # oft_c8, oft_c1, flow_c10 x Spatial, Object
    for path in SHIPPED:
        meta = _meta(path)
        assert set(meta["train_config"]) == set(TrainConfig().to_dict()), path.name


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.stem)
def test_train_config_defaults_are_the_shipped_recipe(path):
    """TrainConfig(policy, horizon) alone equals the recorded train_config field by field."""
    meta = _meta(path)
    cfg = TrainConfig(policy=meta["kind"], horizon=meta["horizon"])
    assert cfg.to_dict() == meta["train_config"]
    assert (cfg.width, cfg.depth, cfg.replan_steps) == (meta["width"], meta["depth"], meta["inference"]["replan_steps"])
    assert cfg.run_name(meta["layout"]["suite"]) == path.stem


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.stem)
def test_lq_train_defaults_are_the_shipped_recipe(path, tmp_path, monkeypatch):
    """`lq train --policy KIND --chunk H` (no other option) builds the recorded configuration."""
    import lq_ros.training.train as train_module
    from lq_ros.cli import app

    seen: list[TrainConfig] = []

    def fake_train(cfg: TrainConfig, data: list[Path], out: Path) -> dict:
        seen.append(cfg)
        return {"metrics": {"params": 0, "train_wall_s": 0.0, "final_train_loss": 0.0, "final_val_loss": 0.0}}

    monkeypatch.setattr(train_module, "train", fake_train)
    meta = _meta(path)
    args = ["train", "--policy", meta["kind"], "--data", str(tmp_path), "--out", str(tmp_path / "w")]
    if meta["horizon"] != KIND_RECIPE[meta["kind"]]["horizon"]:
        args += ["--chunk", str(meta["horizon"])]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    assert len(seen) == 1 and seen[0].to_dict() == meta["train_config"]


def test_kind_defaults_resolve_and_explicit_values_win():
    oft, flow = TrainConfig(policy="oft"), TrainConfig(policy="flow")
    assert (oft.horizon, oft.steps, oft.ema, oft.replan_steps) == (8, 12000, 0.0, 8)
    assert (flow.horizon, flow.steps, flow.ema, flow.replan_steps) == (10, 16000, 0.999, 5)
    assert (default_replan_steps("oft", 1), default_replan_steps("flow", 1)) == (1, 1)
    mine = TrainConfig(policy="flow", horizon=6, steps=50, ema=0.0, replan_steps=6, depth=2, target="plan")
    got = (mine.horizon, mine.steps, mine.ema, mine.replan_steps, mine.depth, mine.target)
    assert got == (6, 50, 0.0, 6, 2, "plan")
    for bad in ({"steps": -1}, {"horizon": -2}, {"ema": 1.0}, {"replan_steps": 9}, {"target": "x"}, {"policy": "act"}):
        with pytest.raises(ValueError):
            TrainConfig(**bad)
