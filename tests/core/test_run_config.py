"""RunConfig: the one source of run parameters (CLI defaults, node parameters, params YAML) and provenance."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from lq_ros.core.run_config import DEFAULT_CAMERA_SIZE_PX, REPO_ROOT, RunConfig, cpu_info, versions
from lq_ros.transport.ros.stack import node_parameters


def test_ros_parameters_round_trip_with_their_declared_types():
    cfg = RunConfig(
        mode="async", latency_s=0, request_threshold=6, merge="weighted_average", policy_args={"chunk_size": 8}
    )
    params = cfg.ros_parameters()
    assert params["latency_s"] == 0.0 and isinstance(params["latency_s"], float)  # a ROS double, not an int
    assert params["policy_args"] == '{"chunk_size": 8}'
    assert RunConfig.from_ros_parameters(params) == cfg
    drawn = RunConfig(mode="async", latency_dist="uniform:0.075:0.275", merge="temporal_ensemble")
    assert drawn.latency_s == 0.2 and drawn.latency_ticks is None  # the expected applied Δt_sim; N per inference
    assert RunConfig.from_ros_parameters(drawn.ros_parameters()) == drawn


def test_keys_of_configurations_without_a_distribution_are_unchanged():
    # Keys from before latency_dist existed (stored sweeps, episode names) stay valid.
    assert RunConfig(mode="async", latency_s=0.2).key() == "9a3c1c680023"
    drawn = RunConfig(mode="async", latency_dist="uniform:0.075:0.275")
    assert drawn.key() != RunConfig(mode="async", latency_s=0.2).key()
    assert "_uniform200ms_" in drawn.episode_name()
    assert RunConfig(latency_dist="0.1") == RunConfig(latency_s=0.1)  # a constant given as a distribution
    with pytest.raises(ValueError, match="unknown distribution"):
        RunConfig(latency_dist="poisson:3")


def test_shipped_params_file_is_derived_from_run_config():
    shipped = yaml.safe_load((REPO_ROOT / "config" / "demo.yaml").read_text())
    assert shipped["/**"]["ros__parameters"] == {**RunConfig().ros_parameters(), "use_sim_time": True}
    generated = node_parameters(RunConfig(), Path("bags/demo/<episode>"), (), DEFAULT_CAMERA_SIZE_PX, {})
    assert {k: v["ros__parameters"] for k, v in shipped.items()} == generated


def test_render_size_comes_from_the_run_then_the_policy():
    assert RunConfig().camera_size_for(None) == DEFAULT_CAMERA_SIZE_PX
    assert RunConfig().camera_size_for(256) == 256  # e.g. openpi's LIBERO example renders 256 x 256
    assert RunConfig(camera_size=128).camera_size_for(256) == 128
    with pytest.raises(ValueError, match="camera_size and max_steps must be >= 0"):
        RunConfig(camera_size=-1)


def test_versions_record_the_cpu_class():
    cpu = cpu_info()
    assert cpu["model"] and cpu["class"].split()[0] in ("x86_64", "aarch64")
    assert versions()["cpu"] == cpu


def test_where_replan_steps_came_from_is_recorded_but_not_part_of_the_key():
    """A run given --replan-steps 5 is the same episode as one whose policy declared 5 (stored sweeps resume)."""
    given, declared = RunConfig(replan_steps_source="flag"), RunConfig(replan_steps_source="policy")
    assert given.key() == declared.key() == RunConfig().key()
    assert declared.to_dict()["replan_steps_source"] == "policy"
    with pytest.raises(ValueError, match="replan_steps_source must be one of"):
        RunConfig(replan_steps_source="guess")


def test_budget_presets_give_each_suite_its_budget_and_the_paper_stays_the_default():
    assert RunConfig(suite="libero_spatial").budget == 220
    assert RunConfig(suite="libero_spatial", budgets="lerobot").budget == 280
    assert RunConfig(suite="libero_10", budgets="xvla").budget == 800
    assert RunConfig(suite="libero_spatial", budgets="lerobot", max_steps=50).budget == 50  # max_steps wins
    # The paper's preset keeps the keys of stored results; another preset is another experiment.
    assert RunConfig(budgets="paper").key() == RunConfig().key() != RunConfig(budgets="lerobot").key()
    with pytest.raises(ValueError, match="unknown budget preset 'lerobot06'; known: paper, lerobot, xvla"):
        RunConfig(budgets="lerobot06")
