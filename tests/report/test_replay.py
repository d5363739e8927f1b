"""lq replay on real bags: re-simulation equals the recording, divergence is found and located, the video has
one non-blank frame per tick with the overlay, unreplayable bags are refused in one line, report links resolve."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path
from urllib.parse import unquote

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from lq_ros.core.executor_protocol import Source
from lq_ros.recording.episode_bag import RUN_METADATA_KEY, read_run_metadata
from lq_ros.report.replay import (
    SOURCE_STYLE,
    cpu_here,
    cpu_recorded,
    format_cpu,
    read_recording,
    read_video,
    replay,
)
from lq_ros.wire import messages as m

#: Short episodes: enough ticks for holds and several chunk switches in both protocols.
MAX_STEPS = 24


@pytest.fixture(scope="module")
def bags(tmp_path_factory, spatial_env) -> dict[str, Path]:
    """One scripted in-process episode per protocol, both with latency: sync 0.1 s (N=2), async 0.2 s (N=4)."""
    from lq_ros.core.run_config import RunConfig
    from lq_ros.transport.inprocess import run_inprocess

    out = tmp_path_factory.mktemp("replay") / "bags"
    paths = {}
    for mode, latency in (("sync", 0.1), ("async", 0.2)):
        cfg = RunConfig(mode=mode, latency_s=latency, max_steps=MAX_STEPS, policy="scripted")
        outcome = run_inprocess(cfg, out, env=spatial_env)
        assert outcome.status == "failure", outcome  # the budget of 24 ticks ends it: a timeout
        paths[mode] = outcome.bag_path
    return paths


pytestmark = [pytest.mark.slow, pytest.mark.sim]


@pytest.mark.parametrize("mode", ["sync", "async"])
def test_replay_equals_the_recording(bags, mode):
    rec = read_recording(bags[mode])
    sources = {c.source for c in rec.commands}
    hold = Source.HOLD_INFERENCE if mode == "sync" else Source.HOLD_STARTUP
    assert {Source.CHUNK, hold} <= sources  # the protocol really held and executed chunks
    assert len(rec.chunk_switch_ticks()) >= 3
    result = replay(bags[mode])
    assert result.equal, result.summary()
    assert result.divergence is None and result.max_position_error_m == 0.0
    assert result.ticks == MAX_STEPS and len(rec.poses) == MAX_STEPS + 1
    assert result.recorded_outcome[:2] == ("timeout", MAX_STEPS) and result.replayed_success_tick is None
    assert result.summary().startswith(f"replay equals the bag: {MAX_STEPS} ticks")


def _copy_bag(
    src: Path, dst: Path, *, tamper_tick: int | None = None, metadata: dict | None = None, action: list | None = None
) -> Path:
    """Rewrite ``src`` into ``dst`` (rosbags), optionally changing the command of one tick (its z, or the whole
    ``action``) or the run metadata."""
    from rosbags.rosbag2 import Reader, StoragePlugin, Writer

    meta = read_run_metadata(src) if metadata is None else metadata
    writer = Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    with Reader(src) as reader:
        conns = {c.id: writer.add_connection(c.topic, c.msgtype, typestore=m.typestore()) for c in reader.connections}
        for conn, t_ns, raw in reader.messages():
            if conn.topic == m.COMMAND.name and tamper_tick is not None:
                msg = m.deserialize(raw, conn.msgtype)
                if msg.tick == tamper_tick:
                    changed = np.array(msg.action)
                    changed[2] = 0.5 if changed[2] < 0 else -0.5  # a different z command
                    msg.action = changed if action is None else np.array(action, dtype=np.float64)
                    raw = m.serialize(msg, conn.msgtype)
            writer.write(conns[conn.id], t_ns, bytes(raw))
    writer.set_custom_data(RUN_METADATA_KEY, json.dumps(meta, sort_keys=True))
    writer.close()
    return dst


def test_a_changed_command_is_found_at_the_next_tick(bags, tmp_path):
    """The bag says one thing, the re-simulation of its commands another: replay names the first tick and size."""
    meta = read_run_metadata(bags["async"])
    meta.pop("cpu", None)
    meta["versions"].pop("cpu", None)  # a bag from before the cpu entry: the recording CPU is unknown
    tampered = _copy_bag(bags["async"], tmp_path / "tampered", tamper_tick=10, metadata=meta)
    result = replay(tampered)
    assert not result.equal
    assert result.divergence.tick == 11  # the command of tick 10 moves the arm during tick 10
    assert 1e-6 < result.divergence.position_error_m < 0.05
    assert result.max_position_error_m >= result.divergence.position_error_m
    text = result.summary()
    assert "DIVERGES from the bag at tick 11" in text
    model = next(line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                 if line.startswith("model name"))  # fmt: skip
    assert "CPU of the recording machine: unknown" in text and model in text and model in cpu_here()
    run = CliRunner().invoke(_app(), ["replay", str(tampered)])
    assert run.exit_code == 1 and "tick 11" in run.output


def test_cpu_entries_are_named():
    assert cpu_recorded({}) == "unknown"
    cpu = {"model": "AMD EPYC 7B13", "class": "x86_64 AVX2", "simd": ["sse4_2", "avx", "avx2", "fma"]}
    assert cpu_recorded({"versions": {"cpu": cpu}}) == "AMD EPYC 7B13 (x86_64 AVX2; sse4_2 avx avx2 fma)"
    assert cpu_recorded({"cpu": "Graviton3"}) == "Graviton3"
    # A raw flag list is cut down to the SIMD extensions that matter.
    assert format_cpu({"model": "X", "flags": "fpu vme avx2 sse4_2 pse"}) == "X (avx2 sse4_2)"


def test_video_has_a_frame_per_tick_with_the_overlay(bags, tmp_path):
    video = tmp_path / "episode.mp4"
    result = replay(bags["async"], video=video, cameras=("agentview", "robot0_eye_in_hand"), size_px=96)
    assert result.equal, result.summary()  # rendering does not disturb the simulation
    assert result.frames == MAX_STEPS + 1 and not list(tmp_path.glob("*.part"))
    meta, frames = read_video(video)
    assert len(frames) == MAX_STEPS + 1 and meta["fps"] == 20
    height, width, _ = frames[0].shape
    assert width == 256 and height > 96  # two 96 px tiles on the minimum width, the strip under them
    for frame in frames:
        tiles = frame[8:88, 8:184].astype(np.float64)  # inside the coloured borders
        assert tiles.std() > 15 and 20 < tiles.mean() < 235, "blank camera image"
        strip = frame[100:, :]
        assert (strip.max(axis=2) > 150).mean() > 0.01, "no text or timeline in the strip"
    moved = np.abs(frames[-1][:96, :96].astype(int) - frames[0][:96, :96].astype(int)).mean()
    assert moved > 2.0, "the agentview image did not change over the episode"
    # The border shows the tick's command source: startup hold (grey) at tick 0, a chunk (green) at tick 10.
    rec = read_recording(bags["async"])
    assert rec.commands[0].source == Source.HOLD_STARTUP and rec.commands[10].source == Source.CHUNK
    grey, green = (np.array(SOURCE_STYLE[s][1]) for s in (Source.HOLD_STARTUP, Source.CHUNK))
    for tick, colour in ((0, grey), (10, green)):
        border = frames[tick][40:56, 0:2].reshape(-1, 3).mean(axis=0)
        assert np.abs(border - colour).max() < 40, (tick, border, colour)


def test_a_video_replay_of_a_camera_less_bag_is_exact(tmp_path):
    """``lq replay --video`` renders cameras the recording had not, and the replay is bit-identical: on LIBERO-Object
    task 0, while an env without cameras skipped the forward pass a renderer runs, it left this bag at tick 13
    (lq_ros.sim.renderer_passes)."""
    from lq_ros.core.run_config import RunConfig
    from lq_ros.policies import make_policy
    from lq_ros.transport.inprocess import run_inprocess

    ticks = 40
    cfg = RunConfig(mode="async", latency_s=0.2, max_steps=ticks, policy="scripted", suite="libero_object", task=0)
    outcome = run_inprocess(cfg, tmp_path / "bags")
    assert make_policy("scripted").camera_names == (), "the bag is recorded in an env without cameras"
    video = tmp_path / "episode.mp4"
    run = CliRunner().invoke(_app(), ["replay", str(outcome.bag_path), "--video", str(video), "--size", "64"])
    assert run.exit_code == 0, run.output
    assert f"replay equals the bag: {ticks} ticks, EE pose bit-identical at every tick" in run.output
    assert len(read_video(video)[1]) == ticks + 1


def _app():
    from lq_ros.cli import app

    return app


def _with_metadata(src: Path, dst: Path, **changes) -> Path:
    shutil.copytree(src, dst)
    meta_file = dst / "metadata.yaml"
    doc = yaml.safe_load(meta_file.read_text())
    custom = doc["rosbag2_bagfile_information"]["custom_data"]
    run = json.loads(custom[RUN_METADATA_KEY])
    run.update(changes)
    custom[RUN_METADATA_KEY] = json.dumps(run)
    meta_file.write_text(yaml.safe_dump(doc))
    return dst


def test_unreplayable_bags_are_refused_in_one_line(bags, tmp_path):
    src = bags["sync"]
    plain = tmp_path / "plain"
    plain.mkdir()
    shutil.copy(next(src.glob("*.mcap")), plain)
    cases = {
        plain: "no metadata.yaml",
        _with_metadata(src, tmp_path / "realtime", lockstep=False): "real time",
        _with_metadata(src, tmp_path / "robot", transport="robot"): "not a lockstep simulation",
        _with_metadata(src, tmp_path / "noconfig", config={"policy": "scripted"}): "lacks the task",
        tmp_path / "missing": "no .mcap file",
    }
    runner = CliRunner()
    for bag, reason in cases.items():
        run = runner.invoke(_app(), ["replay", str(bag), "--video", str(tmp_path / "x.mp4")])
        assert run.exit_code == 2, (bag, run.output)
        lines = [line for line in run.output.splitlines() if line.strip()]
        assert len(lines) == 1 and reason in lines[0] and "Traceback" not in run.output, run.output
    assert not list(tmp_path.glob("x.mp4*"))


def test_report_links_resolve_and_videos_play(bags, tmp_path):
    """lq report --videos 1 on the two bags: a figure per episode, one video per cell, every link resolves."""
    from lq_ros.report.sweep_report import build_report

    folder = tmp_path / "runs"
    folder.mkdir()
    for bag in bags.values():
        shutil.copytree(bag, folder / bag.name)
    calls: dict[str, list] = {}
    report = build_report(folder, n_boot=50, videos=1, progress=lambda s, d, t: calls.setdefault(s, []).append((d, t)))
    assert report.media_warnings == []
    assert calls["episode figures"][-1] == (2, 2) and calls["replay videos"][-1] == (2 * MAX_STEPS, 2 * MAX_STEPS)
    page = report.files["report.html"].read_text()
    links = re.findall(r"""(?:href|src)=["']([^"']+)["']""", page)
    assert sum(link.endswith(".png") and link.startswith("episodes/") for link in links) == 2
    videos = {link for link in links if link.endswith(".mp4")}
    assert len(videos) == 2 and "<h2>Replay videos</h2>" in page
    for link in links:
        if link.startswith("data:"):  # the report's own figures, embedded so the page travels alone
            continue
        assert (report.out_dir / link).exists(), link
    for link in videos:
        assert len(read_video(report.out_dir / link)[1]) == MAX_STEPS + 1
    assert page.count("= bag") >= 2  # the verdict of each replay, next to its link
    md = report.files["report.md"].read_text()
    md_links = re.findall(r"\]\(([^)]+)\)", md)
    assert sum(link.endswith(".mp4") for link in md_links) >= 2
    for link in md_links:  # percent-encoded link targets (lq_ros/report/escape.py)
        assert (report.out_dir / unquote(link)).exists(), link
    # A second run reuses the figures and videos (newer than their bags) instead of rendering again.
    stamps = {p: p.stat().st_mtime_ns for p in report.out_dir.glob("*/*.*")}
    build_report(folder, n_boot=50, videos=1)
    assert {p: p.stat().st_mtime_ns for p in report.out_dir.glob("*/*.*")} == stamps


@pytest.mark.parametrize(
    ("action", "problem"),
    [
        ([0.0, 0.0, float("nan"), 0.0, 0.0, 0.0, -1.0], "non-finite value nan at row 0, column 2"),
        ([0.0, 0.0, 1e308, 0.0, 0.0, 0.0, -1.0], "outside the action bounds"),
        ([0.0, 0.0, 0.1], "shape (1, 3), expected (H>=1, 7)"),
    ],
)
def test_a_recorded_command_the_executor_would_refuse_is_not_simulated(bags, tmp_path, action, problem):
    """Read, not run: the executor's chunk check on every recorded command, before the simulator sees one."""
    bag = _copy_bag(bags["sync"], tmp_path / "hostile", tamper_tick=5, action=action)
    run = CliRunner().invoke(_app(), ["replay", str(bag)])
    assert run.exit_code == 2, run.output
    lines = [line for line in run.output.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in run.output, run.output
    assert f"{bag}: the command of tick 5 would not reach a robot" in " ".join(run.output.split())
    assert problem in run.output


def test_a_mujoco_failure_is_one_line_naming_the_bag(bags, monkeypatch):
    """MuJoCo's own FatalError (its arena overflows, as when it cannot allocate) while re-simulating: one line."""
    import mujoco

    from lq_ros.sim.libero_env import LiberoEnv

    bodies = "".join(f'<body pos="0 0 {0.05 * i}"><freejoint/><geom size="0.1"/></body>' for i in range(30))
    crowded = mujoco.MjModel.from_xml_string(f'<mujoco><size memory="20K"/><worldbody>{bodies}</worldbody></mujoco>')

    def overflowing_step(self, action):
        mujoco.mj_step(crowded, mujoco.MjData(crowded))  # raises mujoco.FatalError (mj_stackAlloc: stack overflow)
        raise AssertionError("MuJoCo did not fail")

    monkeypatch.setattr(LiberoEnv, "step", overflowing_step)
    run = CliRunner().invoke(_app(), ["replay", str(bags["sync"])])
    assert run.exit_code == 2, run.output
    assert "Traceback" not in run.output and not isinstance(run.exception, mujoco.FatalError), run.output
    # (LIBERO's own note on building the task goes to stderr first; the refusal is the one line after it)
    (line,) = [line for line in run.output.splitlines() if "cannot replay" in line]
    assert line == run.output.strip().splitlines()[-1]
    assert f"cannot replay {bags['sync']}: MuJoCo failed: mj_stackAlloc: stack overflow" in line
