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
