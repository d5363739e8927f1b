"""Chunk-boundary metrics (lq_ros/scoring/chunk_boundary.py) on protocols driven through the executor core and on
hand-made trajectories: switch detection, jumps against the old plan, replay checks, jerk alignment."""

import numpy as np
import pytest

from lq_ros.core.executor_protocol import ChunkDue, Command, ExecutorConfig, ExecutorCore, ObservationNeeded
from lq_ros.core.merge import ENSEMBLE_COEFF
from lq_ros.scoring import chunk_boundary as boundary


def run_core(cfg: ExecutorConfig, ticks: int, make_chunk):
    """Drive the core like a transport; return the recorded chunks and commands as a bag would hold them."""
    core, pending, chunks, cmds = ExecutorCore(cfg), {}, [], []
    for t in range(ticks):
        while True:
            step = core.advance(t)
            if isinstance(step, ObservationNeeded):
                pending[step.request.request_id] = (step.request, make_chunk(step.request))
            elif isinstance(step, ChunkDue):
                req, chunk = pending.pop(step.request.request_id)
                core.deliver(req.request_id, chunk)
                chunks.append(boundary.Chunk(req.request_id, req.tick, req.latency_ticks, chunk))
            else:
                assert isinstance(step, Command)
                cmds.append(step)
                break
    commands = boundary.Commands(
        tick=np.array([c.tick for c in cmds]),
        action=np.array([c.action for c in cmds]),
        source=np.array([int(c.source) for c in cmds]),
        request_id=np.array([c.request_id for c in cmds]),
        chunk_index=np.array([c.chunk_index for c in cmds]),
    )
    return chunks, commands


def ramp_chunk(req, horizon=8, offset=0.1):
    """Row i is meant for tick req.tick + i (value tick / 100); each request is offset by `offset` times its
    parity, so consecutive plans disagree by exactly `offset` on every step."""
    c = np.zeros((horizon, 7))
    c[:, :6] = ((req.tick + np.arange(horizon)) / 100.0 + offset * (req.request_id % 2))[:, None]
    return c


def test_replace_jump_is_the_command_step_when_the_old_plan_ran_out():
    cfg = ExecutorConfig(mode="async", latency_ticks=2)
    chunks, cmds = run_core(cfg, 40, ramp_chunk)
    ticks, jumps, overlapping = boundary.switch_jumps("async", "replace", chunks, cmds)
    # Threshold N = 2: a chunk of 8 lands with 6 fresh rows as the old plan ends: switches every 6 ticks.
    assert ticks.tolist() == [8, 14, 20, 26, 32, 38] and overlapping == 0
    # Old plan exhausted: the jump is against the last executed action, one tick earlier on the ramp and
    # from the other request's offset: 0.01 - 0.1 when the new request id is even, 0.01 + 0.1 when odd.
    new_ids = [int(cmds.request_id[t]) for t in ticks]
    expected = [np.sqrt(6) * abs(0.01 + (0.1 if rid % 2 else -0.1)) for rid in new_ids]
    assert jumps == pytest.approx(expected, rel=1e-9)


@pytest.mark.parametrize("merge", ["latest_only", "weighted_average", "temporal_ensemble"])
def test_jump_against_the_overlapping_old_plan(merge):
    cfg = ExecutorConfig(mode="async", latency_ticks=1, merge=merge)
    chunks, cmds = run_core(cfg, 40, ramp_chunk)
    ticks, jumps, overlapping = boundary.switch_jumps("async", merge, chunks, cmds)
    assert overlapping == len(chunks) - 1 and len(ticks) == len(chunks) - 1
    # The old plan for the switch tick and the new chunk's row differ by the offset (0.1 on 6 dims); the
    # executed command moves a fraction of it: all of it (latest_only), 0.7 (weighted_average), or, for the
    # ensemble, the new chunk's ACT weight share w_c / sum_{i<=c} w_i of the gap to the old ensemble.
    full = 0.1 * np.sqrt(6)
    if merge == "latest_only":
        assert jumps == pytest.approx([full] * len(ticks), rel=1e-9)
    elif merge == "weighted_average":
        assert jumps == pytest.approx([0.7 * full] * len(ticks), rel=1e-9)
    else:
        for t, jump in zip(ticks, jumps, strict=True):
            # Chunks covering tick t, oldest first (fresh rows: from their due tick on).
            cover = [c.actions[t - c.observation_tick, 0] for c in chunks if c.due_tick <= t < c.observation_tick + 8]
            w = np.exp(-ENSEMBLE_COEFF * np.arange(len(cover)))
            old = w[:-1] @ cover[:-1] / w[:-1].sum()
            assert jump == pytest.approx(np.sqrt(6) * abs(w @ cover / w.sum() - old), rel=1e-9)


