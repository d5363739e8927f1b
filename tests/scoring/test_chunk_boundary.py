"""Chunk-boundary metrics (lq_ros/scoring/chunk_boundary.py) on protocols driven through the executor core and on
hand-made trajectories: switch detection, jumps against the old plan, replay checks, jerk alignment."""

import numpy as np
import pytest

from lq_ros.core.executor_protocol import ChunkDue, Command, ExecutorConfig, ExecutorCore, ObservationNeeded
from lq_ros.core.merge import ENSEMBLE_COEFF
from lq_ros.scoring import chunk_boundary as boundary


def recorded_commands(cmds: list[Command]) -> boundary.Commands:
    """The executor's commands as the scorer reads them from a bag."""
    return boundary.Commands(
        tick=np.array([c.tick for c in cmds]),
        action=np.array([c.action for c in cmds]),
        source=np.array([int(c.source) for c in cmds]),
        request_id=np.array([c.request_id for c in cmds]),
        chunk_index=np.array([c.chunk_index for c in cmds]),
    )


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
    return chunks, recorded_commands(cmds)


def ramp_chunk(req, horizon=8, offset=0.1):
    """Row i is meant for tick req.tick + i (value tick / 100); each request is offset by `offset` times its
    parity, so consecutive plans disagree by exactly `offset` on every step."""
    c = np.zeros((horizon, 7))
    c[:, :6] = ((req.tick + np.arange(horizon)) / 100.0 + offset * (req.request_id % 2))[:, None]
    return c


def test_replace_jump_is_the_command_step_when_the_old_plan_ran_out():
    cfg = ExecutorConfig(mode="async", latency_ticks=2)
    chunks, cmds = run_core(cfg, 40, ramp_chunk)
    found = boundary.analyse("async", "replace", chunks, cmds)
    ticks, jumps, overlapping = found.switch_ticks, found.jumps, found.overlapping
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
    found = boundary.analyse("async", merge, chunks, cmds)
    ticks, jumps, overlapping = found.switch_ticks, found.jumps, found.overlapping
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
    found = boundary.analyse("sync", "replace", chunks, cmds)
    ticks, jumps = found.switch_ticks, found.jumps
    # Request at tick 0 lands at 2, rows 0..2 run at 2..4, next request at 5 lands at 7: switches every 5 ticks.
    assert ticks.tolist() == [7, 12, 17, 22, 27]
    # New row 0 is for its observation tick, 5 ticks after the old one's; the old chunk's next row (3) is for
    # old + 3: 0.02 apart on the ramp, plus the offsets' difference.
    new_ids = [int(cmds.request_id[t]) for t in ticks]
    assert jumps == pytest.approx([np.sqrt(6) * abs(0.02 + (0.1 if r % 2 else -0.1)) for r in new_ids], rel=1e-9)


def offset_step(rid: int) -> float:
    """ramp_chunk's offset of request ``rid`` minus that of the request before it (0.1 per arm dimension)."""
    return 0.1 if rid % 2 else -0.1


