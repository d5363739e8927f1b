"""``lq replay``: re-simulate a recorded lockstep episode from its bag, check it, render it to MP4.

A lockstep episode depends only on its configuration (suite, task, init state, seed) and on the
commands applied at each tick, and the bag records both (``metadata.yaml`` custom_data ``lq_run`` and
``/lq/command``). Replaying those commands through a fresh :class:`~lq_ros.sim.libero_env.LiberoEnv` must give
back the recorded end-effector trajectory (``/ee_pose``) bit for bit on the same machine class; the
first tick where it does not is reported with its size. MuJoCo promises identical results only on
the same architecture (AVX-512 vs not differs, mujoco issue #2659), so a divergence report names the
CPU of both machines.

The video shows what the cameras would have seen, with an information strip under the images: tick,
sim time, where the tick's command came from (chunk, hold, underrun, rejected), chunk switches and
the episode's outcome, plus a timeline of command sources with a cursor.
"""

from __future__ import annotations

import dataclasses
import json
import math
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

import numpy as np
from rosbags.serde import SerdeError

from lq_ros.core.control import ControlMode, ControlStart
from lq_ros.core.cpu import SIMD_FLAGS
from lq_ros.core.executor_protocol import Source, validate_chunk
from lq_ros.core.run_config import TRANSPORTS, cpu_info
from lq_ros.core.safe_write import commit, output_folder, reserve_temporary, write_text
from lq_ros.core.suite_constants import CONTROL_DT_S, FPS
from lq_ros.recording.episode_bag import RUN_METADATA_KEY, read_run_metadata
from lq_ros.wire import messages as m

DEFAULT_CAMERAS = ("agentview", "robot0_eye_in_hand")
DEFAULT_SIZE_PX = 256
#: Transports whose bags are lockstep simulations (anything else, e.g. a robot, cannot be re-simulated): both.
SIMULATED_TRANSPORTS = TRANSPORTS
#: Versions that can change a trajectory; a difference is reported next to any divergence.
RESULT_VERSIONS = ("mujoco", "robosuite", "libero", "numpy")

#: Display name and RGB colour of each command source (overlay, timeline, figures).
SOURCE_STYLE: dict[int, tuple[str, tuple[int, int, int]]] = {
    Source.CHUNK: ("chunk", (44, 160, 44)),
    Source.HOLD_INFERENCE: ("hold (inference)", (255, 159, 28)),
    Source.HOLD_STARTUP: ("hold (startup)", (140, 140, 140)),
    Source.HOLD_UNDERRUN: ("underrun", (214, 39, 40)),
    Source.HOLD_REJECTED: ("rejected", (148, 103, 189)),
}


class ReplayRefused(Exception):
    """The bag cannot be re-simulated; the message is a one-line reason."""


# -- what the bag recorded ------------------------------------------------------------------------


@dataclass(frozen=True)
class RecordedCommand:
    tick: int
    action: np.ndarray  # (7,) as applied
    source: int  # executor Source value
    request_id: int  # chunk it came from (0 when holding)
    chunk_index: int  # row in that chunk


@dataclass(frozen=True)
class ChunkArrival:
    """A chunk taking effect: applied (or rejected) at ``tick``, computed from ``observation_tick``."""

    tick: int
    request_id: int
    observation_tick: int


@dataclass
class Recording:
    """The parts of an episode bag that determine and describe its trajectory."""

    bag: Path
    metadata: dict
    commands: list[RecordedCommand]
    #: tick -> (position (3,) m, quaternion xyzw (4,)) from /ee_pose
    poses: dict[int, tuple[np.ndarray, np.ndarray]]
    arrivals: list[ChunkArrival]
    #: (kind, tick, reason)
    events: list[tuple[int, int, str]]
    damage: list[str] = field(default_factory=list)
    #: The detail of the STARTED event (its control mode among others; {} without one).
    started: dict = field(default_factory=dict)

    @property
    def ticks(self) -> int:
        return len(self.commands)

    def outcome(self) -> tuple[str, int | None, str]:
        """(event name, tick, reason) of the terminal event; ("unknown", None, "") without one."""
        for kind, tick, reason in self.events:
            if kind in m.EventKind.TERMINAL:
                return m.EventKind.NAMES[kind], tick, reason  # success, timeout, error, stopped
        return "unknown", None, ""

    def chunk_switch_ticks(self) -> list[tuple[int, int]]:
        """(tick, request_id) where the executed chunk changes (the first action of a new chunk)."""
        out, current = [], None
        for c in self.commands:
            if c.source == Source.CHUNK and c.request_id != current:
                out.append((c.tick, c.request_id))
                current = c.request_id
        return out


