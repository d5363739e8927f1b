"""Learned chunk policies: feature layout, dataset I/O, models, training, shipped weights, end to end."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from lq_ros.core.types import Observation, TaskInfo
from lq_ros.policies import PolicyError, make_policy
from lq_ros.policies.learned.chunk_policy import WEIGHTS_DIR, postprocess, shipped_suites
from lq_ros.policies.learned.features import (
    GOAL_DIM,
    PER_OBJECT_DIM,
    PROPRIO_DIM,
    STATE_DIM,
    features,
    goal_slots,
    layout_for,
    raw_from_observation,
)
from lq_ros.policies.learned.networks import ChunkRegressor, FlowChunkModel, integrate
from lq_ros.sim.libero_env import load_task
from lq_ros.training.dataset import Episode, read_frames, read_info, write_dataset
from lq_ros.training.train import TrainConfig, prepare, train

SPATIAL = layout_for("libero_spatial")
OBJECT = layout_for("libero_object")
#: The policies with shipped weights: (policy name, policy args, checkpoint base name, chunk length).
POLICIES = [("oft", {}, "oft_c8", 8), ("oft", {"chunk_size": 1}, "oft_c1", 1), ("flow", {}, "flow_c10", 10)]
#: Suites each checkpoint base name is shipped for (docs/design/learned_policies.md: what is not shipped yet).
SHIPPED_SUITES: dict[str, tuple[str, ...]] = {
    "oft_c8": ("libero_spatial", "libero_object"),
    "oft_c1": ("libero_spatial", "libero_object"),
    "flow_c10": ("libero_spatial", "libero_object"),
}
#: Every shipped (suite, policy name, policy args, base name, chunk length).
SHIPPED = [(suite, *p) for p in POLICIES for suite in SHIPPED_SUITES[p[2]]]
REPLAN = {"oft_c8": 8, "oft_c1": 1, "flow_c10": 5}


def _obs(tick: int = 0, shift: float = 0.0, drop: str = "") -> Observation:
    """A plausible LIBERO-Spatial observation (bowl on the table, plate to its right)."""
    objects = {
        "akita_black_bowl_1": (np.array([-0.06 + shift, 0.20, 0.898]), np.array([0.0, 0.0, 0.0, 1.0])),
        "akita_black_bowl_2": (np.array([-0.19, 0.32, 0.898]), np.array([0.0, 0.0, 0.38, 0.92])),
        "cookies_1": (np.array([0.06, 0.03, 0.909]), np.array([0.0, 0.0, 0.0, 1.0])),
        "glazed_rim_porcelain_ramekin_1": (np.array([-0.20, 0.19, 0.899]), np.array([0.0, 0.0, 0.0, 1.0])),
        "plate_1": (np.array([0.05, 0.21, 0.902]), np.array([0.0, 0.0, 0.0, 1.0])),
    }
    objects.pop(drop, None)
    return Observation(
        tick=tick,
        sim_time_s=0.5 + 0.05 * tick,
        eef_pos=np.array([-0.2, 0.0, 1.18]),
        eef_quat_xyzw=np.array([1.0, 0.0, 0.0, 0.0]),
        gripper_qpos=np.array([0.039, -0.039]),
        joint_pos=np.array([0.0, 0.2, 0.0, -2.4, 0.0, 2.6, 0.8]),
        joint_vel=np.zeros(7),
        objects=objects,
    )


def _object_obs(tick: int = 0, shift: float = 0.0) -> Observation:
    """LIBERO-Object task 0, init state 0 (rounded from a real observation): soup to go in the basket."""
    side, up, flat = np.array([0.0, 0.708, 0.706, 0.0]), np.array([0.5, 0.5, 0.5, 0.5]), np.array([0.0, 0.0, 1.0, 0.0])
    objects = {
        "alphabet_soup_1": (np.array([-0.119 + shift, -0.24, 0.038]), side),
        "basket_1": (np.array([0.015, 0.252, -0.005]), np.array([0.0, 0.0, 0.707, 0.707])),
        "salad_dressing_1": (np.array([0.05, -0.1, 0.073]), up),
        "cream_cheese_1": (np.array([-0.151, 0.058, 0.009]), flat),
        "milk_1": (np.array([0.104, -0.196, 0.07]), up),
        "tomato_sauce_1": (np.array([0.15, 0.03, 0.038]), side),
        "butter_1": (np.array([-0.205, -0.075, 0.009]), flat),
    }
    return Observation(
        tick=tick,
        sim_time_s=0.5 + 0.05 * tick,
        eef_pos=np.array([-0.153, -0.006, 0.248]),
        eef_quat_xyzw=np.array([1.0, 0.0, -0.029, 0.0]),
        gripper_qpos=np.array([0.039, -0.039]),
        joint_pos=np.array([-0.01, -0.151, -0.003, -2.471, -0.001, 2.262, 0.774]),
        joint_vel=np.zeros(7),
        objects=objects,
    )


@pytest.fixture(scope="module")
def task0() -> TaskInfo:
    return load_task("libero_spatial", 0)[0]


# --- feature layout ------------------------------------------------------------------------------------
def test_feature_layout_dims_slots_and_missing_objects():
    assert (PROPRIO_DIM, PER_OBJECT_DIM, GOAL_DIM, STATE_DIM) == (18, 10, 17, 23)
    assert SPATIAL.feature_dim == 18 + 10 * 5 + 17 + 10
    assert OBJECT.feature_dim == 18 + 10 * 11 + 17 + 10
    assert replace(SPATIAL, joint_velocity=True).feature_dim == SPATIAL.feature_dim + 7
    assert goal_slots(SPATIAL, [["on", "akita_black_bowl_1", "plate_1"]]) == (0, 4)
    assert goal_slots(SPATIAL, [["open", "drawer"]]) == (-1, -1)
    # A region goal (LIBERO-Object's basket) resolves to the object the region belongs to.
    assert goal_slots(OBJECT, [["in", "milk_1", "basket_1_contain_region"]]) == (7, 1)
    state, env = raw_from_observation(SPATIAL, _obs())
    assert state.shape == (STATE_DIM,) and env.shape == (SPATIAL.env_state_dim,)
    f = features(SPATIAL, state[None], env[None], np.array([3]), np.array([[0, 4]]))
    assert f.shape == (1, SPATIAL.feature_dim)
    g0 = PROPRIO_DIM + PER_OBJECT_DIM * 5
    goal = f[0, g0 : g0 + GOAL_DIM]
    np.testing.assert_allclose(goal[:3], [0.14, 0.20, -0.282], atol=1e-5)  # bowl - EE
    np.testing.assert_allclose(goal[6:9], [0.11, 0.01, 0.004], atol=1e-5)  # plate - bowl
    np.testing.assert_allclose(goal[9:15], [1, 0, 0, 0, 1, 0], atol=1e-6)  # the bowl's orientation (upright)
    assert f[0, g0 + GOAL_DIM + 3] == 1.0 and f[0, g0 + GOAL_DIM :].sum() == 1.0  # task one-hot
    # A missing goal object: its slot's presence flag and the goal geometry go to zero, nothing is NaN.
    s2, e2 = raw_from_observation(SPATIAL, _obs(drop="plate_1"))
    f2 = features(SPATIAL, s2[None], e2[None], np.array([3]), np.array([[0, 4]]))
    present = PROPRIO_DIM + PER_OBJECT_DIM - 1
    assert np.all(np.isfinite(f2)) and f2[0, present + PER_OBJECT_DIM * 4] == 0.0 and f2[0, present] == 1.0
    assert f2[0, g0 + 15] == 1.0 and f2[0, g0 + 16] == 0.0


def test_features_quaternion_sign_invariant_and_task_checked():
    state, env = raw_from_observation(SPATIAL, _obs())
    flipped = env.reshape(5, 7).copy()
    flipped[:, 3:] *= -1
    s_flip = state.copy()
    s_flip[3:7] *= -1
    a = features(SPATIAL, state[None], env[None], np.array([0]), np.array([[0, 4]]))
    b = features(SPATIAL, s_flip[None], flipped.reshape(1, -1), np.array([0]), np.array([[0, 4]]))
    np.testing.assert_allclose(a, b, atol=1e-6)
    with pytest.raises(ValueError, match="task index"):
        features(SPATIAL, state[None], env[None], np.array([10]), np.array([[0, 4]]))
    with pytest.raises(ValueError, match="no feature layout"):
        layout_for("libero_nowhere")


# --- dataset -------------------------------------------------------------------------------------------
def _episode(rng: np.random.Generator, task: int, length: int) -> Episode:
    return Episode(
        task_index=task, init_index=10 + task, seed=17 + task, noise_std=0.15,
        state=rng.normal(size=(length, STATE_DIM)).astype(np.float32),
        env_state=rng.normal(size=(length, SPATIAL.env_state_dim)).astype(np.float32),
        action=rng.uniform(-1, 1, (length, 7)).astype(np.float32),
        action_executed=rng.uniform(-1, 1, (length, 7)).astype(np.float32),
        action_chunk=rng.uniform(-1, 1, (length, 16, 7)).astype(np.float32),
        success=np.r_[np.zeros(length - 1, bool), True],
    )  # fmt: skip


def _write_synthetic(root, lengths=(5, 7)) -> list[Episode]:
    rng = np.random.default_rng(0)
    eps = [_episode(rng, t, n) for t, n in enumerate(lengths)]
    extra = {
        "suite": "libero_spatial",
        "layout": SPATIAL.to_dict(),
        "goals": {str(t): [["on", "akita_black_bowl_1", "plate_1"]] for t in range(len(lengths))},
    }
    write_dataset(root, eps, extra, {t: f"task {t}" for t in range(len(lengths))})
    return eps


def test_dataset_roundtrip(tmp_path):
    eps = _write_synthetic(tmp_path)
    info, cols = read_frames(tmp_path)
    assert info["fps"] == 20 and info["total_episodes"] == 2 and info["total_frames"] == 12
    assert info["features"]["action.chunk"]["shape"] == [16, 7]
    assert info["features"]["observation.state"]["shape"] == [STATE_DIM]
    np.testing.assert_array_equal(cols["episode_index"], [0] * 5 + [1] * 7)
    np.testing.assert_array_equal(cols["frame_index"], [*range(5), *range(7)])
    np.testing.assert_allclose(cols["timestamp"][:5], np.arange(5) / 20)
    np.testing.assert_array_equal(cols["observation.environment_state"][5:], eps[1].env_state)
    np.testing.assert_array_equal(cols["action.chunk"][:5], eps[0].action_chunk)
    np.testing.assert_array_equal(cols["action"][5:], eps[1].action)
    assert cols["next.success"].sum() == 2
    lines = (tmp_path / "meta" / "episodes.jsonl").read_text().splitlines()
    assert [json.loads(x)["length"] for x in lines] == [5, 7]
    with pytest.raises(ValueError, match="no episodes"):
        write_dataset(tmp_path / "empty", [], {}, {})
    with pytest.raises(FileNotFoundError, match="lq collect"):
        read_info(tmp_path / "missing")


def test_prepare_targets_plan_and_future(tmp_path):
    eps = _write_synthetic(tmp_path)
    _, layout, feats, plan, episode = prepare([tmp_path], 8, "plan")
    assert layout == SPATIAL and feats.shape == (12, SPATIAL.feature_dim)
    np.testing.assert_array_equal(plan[5], eps[1].action_chunk[0, :8])
    _, _, _, fut, _ = prepare([tmp_path], 4, "future")
    np.testing.assert_array_equal(fut[3], eps[0].action[[3, 4, 4, 4]])  # padded with the last label
    _, _, _, _, ep2 = prepare([tmp_path, tmp_path], 4, "plan")
    assert sorted(set(ep2.tolist())) == [0, 1, 2, 3]  # episode ids stay distinct across datasets
    with pytest.raises(ValueError, match="horizon 20"):
        prepare([tmp_path], 20, "plan")


def test_collection_turns_off_the_experts_inflight_replay():
    """LIBERO-Object's expert replays queued rows (async); collected labels must react to every tick."""
    from lq_ros.training.collect import _closed_loop

    expert = make_policy("scripted", chunk_size=16)
    expert.reset(load_task("libero_object", 0)[0], 7)
    assert expert.expert.commit_inflight
    _closed_loop(expert)
    assert not expert.expert.commit_inflight