@pytest.mark.parametrize("merge, w_new", [("weighted_average", 0.7), ("average", 0.5), ("conservative", 0.3)])
def test_pairwise_blend_takes_the_rest_of_the_step_where_the_overlap_ends(merge, w_new):
    """N = 1, H = 8, half-chunk threshold 4: a chunk lands every 4 ticks over 3 ticks of the old plan. On the ramp
    the executed command moves 0.01 a tick plus w_new of the offset gap at the switch and the other 1 - w_new at
    the first tick after the overlap; the jump against the old plan sees only the first part."""
    cfg = ExecutorConfig(mode="async", latency_ticks=1, merge=merge)
    chunks, cmds = run_core(cfg, 40, ramp_chunk)
    found = boundary.analyse("async", merge, chunks, cmds)
    switches = found.switch_ticks.tolist()
    assert switches == [5, 9, 13, 17, 21, 25, 29, 33, 37]
    assert found.overlap_end_ticks.tolist() == [t + 3 for t in switches if t + 3 < 40]
    assert found.handover_ticks.tolist() == sorted(switches + found.overlap_end_ticks.tolist())
    step = {}
    for t in switches:
        delta = offset_step(int(cmds.request_id[t]))
        step[t] = np.sqrt(6) * abs(0.01 + w_new * delta)
        if t + 3 < 40:
            step[t + 3] = np.sqrt(6) * abs(0.01 + (1 - w_new) * delta)
    assert found.executed_steps == pytest.approx([step[t] for t in found.handover_ticks], rel=1e-9)
    assert found.jumps == pytest.approx([w_new * 0.1 * np.sqrt(6)] * len(switches), rel=1e-9)
    # Disagreement before merging: the full offset on every overlapped tick, 3 per arrival, all reached.
    assert found.disagreements == pytest.approx([0.1 * np.sqrt(6)] * 3 * len(switches), rel=1e-9)
    # Every overlapped tick executed a blend: the recorded command differs from the row it is attributed to.
    rows = {c.request_id: c.actions for c in chunks}
    executed = [t for t in range(40) if cmds.source[t] == 0]  # chunk commands (the first ticks hold)
    blended = [t for t in executed if not np.allclose(cmds.action[t], rows[cmds.request_id[t]][cmds.chunk_index[t]])]
    assert len(blended) == len(found.disagreements)


@pytest.mark.parametrize("merge", ["latest_only", "rtc"])
def test_new_chunk_taking_over_whole_has_no_overlap_end(merge):
    """latest_only and rtc (the ramp ignores the prefix) execute the new row from the switch on: the whole step
    is taken there, 0.01 plus the full offset gap, though the old plan still overlapped."""
    cfg = ExecutorConfig(mode="async", latency_ticks=1, merge=merge)
    chunks, cmds = run_core(cfg, 40, ramp_chunk)
    found = boundary.analyse("async", merge, chunks, cmds)
    assert len(found.overlap_end_ticks) == 0 and found.handover_ticks.tolist() == found.switch_ticks.tolist()
    expected = [np.sqrt(6) * abs(0.01 + offset_step(int(cmds.request_id[t]))) for t in found.switch_ticks]
    assert found.executed_steps == pytest.approx(expected, rel=1e-9)
    assert found.disagreements == pytest.approx([0.1 * np.sqrt(6)] * 27, rel=1e-9)


def test_replace_without_overlap_steps_equal_the_jumps_and_nothing_disagrees():
    cfg = ExecutorConfig(mode="async", latency_ticks=2)
    chunks, cmds = run_core(cfg, 40, ramp_chunk)
    found = boundary.analyse("async", "replace", chunks, cmds)
    assert len(found.overlap_end_ticks) == 0 and len(found.disagreements) == 0
    assert found.executed_steps == pytest.approx(found.jumps, rel=1e-12)


def ensemble(chunks, tick: int, landed_before: int | None = None) -> np.ndarray | None:
    """ACT's average of the rows for ``tick`` of every chunk covering it (oldest first, w_i = exp(-m i)), over
    the chunks landed by ``tick`` (or before ``landed_before``); None when none covers it."""
    last = tick if landed_before is None else landed_before - 1
    covering = [c for c in chunks if c.due_tick <= last and tick < c.observation_tick + 8]
    cover = [c.actions[tick - c.observation_tick] for c in covering]
    if not cover:
        return None
    w = np.exp(-ENSEMBLE_COEFF * np.arange(len(cover)))
    return w @ np.array(cover) / w.sum()