def bag_folder(bag: Path) -> Path:
    """The rosbag2 folder of ``bag`` (a folder, or the .mcap file inside one)."""
    bag = Path(bag)
    return bag.parent if bag.suffix == ".mcap" and bag.exists() and not bag.is_dir() else bag


def read_recording(bag: Path, *, poses: bool = True) -> Recording:
    """Commands, EE poses, chunk arrivals and events of a LIBERO-LQ bag (no simulator needed).

    ``poses=False`` skips /ee_pose (the figures read it with the scorer's bulk decoder instead).
    Raises ReplayRefused when the bag is not a readable rosbag2 MCAP folder.
    """
    from lq_ros.recording.mcap_reader import McapDamage, StreamingMcapReader

    folder = bag_folder(bag)
    files = sorted(folder.glob("*.mcap")) if folder.is_dir() else []
    if not files:
        raise ReplayRefused("no .mcap file (not a rosbag2 MCAP bag folder)")
    try:
        metadata = read_run_metadata(folder) if (folder / "metadata.yaml").exists() else {}
    except (ValueError, OSError) as exc:  # not a rosbag2 metadata file, a directory, unreadable
        raise ReplayRefused(f"unreadable run metadata: {exc}") from None
    wanted = {
        m.COMMAND.name: m.COMMAND.msgtype,
        **({m.EE_POSE.name: m.EE_POSE.msgtype} if poses else {}),
        m.ACTION_CHUNK.name: m.ACTION_CHUNK.msgtype,
        m.EPISODE_EVENTS.name: m.EPISODE_EVENTS.msgtype,
    }
    rec = Recording(folder, metadata, [], {}, [], [])
    for file in files:
        reader = StreamingMcapReader(file, wanted)
        try:
            for batch in reader.batches():
                topic, msgtype = batch.channel.topic, batch.channel.msgtype
                if msgtype != wanted[topic]:
                    raise ReplayRefused(f"{file}: {topic} holds {msgtype or '?'}, expected {wanted[topic]}")
                # At most a few hundred messages per topic: the generic deserializer is fast enough.
                for i in range(len(batch)):
                    try:
                        _collect(rec, topic, m.deserialize(batch.payload(i), msgtype))
                    except (SerdeError, ValueError, struct.error) as exc:  # damage: named, refused by the checks
                        reader.damage.append(f"{file}: undecodable {topic} message ({exc})")
        except McapDamage as exc:
            raise ReplayRefused(str(exc)) from exc
        except OSError as exc:
            raise ReplayRefused(f"{file}: cannot read: {exc}") from exc
        rec.damage += reader.damage
    rec.commands.sort(key=lambda c: c.tick)
    rec.arrivals.sort(key=lambda a: (a.tick, a.request_id))
    rec.events.sort(key=lambda e: e[1])
    return rec


def _collect(rec: Recording, topic: str, msg) -> None:
    if topic == m.COMMAND.name:
        action = np.array(msg.action, dtype=np.float64)
        rec.commands.append(RecordedCommand(int(msg.tick), action, int(msg.source), int(msg.request_id),
                                            int(msg.chunk_index)))  # fmt: skip
    elif topic == m.EE_POSE.name:
        from lq_ros.core.suite_constants import tick_of_sim_time

        p, q = msg.pose.position, msg.pose.orientation
        rec.poses[tick_of_sim_time(m.stamp_ns(msg) / 1e9)] = (np.array([p.x, p.y, p.z]), np.array([q.x, q.y, q.z, q.w]))
    elif topic == m.ACTION_CHUNK.name:
        from lq_ros.core.suite_constants import latency_ticks

        # Applied N ticks after its observation, exactly as the executor did (and as its log time says).
        due = int(msg.observation_tick) + latency_ticks(msg.injected_latency_s)
        rec.arrivals.append(ChunkArrival(due, int(msg.request_id), int(msg.observation_tick)))
    else:
        rec.events.append((int(msg.kind), int(msg.tick), str(msg.reason)))
        if msg.kind == m.EventKind.STARTED and not rec.started:
            try:
                detail = json.loads(msg.detail_json) if msg.detail_json else {}
            except RecursionError:
                raise ValueError("STARTED detail nested too deep") from None
            if not isinstance(detail, dict):
                raise ValueError("STARTED detail is not a JSON object")
            rec.started = detail


