"""Delay-aware learned policies (variant=delay): conditioning, the tracker against the real protocol core,
fine-tuning from a naive checkpoint, the variant switch, DAgger collection under latency."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from lq_ros.core.executor_protocol import ExecutorConfig, ExecutorCore, TickDriver
from lq_ros.policies import make_policy
from lq_ros.policies.learned.delay import DelayTracker, conditioning, conditioning_dim
from lq_ros.policies.learned.networks import build_model
from lq_ros.training.dataset import read_frames
from lq_ros.training.recipe import TrainConfig
from lq_ros.training.train import _expand_input, delay_batch, executed_prefixes, train, with_prefix
from tests.training.test_learned import _obs, _write_synthetic


@pytest.mark.parametrize("name", ["oft", "flow"])
def test_unknown_variant_is_refused_naming_the_valid_ones(name):
    with pytest.raises(ValueError, match=r"^unknown variant 'fast'; valid: naive, delay$"):
        make_policy(name, variant="fast")
    with pytest.raises(ValueError, match="unknown mode 'later'; valid: async, sync"):
        DelayTracker(mode="later")


@pytest.mark.parametrize("name", ["oft", "flow"])
def test_delay_variant_of_naive_weights_changes_only_the_async_execution_horizon(name):
    """With the shipped naive weights, variant=delay returns the naive chunk, cut to d + s rows in async (s = d by
    default) and whole in sync (a naive chunk's row 0 is the one for after the hold)."""
    from lq_ros.sim.libero_env import load_task

    task = load_task("libero_spatial", 0)[0]
    naive = make_policy(name)
    naive.reset(task, 7)
    chunk = naive.infer(_obs(tick=0))
    for args, rows in (({"delay": 2}, 4), ({"delay": 2, "execute": 0}, len(chunk)), ({"delay": 3, "execute": 1}, 4),
                       ({"delay": 0}, len(chunk)), ({"delay": 2, "mode": "sync"}, len(chunk))):  # fmt: skip
        policy = make_policy(name, variant="delay", **args)
        policy.reset(task, 7)
        assert policy.weights_path == naive.weights_path
        np.testing.assert_array_equal(policy.infer(_obs(tick=0)), chunk[:rows], str(args))


def test_numpy_and_training_conditioning_agree():
    gen = torch.Generator().manual_seed(3)
    prefix = torch.randn(64, 5, 7, generator=gen)
    cond, mask, d = delay_batch(prefix, 8, 5, gen)
    assert cond.shape == (64, conditioning_dim(5)) and set(d.tolist()) == set(range(6))
    np.testing.assert_allclose(cond.numpy(), conditioning(d.numpy(), prefix.numpy(), 5))
    np.testing.assert_array_equal(mask.numpy(), np.arange(8)[None] >= d.numpy()[:, None])
    # The flow targets' rows < d are the given prefix, the rest the labels.
    targets = torch.randn(64, 8, 7, generator=gen)
    mixed = with_prefix(targets, prefix, mask)
    for i in range(64):
        k = int(d[i])
        assert torch.equal(mixed[i, :k], prefix[i, :k]) and torch.equal(mixed[i, k:], targets[i, k:])
    with pytest.raises(ValueError, match="0..5"):
        conditioning(np.array([6]), np.zeros((1, 5, 7)), 5)


@pytest.mark.parametrize("kind", ["oft", "flow"])
def test_fine_tuning_starts_as_the_naive_model(kind):
    """Zero weights on the conditioning inputs: whatever d and prefix, the expanded model is the naive one."""
    torch.manual_seed(0)
    naive = build_model(kind, 20, 8, 32, 1)
    extra = conditioning_dim(4)
    delayed = build_model(kind, 20 + extra, 8, 32, 1)
    delayed.load_state_dict(_expand_input(naive.state_dict(), kind, extra))
    x, cond = torch.randn(5, 20), torch.randn(5, extra)
    with torch.no_grad():
        _same_outputs(kind, naive, delayed, x, cond)


def _same_outputs(kind, naive, delayed, x, cond):
    if kind == "oft":
        np.testing.assert_allclose(delayed(torch.cat([x, cond], 1)), naive(x), atol=1e-6)
    else:
        x_t, t = torch.randn(5, 8, 7), torch.rand(5)
        np.testing.assert_allclose(
            delayed.velocity(torch.cat([x, cond], 1), x_t, t), naive.velocity(x, x_t, t), atol=1e-6
        )


def _drive(mode: str, n: int, horizon: int, replan: int, delay: int = -1, ticks: int = 60, log=None, sized=False):
    """Run the protocol core with a stub chunk source; returns [(request tick, tracker's (d, prefix), the commands
    actually executed at ticks t .. t + d - 1)] and the tracker's chunks. ``log`` (an ExecutedLog) is told every
    chunk as the look-ahead tells it, and the commands it names for the 6 ticks before each request are recorded
    in ``log.seen`` beside the ones executed. ``sized``: async chunks of d + d rows, as the variant returns them."""
    core = ExecutorCore(ExecutorConfig(mode=mode, latency_ticks=n, replan_steps=replan))
    tracker = DelayTracker(mode, delay, delay_max=8, replan_steps=replan)
    rng = np.random.default_rng(1)
    seen, commands, pending = [], {}, {}

    class Handlers:
        def ready(self):
            return True

        def request(self, req):
            known = tracker.knows_delay
            d, rows = tracker.context(req.tick)
            chunk = np.round(rng.uniform(-1, 1, (horizon, 7)), 3)
            chunk[:, -1] = rng.choice([-1.0, 1.0])
            if mode == "sync":
                chunk = chunk[d:]
            elif sized and d:
                chunk = chunk[: 2 * d]
            tracker.returned(req.tick, chunk)
            if log is not None:  # (as the policy tells it: lq_ros.policies.learned.chunk_policy)
                if known:
                    log.place(d)
                log.seen.append((req.tick, log.before(req.tick, 6)))
                log.chunk(req.tick, d if known else None, chunk)
            pending[req.request_id] = chunk
            seen.append((req.tick, d, rows))
            return True

        def chunk_due(self, req):
            core.deliver(req.request_id, pending.pop(req.request_id))
            return True

        def failed(self, reason):
            raise AssertionError(reason)

        def command(self, cmd):
            commands[cmd.tick] = cmd.action
            return cmd.tick < ticks

    TickDriver(core, Handlers()).drive()
    done = [(t, d, rows) for t, d, rows in seen if t + d <= max(commands) + 1]
    if log is not None:
        log.commands = commands
    return [(t, d, rows, np.array([commands[k] for k in range(t, t + d)]).reshape(d, 7)) for t, d, rows in done]


@pytest.mark.parametrize(("mode", "n", "horizon", "replan"), [("async", 0, 8, 8), ("async", 2, 10, 5),
                                                               ("async", 3, 8, 8), ("sync", 2, 10, 5),
                                                               ("sync", 4, 8, 8)])  # fmt: skip
def test_tracker_prefix_is_what_the_executor_runs_while_inferring(mode, n, horizon, replan):
    """Told only the protocol, the tracker's d is the latency N and its prefix the commands the executor really
    sends while the policy infers (after the first request, which has nothing to estimate from)."""
    requests = _drive(mode, n, horizon, replan)
    assert len(requests) > 4
    for tick, d, rows, executed in requests[1:]:
        assert d == n, (tick, d)
        np.testing.assert_array_equal(rows, executed)
    # Told the delay, the first request is right too.
    _, d, rows, executed = _drive(mode, n, horizon, replan, delay=n)[0]
    assert d == n
    np.testing.assert_array_equal(rows, executed)


@pytest.mark.parametrize(("n", "horizon"), [(6, 8), (6, 10), (8, 10), (3, 8)])
def test_tracker_finds_the_latency_when_its_chunks_are_shorter_than_2n(n, horizon):
    """Chunks of d + d rows, as the variant returns them, from a first chunk shorter than 2N: that chunk runs out
    before the next lands, so the rest of it is not the latency; the tracker still finds d = N by the third request
    and its prefix is then the arm commands the executor really sends (an underrun's holds included)."""
    requests = _drive("async", n, horizon, horizon, ticks=80, sized=True)
    assert len(requests) > 6
    for tick, d, rows, executed in requests[2:]:
        assert d == n, (tick, d)
        np.testing.assert_array_equal(rows[:, :6], executed[:, :6])


def test_executed_prefixes_stay_in_their_episode(tmp_path):
    eps = _write_synthetic(tmp_path, lengths=(5, 7))
    pre = executed_prefixes([tmp_path], 3)
    assert pre.shape == (12, 3, 7)
    np.testing.assert_array_equal(pre[0], eps[0].action_executed[:3])
    np.testing.assert_array_equal(pre[4], np.repeat(eps[0].action_executed[4:5], 3, axis=0))  # padded, not ep 1
    np.testing.assert_array_equal(pre[5], eps[1].action_executed[:3])


def test_successful_only_keeps_the_frames_of_successful_episodes(tmp_path):
    from dataclasses import replace

    from lq_ros.training.dataset import write_dataset
    from lq_ros.training.train import successful_frames
    from tests.training.test_learned import SPATIAL, _episode

    rng = np.random.default_rng(0)
    ok, failed = _episode(rng, 0, 4), _episode(rng, 1, 3)
    failed = replace(failed, success=np.zeros(3, bool))
    goals = {str(t): [["on", "akita_black_bowl_1", "plate_1"]] for t in range(2)}
    write_dataset(tmp_path, [failed, ok], {"suite": "libero_spatial", "layout": SPATIAL.to_dict(), "goals": goals},
                  {0: "a", 1: "b"})  # fmt: skip
    np.testing.assert_array_equal(successful_frames([tmp_path]), [False] * 3 + [True] * 4)


@pytest.mark.parametrize("kind", ["oft", "flow"])
def test_fine_tune_records_its_config_and_runs_as_delay_variant(tmp_path, kind):
    from lq_ros.core.types import TaskInfo

    data = tmp_path / "data"
    _write_synthetic(data, lengths=(30, 40))
    naive = train(TrainConfig(policy=kind, horizon=6, steps=10, width=32, depth=1, log_every=5), [data], tmp_path)
    cfg = TrainConfig(policy=kind, horizon=6, steps=10, width=32, depth=1, log_every=5, delay_max=4,
                      init_from=f"{kind}_c6_libero_spatial", lr=3e-4, successful_only=True)  # fmt: skip
    meta = train(cfg, [data], tmp_path)
    assert meta["train_config"] == cfg.to_dict() and meta["train_config"]["delay_max"] == 4
    assert meta["train_config"]["successful_only"] is True
    assert meta["delay"]["delay_max"] == 4 and meta["delay"]["init_from"]["name"] == f"{kind}_c6_libero_spatial"
    assert meta["stats"] == naive["stats"]  # the initial checkpoint's normalisation is kept
    assert "delay_max" not in naive["train_config"] and "init_from" not in naive["train_config"]
    path = tmp_path / f"{kind}_c6_delay_libero_spatial.json"
    assert json.loads(path.read_text())["delay"]["delay_max"] == 4
    task = TaskInfo(suite="libero_spatial", task_id=0, name="t", instruction="t",
                    goal=[["on", "akita_black_bowl_1", "plate_1"]], step_budget=220, num_init_states=50)  # fmt: skip
    chunks = []
    for _ in range(2):
        policy = make_policy(kind, weights=str(path), variant="delay", mode="sync", delay=2)
        policy.reset(task, 7)
        chunks.append(policy.infer(_obs(tick=0)))
    assert chunks[0].shape == (4, 7)  # sync: the chunk from row d on
    np.testing.assert_array_equal(chunks[0], chunks[1])
    # Async: d + s rows, s = d by default (inference back to back), the whole chunk with execute=0, else s.
    for execute, rows in ((-1, 4), (0, 6), (1, 3)):
        policy = make_policy(kind, weights=str(path), variant="delay", delay=2, execute=execute)
        policy.reset(task, 7)
        assert policy.infer(_obs(tick=0)).shape == (rows, 7), execute


@pytest.mark.parametrize("kind", ["oft", "flow"])
def test_freeze_base_trains_only_the_conditioning_and_keeps_d0_the_initial_model(tmp_path, kind):
    from lq_ros.core.merge import ActionPrefix
    from lq_ros.core.types import TaskInfo

    data = tmp_path / "data"
    _write_synthetic(data, lengths=(30, 40))
    small = {"policy": kind, "horizon": 6, "width": 32, "depth": 1, "log_every": 5}
    train(TrainConfig(**small, steps=10), [data], tmp_path)
    cfg = TrainConfig(**small, steps=20, delay_max=4, init_from=f"{kind}_c6_libero_spatial", freeze_base=True, lr=1e-2)
    train(cfg, [data], tmp_path)
    naive = torch.load(tmp_path / f"{kind}_c6_libero_spatial.pt")
    tuned = torch.load(tmp_path / f"{kind}_c6_delay_libero_spatial.pt")
    first = "inp.weight" if kind == "oft" else "obs.weight"
    features = naive[first].shape[1]
    for key, value in naive.items():
        if key != first:
            assert torch.equal(tuned[key], value), key
    np.testing.assert_array_equal(tuned[first][:, :features], naive[first])
    assert not tuned[first][:, features + 1 :].eq(0).all()  # the conditioning columns learned something
    np.testing.assert_array_equal(tuned[first][:, features], 0.0)  # the d = 0 slot stays zero
    task = TaskInfo(suite="libero_spatial", task_id=0, name="t", instruction="t",
                    goal=[["on", "akita_black_bowl_1", "plate_1"]], step_budget=220, num_init_states=50)  # fmt: skip
    a = make_policy(kind, weights=str(tmp_path / f"{kind}_c6_libero_spatial.json"))
    b = make_policy(kind, weights=str(tmp_path / f"{kind}_c6_delay_libero_spatial.json"), variant="delay")
    for p in (a, b):
        p.reset(task, 7)
    np.testing.assert_allclose(b.infer(_obs(tick=0)), a.infer(_obs(tick=0)), atol=1e-5)  # d = 0: the naive chunk
    if kind == "flow":  # with an executor prefix (merge rtc) d = 2: conditioned, not the naive chunk
        prefix = ActionPrefix(np.full((3, 7), 0.5), 2, "hard")
        assert not np.allclose(b.infer(_obs(tick=0), prefix)[2:4], a.infer(_obs(tick=0))[2:4])


def test_shipped_naive_chunks_are_unchanged_by_the_variant_code():
    """The naive path is the one it was: same chunk from the default policy as from variant=naive."""
    from lq_ros.sim.libero_env import load_task

    task = load_task("libero_spatial", 0)[0]
    a, b = make_policy("flow"), make_policy("flow", variant="naive")
    a.reset(task, 7)
    b.reset(task, 7)
    np.testing.assert_array_equal(a.infer(_obs(tick=2)), b.infer(_obs(tick=2)))
    assert "variant" not in a.params()


@pytest.mark.sim
def test_dagger_under_latency_collects_executor_driven_episodes(tmp_path):
    from typer.testing import CliRunner

    from lq_ros.cli import app

    out = tmp_path / "d"
    res = CliRunner().invoke(app, ["collect", "--out", str(out), "--tasks", "0", "--inits", "10-11", "--noise", "0",
                                   "--workers", "1", "--latency-ticks", "3", "--modes", "sync",
                                   "--latency-driver", "scripted", "--gripper-noise", "0.2", "--keep-failures",
                                   "--max-steps", "60"])  # fmt: skip
    assert res.exit_code == 0, res.output
    info, cols = read_frames(out)
    episodes = [json.loads(line) for line in (out / "meta" / "episodes.jsonl").read_text().splitlines()]
    assert [(e["mode"], e["latency_ticks"], e["driver"]) for e in episodes] == [("sync", 3, "scripted")] * 2
    assert info["collect_config"]["latency_ticks"] == [3] and info["collect_config"]["gripper_noise"] == 0.2
    first = cols["episode_index"] == 0
    executed = cols["action.executed"][first]
    # Sync at N = 3: the robot starts held (zero arm delta) for the first inference's 3 ticks.
    np.testing.assert_array_equal(executed[:3, :6], 0.0)
    # Noise 0 on the arm: the executed arm commands are the driver's, not the labels; the gripper was perturbed.
    assert not np.array_equal(executed[:, :6], cols["action"][first][:, :6])
    assert (cols["action.executed"][:, 6] != cols["action"][:, 6]).any()


@pytest.mark.parametrize("name", ["flow", "oft"])
@pytest.mark.sim
def test_real_delay_aware_episode_succeeds_async_at_0_1_s(tmp_path, name):
    """LIBERO-Object task 7 init 0, async at 0.1 s, variant=delay on the shipped weights: a success (the latency
    study, docs/design/learned_policies.md, recorded 114 ticks for flow and 108 for oft on its machine)."""
    from lq_ros.core.run_config import RunConfig
    from lq_ros.transport.inprocess import run_inprocess

    replan = {"flow": 5, "oft": 8}[name]
    cfg = RunConfig(suite="libero_object", task=7, init=0, seed=7, mode="async", latency_s=0.1, merge="replace",
                    policy=name, policy_args={"variant": "delay"}, replan_steps=replan)  # fmt: skip
    outcome = run_inprocess(cfg, tmp_path)
    assert outcome.status == "success", (outcome.ticks, outcome.reason)