def test_temporal_ensemble_steps_are_between_consecutive_ensembles():
    """Default threshold H: a chunk lands every tick, every tick is a switch, no tick runs a single chunk."""
    cfg = ExecutorConfig(mode="async", latency_ticks=1, merge="temporal_ensemble")
    chunks, cmds = run_core(cfg, 40, ramp_chunk)
    found = boundary.analyse("async", "temporal_ensemble", chunks, cmds)
    assert found.switch_ticks.tolist() == list(range(2, 40)) and len(found.overlap_end_ticks) == 0
    arm = boundary.ARM_DIMS
    expected = [np.linalg.norm((ensemble(chunks, t) - ensemble(chunks, t - 1))[arm]) for t in range(2, 40)]
    assert found.executed_steps == pytest.approx(expected, rel=1e-9)
    disagree = []
    for c in sorted(chunks, key=lambda c: c.due_tick):
        for tick in range(c.due_tick, min(c.observation_tick + 8, 40)):
            old = ensemble(chunks, tick, landed_before=c.due_tick)
            if old is not None:
                disagree.append(np.linalg.norm((c.actions[tick - c.observation_tick] - old)[arm]))
    assert found.disagreements == pytest.approx(disagree, rel=1e-9)


def test_sync_step_is_from_the_hold_that_ran():
    """Sync holds (arm command 0) while inferring: the executed step at a switch is the new row itself, not its
    distance to the old chunk's discarded next row (the jump)."""
    cfg = ExecutorConfig(mode="sync", latency_ticks=2, replan_steps=3)
    chunks, cmds = run_core(cfg, 30, ramp_chunk)
    found = boundary.analyse("sync", "replace", chunks, cmds)
    ticks = found.switch_ticks.tolist()
    assert ticks == [7, 12, 17, 22, 27] and found.handover_ticks.tolist() == ticks
    assert all(cmds.source[t - 1] != 0 and not cmds.action[t - 1][:6].any() for t in ticks)  # a stop hold ran
    obs_tick = {c.request_id: c.observation_tick for c in chunks}
    rids = [int(cmds.request_id[t]) for t in ticks]
    expected = [np.sqrt(6) * (obs_tick[r] / 100 + 0.1 * (r % 2)) for r in rids]
    assert found.executed_steps == pytest.approx(expected, rel=1e-9)
    assert not np.allclose(found.executed_steps, found.jumps)
    assert len(found.disagreements) == 0 and len(found.overlap_end_ticks) == 0


def test_async_step_after_an_underrun_is_from_the_hold():
    """Threshold 0: the next request is made when the buffer is empty, so N = 2 ticks of underrun hold; the new
    chunk's first fresh row is for its due tick t (value t / 100 plus its offset)."""
    cfg = ExecutorConfig(mode="async", latency_ticks=2, request_threshold=0)
    chunks, cmds = run_core(cfg, 30, ramp_chunk)
    found = boundary.analyse("async", "replace", chunks, cmds)
    assert found.switch_ticks.tolist() == [10, 18, 26]
    assert all(cmds.source[t - 1] == 3 for t in found.switch_ticks)  # HOLD_UNDERRUN
    expected = [np.sqrt(6) * (t / 100 + 0.1 * (cmds.request_id[t] % 2)) for t in found.switch_ticks]
    assert found.executed_steps == pytest.approx(expected, rel=1e-9)


def test_replay_mismatch_is_detected():
    cfg = ExecutorConfig(mode="async", latency_ticks=1, merge="weighted_average")
    chunks, cmds = run_core(cfg, 20, ramp_chunk)
    with pytest.raises(boundary.ReplayMismatch, match="tick"):
        boundary.analyse("async", "replace", chunks, cmds)  # the wrong merge rule
    tampered = boundary.Commands(cmds.tick, cmds.action.copy(), cmds.source, cmds.request_id, cmds.chunk_index)
    tampered.action[12, 0] += 1e-6
    with pytest.raises(boundary.ReplayMismatch, match="tick 12"):
        boundary.analyse("async", "weighted_average", chunks, tampered)
    boundary.analyse("async", "blend", chunks, cmds)  # old bags' name of the same rule


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


# -- real episodes: the scorer's fields against a direct recomputation from the bag's /lq/command messages ------