@dataclass(frozen=True)
class ReplaySetup:
    """What a replay needs of the run configuration: the commands are recorded, so the protocol's
    parameters only label the video (and a configuration a newer RunConfig would refuse still replays)."""

    suite: str
    task: int
    init: int
    seed: int
    mode: str
    latency_s: float
    #: How the recorded commands are meant (lq_ros.core.control): the simulator's controller is switched alike.
    control_mode: ControlMode = ControlMode.RELATIVE


def check_replayable(rec: Recording) -> ReplaySetup:
    """The setup to re-simulate ``rec`` with; raises ReplayRefused with the reason it cannot be."""
    folder = rec.bag
    if not (folder / "metadata.yaml").exists():
        raise ReplayRefused("no metadata.yaml: a plain MCAP from another tool (or a recorder that died), "
                            "so there is no configuration to re-simulate from")  # fmt: skip
    meta = rec.metadata
    if not meta:
        raise ReplayRefused(f"no LIBERO-LQ run metadata (metadata.yaml custom_data {RUN_METADATA_KEY}): "
                            "not recorded by this stack (e.g. a robot bag)")  # fmt: skip
    transport = meta.get("transport")
    if transport not in SIMULATED_TRANSPORTS:
        raise ReplayRefused(f"transport {transport!r} is not a lockstep simulation "
                            f"(replayable: {', '.join(SIMULATED_TRANSPORTS)})")  # fmt: skip
    if meta.get("lockstep") is not True:
        raise ReplayRefused("recorded in real time (not lockstep): its commands depended on wall-clock timing")
    cfg = meta.get("config") or {}
    try:
        setup = ReplaySetup(str(cfg["suite"]), int(cfg["task"]), int(cfg["init"]), int(cfg["seed"]),
                            str(cfg.get("mode", "?")), float(cfg.get("latency_s", math.nan)))  # fmt: skip
    except (KeyError, TypeError, ValueError) as exc:
        raise ReplayRefused(f"run configuration lacks the task, init state or seed ({exc!r})") from exc
    if rec.damage:
        raise ReplayRefused(f"bag damaged: {rec.damage[0]}")
    try:
        setup = dataclasses.replace(setup, control_mode=ControlStart.from_detail(rec.started).mode)
    except ValueError as exc:
        raise ReplayRefused(str(exc)) from None
    if not rec.commands:
        raise ReplayRefused(f"no commands on {m.COMMAND.name}")
    ticks = [c.tick for c in rec.commands]
    if ticks != list(range(len(ticks))):
        missing = sorted(set(range(max(ticks) + 1)) - set(ticks))
        raise ReplayRefused(f"commands are not one per tick from 0 (missing ticks {missing[:5]}, "
                            f"{len(ticks)} commands)")  # fmt: skip
    if 0 not in rec.poses:
        raise ReplayRefused(f"no {m.EE_POSE.name} at tick 0")
    for c in rec.commands:  # the executor's own check of a chunk, on each recorded command (a one-row chunk)
        problem = validate_chunk(c.action.reshape(1, -1), control_mode=setup.control_mode)
        if problem is not None:
            raise ReplayRefused(f"the command of tick {c.tick} would not reach a robot: {problem}")
    return setup


# -- machines -------------------------------------------------------------------------------------


def format_cpu(cpu) -> str:
    """One line for a CPU entry: a string as is, or a dict with model / class / simd (or flags)."""
    if not cpu:
        return "unknown"
    if not isinstance(cpu, dict):
        return str(cpu)
    simd = cpu.get("simd") or cpu.get("flags") or []
    if isinstance(simd, str):
        simd = simd.split()
    simd = [f for f in simd if f in SIMD_FLAGS]  # a full flag list would drown the ones that matter
    details = "; ".join(x for x in (cpu.get("class"), " ".join(simd)) if x)
    model = cpu.get("model") or "unknown model"
    return f"{model} ({details})" if details else str(model)


