"""The per-episode figure on a real bag: its panels hold the episode's data, the power integrates to the
scorer's energy (substep integrals and 20 Hz samples), and the PNG is drawn on."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import matplotlib.image as mpimg
import matplotlib.pyplot as plt
import numpy as np
import pytest

from lq_ros.core.executor_protocol import Source
from lq_ros.report.episode_plot import (
    ACTION_LABELS,
    PANELS,
    episode_figure,
    episode_power,
    instantaneous_power,
    load_episode_view,
    write_episode_figure,
)
from lq_ros.scoring.metrics import energy_terms

MAX_STEPS = 30

pytestmark = [pytest.mark.slow, pytest.mark.sim]


@pytest.fixture(scope="module")
def bag(tmp_path_factory) -> Path:
    """A scripted async episode with 0.2 s latency (N = 4): startup holds, then a chunk switch every 4 ticks."""
    from lq_ros.core.run_config import RunConfig
    from lq_ros.transport.inprocess import run_inprocess

    cfg = RunConfig(mode="async", latency_s=0.2, max_steps=MAX_STEPS, policy="scripted")
    return run_inprocess(cfg, tmp_path_factory.mktemp("plot")).bag_path


@pytest.fixture(scope="module")
def view(bag):
    return load_episode_view(bag)


@pytest.fixture(scope="module")
def figure(view):
    fig = episode_figure(view)
    yield fig
    plt.close(fig)


def _data_lines(ax) -> list:
    return [line for line in ax.get_lines() if len(line.get_xdata()) > 1 and np.isfinite(line.get_ydata()).any()]


def test_view_holds_the_episode(view):
    assert view.status == "timeout" and view.end_tick == MAX_STEPS
    assert list(view.ee_ticks) == list(range(MAX_STEPS + 1)) and view.ee_pos.shape == (MAX_STEPS + 1, 3)
    assert list(view.command_ticks) == list(range(MAX_STEPS)) and view.actions.shape == (MAX_STEPS, 7)
    assert list(view.sources[:4]) == [Source.HOLD_STARTUP] * 4 and Source.CHUNK in view.sources
    assert view.switch_ticks[:3] == [4, 8, 12]
    assert list(view.energy_ticks) == list(range(1, MAX_STEPS + 1))  # one substep integral per tick


def test_figure_has_the_expected_panels(figure, view):
    axes = [ax for ax in figure.axes if ax.get_label() != "<colorbar>"]
    titles = [ax.get_title() for ax in axes]
    assert len(titles) == len(PANELS) and all(t.startswith(p) for t, p in zip(titles, PANELS, strict=True)), titles
    top, side, actions, speed, jerk, power = axes
    for ax in (top, side):  # path line + start + end markers, and the per-tick scatter
        assert len(_data_lines(ax)) >= 1 and ax.collections
    xs = _data_lines(top)[0].get_xdata()
    assert np.allclose(xs, view.ee_pos[:, 0])
    labels = [line.get_label() for line in _data_lines(actions)]
    assert labels[:7] == list(ACTION_LABELS)
    switch_lines = [line for line in actions.get_lines() if line.get_linestyle() == ":"]
    assert len(switch_lines) == len(view.switch_ticks)
    shaded = [p for p in actions.patches if p.get_label() == "hold (startup)"]
    assert len(shaded) == 1  # ticks 0-3: one shaded run
    assert len(_data_lines(speed)) == 1 and len(_data_lines(speed)[0].get_xdata()) == MAX_STEPS
    assert len(_data_lines(jerk)[0].get_xdata()) == MAX_STEPS - 2
    assert len(_data_lines(power)) == 3 and "substep" in power.get_title()


def test_power_integrates_to_the_scored_energy(bag, view):
    """Σ power·dt of the figure equals the scorer's energy terms, for both data sources."""
    from lq_ros.scoring.bag_scorer import score_bag

    samples_only = dataclasses.replace(view, energy_ticks=view.energy_ticks[:0])  # as a bag without integrals
    for energy_rate, v in (("substep", view), ("control", samples_only)):
        power = episode_power(v)
        row = score_bag(bag, energy_rate=energy_rate)
        assert row["energy_sampling"] == energy_rate
        for series, key in ((power.mech_w, "energy_mech_j"), (power.elec_w, "energy_elec_j"),
                            (power.overhead_w, "energy_overhead_j")):  # fmt: skip
            assert np.sum(series * power.dt_s) == pytest.approx(row[key], rel=1e-9), (energy_rate, key)
        assert len(power.ticks) == MAX_STEPS
    # Per sample, the same integrand as metrics.energy_terms.
    rng = np.random.default_rng(0)
    tau, qd = rng.normal(size=(50, 7)) * 10, rng.normal(size=(50, 7))
    mech, elec, over = instantaneous_power(tau, qd)
    terms = energy_terms(tau, qd, 0.002)
    assert (mech.sum() * 0.002, elec.sum() * 0.002, over.sum() * 0.002) == pytest.approx(
        (terms.mech_j, terms.elec_j, terms.overhead_j)
    )
    assert (mech >= 0).all() and (mech == 0).any()  # negative power is clipped, as in eq. 7


def test_png_is_drawn_on(bag, tmp_path):
    path = write_episode_figure(bag, tmp_path / "episode.png")
    image = mpimg.imread(path)[..., :3]
    assert image.shape[0] > 800 and image.shape[1] > 800
    not_white = (image < 0.95).any(axis=2).mean()
    assert 0.05 < not_white < 0.8, not_white
    assert len(np.unique((image * 255).astype(np.uint8).reshape(-1, 3), axis=0)) > 50


# -- the Foxglove layout -----------------------------------------------------------------------------------

LAYOUT = Path(__file__).resolve().parents[2] / "config" / "foxglove_layout.json"


def _leaves(node) -> set[str]:
    return {node} if isinstance(node, str) else _leaves(node["first"]) | _leaves(node["second"])


def _layout_paths(layout: dict) -> list[str]:
    """Every message path and topic the layout's panels read."""
    out = []
    for cfg in layout["configById"].values():
        out += [p["value"] for p in cfg.get("paths", [])]
        out += [cfg[k]["value"] for k in ("xAxisPath",) if k in cfg]
        out += [cfg["topicPath"]] if "topicPath" in cfg else []
        out += list(cfg.get("topics", {}))
    return out


def test_foxglove_layout_reads_what_a_bag_holds(bag):
    """Every panel is placed; every topic and field path resolves on the bag's messages, decoded from the
    schemas embedded in the bag (as Foxglove decodes them)."""
    import json
    import re

    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    layout = json.loads(LAYOUT.read_text())
    assert _leaves(layout["layout"]) == set(layout["configById"])
    paths = _layout_paths(layout)
    topics = {p.split(".", 1)[0] for p in paths}
    assert {"/ee_pose", "/joint_states", "/lq/command", "/lq/action_chunk", "/lq/episode_events"} <= topics
    first: dict[str, object] = {}
    with open(next(bag.glob("*.mcap")), "rb") as f:
        for _, channel, _, decoded in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages(
            topics=sorted(topics)
        ):
            first.setdefault(channel.topic, decoded)
    assert set(first) == topics
    for p in paths:
        topic, _, fields = p.partition(".")
        value = first[topic]
        for name, index in re.findall(r"(\w+)(?:\[(\d+)\])?", fields):
            value = getattr(value, name)
            value = value[int(index)] if index else value
        assert value is not None, p