def test_shard_written_before_a_setting_existed_is_reused():
    """A shard's saved configuration without a newer setting counts as that setting's default."""
    from lq_ros.training.collect import CollectConfig, _shard_key

    cfg = CollectConfig(suite="libero_object", tasks=(0, 1), inits=(10, 11), repeats=2, workers=2)
    old = {k: v for k, v in cfg.to_dict().items() if k not in ("fresh", "driver", "keep_failures")}
    assert _shard_key({**old, "tasks": [0], "workers": 1}) == _shard_key(cfg.to_dict())
    assert _shard_key({**old, "repeats": 1}) != _shard_key(cfg.to_dict())


# --- models --------------------------------------------------------------------------------------------
def test_model_shapes_flow_determinism_and_hook():
    torch.manual_seed(0)
    feats = torch.randn(3, SPATIAL.feature_dim)
    oft = ChunkRegressor(SPATIAL.feature_dim, 8, width=32, depth=1)
    assert oft(feats).shape == (3, 8, 7)
    flow = FlowChunkModel(SPATIAL.feature_dim, 10, width=32, depth=1)
    actions = torch.randn(3, 10, 7)
    assert torch.isfinite(flow.loss(feats, actions, torch.Generator().manual_seed(1)))
    noise = torch.randn(3, 10, 7, generator=torch.Generator().manual_seed(2))
    a, b = flow.sample(feats, noise, 4), flow.sample(feats, noise.clone(), 4)
    assert a.shape == (3, 10, 7) and torch.equal(a, b)
    assert not torch.equal(a, flow.sample(feats, noise + 1.0, 4))
    # The hook sees every step (flow times 1/4 .. 1) and may steer the chunk: pinning a prefix holds it.
    seen, prefix = [], torch.full((3, 2, 7), 0.5)

    def pin(x, t, v):
        seen.append(t)
        return torch.cat([prefix, x[:, 2:]], dim=1)

    with torch.no_grad():
        pinned = integrate(flow.velocity, feats, noise, 4, pin)
    assert seen == [0.25, 0.5, 0.75, 1.0] and torch.equal(pinned[:, :2], prefix)
    assert torch.equal(flow.sample(feats, noise, 4, hook=None), a)