def test_sync_jump_is_against_the_old_chunks_next_row():
    cfg = ExecutorConfig(mode="sync", latency_ticks=2, replan_steps=3)
    chunks, cmds = run_core(cfg, 30, ramp_chunk)
    ticks, jumps, _ = boundary.switch_jumps("sync", "replace", chunks, cmds)
    # Request at tick 0 lands at 2, rows 0..2 run at 2..4, next request at 5 lands at 7: switches every 5 ticks.
    assert ticks.tolist() == [7, 12, 17, 22, 27]
    # New row 0 is for its observation tick, 5 ticks after the old one's; the old chunk's next row (3) is for
    # old + 3: 0.02 apart on the ramp, plus the offsets' difference.
    new_ids = [int(cmds.request_id[t]) for t in ticks]
    assert jumps == pytest.approx([np.sqrt(6) * abs(0.02 + (0.1 if r % 2 else -0.1)) for r in new_ids], rel=1e-9)


def test_replay_mismatch_is_detected():
    cfg = ExecutorConfig(mode="async", latency_ticks=1, merge="weighted_average")
    chunks, cmds = run_core(cfg, 20, ramp_chunk)
    with pytest.raises(boundary.ReplayMismatch, match="tick"):
        boundary.switch_jumps("async", "replace", chunks, cmds)  # the wrong merge rule
    tampered = boundary.Commands(cmds.tick, cmds.action.copy(), cmds.source, cmds.request_id, cmds.chunk_index)
    tampered.action[12, 0] += 1e-6
    with pytest.raises(boundary.ReplayMismatch, match="tick 12"):
        boundary.switch_jumps("async", "weighted_average", chunks, tampered)
    boundary.switch_jumps("async", "blend", chunks, cmds)  # old bags' name of the same rule


def test_jerk_window_is_centred_on_the_switch_command():
    """A position step at p_{t+1} (the first pose the switch command at tick t moves) has third differences
    1, -2, 1 at k = t+1, t+2, t+3: all inside the ±2-tick window k = t..t+4, none outside."""
    t_switch, dt = 20, 0.05
    pos = np.zeros((60, 3))
    pos[t_switch + 1 :, 0] = 1.0
    near_mean, ratio, why = boundary.jerk_near_switches(pos, np.array([t_switch]), dt)
    assert ratio is None and why == "zero jerk away from the switches"
    assert near_mean == pytest.approx((0 + 1 + 2 + 1 + 0) / 5 / dt**3)
    # The same step ten ticks after the switch is outside every window: the boundary looks smooth.
    far = np.zeros((60, 3))
    far[t_switch + 10 :, 0] = 1.0
    near_mean, ratio, why = boundary.jerk_near_switches(far, np.array([t_switch]), dt)
    assert why is None and near_mean == 0.0 and ratio == 0.0


def test_jerk_ratio_needs_samples_away_from_switches():
    pos = np.random.default_rng(1).normal(size=(40, 3))
    _, ratio, why = boundary.jerk_near_switches(pos, np.arange(2, 40, 4), 0.05, first_chunk_tick=0)
    assert ratio is None and "a switch every 4.0 ticks" in why
    near, ratio, why = boundary.jerk_near_switches(pos, np.array([15, 30]), 0.05, first_chunk_tick=0)
    assert why is None and np.isfinite(ratio) and near > 0
    with pytest.raises(ValueError, match="no chunk switch"):
        boundary.jerk_near_switches(pos, np.array([], dtype=int), 0.05)