@pytest.fixture(scope="module")
def env(spatial_env):
    return spatial_env


def bag_commands_and_rows(bag):
    """(ticks' commands as (action, source, request id, row), request id -> chunk rows) read with rosbags."""
    from lq_ros.recording.bag_compare import bag_messages
    from lq_ros.wire import messages as m

    msgs = bag_messages(bag)
    cmds = [m.deserialize(raw, m.COMMAND.msgtype) for _, raw in msgs[m.COMMAND.name]]
    cmds.sort(key=lambda c: c.tick)
    assert [c.tick for c in cmds] == list(range(len(cmds)))
    chunks = [m.deserialize(raw, m.ACTION_CHUNK.msgtype) for _, raw in msgs[m.ACTION_CHUNK.name]]
    rows = {c.request_id: m.chunk_actions(c) for c in chunks}
    return [(np.asarray(c.action), int(c.source), int(c.request_id), int(c.chunk_index)) for c in cmds], rows


@pytest.mark.parametrize(
    "mode, merge, latency_s",
    [("sync", "replace", 0.1), ("async", "weighted_average", 0.05)],
)
@pytest.mark.sim
def test_real_episode_fields_equal_a_recomputation_from_the_commands(tmp_path, env, mode, merge, latency_s):
    """The scripted expert (chunks of 8, closed loop: successive chunks disagree a little) for 60 ticks. Switches:
    a chunk command of another request than the last one; overlap ends (weighted_average, N = 1: each tick is
    overlapped by at most two chunks): the first command equal to its own chunk row after one that is a blend;
    the disagreement of a blended tick is ‖a - c‖ / 0.3 since c = 0.3 o + 0.7 a."""
    from lq_ros.core.run_config import RunConfig
    from lq_ros.scoring.bag_scorer import score_bag
    from lq_ros.transport.inprocess import run_inprocess

    cfg = RunConfig(policy="scripted", mode=mode, merge=merge, latency_s=latency_s, max_steps=60)
    outcome = run_inprocess(cfg, tmp_path, env=env)
    row = score_bag(outcome.bag_path)
    cmds, rows = bag_commands_and_rows(outcome.bag_path)
    arm = boundary.ARM_DIMS

    def pure(t: int) -> bool:
        action, source, rid, idx = cmds[t]
        return source == 0 and np.array_equal(action, rows[rid][idx])

    switches, ends, last_rid = [], [], None
    for t, (_, source, rid, _) in enumerate(cmds):
        if source != 0:
            continue
        if last_rid is not None and rid != last_rid:
            switches.append(t)
        elif t > 0 and cmds[t - 1][1] == 0 and cmds[t - 1][2] == rid and pure(t) and not pure(t - 1):
            ends.append(t)
        last_rid = rid
    steps = [np.linalg.norm(cmds[t][0][arm] - cmds[t - 1][0][arm]) for t in sorted(switches + ends)]
    assert len(switches) >= 5 and row["chunk_switches"] == len(switches)
    assert row["chunk_overlap_ends"] == len(ends)
    assert row["switch_executed_step_mean"] == pytest.approx(np.mean(steps), rel=1e-9)
    assert row["switch_executed_step_max"] == pytest.approx(np.max(steps), rel=1e-9)
    blended = [t for t in range(len(cmds)) if cmds[t][1] == 0 and not pure(t)]
    if mode == "sync":
        assert not ends and not blended and row["chunk_disagreement_mean"] is None
        assert all(cmds[t - 1][1] == 1 for t in switches)  # the step is from the hold that ran (HOLD_INFERENCE)
    else:
        assert len(ends) >= 5 and row["chunks_overlapping"] == len(switches)
        gaps = [np.linalg.norm(rows[cmds[t][2]][cmds[t][3]][arm] - cmds[t][0][arm]) / 0.3 for t in blended]
        # 3 overlapped ticks per arrival (the last arrival's may be cut by the episode's end), each a real blend.
        assert 3 * len(ends) <= len(blended) <= 3 * len(switches) and min(gaps) > 0
        assert row["chunk_disagreement_mean"] == pytest.approx(np.mean(gaps), rel=1e-6)


