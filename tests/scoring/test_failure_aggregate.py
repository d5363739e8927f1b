"""Failure modes in the scorer's rows (bag_scorer), per cell (failure_aggregate) and in the figure: task state read
from a bag our writer made, an old bag without it, a damaged task-state message, fractions and their sentences."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from lq_ros.core.types import TaskStateSample
from lq_ros.recording.episode_bag import EpisodeBagWriter
from lq_ros.report.failure_figures import fig_failure_modes
from lq_ros.scoring import failure_modes
from lq_ros.scoring.bag_scorer import score_bag
from lq_ros.scoring.failure_aggregate import mode_fractions, shift_sentences
from lq_ros.wire import messages as m
from tests.scoring.test_bag_scorer import write_episode_bag

NAMES = ("bowl", "plate", "other_bowl")


def sample(tick: int, *, grasped: bool, bowl_xyz, on: bool) -> TaskStateSample:
    pos = np.array([bowl_xyz, (0.3, 0.0, 0.9), (0.0, 0.2, 0.9)], dtype=np.float64)
    return TaskStateSample(
        object_names=NAMES,
        object_pos=pos,
        object_quat_xyzw=np.tile([0.0, 0.0, 0.0, 1.0], (3, 1)),
        gripper_contact=np.array([grasped, False, False]),
        grasped=np.array([grasped, False, False]),
        predicate_names=("(on bowl plate)",),
        predicate_values=np.array([on]),
    )


def episode_with_task_state(path, *, drop_at: int | None, extra: bytes | None = None):
    """write_episode_bag's episode (400 ticks, ends in a timeout) plus a task state per tick: the bowl grasped at
    tick 50 and carried towards the plate; released at ``drop_at`` (falls where it was) or never."""
    bag = write_episode_bag(path, end_kind=m.EventKind.TIMEOUT)
    # Rewrite it with the task topics: our writer appends nothing to a closed bag, so write a second one.
    from lq_ros.recording.bag_compare import bag_messages

    messages = bag_messages(bag)
    out = path.with_name(path.name + "_task")
    writer = EpisodeBagWriter(out, [*m.CORE_TOPICS, *m.TASK_TOPICS])
    from lq_ros.recording.episode_bag import read_run_metadata

    writer.set_run_metadata(read_run_metadata(bag))
    for topic in m.CORE_TOPICS:
        for t_ns, raw in messages.get(topic.name, []):
            writer.write(topic, t_ns, raw)
    ee = messages[m.EE_POSE.name]
    for tick, (t_ns, _) in enumerate(ee):
        held = 50 <= tick and (drop_at is None or tick < drop_at)
        x = min(0.25, 0.002 * max(0, min(tick, drop_at or 10**6) - 50))
        z = 0.95 if held else 0.9  # lifted while held, on the table before and after
        for topic, ts, data in m.task_state_msgs(t_ns, tick, sample(tick, grasped=held, bowl_xyz=(x, 0.0, z),
                                                                    on=False)):  # fmt: skip
            writer.write(topic, ts, data)
    if extra is not None:
        writer.write(m.TASK_STATE, ee[10][0], extra)
    writer.close()
    return out


def test_a_bag_with_task_state_gets_its_failure_mode(tmp_path):
    row = score_bag(episode_with_task_state(tmp_path / "drop", drop_at=100))
    assert row["status"] == "failure"
    assert (row["failure_mode"], row["furthest_phase"], row["progress"]) == ("dropped_in_transit", "moved", 0.0)
    assert row["unmet_predicate"] == "(on bowl plate)" and row["predicate_events"] == []


def test_an_old_bag_is_unavailable_never_none(tmp_path):
    row = score_bag(write_episode_bag(tmp_path / "old"))
    assert row["status"] == "success" and row["failure_mode"] == "unavailable"
    assert row["progress"] is None and "no /lq/task/state records" in row["null_reasons"]["failure_mode"]


def test_a_damaged_task_state_message_is_skipped_as_damage(tmp_path):
    good = m.task_state_msgs(0, 10, sample(10, grasped=False, bowl_xyz=(0, 0, 0.9), on=False))[1][2]
    bad = good[:-12]  # cut: its arrays run past the end
    row = score_bag(episode_with_task_state(tmp_path / "cut", drop_at=None, extra=bad))
    assert row["failure_mode"] in failure_modes.FAILURE_MODES and row["partial"] is True
    assert any("undecodable /lq/task/state" in w for w in row["warnings"]), row["warnings"]


def episodes_frame(rising: str = "grasp_missed") -> pd.DataFrame:
    """Six tasks x 10 episodes per latency; at 0.2 s four more failures per task, all ``rising`` (a missed grasp)."""
    rows = []
    for latency, drops in ((0.0, 1), (0.2, 5)):
        for task in range(6):
            for i in range(10):
                mode = rising if i < drops else ("never_reached" if i == 9 else "none")
                status = "success" if mode == "none" else "failure"
                cell = {"policy": "flow", "mode": "async", "latency_s": latency, "latency_dist": "constant"}
                rows.append({**cell, "suite": "libero_object", "task": task, "status": status, "failure_mode": mode})
    rows.append({**rows[0], "status": "failure", "failure_mode": "unavailable"})  # an old bag: counted apart
    rows.append({**rows[0], "status": "error", "failure_mode": "error"})
    return pd.DataFrame(rows)


def test_fractions_per_cell_add_up_to_the_failure_rate_with_clustered_intervals():
    fractions = mode_fractions(episodes_frame(), ("policy", "mode", "latency_s", "latency_dist", "suite"), n_boot=200)
    cell = fractions[fractions["latency_s"] == 0.2].set_index("failure_mode")
    assert set(cell.index) == {*failure_modes.FAILURE_MODES, *failure_modes.PROTOCOL_MODES}
    assert cell.loc["grasp_missed", "count"] == 30 and cell["n"].iloc[0] == 60
    assert cell["fraction"].sum() == pytest.approx(36 / 60)
    low, high = cell.loc["grasp_missed", ["ci_lo", "ci_hi"]]
    assert low < 0.5 < high and cell["n_tasks"].iloc[0] == 6
    zero = fractions[fractions["latency_s"] == 0.0]
    assert zero["n_unavailable"].iloc[0] == 1 and zero["n_error"].iloc[0] == 1 and zero["n"].iloc[0] == 60


def test_the_sentence_says_where_the_extra_failures_went():
    fractions = mode_fractions(episodes_frame(), ("policy", "mode", "latency_s", "latency_dist", "suite"), n_boot=200)
    (sentence,) = shift_sentences(fractions, ("suite", "policy", "mode"))
    expected = "libero_object, flow, async at 0.2 s: 36 of 60 episodes failed, against 12 of 60 at 0 s."
    assert sentence.startswith(expected)
    assert "Most of the rise is grasp missed (+24; 50% of the cell, 95% CI" in sentence


def test_no_sentence_quotes_an_unvalidated_mode():
    fractions = mode_fractions(episodes_frame("dropped_in_transit"), ("policy", "mode", "latency_s", "latency_dist",
                                                                      "suite"), n_boot=200)  # fmt: skip
    (sentence,) = shift_sentences(fractions, ("suite", "policy", "mode"))
    assert "dropped" not in sentence and "not validated against an observer" in sentence
    assert "dropped_in_transit" not in failure_modes.VALIDATED_MODES


def test_no_action_executed_is_counted_apart_and_shown_apart():
    """A starved protocol's episodes: their own row and count, a sentence that says whose failure it is, and a
    hatched bar above a gap in the figure."""
    frame = episodes_frame()
    starved = (frame["latency_s"] == 0.2) & (frame["failure_mode"] == "grasp_missed")
    frame.loc[starved, "failure_mode"] = "no_action_executed"
    frame.loc[starved & (frame["task"] == 0), "collateral"] = True
    fractions = mode_fractions(frame, ("policy", "mode", "latency_s", "latency_dist", "suite"), n_boot=200)
    cell = fractions[fractions["latency_s"] == 0.2].set_index("failure_mode")
    assert cell.loc["no_action_executed", "count"] == 30 == cell["n_no_action"].iloc[0]
    assert cell.loc["grasp_missed", "count"] == 0 and cell["n_collateral"].iloc[0] == 5
    (sentence,) = shift_sentences(fractions, ("suite", "policy", "mode"))
    assert "30 of them ran no fresh action at all (the protocol's failure, not the policy's)." in sentence
    fig = fig_failure_modes(fractions)
    hatched = [p for p in fig.axes[0].patches if p.get_hatch() == "xxx" and p.get_height() > 0]
    assert [round(p.get_height(), 3) for p in hatched] == [0.5]
    assert hatched[0].get_y() == pytest.approx(0.1 + 0.02)  # above the policy's modes, after a gap


def test_the_figure_stacks_the_modes_per_protocol():
    fractions = mode_fractions(episodes_frame(), ("policy", "mode", "latency_s", "latency_dist", "suite"), n_boot=200)
    fig = fig_failure_modes(fractions)
    (ax,) = fig.axes[:1]
    heights = sorted(round(p.get_height(), 3) for p in ax.patches if p.get_height() > 0)
    assert heights == [0.1, 0.1, 0.1, 0.5]  # 0 s: never reached, dropped; 0.2 s: never reached, dropped
    assert fig_failure_modes(mode_fractions(pd.DataFrame(), ("policy",))) is None


def paired_frame(zero_modes: list[str], cell_modes: list[str], tasks: int) -> pd.DataFrame:
    """Episodes of one series at 0 s and 0.2 s, one per (task, init): init i of task t at index t * inits + i."""
    inits = len(zero_modes) // tasks
    rows = []
    for latency, modes in ((0.0, zero_modes), (0.2, cell_modes)):
        for index, mode in enumerate(modes):
            rows.append({"suite": "s", "policy": "p", "mode": "async", "latency_s": latency,
                         "latency_dist": "constant", "task": index // inits, "init": index % inits, "seed": 7,
                         "status": "success" if mode == "none" else "failure", "failure_mode": mode})  # fmt: skip
    return pd.DataFrame(rows)


def test_paired_mode_change_over_shared_pairs_with_a_task_clustered_interval():
    from lq_ros.scoring.failure_aggregate import paired_mode_change
    from lq_ros.scoring.intervals import tango_paired_ci

    tasks, inits = 10, 5
    zero = ["none"] * (tasks * inits)
    # At 0.2 s the first 3 inits of every task miss the grasp: a change of +0.6, the same in every task.
    cell = ["grasp_missed" if i % inits < 3 else "none" for i in range(tasks * inits)]
    series = {"suite": "s", "policy": "p", "mode": "async"}
    out = paired_mode_change(paired_frame(zero, cell, tasks), series, 0.2, "grasp_missed")
    assert (out["n_pairs"], out["n_tasks"]) == (50, 10)
    assert out["change"] == pytest.approx(0.6)
    # No spread between tasks, yet not a certain +0.6 (a task-cluster bootstrap gave [0.6, 0.6]): Tango's interval
    # of 30 of 50 pairs discordant one way.
    assert (out["ci_lo"], out["ci_hi"]) == pytest.approx(tango_paired_ci(0, 30, 0, 20))
    assert out["ci_lo"] < 0.5 and out["ci_hi"] > 0.7
    # All of the change in 3 of 10 tasks: the same mean, but an interval that spans that clustering.
    cell = ["grasp_missed" if i // inits < 3 else "none" for i in range(tasks * inits)]
    out = paired_mode_change(paired_frame(zero, cell, tasks), series, 0.2, "grasp_missed")
    assert out["change"] == pytest.approx(0.3)
    assert out["ci_lo"] < 0.15 and out["ci_hi"] > 0.45
    # Pairs classified at only one latency are left out (an error, a bag without task state).
    frame = paired_frame(zero, cell, tasks)
    frame.loc[0, "failure_mode"] = "unavailable"
    frame.loc[1, "status"] = "error"
    assert paired_mode_change(frame, series, 0.2, "grasp_missed")["n_pairs"] == 48


def test_shift_sentences_say_the_paired_change_and_whether_its_interval_excludes_none():
    tasks, inits = 10, 5
    zero = ["none"] * (tasks * inits)
    cell = ["grasp_missed" if i % inits < 3 else "none" for i in range(tasks * inits)]
    episodes = paired_frame(zero, cell, tasks)
    fractions = mode_fractions(episodes, ("suite", "policy", "mode", "latency_s", "latency_dist"))
    (sentence,) = shift_sentences(fractions, ("suite", "policy", "mode"), episodes=episodes)
    assert "Most of the rise is grasp missed (+30" in sentence
    expected = "Paired change from 0 s: +60%, 95% CI +46% to +72% over 50 pairs in 10 tasks (excludes no change)"
    assert expected in sentence


def test_the_failure_section_opens_with_what_the_modes_are_validated_against():
    from lq_ros.report.sweep_report import FAILURE_NOTE
    from lq_ros.scoring.failure_aggregate import validation_note

    note = validation_note()
    assert FAILURE_NOTE.startswith(note) and "two labellers blind" in note and "kappa 0.89" in note
    named = {mode for mode in failure_modes.MODES if mode.replace("_", " ") in note}
    assert named == set(failure_modes.VALIDATED_MODES)  # no unvalidated mode quoted
