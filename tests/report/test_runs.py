"""Two run folders in one report: a policy in both is a variant per run, compared on the episodes both ran."""

from __future__ import annotations

import json

import pandas as pd
import pytest

from lq_ros.report import episode_media as media
from lq_ros.report import runs
from lq_ros.report.sweep_report import build_report
from lq_ros.run.sweep import ResultStore
from lq_ros.wire.messages import EventKind
from tests.report.test_figure_rules import _row


def write_run(folder, successes: int) -> None:
    """A sweep folder of 'sine' episodes, sync at 0 s: tasks 0-5, inits 0-1; the first ``successes`` succeed."""
    store = ResultStore(folder)
    store.create()
    for i, (task, init) in enumerate((t, n) for t in range(6) for n in range(2)):
        row = _row("libero_spatial", mode="sync", task=task, init=init, policy="sine",
                   status="success" if i < successes else "failure")  # fmt: skip
        key = f"{folder.name}{i:03d}"
        store.write({"key": key, "status": row["status"], "bag": None, "row": row, "attempts": []})


def test_a_policy_in_two_runs_is_compared_pair_by_pair(tmp_path):
    write_run(tmp_path / "before", successes=12)
    write_run(tmp_path / "after", successes=3)
    report = build_report([tmp_path / "before", tmp_path / "after"], tmp_path / "compare", n_boot=100)
    assert set(report.episodes["policy"]) == {"sine · before", "sine · after"}  # never pooled into one cell
    assert set(report.episodes["run"]) == {"before", "after"}
    compared = pd.read_csv(tmp_path / "compare" / "paired_policies.csv")
    [row] = compared.to_dict("records")
    assert {row["arm_a"], row["arm_b"]} == {"sine · before", "sine · after"} and row["n_pairs"] == 12
    assert (tmp_path / "compare" / "report.html").exists()


def test_run_names_and_refusals(tmp_path):
    assert runs.run_names([tmp_path / "a" / "x", tmp_path / "b" / "y"]) == ["x", "y"]
    assert runs.run_names([tmp_path / "a" / "x", tmp_path / "b" / "x"]) == ["a/x", "b/x"]
    write_run(tmp_path / "one", successes=1)
    with pytest.raises(ValueError, match="named twice"):
        runs.load_runs([tmp_path / "one", tmp_path / "one"], lambda d: pd.DataFrame())
    with pytest.raises(ValueError, match="--out"):
        build_report([tmp_path / "one", tmp_path / "one"])
    assert json.loads((tmp_path / "one" / "results" / "one000.json").read_text())["row"]["policy"] == "sine"


def test_media_names_are_prefixed_by_their_run(tmp_path):
    bags = {0: tmp_path / "a" / "ep", 1: tmp_path / "b" / "ep", 2: tmp_path / "b" / "other", 3: None}
    names = media.media_names(bags, tmp_path, {0: "a", 1: "b", 2: "b", 3: "b"})
    assert names == {0: "a__ep", 1: "b__ep", 2: "b__other"}
    assert media.media_names(bags, tmp_path) == {0: f"ep-{_hash('a/ep')}", 1: f"ep-{_hash('b/ep')}", 2: "other"}
    # A run name that is a path below the runs' common parent is a safe file name part.
    assert media.media_names({0: tmp_path / "x" / "ep"}, tmp_path, {0: "runs/x y"}) == {0: "runs_x_y__ep"}


def _hash(text: str) -> str:
    import hashlib

    return hashlib.sha256(text.encode()).hexdigest()[:10]


def test_two_runs_episodes_of_one_folder_name_get_a_figure_each(tmp_path):
    """Run folders of bags whose episodes share their folder names: each episode links its own run's figure."""
    from tests.scoring.test_bag_scorer import write_episode_bag

    write_episode_bag(tmp_path / "before" / "ep", n_ticks=300)
    write_episode_bag(tmp_path / "after" / "ep", n_ticks=120, end_kind=EventKind.TIMEOUT)
    report = build_report([tmp_path / "before", tmp_path / "after"], tmp_path / "compare", n_boot=50)
    plots = dict(zip(report.episodes["run"], report.episodes["plot"], strict=True))
    assert plots == {"before": "episodes/before__ep.png", "after": "episodes/after__ep.png"}
    files = [(tmp_path / "compare" / p).read_bytes() for p in plots.values()]
    assert files[0] != files[1]  # each drawn from its own bag
    assert all(p in report.files["report.html"].read_text() for p in plots.values())


def test_a_report_into_the_same_out_never_reuses_a_figure_of_another_bag_of_that_name(tmp_path):
    """The figure cache keeps a figure newer than its bag only if it was drawn from that bag: a report of another
    folder into the same --out redraws an episode whose bag merely shares the folder name."""
    import os

    from tests.scoring.test_bag_scorer import write_episode_bag

    other = write_episode_bag(tmp_path / "b" / "ep", n_ticks=120, end_kind=EventKind.TIMEOUT)
    for f in other.iterdir():  # older than anything the first report draws
        os.utime(f, (1e9, 1e9))
    write_episode_bag(tmp_path / "a" / "ep", n_ticks=300)
    out = tmp_path / "out"
    build_report(tmp_path / "a", out, n_boot=50)
    first = (out / "episodes" / "ep.png").read_bytes()
    build_report(tmp_path / "b", out, n_boot=50)
    second = (out / "episodes" / "ep.png").read_bytes()
    assert second != first  # b's own episode, not a's figure kept because it is newer than b's bag
    drawn = (out / "episodes" / "ep.png").stat().st_mtime_ns
    build_report(tmp_path / "b", out, n_boot=50)
    assert (out / "episodes" / "ep.png").stat().st_mtime_ns == drawn  # its own figure is still reused