@cache
def cpu_here() -> str:
    """This machine's CPU model, class and SIMD flags (lq_ros.core.run_config.cpu_info, as recorded in bags)."""
    return format_cpu(cpu_info())


def cpu_recorded(metadata: dict) -> str:
    """The recording machine's CPU: the run metadata's ``cpu`` entry (or ``versions.cpu``); "unknown" without."""
    return format_cpu(metadata.get("cpu") or (metadata.get("versions") or {}).get("cpu"))


def version_differences(recorded: dict, here: dict) -> list[str]:
    """ "name bag -> here" for each result-relevant version that differs."""
    return [
        f"{k} {recorded.get(k)} (bag) vs {here.get(k)} (here)"
        for k in RESULT_VERSIONS
        if recorded.get(k) is not None and recorded.get(k) != here.get(k)
    ]


# -- replay ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Divergence:
    """First tick where the replayed EE pose differs from the recorded one."""

    tick: int
    position_error_m: float
    angle_error_rad: float


@dataclass
class ReplayResult:
    bag: Path
    ticks: int  # commands applied
    equal: bool  # every EE pose (and the outcome tick) bit-identical
    divergence: Divergence | None
    max_position_error_m: float
    max_error_tick: int
    recorded_outcome: tuple[str, int | None, str]
    #: first tick at which the replayed env reported success (None: never)
    replayed_success_tick: int | None
    cpu_recorded: str
    cpu_here: str
    version_differences: list[str]
    video: Path | None = None
    frames: int = 0
    cameras: tuple[str, ...] = ()

    @property
    def outcome_matches(self) -> bool:
        status, tick, _ = self.recorded_outcome
        if status == "success":
            return self.replayed_success_tick == tick
        return self.replayed_success_tick is None

    def summary(self) -> str:
        """Human-readable verdict, several lines."""
        status, tick, _ = self.recorded_outcome
        outcome = f"{status}" + (f" at tick {tick}" if tick is not None else "")
        lines = []
        if self.equal:
            lines.append(f"replay equals the bag: {self.ticks} ticks, EE pose bit-identical at every tick; "
                         f"outcome {outcome} as recorded")  # fmt: skip
        else:
            d = self.divergence
            if d is not None:
                lines.append(
                    f"replay DIVERGES from the bag at tick {d.tick}: |Δp| = {d.position_error_m:.3g} m, "
                    f"orientation {d.angle_error_rad:.3g} rad; largest |Δp| {self.max_position_error_m:.3g} m at "
                    f"tick {self.max_error_tick}"
                )
            t = self.replayed_success_tick
            replayed = "no success" if t is None else f"success at tick {t}"
            if not self.outcome_matches:
                lines.append(f"outcome differs: recorded {outcome}, replayed {replayed}")
            lines.append(f"CPU of the recording machine: {self.cpu_recorded}; this machine: {self.cpu_here}")
            lines.append("versions: " + ("; ".join(self.version_differences) or "the same as recorded"))
        if self.video is not None:
            lines.append(f"video: {self.video} ({self.frames} frames at {FPS} fps, cameras {', '.join(self.cameras)})")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        d = self.divergence
        return {
            "bag": str(self.bag),
            "ticks": self.ticks,
            "equal": self.equal,
            "divergence": None if d is None else {"tick": d.tick, "position_error_m": d.position_error_m,
                                                  "angle_error_rad": d.angle_error_rad},
            "max_position_error_m": self.max_position_error_m,
            "recorded_outcome": list(self.recorded_outcome),
            "replayed_success_tick": self.replayed_success_tick,
            "cpu_recorded": self.cpu_recorded,
            "cpu_here": self.cpu_here,
            "version_differences": self.version_differences,
            "video": None if self.video is None else str(self.video),
            "frames": self.frames,
        }  # fmt: skip


def _angle_between(q1: np.ndarray, q2: np.ndarray) -> float:
    dot = abs(float(np.dot(q1, q2)) / (np.linalg.norm(q1) * np.linalg.norm(q2)))
    return 2.0 * math.acos(min(1.0, dot))