def test_postprocess_clips_and_makes_the_gripper_ternary():
    raw = np.array([[2.0, -3.0, 0.1, 0, 0, 0, 0.7], [0, 0, 0, 0, 0, 0, 0.2], [0, 0, 0, 0, 0, 0, -0.9]])
    out = postprocess(raw)
    np.testing.assert_array_equal(out[0, :3], [1.0, -1.0, 0.1])
    np.testing.assert_array_equal(out[:, 6], [1.0, 0.0, -1.0])  # close, hold, open


# --- shipped weights -----------------------------------------------------------------------------------
def test_shipped_checkpoints_are_the_listed_ones_small_with_loss_curves():
    files = sorted(WEIGHTS_DIR.glob("*.pt"))
    assert sum(f.stat().st_size for f in files) < 20e6
    # Every weight file in the package is one this module loads below (no stale, unloadable leftovers).
    assert sorted(f.stem for f in files) == sorted(f"{base}_{suite}" for suite, _, _, base, _ in SHIPPED)
    for base, suites in SHIPPED_SUITES.items():
        assert shipped_suites(base) == sorted(suites), base
        for suite in suites:
            stem = WEIGHTS_DIR / f"{base}_{suite}"
            assert (WEIGHTS_DIR / f"{stem.name}.loss.png").is_file()
            assert (WEIGHTS_DIR / f"{stem.name}.loss.csv").is_file()
            meta = json.loads(stem.with_suffix(".json").read_text())
            assert meta["layout"] == layout_for(suite).to_dict() and meta["dataset"]["episodes"] >= 500
            assert meta["metrics"]["train_wall_s"] < 30 * 60