# -- real time: late chunks and missed commands, driven through the core as the wall-clock executor does ---------


def run_core_realtime(cfg: ExecutorConfig, ticks: int, make_chunk, late_by):
    """Drive the core like the wall-clock executor: the chunk of request r arrives ``late_by(r)`` ticks after its
    due tick, and until then each due tick is marked late (the executor's ``core.late``). Chunks are recorded as the
    bag holds them, with their nominal latency; returns (chunks, commands, request id -> tick it took effect)."""
    core, pending, chunks, cmds, applied = ExecutorCore(cfg), {}, [], [], {}
    for t in range(ticks):
        while True:
            step = core.advance(t)
            if isinstance(step, ObservationNeeded):
                req = step.request
                pending[req.request_id] = (req, make_chunk(req), req.due_tick + late_by(req.request_id))
            elif isinstance(step, ChunkDue):
                req, chunk, arrives = pending[step.request.request_id]
                if t < arrives:
                    core.late(t)
                    continue
                del pending[req.request_id]
                core.deliver(req.request_id, chunk)
                chunks.append(boundary.Chunk(req.request_id, req.tick, req.latency_ticks, chunk))
                applied[req.request_id] = t
            else:
                assert isinstance(step, Command), step
                cmds.append(step)
                break
    return chunks, recorded_commands(cmds), applied


def late_pattern(request_id: int) -> int:
    """Ticks late: 0, 1, 3, 0, 2, 1, 0, ... (a mix of on-time and late chunks)."""
    return (0, 1, 3, 0, 2, 1)[request_id % 6]


def as_if_lockstep(chunks, applied):
    """The same chunks recorded with the latency they really had (applied tick - observation tick): in lockstep
    each takes effect at its due tick, so this is what a lockstep replay of the real-time episode must give."""
    return [boundary.Chunk(c.request_id, c.observation_tick, applied[c.request_id] - c.observation_tick, c.actions)
            for c in chunks]  # fmt: skip