def replay(
    bag: Path,
    *,
    video: Path | None = None,
    cameras: tuple[str, ...] = DEFAULT_CAMERAS,
    size_px: int = DEFAULT_SIZE_PX,
    env=None,
    on_tick: Callable[[int, int], None] | None = None,
) -> ReplayResult:
    """Re-simulate ``bag``'s commands from its recorded configuration and compare the EE trajectory.

    ``video``: also render ``cameras`` (``size_px`` square each) at every tick into this MP4.
    ``env``: a LiberoEnv of the bag's suite and task to reuse (with those cameras when rendering).
    ``on_tick(done, total)`` reports progress. Raises ReplayRefused when the bag cannot be replayed.
    """
    import mujoco

    rec = read_recording(bag)
    cfg = check_replayable(rec)
    if video is not None and not cameras:
        raise ReplayRefused("a video needs at least one camera")
    try:
        return _replay(rec, cfg, video, cameras, size_px, env, on_tick)
    except mujoco.FatalError as exc:  # e.g. MuJoCo could not allocate its model or data: one line, not a traceback
        raise ReplayRefused(f"MuJoCo failed: {' '.join(str(exc).split())}") from None
    except MemoryError:
        raise ReplayRefused("out of memory while re-simulating") from None


def _replay(rec: Recording, cfg: ReplaySetup, video, cameras, size_px, env, on_tick) -> ReplayResult:
    """The body of :func:`replay` once the bag is known to be replayable."""
    from lq_ros.core.run_config import versions

    own_env = env is None
    if env is None:
        from lq_ros.sim.libero_env import LiberoEnv

        try:
            env = LiberoEnv(cfg.suite, cfg.task, camera_names=tuple(cameras) if video else (), camera_size=size_px)
        except ValueError as exc:
            raise ReplayRefused(f"cannot build the recorded task: {exc}") from exc
    writer = None
    total = rec.ticks
    # Written under a fresh temporary name (never through a link), renamed when complete: a stopped replay leaves
    # no truncated video.
    if video is not None:
        output_folder(Path(video).parent, "video folder")
    partial = reserve_temporary(video) if video is not None else None
    try:
        try:
            state = env.reset(cfg.init, cfg.seed, control_mode=cfg.control_mode)
        except ValueError as exc:  # e.g. an init state this LIBERO package does not have
            raise ReplayRefused(f"cannot reset to the recorded init state: {exc}") from exc
        overlay = Overlay(rec, cfg, len(cameras) * size_px, size_px) if video is not None else None
        divergence: Divergence | None = None
        max_err, max_tick, success_tick = 0.0, 0, None

        def check(tick: int, pos: np.ndarray, quat: np.ndarray) -> None:
            nonlocal divergence, max_err, max_tick
            recorded = rec.poses.get(tick)
            if recorded is None:  # a pose missing from the bag cannot be compared: that is a divergence too
                err, angle = math.inf, math.inf
            elif np.array_equal(recorded[0], pos) and np.array_equal(recorded[1], quat):
                return
            else:
                err, angle = float(np.linalg.norm(recorded[0] - pos)), _angle_between(recorded[1], quat)
            if divergence is None:
                divergence = Divergence(tick, err, angle)
            if err > max_err or max_err == 0.0:
                max_err, max_tick = err, tick

        def frame(tick: int) -> None:
            nonlocal writer
            if overlay is None:
                return
            try:
                images = env.observe(with_images=True).images
            except ValueError as exc:  # robosuite/MuJoCo: no such camera
                raise ReplayRefused(f"cannot render cameras {', '.join(cameras)}: {exc}") from exc
            if writer is None:  # opened once the cameras are known to render
                writer = Mp4Writer(partial, overlay.width, overlay.height)
            writer.write(overlay.compose([images[c] for c in cameras], tick, divergence))

        check(0, state.eef_pos, state.eef_quat_xyzw)
        frame(0)
        for cmd in rec.commands:
            state = env.step(cmd.action)
            check(cmd.tick + 1, state.eef_pos, state.eef_quat_xyzw)
            if state.success and success_tick is None:
                success_tick = cmd.tick + 1
            frame(cmd.tick + 1)
            if on_tick:
                on_tick(cmd.tick + 1, total)
        frames = writer.frames if writer else 0
        if writer is not None:
            writer.close()
            writer = None
            commit(partial, video)
    finally:
        if writer is not None:
            writer.close()
        if partial is not None:
            partial.unlink(missing_ok=True)
        if own_env:
            env.close()
    result = ReplayResult(
        bag=rec.bag,
        ticks=total,
        equal=False,
        divergence=divergence,
        max_position_error_m=max_err,
        max_error_tick=max_tick,
        recorded_outcome=rec.outcome(),
        replayed_success_tick=success_tick,
        cpu_recorded=cpu_recorded(rec.metadata),
        cpu_here=cpu_here(),
        version_differences=version_differences(rec.metadata.get("versions") or {}, versions()),
        video=Path(video) if video is not None else None,
        frames=frames,
        cameras=tuple(cameras) if video is not None else (),
    )
    result.equal = divergence is None and result.outcome_matches
    return result


