"""The two execution protocols of LIBERO-LQ (paper section 3.2) as one tick-driven core.

The core knows nothing of transports. A transport (the ROS executor node or the in-process runner)
drives each control tick ``m`` by calling :meth:`ExecutorCore.advance` until it returns the tick's
:class:`Command`; every other answer says what the tick needs first:

- :class:`ChunkDue`: the chunk requested at tick ``m - N`` (N = latency ticks) takes effect now; the
  transport waits for it (wall clock) and hands it to :meth:`ExecutorCore.deliver`;
- :class:`ObservationNeeded`: inference starts on the observation of tick ``m``; the transport
  captures that observation and gives it to the policy (with N = 0 its chunk is due at once, so the
  next answer is a ``ChunkDue``);
- :class:`Failed`: the episode must end as an error (the reason is given).

Because a chunk requested at tick n is applied exactly at tick n + N whatever its wall-clock
inference time, results never depend on the measured latency (lockstep determinism). With a latency
distribution (lq_ros/core/latency.py) each request draws its own N from (the episode's latency stream, request id).

**One inference in flight.** A request is made only when no other is outstanding, as with a policy server
that answers one request at a time (openpi, LeRobot's and OpenVLA's servers, this stack's policy node).
Consequences: chunks can never arrive out of order (request k + 1 starts after chunk k took effect, so its
due tick is later whatever the draws); a long draw delays every later request (the buffer may run dry:
underrun ticks); and the old plan can overlap a new chunk only when H > 2N (a chunk of H rows lands with
H - N fresh ones, and the next one needs N more ticks), whatever the request threshold.

Every transport runs the same loop around the core, :class:`TickDriver`: ask about the current tick, hand
the answer to the transport's :class:`TickHandlers`, go on until a handler waits for something. Only what
"now" and "waiting" mean differs (a function call in process, a message through ROS, a wall-clock deadline
in real time).

What a command means (relative steps or absolute EE poses), its bounds and the hold are the episode's control mode
(lq_ros/core/control.py), given by the simulator before tick 0 (:meth:`ExecutorCore.start`).

An anchored chunk (lq_ros/core/relative_actions.py: a LeRobot checkpoint's relative actions) holds rows that are made
absolute with the state of the tick that executes each, as ``lerobot-eval`` does: before such a row's command the
core answers :class:`StateNeeded`, and the transport hands it that tick's state (:meth:`ExecutorCore.observe_state`).

The async merge strategies are in lq_ros/core/merge.py; ``rtc``/``rtc_hard`` also hand the policy the executing
prefix with the request (:attr:`Request.prefix`).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from enum import IntEnum, StrEnum
from typing import Protocol

import numpy as np

from lq_ros.core.control import ControlMode, ControlStart, action_bounds, bounds_text, hold_action
from lq_ros.core.latency import LatencyDist, applied_seconds, request_latency
from lq_ros.core.merge import (
    ENSEMBLE_COEFF,
    NEEDS_OVERLAP,
    PREFIX_SCHEDULE,
    PREFIX_STRATEGIES,
    ActionPrefix,
    Merge,
    Planned,
    apply_chunk,
    default_threshold,
)
from lq_ros.core.relative_actions import ANCHORED_COLUMNS, anchor_problem, is_anchored, resolve, split_chunk
from lq_ros.core.suite_constants import ACTION_DIM, DUMMY_ACTION


class Mode(StrEnum):
    SYNC = "sync"  # hold while inferring (stop-and-go)
    ASYNC = "async"  # keep consuming a buffer while the next chunk is computed


class Hold(StrEnum):
    STOP = "stop"  # zero arm delta, last gripper command (absolute control: the last target, as REPEAT)
    REPEAT = "repeat"  # repeat the last applied action


class Source(IntEnum):
    """Where a command came from; values equal the ActionCommand.SOURCE_* constants."""

    CHUNK = 0
    HOLD_INFERENCE = 1  # sync: waiting for the requested chunk
    HOLD_STARTUP = 2  # async: no chunk received yet
    HOLD_UNDERRUN = 3  # async: buffer ran dry
    HOLD_REJECTED = 4  # the last chunk was rejected as malformed


@dataclass(frozen=True)
class ExecutorConfig:
    mode: Mode = Mode.SYNC
    #: N = round(dt_sim / dt_c): ticks an inference occupies in sim time. With ``latency`` given this is
    #: set to its nominal N (the expected applied N rounded up), which the default thresholds use.
    latency_ticks: int = 0
    #: sync: actions of each chunk executed before the next inference is requested.
    replan_steps: int = 5
    hold: Hold = Hold.STOP
    #: async: request the next chunk when at most this many actions remain buffered
    #: (None: the merge strategy's default, lq_ros.core.merge.default_threshold; replace: N).
    request_threshold: int | None = None
    #: async: actions of slack added to the threshold (request at N + K with replace). With K = 0 a chunk
    #: of ``replace`` lands exactly as the buffer empties in lockstep: the best case, where any real-time
    #: jitter is an underrun. K > 0 absorbs up to K ticks of lateness at the price of K replanned actions.
    request_slack: int = 0
    merge: Merge = Merge.REPLACE
    #: async, merge=temporal_ensemble: ACT's m in w_i = exp(-m i).
    ensemble_coeff: float = ENSEMBLE_COEFF
    #: The latency distribution each request draws its N from (None: the constant ``latency_ticks``).
    latency: LatencyDist | None = None
    #: The episode's latency stream (lq_ros.core.latency.latency_stream): request k's draw is seeded by (stream, k).
    latency_stream: tuple[int, ...] = (0,)
    #: Consecutive rejected chunks after which the episode ends as an error.
    max_consecutive_rejections: int = 3

    def __post_init__(self) -> None:
        object.__setattr__(self, "mode", Mode(self.mode))
        object.__setattr__(self, "hold", Hold(self.hold))
        try:
            object.__setattr__(self, "merge", Merge(self.merge))
        except ValueError:
            raise ValueError(f"unknown merge {self.merge!r}; known: {', '.join(m.value for m in Merge)}") from None
        if self.latency is not None:
            object.__setattr__(self, "latency_ticks", self.latency.nominal_ticks())
        if self.latency_ticks < 0:
            raise ValueError(f"latency_ticks must be >= 0, got {self.latency_ticks}")
        if self.replan_steps < 1:
            raise ValueError(f"replan_steps must be >= 1, got {self.replan_steps}")
        if self.request_threshold is not None and self.request_threshold < 0:
            raise ValueError(f"request_threshold must be >= 0, got {self.request_threshold}")
        if self.request_slack < 0:
            raise ValueError(f"request_slack must be >= 0 actions, got {self.request_slack}")
        if self.request_slack and self.mode is not Mode.ASYNC:
            raise ValueError("request_slack applies to the async protocol only (sync requests when a chunk is done)")
        if not self.ensemble_coeff >= 0.0:
            raise ValueError(f"ensemble_coeff must be >= 0, got {self.ensemble_coeff}")
        if self.merge is not Merge.REPLACE and self.mode is not Mode.ASYNC:
            raise ValueError(f"merge {self.merge.value!r} applies to the async protocol only; use merge 'replace'")
        same_as = NEEDS_OVERLAP.get(self.merge)
        explicit = None if self.request_threshold is None else self.request_threshold + self.request_slack
        if same_as is not None and explicit is not None and explicit <= self.min_ticks:
            # The buffered rest of the old plan overlaps the new chunk only if more than N actions were
            # left when it was requested; otherwise the buffer is empty when it lands.
            n = f"N={self.min_ticks}"
            if self.latency is not None and self.latency.kind != "constant":
                n = f"the smallest N={self.min_ticks} of {self.latency.text}"
            raise ValueError(
                f"merge {self.merge.value!r} never sees overlapping chunks with request_threshold + request_slack "
                f"{explicit} <= latency ticks {n} (the buffer is empty when the next chunk lands: "
                f"identical to {same_as.value!r}); set request_threshold > {self.min_ticks}, leave it at the "
                f"strategy's default (-1), or use merge {same_as.value!r}"
            )

    @property
    def min_ticks(self) -> int:
        """The smallest N a request can draw."""
        return self.latency_ticks if self.latency is None else self.latency.min_ticks()

    def threshold(self, horizon: int | None = None) -> int:
        """Request threshold (actions left): the run's, else the strategy's default for chunks of ``horizon``,
        plus the request slack."""
        if self.request_threshold is not None:
            return self.request_threshold + self.request_slack
        return default_threshold(self.merge, self.latency_ticks, horizon) + self.request_slack

    def request_latency(self, request_id: int) -> tuple[int, float]:
        """(N, applied Δt_sim s) of request ``request_id`` (lq_ros.core.latency.request_latency)."""
        if self.latency is None:
            return self.latency_ticks, applied_seconds(self.latency_ticks)
        return request_latency(self.latency, self.latency_stream, request_id)


@dataclass(frozen=True)
class Request:
    request_id: int  # 1, 2, ... (0 means "none" on the wire)
    tick: int  # tick of the observation inference runs on
    due_tick: int  # tick at which the chunk is applied: tick + N
    #: Applied Δt_sim of this inference, seconds (N dt_c; recorded as ActionChunk.injected_latency_s).
    latency_s: float = 0.0
    #: merge rtc/rtc_hard: the executing prefix the policy inpaints its chunk against (None otherwise).
    prefix: ActionPrefix | None = field(default=None, compare=False)

    @property
    def latency_ticks(self) -> int:
        return self.due_tick - self.tick


@dataclass(frozen=True)
class Command:
    tick: int
    action: np.ndarray  # (7,)
    source: Source
    request_id: int = 0
    chunk_index: int = 0


@dataclass(frozen=True)
class ChunkDue:
    """The chunk of ``request`` takes effect at this tick: deliver it before anything else."""

    request: Request


@dataclass(frozen=True)
class ObservationNeeded:
    """Inference starts on this tick's observation (the chunk is due at ``request.due_tick``)."""

    request: Request