@pytest.mark.parametrize(("suite", "name", "args", "base", "horizon"), SHIPPED)
def test_shipped_weights_load_per_suite_and_infer_deterministically(suite, name, args, base, horizon):
    task = load_task(suite, 0)[0]
    policy = make_policy(name, **args)
    policy.reset(task, seed=7)
    assert policy.weights_path.name == f"{base}_{suite}.json" and policy.layout == layout_for(suite)
    obs = _obs(tick=3) if suite == "libero_spatial" else _object_obs(tick=3)
    chunk = policy.infer(obs)
    assert chunk.shape == (horizon, 7) and np.all(np.abs(chunk) <= 1.0)
    assert set(np.unique(chunk[:, 6])) <= {-1.0, 0.0, 1.0}
    again = make_policy(name, **args)
    again.reset(task, seed=7)
    np.testing.assert_array_equal(again.infer(obs), chunk)
    # The chunk depends on the observation (not a constant output).
    moved = _obs(tick=3, shift=0.08) if suite == "libero_spatial" else _object_obs(tick=3, shift=0.08)
    assert not np.array_equal(policy.infer(moved), chunk)
    assert policy.replan_steps == REPLAN[base]


def test_policy_weights_errors(task0):
    policy = make_policy("oft", weights="oft_c8_libero_spatial")  # a full name pins that checkpoint
    other = TaskInfo(**{**task0.to_dict(), "suite": "libero_object"})
    with pytest.raises(PolicyError, match="libero_spatial"):
        policy.reset(other, 0)
    goal = TaskInfo(**{**task0.to_dict(), "suite": "libero_goal"})
    with pytest.raises(PolicyError, match="shipped for: " + ", ".join(sorted(SHIPPED_SUITES["flow_c10"]))):
        make_policy("flow").reset(goal, 0)
    with pytest.raises(PolicyError, match="reset"):
        make_policy("flow").infer(_obs())
    with pytest.raises(FileNotFoundError, match="shipped"):
        make_policy("oft", weights="no_such_weights")
    with pytest.raises(ValueError, match="chunk_size 1 or 8"):
        make_policy("oft", chunk_size=4)
    with pytest.raises(ValueError, match="'flow' checkpoint"):
        make_policy("oft", weights="flow_c10_libero_spatial")