# -- video ----------------------------------------------------------------------------------------


class Mp4Writer:
    """H.264 MP4 (yuv420p, plays in browsers) through the ffmpeg binary shipped by imageio-ffmpeg."""

    def __init__(self, path: Path, width: int, height: int, fps: int = FPS) -> None:
        import imageio_ffmpeg

        if width % 2 or height % 2:
            raise ValueError(f"H.264 yuv420p needs even frame sizes, got {width}x{height}")
        path.parent.mkdir(parents=True, exist_ok=True)
        self.path, self.size, self.frames = path, (width, height), 0
        self._gen = imageio_ffmpeg.write_frames(
            str(path), (width, height), fps=fps, codec="libx264", pix_fmt_out="yuv420p", quality=7,
            macro_block_size=2, ffmpeg_log_level="error", output_params=["-movflags", "+faststart", "-f", "mp4"],
        )  # fmt: skip
        self._gen.send(None)

    def write(self, frame: np.ndarray) -> None:
        if frame.shape != (self.size[1], self.size[0], 3):
            raise ValueError(f"frame of shape {frame.shape}, writer expects {(self.size[1], self.size[0], 3)}")
        self._gen.send(np.ascontiguousarray(frame, dtype=np.uint8))
        self.frames += 1

    def close(self) -> None:
        self._gen.close()


def read_video(path: Path) -> tuple[dict, list[np.ndarray]]:
    """(ffmpeg metadata, RGB frames) of an MP4 (tests, checks)."""
    import imageio_ffmpeg

    gen = imageio_ffmpeg.read_frames(str(path))
    meta = next(gen)
    w, h = meta["size"]
    frames = [np.frombuffer(raw, dtype=np.uint8).reshape(h, w, 3) for raw in gen]
    return meta, frames


@cache
def _font(size_px: int):
    from matplotlib import font_manager
    from PIL import ImageFont

    path = font_manager.findfont(font_manager.FontProperties(family="DejaVu Sans Mono"))
    return ImageFont.truetype(path, size_px)