def assert_same(a: boundary.Boundaries, b: boundary.Boundaries) -> None:
    for name in ("switch_ticks", "jumps", "overlap_end_ticks", "handover_ticks", "executed_steps", "disagreements"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert a.overlapping == b.overlapping and a.first_chunk_tick == b.first_chunk_tick


@pytest.mark.parametrize(
    "mode, merge, latency_ticks",
    [("async", "replace", 2), ("async", "weighted_average", 1), ("async", "temporal_ensemble", 1),
     ("async", "latest_only", 1), ("sync", "replace", 2)],
)  # fmt: skip
def test_late_chunks_take_effect_where_the_commands_say(mode, merge, latency_ticks):
    """The lockstep replay refuses a real-time stream (a chunk late at its due tick looks like a hold over a full
    buffer, or a switch where none was due); the real-time replay finds every chunk's tick and equals the lockstep
    replay of the same chunks recorded with the latency they really had."""
    cfg = ExecutorConfig(mode=mode, latency_ticks=latency_ticks, merge=merge, replan_steps=3)
    chunks, cmds, applied = run_core_realtime(cfg, 80, ramp_chunk, late_pattern)
    assert any(applied[c.request_id] > c.due_tick for c in chunks)
    found = boundary.analyse(mode, merge, chunks, cmds, realtime=True)
    assert found.applied_ticks == applied
    assert_same(found, boundary.analyse(mode, merge, as_if_lockstep(chunks, applied), cmds))
    # Every chunk with a fresh row switches where it took effect (the first excepted): the late ones too.
    fresh = [c for c in chunks[1:] if len(c.actions) > applied[c.request_id] - c.observation_tick]
    expected = [applied[c.request_id] for c in fresh]
    assert found.switch_ticks.tolist() == expected
    if mode == "async":
        with pytest.raises(boundary.ReplayMismatch, match="tick"):
            boundary.analyse(mode, merge, chunks, cmds)  # the lockstep replay: chunks at their due ticks


def test_realtime_replay_of_an_on_time_stream_equals_the_lockstep_replay():
    cfg = ExecutorConfig(mode="async", latency_ticks=1, merge="weighted_average")
    chunks, cmds = run_core(cfg, 60, ramp_chunk)
    assert_same(
        boundary.analyse("async", "weighted_average", chunks, cmds, realtime=True),
        boundary.analyse("async", "weighted_average", chunks, cmds),
    )


def two_horizons(req):
    """Chunk 1 long (8 rows), chunk 2 short (2 rows), the rest 8: a late chunk 2 has no fresh row left."""
    return ramp_chunk(req, horizon=2 if req.request_id == 2 else 8)


def test_a_late_chunk_with_no_fresh_row_empties_the_buffer_at_the_first_hold():
    """Threshold 6, N = 1: chunk 1 lands at tick 1 with 7 rows; request 2 is made at tick 2 and due at 3, one tick
    late it lands at 4 with both its rows stale: the buffer (rows for 4..7) is dropped and tick 4 holds."""
    cfg = ExecutorConfig(mode="async", latency_ticks=1, request_threshold=6)
    chunks, cmds, applied = run_core_realtime(cfg, 30, two_horizons, lambda rid: 1 if rid == 2 else 0)
    assert applied[2] == 4 and cmds.source[4] == 3  # HOLD_UNDERRUN with actions of chunk 1 still planned
    found = boundary.analyse("async", "replace", chunks, cmds, realtime=True)
    assert found.applied_ticks == applied
    assert_same(found, boundary.analyse("async", "replace", as_if_lockstep(chunks, applied), cmds))
    # A request made while that chunk had not taken effect contradicts one inference in flight.
    tampered = boundary.Commands(cmds.tick, cmds.action.copy(), cmds.source.copy(), cmds.request_id.copy(),
                                 cmds.chunk_index.copy())  # fmt: skip
    tampered.source[4], tampered.request_id[4], tampered.chunk_index[4] = 0, 1, 4  # chunk 1 ran on at tick 4
    tampered.action[4] = chunks[0].actions[4]
    with pytest.raises(boundary.ReplayMismatch, match="request 2 had not taken effect"):
        boundary.analyse("async", "replace", chunks, tampered, realtime=True)


def test_missed_commands_are_stop_holds_in_the_executed_series():
    """N = 1, H = 8, half-chunk threshold: a chunk lands every 4 ticks (5, 9, 13, ...) over 3 ticks of the old plan,
    whose overlap ends 3 ticks later. The sim missed ticks 9 (the first command of a chunk) and 12 (its overlap end).
    The switch moves to 10, its executed step is from the stop hold (arm 0) and its jump is against the old plan for
    tick 10; 12 is a hold, no overlap end, and the switch at 13 steps from that hold."""
    cfg = ExecutorConfig(mode="async", latency_ticks=1, merge="weighted_average")
    chunks, cmds = run_core(cfg, 30, ramp_chunk)
    plain = boundary.analyse("async", "weighted_average", chunks, cmds)
    assert 9 in plain.switch_ticks.tolist()
    rid = int(cmds.request_id[9])
    assert cmds.request_id[10] == rid and cmds.request_id[12] == rid and cmds.source[12] == 0
    found = boundary.analyse("async", "weighted_average", chunks, cmds, realtime=True, missed_ticks=[9, 12, 99])
    assert found.switch_ticks.tolist() == [10 if t == 9 else t for t in plain.switch_ticks.tolist()]
    assert {9, 12, 13} <= set(plain.handover_ticks.tolist())
    handovers = found.handover_ticks.tolist()
    assert 9 not in handovers and 12 not in handovers and {10, 13} <= set(handovers)
    for t in (10, 13):  # from the stop hold: the whole arm command
        assert found.executed_steps[handovers.index(t)] == pytest.approx(np.linalg.norm(cmds.action[t][:6]), rel=1e-12)
    # The old plan for tick 10: the row of the chunk before, one tick after the one that met tick 9.
    old = next(c for c in chunks if c.request_id == rid - 1)
    expected_jump = np.linalg.norm(cmds.action[10][:6] - old.actions[10 - old.observation_tick][:6])
    assert found.jumps[found.switch_ticks.tolist().index(10)] == pytest.approx(expected_jump, rel=1e-12)
    # What the executor planned is not what the sim missed: overlaps and disagreement are unchanged.
    assert found.overlapping == plain.overlapping
    np.testing.assert_array_equal(found.disagreements, plain.disagreements)


def test_missed_commands_hold_the_last_target_in_absolute_control():
    """In absolute control a missed command repeats the last one (the sim's hold): the switch that moves past a missed
    tick steps from the last target, not from a zero that would mean the world origin."""
    from lq_ros.core.control import ControlMode, ControlStart

    cfg = ExecutorConfig(mode="async", latency_ticks=1, merge="weighted_average")
    chunks, cmds = run_core(cfg, 30, ramp_chunk)
    control = ControlStart(ControlMode.ABSOLUTE, (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0))
    found = boundary.analyse(
        "async", "weighted_average", chunks, cmds, realtime=True, missed_ticks=[9, 12], control=control
    )
    handovers = found.handover_ticks.tolist()
    for t, held in ((10, 8), (13, 11)):  # ticks 9 and 12 executed the commands of ticks 8 and 11 again
        expected = np.linalg.norm(cmds.action[t][:6] - cmds.action[held][:6])
        assert found.executed_steps[handovers.index(t)] == pytest.approx(expected, rel=1e-12)
        relative = np.linalg.norm(cmds.action[t][:6])  # what a relative stop hold (a zero) would give
        assert abs(expected - relative) > 0.1


def test_jerk_windows_in_time_select_the_tick_windows_on_a_20_hz_series():
    pos = np.random.default_rng(3).normal(size=(80, 3))
    switches = np.array([12, 30, 51])
    t_s = np.arange(80) * 0.05
    timed = boundary.jerk_near_switch_times(t_s, pos, switches, 0.0, 0.05, 3)
    ticked = boundary.jerk_near_switches(pos, switches, 0.05, 3)
    assert ticked[2] is None and timed[2] is None
    assert timed[:2] == pytest.approx(ticked[:2], rel=1e-12)
    # Switches every 4 ticks: neither has enough samples elsewhere.
    dense = np.arange(4, 80, 4)
    assert boundary.jerk_near_switch_times(t_s, pos, dense, 0.0, 0.05)[1] is None
    assert boundary.jerk_near_switches(pos, dense, 0.05)[1] is None


def test_jerk_windows_in_time_on_a_100_hz_series():
    """A position step between two 100 Hz samples 0.06 s into switch tick 20's command (centre 1.025 s): its jerk
    samples are centred within 0.1 s of it, so all of the step's jerk is near the switch; the same step 0.5 s later
    is all elsewhere."""
    t_s = np.arange(400) * 0.01
    pos = np.zeros((400, 3))
    pos[109:, 0] = 1e-3
    near_mean, ratio, why = boundary.jerk_near_switch_times(t_s, pos, np.array([20]), 0.0, 0.05)
    assert near_mean > 0 and why == "zero jerk away from the switches"
    later = np.zeros((400, 3))
    later[159:, 0] = 1e-3
    near_mean, ratio, why = boundary.jerk_near_switch_times(t_s, later, np.array([20]), 0.0, 0.05)
    assert near_mean == 0.0 and ratio == 0.0 and why is None
