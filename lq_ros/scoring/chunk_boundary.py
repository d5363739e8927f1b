"""Chunk-boundary quality: what happens where execution switches from one action chunk to the next.

Users feel the chunk boundary as a jolt or a vibration when the queue refills (LeRobot #2938, openpi
#393); these metrics measure it from a bag's recorded chunks, commands and end-effector poses.

All action-space distances are Euclidean norms over the six arm dimensions of the 7-D OSC delta action
(position and rotation deltas, action units). The gripper (the last dimension) is left out: it is a
discrete open/close command (±1), so a toggle is a step of 2 whatever the strategy, and it would count
grasp events rather than how chunks are joined.

**Switch.** Tick t is a switch when its command came from a chunk (source CHUNK) whose request id differs
from that of the last earlier chunk command (holds in between allowed; the first chunk command of an
episode is not a switch). With blending strategies the command at t may mix chunks; it is attributed to
the newest one, so the switch is the tick the new chunk lands.

**Overlap end.** With a blending strategy (``weighted_average``, ``average``, ``conservative``,
``temporal_ensemble``) the ticks where a new chunk met the old plan execute a mix of both; the first tick
after them executes the new chunk alone. Tick t is an overlap end when the commands at t - 1 and t are
chunk commands of the same request, the one at t - 1 merged several chunks and the one at t only one (the
replay below knows how many chunks each executed step merged). ``replace``, ``latest_only``, ``rtc``,
``rtc_hard`` and sync never merge, so they have none: their new chunk takes over whole at the switch.

**Executed step at handovers** (``switch_executed_step_mean``, ``_max``; action units): ‖c_t - c_{t-1}‖
of the executed commands (the /lq/command actions, whatever their source) at every *handover* tick: every
switch and every overlap end (a tick that is both counts once). c_{t-1} is the command that ran at the tick
before, a hold included (sync's stop-and-go hold, an async underrun hold). This is the same quantity for
every strategy and protocol: a blend that moves 0.7 of the way at the switch moves the remaining 0.3 at the
overlap end, and both steps are counted. Per episode: the mean and the max over its handover ticks.

**Chunk disagreement** (``chunk_disagreement_mean``, action units): ‖a_t - o_t‖ between the new chunk's
row a_t and the old plan's action o_t for the same tick t (the executor's buffer just before the new chunk
is merged: for ``temporal_ensemble`` the running ensemble), before any merging, over every overlapped tick
that the episode reached (one term per arriving chunk and tick). It says how far the policy's successive
plans disagree where they overlap, whatever the merge does with it; null when no tick overlapped (sync,
``replace`` at its default threshold, every strategy once H <= 2N).

**Jump against the old plan** (``chunk_switch_jump_*``, action units; kept for older tables, not an executed
step): ‖c_t - p_t‖ at the switches only, where c_t is the command executed at the switch and p_t the
command the old plan held for tick t just before the new chunk was merged: the head of the executor's buffer
(async) or the old chunk's next unexecuted row (sync, whose stop-and-go drops it, so p_t never ran). When
the old plan had nothing left for t (async ``replace`` at its default threshold, or after an underrun) p_t is
the last action executed from the old plan. It measures how far the switch departs from the plan it
replaces, so by construction it is w_new ‖a_t - o_t‖ for a pairwise blend (0.7 for ``weighted_average``,
0.3 for ``conservative``) and the rest of the step is taken after the overlap, where it does not look:
compare strategies with the executed step instead.

The plan is reconstructed by replaying the recorded chunks through the run's merge strategy
(lq_ros/core/merge.py, the executor's own code); the replayed commands must equal the recorded ones (to
1e-9), otherwise the metrics are null with the first tick that differs.

**Real time** (``clock: realtime``, the sim on the wall clock or a robot). Nothing waits, so two things
differ from lockstep, and the replay follows what was recorded instead of the nominal schedule:

- *A late chunk* (not there 25 ms into its due tick: lq_ros/transport/ros/wall_clock.py) takes effect at
  the first later tick after it arrived; until then the executor runs on its buffer or holds. Its stale
  rows are the ticks that really passed since its observation. The bag does not say at which tick a chunk
  took effect, but its commands do: it is the first tick at or after the due tick whose command names that
  request (async: its row must be the ticks passed since the observation). A chunk with no fresh row left
  (every row stale) names no tick: it empties the buffer, so it took effect at the first hold recorded
  while the replayed buffer still held actions (or at once when the buffer is empty, where the tick makes
  no difference). A chunk still waiting when the next request was made is a mismatch (one inference in
  flight).
- *A late command* (the real-time sim did not have tick t's command when it stepped t) is a stop hold:
  the sim stepped zero arm delta and the last gripper command (absolute control: the last command), and counts the
  tick as a missed command (the bag's metadata lists the ticks). The executor's replay is unchanged (it sent that
  command), but the executed series that every metric above reads is what the sim applied: a missed tick is a
  hold there. A switch whose first command was missed is the next tick that executed the new chunk; its old plan is the
  one for that tick. A robot applies every command when it arrives: no tick is missed.

In lockstep every chunk takes effect at its due tick and nothing is missed; the replay checks both.

**Jerk near switches** (``chunk_switch_jerk_ratio``): the jerk sample j_k = (p_k - 3p_{k-1} + 3p_{k-2} -
p_{k-3}) / dt³ of the 20 Hz EE positions (p_k after k ticks) is centred at (k - 1.5) dt; the command of
switch tick t acts over [t, t + 1] dt, centred at (t + 0.5) dt. The samples within ±2 ticks of a switch
are those with |k - 2 - t| <= 2, i.e. k = t .. t + 4 (the four whose stencil contains p_{t+1}, the first
pose the new command moves, and one before). The ratio is the mean jerk norm over the samples within
±2 ticks of any switch divided by the mean over all other samples; ``chunk_switch_jerk_mean`` is the
numerator (m/s³). 1 means the boundary is no rougher than the rest of the motion. Samples up to ±2 ticks
after the first chunk command (the arm starts from rest) and before it are in neither population; with
fewer than 5 samples away from every switch (a switch every 5 ticks or less) the ratio is null with the
reason. A robot's EE pose comes at its own rate (e.g. 100 Hz), not one sample per tick: the same windows are
taken in time (:func:`jerk_near_switch_times`): tick t starts at t0 + t dt_c (t0: the STARTED stamp, the
robot's sample expected at tick 0), a jerk sample is near a switch when its centre is within 2 dt_c of the
switch command's centre, and the ratio needs 5 ticks' worth of samples away from every switch.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lq_ros.core.control import ControlStart, hold_action
from lq_ros.core.executor_protocol import Source
from lq_ros.core.merge import ENSEMBLE_COEFF, Merge, apply_chunk
from lq_ros.scoring import metrics

#: Arm dimensions of the 7-D action (OSC position and rotation deltas); the gripper is the last.
ARM_DIMS = slice(0, 6)
#: Jerk samples within this many ticks of a switch count as near it.
SWITCH_WINDOW_TICKS = 2
#: The jerk ratio needs at least this many samples away from every switch.
MIN_ELSEWHERE = 5
#: Recorded and replayed commands may differ by float rounding (e.g. the old ``blend`` rule), no more.
REPLAY_TOL = 1e-9
#: Old bags called weighted_average ``blend`` (the same rule).
_ALIASES = {"blend": Merge.WEIGHTED_AVERAGE}
#: Every row field of this module (lq_ros/scoring/bag_scorer.py nulls them together when the bag cannot be scored).
KEYS = (
    "chunk_switches",
    "chunks_overlapping",
    "chunk_overlap_ends",
    "switch_executed_step_mean",
    "switch_executed_step_max",
    "chunk_disagreement_mean",
    "chunk_switch_jump_mean",
    "chunk_switch_jump_p90",
    "chunk_switch_jump_max",
    "chunk_switch_jerk_mean",
    "chunk_switch_jerk_ratio",
)
#: The fields that follow from the executor's plan alone (the recorded chunks and commands), not from what the
#: robot executed: known even when a real-time bag does not say which commands the sim missed.
PLAN_KEYS = ("chunks_overlapping", "chunk_disagreement_mean")
#: The fields that need at least one switch (null with "no chunk switch" otherwise).
PER_SWITCH_KEYS = (
    "switch_executed_step_mean",
    "switch_executed_step_max",
    "chunk_switch_jump_mean",
    "chunk_switch_jump_p90",
    "chunk_switch_jump_max",
    "chunk_switch_jerk_mean",
    "chunk_switch_jerk_ratio",
)


@dataclass(frozen=True)
class Chunk:
    request_id: int
    observation_tick: int
    latency_ticks: int
    #: None: the policy failed or the chunk was malformed (never executed); the caller validates
    #: (executor.validate_chunk) when it builds the record.
    actions: np.ndarray | None

    @property
    def due_tick(self) -> int:
        return self.observation_tick + self.latency_ticks


@dataclass(frozen=True)
class Commands:
    tick: np.ndarray  # (T,)
    action: np.ndarray  # (T, 7)
    source: np.ndarray  # (T,)
    request_id: np.ndarray  # (T,)
    chunk_index: np.ndarray  # (T,)


class ReplayMismatch(ValueError):
    """The recorded commands do not follow from the recorded chunks under the run's protocol."""