class Overlay:
    """Composes video frames: camera tiles side by side, a border in the command source's colour, and an
    information strip (tick, sim time, source, chunk, outcome) with a timeline of sources underneath."""

    TIMELINE_PX = 8
    MIN_WIDTH_PX = 256
    BORDER_PX = 3

    def __init__(self, rec: Recording, cfg: ReplaySetup, tiles_width: int, tile_px: int) -> None:
        self.rec, self.cfg = rec, cfg
        # At least MIN_WIDTH_PX wide so the strip's text fits under small images (tiles stay at the left).
        width = max(tiles_width, self.MIN_WIDTH_PX)
        self.width = width + width % 2  # H.264 yuv420p: even sizes
        self.font_px = 12
        line = self.font_px + 3
        strip = 3 * line + self.TIMELINE_PX + 8
        self.height = tile_px + strip + (tile_px + strip) % 2
        self.tile_px, self.line_px = tile_px, line
        self.commands = {c.tick: c for c in rec.commands}
        self.arrivals = {a.tick: a for a in rec.arrivals}
        self.switches = dict(rec.chunk_switch_ticks())
        self.rejected = {tick for kind, tick, _ in rec.events if kind == m.EventKind.CHUNK_REJECTED}
        self.outcome = rec.outcome()
        self.timeline = self._timeline()

    def _timeline(self) -> np.ndarray:
        """(TIMELINE_PX, width, 3): one colour per tick's command source, black marks at chunk switches."""
        n = max(1, self.rec.ticks)
        bar = np.full((self.TIMELINE_PX, self.width, 3), 40, dtype=np.uint8)
        xs = np.linspace(0, self.width, n + 1).astype(int)
        for c in self.rec.commands:
            bar[:, xs[c.tick] : max(xs[c.tick] + 1, xs[c.tick + 1])] = SOURCE_STYLE.get(c.source, ("?", (255,) * 3))[1]
        for tick in self.switches:
            bar[: self.TIMELINE_PX // 2, xs[tick]] = 0
        self._xs = xs
        return bar

    def compose(self, images: list[np.ndarray], tick: int, divergence: Divergence | None) -> np.ndarray:
        from PIL import Image, ImageDraw

        frame = np.zeros((self.height, self.width, 3), dtype=np.uint8)
        tiles = np.concatenate(images, axis=1)
        frame[: tiles.shape[0], : tiles.shape[1]] = tiles
        cmd = self.commands.get(tick)
        name, colour = SOURCE_STYLE.get(cmd.source, ("?", (255, 255, 255))) if cmd else ("end", (255, 255, 255))
        b = self.BORDER_PX
        for x0 in range(0, tiles.shape[1], self.tile_px):  # a coloured frame around every tile
            tile = frame[: self.tile_px, x0 : x0 + self.tile_px]
            tile[:b], tile[-b:], tile[:, :b], tile[:, -b:] = colour, colour, colour, colour
        strip_y = self.tile_px
        img = Image.fromarray(frame)
        draw = ImageDraw.Draw(img)
        font, lh, x = _font(self.font_px), self.line_px, 4
        t_s = tick * CONTROL_DT_S
        cfg = self.cfg
        draw.text((x, strip_y + 2), f"tick {tick:>3}/{self.rec.ticks}  {t_s:5.2f} s  {cfg.mode} Δt {cfg.latency_s:g} s",
                  font=font, fill=(230, 230, 230))  # fmt: skip
        if cmd is None:
            what = "end of episode"
        elif cmd.source == Source.CHUNK:
            what = f"chunk #{cmd.request_id} row {cmd.chunk_index}"
        else:
            what = name
        note = ""
        if tick in self.rejected:
            note = "  ✗ chunk rejected"
        elif tick in self.switches:
            arrival = self.arrivals.get(tick)
            age = f" (obs t{arrival.observation_tick})" if arrival else ""
            note = f"  ▶ new chunk{age}"
        elif tick in self.arrivals:
            note = f"  chunk #{self.arrivals[tick].request_id} arrived"
        draw.text((x, strip_y + 2 + lh), what, font=font, fill=colour)
        draw.text((x + draw.textlength(what, font=font), strip_y + 2 + lh), note, font=font, fill=(255, 255, 255))
        status, end_tick, _ = self.outcome
        final = cmd is None
        text = f"outcome: {status}" + (f" @ tick {end_tick}" if end_tick is not None else "")
        out_colour = {"success": (80, 220, 80), "timeout": (255, 170, 60)}.get(status, (255, 80, 80))
        draw.text((x, strip_y + 2 + 2 * lh), text.upper() if final else text, font=font,
                  fill=out_colour if final else (170, 170, 170))  # fmt: skip
        if divergence is not None:
            diverged = f"≠ bag since t{divergence.tick}"
            draw.text((self.width - 4 - draw.textlength(diverged, font=font), strip_y + 2 + 2 * lh), diverged,
                      font=font, fill=(255, 60, 60))  # fmt: skip
        frame = np.asarray(img).copy()
        bar = self.timeline.copy()
        cx = min(self._xs[min(tick, len(self._xs) - 1)], self.width - 2)
        bar[:, cx : cx + 2] = 255
        frame[self.height - self.TIMELINE_PX - 2 : self.height - 2] = bar
        return frame


def write_sidecar(result: ReplayResult, path: Path) -> None:
    """The replay verdict as JSON next to its video (the report reads it back instead of replaying)."""
    write_text(path, json.dumps(result.to_dict(), indent=1, sort_keys=True))