@dataclass(frozen=True)
class StateNeeded:
    """This tick executes a row of an anchored chunk: hand the core the tick's anchor state
    (:meth:`ExecutorCore.observe_state`) before its command."""

    tick: int


@dataclass(frozen=True)
class Failed:
    """The episode ends as an error."""

    reason: str


#: What :meth:`ExecutorCore.advance` answers.
TickStep = ChunkDue | ObservationNeeded | StateNeeded | Failed | Command


@dataclass
class ExecutorStats:
    inferences: int = 0
    chunks_applied: int = 0
    chunks_rejected: int = 0
    hold_ticks: int = 0  # every held tick, whatever the reason
    underrun_ticks: int = 0  # async: buffer ran dry after the first chunk
    stale_actions_dropped: int = 0
    source_ticks: dict[str, int] = field(default_factory=dict)


def validate_chunk(
    chunk: object, action_dim: int = ACTION_DIM, control_mode: ControlMode = ControlMode.RELATIVE
) -> str | None:
    """Reason why ``chunk`` must not reach the robot, or None when it is a well-formed (H, D) chunk within the
    bounds of ``control_mode`` (lq_ros.core.control.action_bounds), or a well-formed anchored (H, 2 D) chunk
    (lq_ros.core.relative_actions.anchor_problem)."""
    try:
        arr = np.asarray(chunk, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        return f"not a numeric array: {exc}"
    anchored = action_dim == ACTION_DIM and arr.ndim == 2 and arr.shape[1] == ANCHORED_COLUMNS
    if arr.ndim != 2 or arr.shape[0] < 1 or (arr.shape[1] != action_dim and not anchored):
        return f"shape {arr.shape}, expected (H>=1, {action_dim}) (anchored relative actions: (H>=1, {2 * action_dim}))"
    if not np.all(np.isfinite(arr)):
        bad = np.argwhere(~np.isfinite(arr))[0]
        return f"non-finite value {arr[tuple(bad)]} at row {bad[0]}, column {bad[1]}"
    if anchored:
        return anchor_problem(arr, control_mode)
    low, high = action_bounds(control_mode)
    outside = (arr < low) | (arr > high)
    if outside.any():
        bad = np.argwhere(outside)[0]
        return (
            f"value {arr[tuple(bad)]:.6g} at row {bad[0]}, column {bad[1]} outside the action bounds "
            f"{bounds_text(control_mode)}"
        )
    return None


class ExecutorCore:
    """Synchronous hold or asynchronous buffer, one command per tick. See the module docstring."""

    def __init__(self, config: ExecutorConfig) -> None:
        self.config = config
        self.stats = ExecutorStats()
        #: Set when the episode must end as an error (reason).
        self.error: str | None = None
        self._warnings: list[str] = []
        self._warned_no_fresh = False
        self._warned_no_overlap = False
        self._next_request_id = 1
        self._outstanding: Request | None = None
        self._control = ControlStart()
        self._last_action = np.asarray(DUMMY_ACTION, dtype=np.float64)
        self._last_rejected = False
        self._consecutive_rejections = 0
        # sync: the chunk being executed and how far we are in it
        self._chunk: np.ndarray | None = None
        self._chunk_id = 0
        self._chunk_pos = 0
        # async: the plan, one step per coming tick (lq_ros.core.merge.Planned)
        self._buffer: deque[Planned] = deque()
        self._received_any = False
        #: Rows of the last chunk applied (the strategies' default thresholds are relative to it).
        self._horizon: int | None = None
        #: Last tick whose inference decision was taken (once per tick).
        self._planned_tick: int | None = None
        #: Anchor weights of the episode's chunks (None: plain chunks); fixed by the first chunk applied.
        self._weights: np.ndarray | None = None
        #: The anchor state handed for a tick (observe_state): (tick, state).
        self._state: tuple[int, np.ndarray] | None = None

    def start(self, control: ControlStart) -> None:
        """The episode's control mode and the command held before its first chunk (the simulator's, from its
        STARTED event); before tick 0. Without it the episode is relative, held from LIBERO's dummy action."""
        if self._planned_tick is not None:
            raise RuntimeError("the control mode is set before tick 0")
        self._control = control
        self._last_action = np.asarray(control.start_action, dtype=np.float64)

    @property
    def control_mode(self) -> ControlMode:
        return self._control.mode

    def advance(self, tick: int) -> TickStep:
        """The next thing control tick ``tick`` needs; call again until it returns the Command."""
        if self.error is not None:
            return Failed(self.error)
        req = self._outstanding
        if req is not None and req.due_tick == tick:
            return ChunkDue(req)
        if req is not None and req.due_tick < tick:
            raise RuntimeError(f"request {req.request_id} was due at tick {req.due_tick}, now {tick}: not delivered")
        if self._planned_tick != tick:
            # Once per tick, after the due chunk (if any) took effect: does inference start now?
            self._planned_tick = tick
            new = self._start_inference(tick)
            if new is not None:
                return ObservationNeeded(new)
        if self._weights is not None and self._next_is_row() and (self._state is None or self._state[0] != tick):
            return StateNeeded(tick)
        return self._command(tick)

    def observe_state(self, tick: int, state: object) -> None:
        """The anchor state (lq_ros.core.relative_actions.anchor_state) of ``tick``, asked for by StateNeeded."""
        arr = np.asarray(state, dtype=np.float32)
        if arr.ndim != 1 or arr.shape[0] < ACTION_DIM or not np.all(np.isfinite(arr)):
            raise ValueError(f"tick {tick}: anchor state of shape {arr.shape} (finite, at least {ACTION_DIM} values)")
        self._state = (tick, arr)

    def _next_is_row(self) -> bool:
        """Whether the next command comes from a chunk row (not a hold)."""
        if self.config.mode is Mode.SYNC:
            return self._chunk is not None and self._chunk_pos < len(self._chunk)
        return bool(self._buffer)

    def _start_inference(self, tick: int) -> Request | None:
        if self._outstanding is not None:
            return None  # one inference in flight (see the module docstring)
        if self.config.mode is Mode.SYNC:
            need = self._chunk is None or self._chunk_pos >= min(self.config.replan_steps, len(self._chunk))
        else:
            need = len(self._buffer) <= self.config.threshold(self._horizon)
        if not need:
            return None
        if self.config.mode is Mode.SYNC:
            self._chunk = None  # stop-and-go: nothing of the old chunk runs while inferring
        rid = self._next_request_id
        n, latency_s = self.config.request_latency(rid)
        prefix = None
        if self.config.merge in PREFIX_STRATEGIES:
            # The plan for ticks tick, tick + 1, ...: its first d rows execute while the policy infers. A policy
            # cannot know its own latency in advance, so d is the expected N (rounded up), not this draw's n:
            # the same as n for a constant latency; with a distribution the n stale rows are dropped as always.
            plan = np.array([p.action for p in self._buffer]) if self._buffer else np.zeros((0, ACTION_DIM))
            prefix = ActionPrefix(plan, self.config.latency_ticks, PREFIX_SCHEDULE[self.config.merge])
        req = Request(rid, tick, tick + n, latency_s, prefix)
        self._next_request_id += 1
        self._outstanding = req
        self.stats.inferences += 1
        return req

    def deliver(self, request_id: int, chunk: object) -> str | None:
        """Apply the chunk of ``request_id`` at its due tick; returns the rejection reason or None."""
        req = self._outstanding
        if req is None or req.request_id != request_id:
            raise RuntimeError(f"chunk for request {request_id} delivered, outstanding is {req}")
        self._outstanding = None
        reason = validate_chunk(chunk, control_mode=self._control.mode)
        if reason is not None:
            return self._reject(reason)
        arr = np.array(chunk, dtype=np.float64)
        anchored = is_anchored(arr)
        if self._received_any and anchored != (self._weights is not None):
            reason = "a chunk with anchored relative actions after plain ones (or the reverse) in one episode"
        elif anchored and self._weights is not None and not np.array_equal(split_chunk(arr)[1], self._weights):
            reason = "anchor weights differ from those of the episode's earlier chunks"
        if reason is not None:
            return self._reject(reason)
        arr, weights = split_chunk(arr)
        self._weights = weights
        self._last_rejected = False
        self._consecutive_rejections = 0
        self._received_any = True
        self.stats.chunks_applied += 1
        if self.config.mode is Mode.SYNC:
            self._chunk, self._chunk_id, self._chunk_pos = arr, request_id, 0
        else:
            self._merge(arr, req)
        return None

    def _reject(self, reason: str) -> str:
        self.stats.chunks_rejected += 1
        self._last_rejected = True
        self._consecutive_rejections += 1
        if self._consecutive_rejections >= self.config.max_consecutive_rejections:
            self.error = f"{self._consecutive_rejections} consecutive malformed chunks; last: {reason}"
        return reason

    def observed_at(self, request_id: int, tick: int) -> None:
        """Real time only: the policy was given the observation of ``tick``, later than the one requested (the sim had
        passed the requested tick when the request reached it). The chunk's rows are planned from that tick, so its
        stale rows are counted from there. Call before :meth:`deliver`; ValueError for a tick before the request's
        or after the chunk's due tick.
        """
        req = self._outstanding
        if req is None or req.request_id != request_id:
            raise RuntimeError(f"observation of request {request_id} reported, outstanding is {req}")
        if not req.tick <= tick <= req.due_tick:
            raise ValueError(
                f"request {request_id}: observation tick {tick} outside its request tick {req.tick} .. due tick "
                f"{req.due_tick}"
            )
        self._outstanding = Request(req.request_id, tick, req.due_tick, req.latency_s, req.prefix)

    def late(self, tick: int) -> None:
        """Real time only: the chunk due at ``tick`` has not arrived in time; it takes effect at a later tick.

        The tick then holds (sync) or runs on the buffer (async). When the chunk finally arrives, its
        latency ticks are the ones that really passed, so async drops exactly the rows that went stale.
        """
        req = self._outstanding
        if req is None or req.due_tick != tick:
            raise RuntimeError(f"no chunk due at tick {tick} (outstanding: {req})")
        self._outstanding = Request(req.request_id, req.tick, tick + 1, req.latency_s, req.prefix)

    def take_warnings(self) -> list[str]:
        """Protocol warnings since the last call, for the transport to publish (one WARNING event each)."""
        taken, self._warnings = self._warnings, []
        return taken

    def _merge(self, chunk: np.ndarray, req: Request) -> None:
        # Rows 0..N-1 were meant for the ticks that passed while inferring: stale, never executed.
        n = req.latency_ticks
        constant = self.config.latency is None or self.config.latency.kind == "constant"
        if len(chunk) <= n and not self._warned_no_fresh and constant:  # (one long draw is no protocol flaw)
            self._warned_no_fresh = True
            self._warnings.append(
                f"async chunk of {len(chunk)} actions with N={n} latency ticks: every "
                "action is stale on arrival, nothing fresh is executed (use a chunk longer than N)"
            )
        buffer, stale = apply_chunk(
            self.config.merge, self._buffer, chunk, req.request_id, n, self.config.ensemble_coeff
        )
        self.stats.stale_actions_dropped += stale
        self._buffer = deque(buffer)
        self._horizon = len(chunk)
        self._check_overlap_possible(len(chunk))

    def _check_overlap_possible(self, horizon: int) -> None:
        """Warn once when a strategy that needs overlap can never get it with chunks of ``horizon`` rows."""
        if self._warned_no_overlap or self.config.merge not in NEEDS_OVERLAP:
            return
        n_min = self.config.min_ticks
        # At a request at most min(threshold, H - N_prev) actions are buffered; overlap needs more than N.
        if min(self.config.threshold(horizon), horizon - n_min) <= n_min:
            self._warned_no_overlap = True
            self._warnings.append(
                f"merge {self.config.merge.value!r} can never see overlapping chunks: chunks of H={horizon} "
                f"actions with one inference in flight and N >= {n_min} latency ticks leave no old plan when the "
                f"next chunk lands (needs H > 2N); it runs identical to {NEEDS_OVERLAP[self.config.merge].value!r}"
            )

    def _command(self, tick: int) -> Command:
        cmd = self._next_command(tick)
        self._last_action = cmd.action
        name = cmd.source.name.lower()
        self.stats.source_ticks[name] = self.stats.source_ticks.get(name, 0) + 1
        if cmd.source is not Source.CHUNK:
            self.stats.hold_ticks += 1
        if cmd.source is Source.HOLD_UNDERRUN:
            self.stats.underrun_ticks += 1
        return cmd

    def _next_command(self, tick: int) -> Command:
        if self.config.mode is Mode.SYNC:
            if self._chunk is not None and self._chunk_pos < len(self._chunk):
                i = self._chunk_pos
                self._chunk_pos += 1
                return Command(tick, self._executed(self._chunk[i]), Source.CHUNK, self._chunk_id, i)
            source = Source.HOLD_REJECTED if self._last_rejected else Source.HOLD_INFERENCE
        else:
            if self._buffer:
                step = self._buffer.popleft()
                return Command(tick, self._executed(step.action), Source.CHUNK, step.request_id, step.chunk_index)
            if self._last_rejected:
                source = Source.HOLD_REJECTED
            else:
                source = Source.HOLD_UNDERRUN if self._received_any else Source.HOLD_STARTUP
        return Command(tick, self._hold_action(), source)

    def _executed(self, row: np.ndarray) -> np.ndarray:
        """A plan row as the command of its tick: a relative row anchored with the tick's state (StateNeeded)."""
        if self._weights is None:
            return row
        return resolve(row, self._weights, self._state[1], self._control.mode)

    def _hold_action(self) -> np.ndarray:
        if self.config.hold is Hold.REPEAT:
            return self._last_action.copy()
        return hold_action(self._control.mode, self._last_action)


class TickHandlers(Protocol):
    """What a transport does with each answer of the core (:class:`TickDriver`). A handler returns True to go on
    deciding, False to wait (for an observation, a chunk, the sim, the wall clock, or the end of the episode)."""

    def ready(self) -> bool:
        """Whether the driver's tick can be decided now."""

    def request(self, request: Request) -> bool:
        """Inference starts on the observation of ``request.tick``."""

    def chunk_due(self, request: Request) -> bool:
        """The chunk of ``request`` takes effect now: deliver it (:meth:`ExecutorCore.deliver`), or wait for it."""

    def failed(self, reason: str) -> None:
        """The episode ends as an error."""

    def state_needed(self, tick: int) -> bool:
        """Hand the core the anchor state of ``tick`` (:meth:`ExecutorCore.observe_state`; anchored chunks only), or
        wait for it. A transport without one leaves it out: the episode then ends as an error."""

    def command(self, command: Command) -> bool:
        """Send (or apply) the tick's command; after it the driver is at the next tick."""


#: Why an anchored chunk ends an episode on a transport that cannot give the core each tick's state.
NO_STATE = (
    "this transport cannot give the executor each tick's robot state, which anchored relative actions (a LeRobot "
    "checkpoint's use_relative_actions) need: run it in process or on the lockstep clock (a robot and the real-time "
    "clock give none), or pass the policy argument relative_anchor=chunk"
)


class TickDriver:
    """The one loop of every transport around :meth:`ExecutorCore.advance`.

    ``tick`` is the tick being decided (the next one once its command went out). :meth:`drive` asks the core
    about it and hands each answer to the handlers until one of them waits, the tick is not ready, or the core
    failed; a transport calls it again when what it waited for has come.
    """

    def __init__(self, core: ExecutorCore, handlers: TickHandlers, tick: int = 0) -> None:
        self.core = core
        self.handlers = handlers
        self.tick = tick
        self.failed = False

    def drive(self) -> None:
        handlers = self.handlers
        while not self.failed and handlers.ready():
            step = self.core.advance(self.tick)
            if isinstance(step, ObservationNeeded):
                go = handlers.request(step.request)
            elif isinstance(step, ChunkDue):
                go = handlers.chunk_due(step.request)
            elif isinstance(step, StateNeeded):
                state = getattr(handlers, "state_needed", None)
                if state is None:
                    self.failed = True
                    handlers.failed(NO_STATE)
                    return
                go = state(step.tick)
            elif isinstance(step, Failed):
                self.failed = True
                handlers.failed(step.reason)
                return
            else:
                go = handlers.command(step)
                self.tick += 1
            if not go:
                return