@dataclass(frozen=True)
class Boundaries:
    """Where an episode's chunks hand over and by how much (the module docstring defines each quantity)."""

    #: Ticks whose command came from another request than the last earlier chunk command.
    switch_ticks: np.ndarray
    #: ‖c_t - p_t‖ (arm) against the old plan at each switch tick (``chunk_switch_jump_*``).
    jumps: np.ndarray
    #: Chunks that met a non-empty old plan (async).
    overlapping: int
    #: First ticks executing a single chunk after ticks that executed a merge of several.
    overlap_end_ticks: np.ndarray
    #: Switch and overlap-end ticks, sorted, each once.
    handover_ticks: np.ndarray
    #: ‖c_t - c_{t-1}‖ (arm) of the executed commands at each handover tick.
    executed_steps: np.ndarray
    #: ‖a_t - o_t‖ (arm), new chunk row against the old plan, one per arriving chunk and overlapped tick reached.
    disagreements: np.ndarray
    #: First tick that executed a chunk command (None: none did).
    first_chunk_tick: int | None = None
    #: Request id -> tick at which its chunk took effect (real time: may be after its due tick).
    applied_ticks: dict[int, int] = field(default_factory=dict)


def analyse(
    mode: str,
    merge: str,
    chunks: list[Chunk],
    cmds: Commands,
    ensemble_coeff: float = ENSEMBLE_COEFF,
    *,
    realtime: bool = False,
    missed_ticks: tuple[int, ...] | list[int] = (),
    control: ControlStart | None = None,
) -> Boundaries:
    """The chunk boundaries of an episode (switches, overlap ends, executed steps, disagreement, jumps against
    the old plan) by replaying its chunks through the run's merge strategy; raises ReplayMismatch.

    ``realtime``: chunks may take effect after their due tick (found from the commands, see the module
    docstring); otherwise each takes effect exactly at its due tick. ``missed_ticks``: ticks the real-time sim
    stepped with the stop hold because their command came too late (the executed series holds there), the hold of
    the episode's ``control`` mode (default: relative, held from LIBERO's dummy action).
    """
    control = control or ControlStart()
    order = np.argsort(cmds.tick, kind="stable")
    ticks, actions = cmds.tick[order], cmds.action[order]
    sources, rids, idxs = cmds.source[order], cmds.request_id[order], cmds.chunk_index[order]
    if len(ticks) and not np.array_equal(ticks, np.arange(len(ticks))):
        raise ReplayMismatch("the command ticks are not 0, 1, 2, ... (a gap or a duplicate)")
    strategy = _ALIASES.get(merge) or Merge(merge or "replace")
    valid = {c.request_id: c for c in chunks if c.actions is not None}
    due: dict[int, list[Chunk]] = {}
    for c in sorted(valid.values(), key=lambda c: c.request_id):
        due.setdefault(c.due_tick, []).append(c)
    # Real time: the observation tick of the request after each one (one inference in flight: a chunk has
    # taken effect by then).
    requested = sorted((c.request_id, c.observation_tick) for c in chunks)
    next_request_tick = {rid: nxt for (rid, _), (_, nxt) in zip(requested, requested[1:], strict=False)}
    waiting: list[Chunk] = []  # real time: due but not yet taken by the executor
    applied_ticks: dict[int, int] = {}
    buffer: list = []
    sync_chunk: Chunk | None = None
    # request id -> the old plan it met: async, the buffered actions for its applied tick on; sync, the old
    # chunk's next unexecuted row (None: nothing left).
    old_plans: dict[int, list[np.ndarray] | np.ndarray | None] = {}
    overlapping = 0
    disagreements: list[float] = []
    votes = [1] * len(ticks)  # chunks merged into each tick's executed command (1: one chunk, or a hold)
    last_row: tuple[int, int] | None = None  # (request id, row) of the last chunk command before tick t
    # (tick, replayed action, request id, row) of every chunk command, compared with the bag at once below
    # (a comparison per tick was two thirds of an episode's scoring time).
    replayed: list[tuple[int, np.ndarray, int, int]] = []
    # Python lists for the per-tick loops: indexing numpy scalars there costs more than the work.
    source_list, rid_list, idx_list = sources.tolist(), rids.tolist(), idxs.tolist()

    def mismatch(reason: str) -> ReplayMismatch:
        """The first replayed command that differs from the bag, else ``reason``."""
        first = _first_mismatch(replayed, actions, rids, idxs)
        if first is not None:
            t, e_rid, e_idx = first
            reason = (
                f"tick {t}: recorded request {rids[t]} row {idxs[t]}, replayed request {e_rid} row {e_idx} "
                f"(merge {strategy.value})"
            )
        return ReplayMismatch(reason)

    def takes_effect(c: Chunk, t: int) -> bool:
        """Real time: whether the waiting chunk ``c`` took effect at tick ``t`` (the module docstring's rule)."""
        if source_list[t] == Source.CHUNK and rid_list[t] == c.request_id:
            return True
        stale = mode != "sync" and len(c.actions) <= t - c.observation_tick
        return stale and (source_list[t] != Source.CHUNK or not buffer)

    for t in range(len(ticks)):
        arriving = due.get(t, [])
        if realtime:
            waiting.extend(arriving)
            arriving = [c for c in waiting if takes_effect(c, t)]
            waiting = [c for c in waiting if c not in arriving]
            late = [c for c in waiting if next_request_tick.get(c.request_id, len(ticks)) <= t]
            if late:
                raise mismatch(
                    f"tick {t}: a request was made while the chunk of request {late[0].request_id} had not taken "
                    "effect (one inference in flight)"
                )
        for c in arriving:
            applied_ticks[c.request_id] = t
            n = t - c.observation_tick  # the ticks that passed (lockstep: the chunk's latency ticks)
            if mode == "sync":
                nxt = None
                if sync_chunk is not None and last_row is not None and last_row[0] == sync_chunk.request_id:
                    row = last_row[1] + 1
                    nxt = sync_chunk.actions[row] if row < len(sync_chunk.actions) else None
                old_plans[c.request_id] = nxt
                sync_chunk = c
            else:
                old_plans[c.request_id] = [step.action for step in buffer]
                overlapping += bool(buffer)
                fresh = np.asarray(c.actions, dtype=np.float64)[min(n, len(c.actions)) :]
                # Old plan row k and fresh row k are for tick t + k; only ticks the episode reached count.
                reached = min(len(buffer), len(fresh), len(ticks) - t)
                disagreements.extend(
                    float(np.linalg.norm(fresh[k][ARM_DIMS] - buffer[k].action[ARM_DIMS])) for k in range(reached)
                )
                buffer, _ = apply_chunk(strategy, buffer, c.actions, c.request_id, n, ensemble_coeff)
        if source_list[t] != Source.CHUNK:
            if mode != "sync" and buffer:
                raise mismatch(f"tick {t}: a hold was recorded while the replayed buffer held actions")
            continue
        last_row = (rid_list[t], idx_list[t])
        if mode == "sync":
            chunk = valid.get(rid_list[t])
            if chunk is None or idx_list[t] >= len(chunk.actions):
                raise mismatch(f"tick {t}: the command names request {rids[t]} row {idxs[t]}, not recorded")
            replayed.append((t, chunk.actions[idx_list[t]], int(rids[t]), int(idxs[t])))
        else:
            if not buffer:
                raise mismatch(f"tick {t}: a chunk command was recorded but the replayed buffer is empty")
            step = buffer.pop(0)
            votes[t] = step.votes
            replayed.append((t, step.action, step.request_id, step.chunk_index))
    if _first_mismatch(replayed, actions, rids, idxs) is not None:
        raise mismatch("")

    # What the robot executed: the recorded commands, with the stop hold at every tick the sim missed.
    executed, exec_sources, exec_rids = actions, source_list, rid_list
    missed = sorted({int(t) for t in missed_ticks if 0 <= t < len(ticks)})
    if missed:
        executed, exec_sources, exec_rids = actions.copy(), list(source_list), list(rid_list)
        for t in missed:
            last = executed[t - 1] if t else np.asarray(control.start_action, dtype=np.float64)
            executed[t] = hold_action(control.mode, last)
            exec_sources[t], exec_rids[t] = int(Source.HOLD_INFERENCE), 0

    def old_plan_for(rid: int, t: int) -> np.ndarray | None:
        """The old plan's action for tick ``t`` when the chunk of ``rid`` took effect (None: none left)."""
        plan = old_plans.get(rid)
        if plan is None or not isinstance(plan, list):
            return plan
        k = t - applied_ticks[rid]  # > 0 only when the sim missed the new chunk's first commands
        return plan[k] if k < len(plan) else None

    switch_ticks, jumps, overlap_ends = [], [], []
    last_rid, last_action = None, None
    for t in range(len(ticks)):
        if exec_sources[t] != Source.CHUNK:
            continue
        if last_rid is not None and exec_rids[t] != last_rid:
            planned = old_plan_for(exec_rids[t], t)
            planned = last_action if planned is None else planned
            switch_ticks.append(t)
            jumps.append(float(np.linalg.norm(executed[t][ARM_DIMS] - planned[ARM_DIMS])))
        elif (
            t > 0
            and exec_sources[t - 1] == Source.CHUNK
            and exec_rids[t - 1] == exec_rids[t]
            and votes[t] == 1
            and votes[t - 1] > 1
        ):
            overlap_ends.append(t)
        last_rid, last_action = exec_rids[t], executed[t]
    handovers = np.array(sorted({*switch_ticks, *overlap_ends}), dtype=np.int64)
    arm = executed[:, ARM_DIMS]
    steps = np.linalg.norm(arm[handovers] - arm[handovers - 1], axis=1) if len(handovers) else np.zeros(0)
    first = next((t for t, src in enumerate(exec_sources) if src == Source.CHUNK), None)
    return Boundaries(
        switch_ticks=np.array(switch_ticks, dtype=np.int64),
        jumps=np.array(jumps),
        overlapping=overlapping,
        overlap_end_ticks=np.array(overlap_ends, dtype=np.int64),
        handover_ticks=handovers,
        executed_steps=steps,
        disagreements=np.array(disagreements),
        first_chunk_tick=first,
        applied_ticks=applied_ticks,
    )