# --- real episodes -------------------------------------------------------------------------------------
#: One short in-process episode per shipped checkpoint that its weights solve (checked when chosen; the
#: evaluation in docs/design/learned_policies.md has the rates): LIBERO-Spatial task 0 init 0 (~115 ticks),
#: LIBERO-Object task 7 init 0 (milk, the shortest).
EPISODE = {"libero_spatial": {"task": 0, "init": 0}, "libero_object": {"task": 7, "init": 0}}


@pytest.mark.parametrize(("suite", "name", "args", "base", "horizon"), SHIPPED)
@pytest.mark.sim
def test_real_episode_succeeds_inprocess(tmp_path, suite, name, args, base, horizon):
    from lq_ros.core.run_config import RunConfig
    from lq_ros.transport.inprocess import run_inprocess

    cfg = RunConfig(suite=suite, **EPISODE[suite], seed=7, policy=name, policy_args=args, replan_steps=REPLAN[base])
    outcome = run_inprocess(cfg, tmp_path)
    assert outcome.status == "success", (outcome.status, outcome.ticks, outcome.reason)


# --- end to end ----------------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.sim
def test_collect_train_load_infer_end_to_end(tmp_path, task0, spatial_env):
    """Collect two real expert episodes of one init state, train both kinds a few steps, load, infer."""
    from typer.testing import CliRunner

    from lq_ros.cli import app

    data = tmp_path / "data"
    runner = CliRunner()
    res = runner.invoke(app, ["collect", "--out", str(data), "--tasks", "0", "--inits", "10", "--noise", "0,0.2",
                              "--repeats", "2", "--workers", "1"])  # fmt: skip
    assert res.exit_code == 0, res.output
    info, cols = read_frames(data)
    assert info["total_episodes"] == 2 and info["collection"]["per_task"]["0"]["successes"] == 2
    second = cols["episode_index"] == 1
    assert cols["next.success"][second][-1] and not cols["next.success"][second][:-1].any()
    noise = cols["action.executed"][second, :6] - cols["action"][second, :6]
    assert 0.05 < noise.std() < 0.3  # executed = label + noise (clipped); the gripper is never perturbed
    assert np.array_equal(cols["action.executed"][~second], cols["action"][~second])  # noise level 0
    np.testing.assert_array_equal(cols["action.executed"][:, 6], cols["action"][:, 6])
    np.testing.assert_array_equal(cols["action.chunk"][:, 0], cols["action"])

    out = tmp_path / "w"
    meta = train(TrainConfig(policy="flow", horizon=10, steps=20, log_every=10, width=32, depth=1, replan_steps=5),
                 [data], out)  # fmt: skip
    assert [e["step"] for e in meta["metrics"]["log"]] == [10, 20]
    assert (out / "flow_c10_libero_spatial.loss.png").is_file()
    assert (out / "flow_c10_libero_spatial.loss.csv").read_text().startswith("step,train_loss,val_loss,wall_s")
    res = runner.invoke(app, ["train", "--policy", "oft", "--data", str(data), "--out", str(out), "--steps", "20",
                              "--width", "32", "--depth", "1"])  # fmt: skip
    assert res.exit_code == 0, res.output
    spatial_env.reset(0, 7)
    obs = spatial_env.observe(with_images=False)
    for name, weights, horizon in (
        ("oft", out / "oft_c8_libero_spatial.json", 8),
        ("flow", out / "flow_c10_libero_spatial.pt", 10),
    ):
        policy = make_policy(name, weights=str(weights))
        policy.reset(task0, 7)
        chunk = policy.infer(obs)
        assert chunk.shape == (horizon, 7) and np.all(np.isfinite(chunk))