def _first_mismatch(replayed, actions, rids, idxs) -> tuple[int, int, int] | None:
    """(tick, replayed request id, row) of the first replayed chunk command that differs from the bag."""
    if not replayed:
        return None
    ts = np.array([r[0] for r in replayed])
    expected = np.array([r[1] for r in replayed])
    ids = np.array([(r[2], r[3]) for r in replayed])
    bad = (ids[:, 0] != rids[ts]) | (ids[:, 1] != idxs[ts]) | (np.abs(expected - actions[ts]) > REPLAY_TOL).any(axis=1)
    if not bad.any():
        return None
    k = int(np.flatnonzero(bad)[0])
    return int(ts[k]), int(ids[k, 0]), int(ids[k, 1])


def jerk_near_switches(
    pos: np.ndarray, switch_ticks: np.ndarray, dt: float, first_chunk_tick: int = 0
) -> tuple[float, float | None, str | None]:
    """(mean jerk within ±2 ticks of a switch, that / mean jerk elsewhere, why the ratio is None); raises
    ValueError when no sample is near a switch.

    Samples up to ±2 ticks after ``first_chunk_tick`` (the first chunk command: the arm starts moving from
    rest) belong to neither population. The ratio needs at least :data:`MIN_ELSEWHERE` samples more than
    2 ticks from every switch: with a switch every 5 ticks or less the windows cover the whole motion.
    """
    if not len(switch_ticks):
        raise ValueError("no chunk switch")
    j = metrics.jerk_norms(pos, dt)  # j[m] has newest pose k = m + 3
    k = np.arange(len(j)) + 3
    near = np.zeros(len(j), dtype=bool)
    for t in switch_ticks:
        near |= np.abs(k - 2 - t) <= SWITCH_WINDOW_TICKS
    considered = k - 2 - first_chunk_tick > SWITCH_WINDOW_TICKS
    near &= considered
    far = considered & ~near
    if not near.any():
        raise ValueError("no jerk sample within ±2 ticks of a switch")
    near_mean = float(j[near].mean())
    if far.sum() < MIN_ELSEWHERE:
        period = float(np.mean(np.diff(switch_ticks))) if len(switch_ticks) > 1 else float("nan")
        why = (
            f"only {int(far.sum())} jerk samples are more than ±{SWITCH_WINDOW_TICKS} ticks from a switch (a switch "
            f"every {period:.1f} ticks): nothing to compare with"
        )
        return near_mean, None, why
    elsewhere = float(j[far].mean())
    if elsewhere <= 0.0:
        return near_mean, None, "zero jerk away from the switches"
    return near_mean, near_mean / elsewhere, None


def jerk_near_switch_times(
    t_s: np.ndarray,
    pos: np.ndarray,
    switch_ticks: np.ndarray,
    t0_s: float,
    tick_s: float,
    first_chunk_tick: int = 0,
) -> tuple[float, float | None, str | None]:
    """:func:`jerk_near_switches` for a pose series at its own uniform rate (a robot's), the windows in time.

    ``t_s``: the samples' stamps (s), uniform; ``t0_s``: when tick 0 starts on that clock; ``tick_s``: the
    control period. Tick t's command is centred at t0 + (t + 0.5) tick_s; a jerk sample (stencil p_k..p_{k-3})
    at t_k - 1.5 dt. Near: within 2 ticks of a switch's centre; considered: more than 2 ticks after the first
    chunk command's centre; the ratio needs 5 ticks' worth of samples elsewhere. On a 20 Hz series stamped on
    the ticks this selects the same samples as :func:`jerk_near_switches`.
    """
    if not len(switch_ticks):
        raise ValueError("no chunk switch")
    t_s = np.asarray(t_s, dtype=np.float64)
    dt = float(np.median(np.diff(t_s)))
    j = metrics.jerk_norms(pos, dt)  # j[m] has newest pose k = m + 3
    centre = t_s[3:] - 1.5 * dt
    window = SWITCH_WINDOW_TICKS * tick_s * (1 + 1e-9)  # (float rounding of the stamps)
    near = np.zeros(len(j), dtype=bool)
    for t in switch_ticks:
        near |= np.abs(centre - (t0_s + (t + 0.5) * tick_s)) <= window
    considered = centre - (t0_s + (first_chunk_tick + 0.5) * tick_s) > window
    near &= considered
    far = considered & ~near
    if not near.any():
        raise ValueError("no jerk sample within ±2 ticks of a switch")
    near_mean = float(j[near].mean())
    needed = MIN_ELSEWHERE * tick_s / dt
    if far.sum() < needed - 1e-9:
        period = float(np.mean(np.diff(switch_ticks))) if len(switch_ticks) > 1 else float("nan")
        why = (
            f"only {int(far.sum())} jerk samples ({far.sum() * dt:.2f} s) are more than ±{SWITCH_WINDOW_TICKS} ticks "
            f"from a switch (a switch every {period:.1f} ticks): nothing to compare with"
        )
        return near_mean, None, why
    elsewhere = float(j[far].mean())
    if elsewhere <= 0.0:
        return near_mean, None, "zero jerk away from the switches"
    return near_mean, near_mean / elsewhere, None
