"""benchmarks/failure_labels.py passes: two blind labelling passes and their adjudication against the classifier,
on the committed labelled set's bags (the labellers here: its labels, one of them changed)."""

from __future__ import annotations

import csv
import importlib.util
import json
import shutil
import sys
from pathlib import Path

import pytest

_PATH = Path(__file__).resolve().parents[2] / "benchmarks" / "failure_labels.py"
_SPEC = importlib.util.spec_from_file_location("failure_labels", _PATH)
fl = importlib.util.module_from_spec(_SPEC)
sys.modules.setdefault("failure_labels", fl)
_SPEC.loader.exec_module(fl)

DATA = Path(__file__).resolve().parents[1] / "data/failure_labels"


def test_passes_reports_the_labellers_kappa_and_the_unvalidated_modes(tmp_path, monkeypatch, capsys):
    shutil.copy(DATA / "episodes.json", tmp_path)
    (tmp_path / "bags").symlink_to(DATA / "bags")
    rows = list(csv.DictReader((DATA / "labels.csv").open()))
    for name, changed in (("labels_a.csv", False), ("labels_b.csv", True), ("adjudicated.csv", False)):
        with (tmp_path / name).open("w") as f:
            writer = csv.DictWriter(f, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows([{**rows[0], "label": "never_reached"}, *rows[1:]] if changed else rows)
    monkeypatch.setattr(fl, "DATA", tmp_path)
    out = fl.passes()
    assert (out["between"]["agreed"], out["between"]["n"]) == (47, 48)
    assert (out["classifier"]["agreed"], out["classifier"]["n"]) == (29, 48)
    assert out["met"] == {"agreement": False, "kappa": False}  # no LIBERO-Goal episode: not assessed
    assert out["unvalidated"] == ["never_reached", "pushed_or_toppled", "stopped_short"]
    assert "classifier grasp_missed: the adjudicated label agrees on 15 of 15" in capsys.readouterr().out
    (tmp_path / "labels_b.csv").unlink()
    with pytest.raises(SystemExit, match="labels_b.csv: missing"):
        fl.passes()


def test_the_targets_are_the_frozen_ones():
    """Frozen before the set of config/sweeps/failure_validation.yaml was labelled: changing one needs a new set."""
    assert dict(fl.TARGETS) == {"agreement": 0.85, "kappa": 0.75, "libero_goal": 0.80, "precision": 0.70}
    with pytest.raises(TypeError):
        fl.TARGETS["agreement"] = 0.5


def test_passes_refuses_a_label_that_is_no_mode(tmp_path, monkeypatch):
    shutil.copy(DATA / "episodes.json", tmp_path)
    rows = list(csv.DictReader((DATA / "labels.csv").open()))
    for name in ("labels_a.csv", "labels_b.csv", "adjudicated.csv"):
        with (tmp_path / name).open("w") as f:
            writer = csv.DictWriter(f, fieldnames=["episode", "label"], extrasaction="ignore")
            writer.writeheader()
            writer.writerows([{**rows[0], "label": "missed grasp"}, *rows[1:]] if name == "labels_b.csv" else rows)
    monkeypatch.setattr(fl, "DATA", tmp_path)
    with pytest.raises(SystemExit, match=r"labels_b.csv: .*unknown label 'missed grasp'; valid: no_action_executed"):
        fl.passes()
    (tmp_path / "labels_b.csv").write_text("episode,mode\n")
    with pytest.raises(SystemExit, match="labels_b.csv: needs a header with the columns episode and label"):
        fl.passes()


def _sweep(root: Path, rows: list[dict]) -> Path:
    (root / "results").mkdir(parents=True)
    for row in rows:
        (root / "results" / f"{row['episode']}.json").write_text(json.dumps({"row": row}))
    return root


def test_select_by_suite_gives_each_suite_its_share(tmp_path, monkeypatch):
    """One policy's suite (2 strata) against three policies' (6 strata): by suite, 8 and 8 of 16; over all strata
    alike, 4 and 12. Successes and other init states are never picked."""
    rows = []
    for suite, policies in (("libero_10", ["scripted"]), ("libero_spatial", ["scripted", "flow", "oft"])):
        for policy in policies:
            for mode in ("sync", "async"):
                for i in range(6):
                    episode = f"{suite}_{policy}_{mode}_{i}"
                    status = "success" if i == 5 else "failure"
                    rows.append({"episode": episode, "suite": suite, "mode": mode, "latency_s": 0.2,
                                 "policy": policy, "status": status, "init": 45 if i else 3})  # fmt: skip
    sweep = _sweep(tmp_path / "sweep", rows)
    monkeypatch.setattr(fl, "DATA", tmp_path / "set")
    cases = ((True, {"libero_10": 8, "libero_spatial": 8}), (False, {"libero_10": 4, "libero_spatial": 12}))
    for by_suite, want in cases:
        fl.select(sweep, 16, 0, {45}, by_suite=by_suite)
        picked = fl._picked()
        assert len(picked) == 16 and not any(name.endswith(("_0", "_5")) for name in picked)
        assert {s: sum(n.startswith(s) for n in picked) for s in want} == want


def test_select_counts_a_policy_run_with_arguments_as_a_policy_of_its_own(tmp_path, monkeypatch):
    rows = [{"episode": f"e{i}_{c}", "suite": "libero_goal", "mode": "async", "latency_s": 0.4, "policy": "scripted",
             "policy_args": {"chunk_size": c} if c != 8 else {}, "status": "failure", "init": 45}
            for c in (8, 10) for i in range(4)]  # fmt: skip
    monkeypatch.setattr(fl, "DATA", tmp_path / "set")
    fl.select(_sweep(tmp_path / "sweep", rows), 4, 0, None, by_suite=True)
    assert sorted(name[-2:] for name in fl._picked()) == ["10", "10", "_8", "_8"]


def test_select_defers_a_suites_starved_episodes_past_its_limit(tmp_path, monkeypatch):
    """Each suite: 3 failures of a degenerate protocol, and 2 others (Goal) or 1 (LIBERO-10). With at most 1
    degenerate per suite, 5 picks are every other failure and one starved of each suite; a 6th takes a second
    starved one only because no other failure is left."""
    rows = []
    for suite, others in (("libero_goal", 2), ("libero_10", 1)):
        for i in range(3 + others):
            starved = i < 3
            rows.append({"episode": f"{suite}_{'starved' if starved else 'policy'}_{i}", "suite": suite,
                         "mode": "async", "latency_s": 0.4 if starved else 0.2, "policy": "scripted",
                         "status": "failure", "init": 45, "degenerate_protocol": starved})  # fmt: skip
    sweep = _sweep(tmp_path / "sweep", rows)
    monkeypatch.setattr(fl, "DATA", tmp_path / "set")
    fl.select(sweep, 5, 0, None, by_suite=True, degenerate=1)
    picked = fl._picked()
    assert sum("starved" in n for n in picked) == 2 and sum("policy" in n for n in picked) == 3
    fl.select(sweep, 6, 0, None, by_suite=True, degenerate=1)
    assert sum("starved" in n for n in fl._picked()) == 3
    fl.select(sweep, 5, 0, None, by_suite=True)  # no limit: the suites' strata in turn, starved or not
    assert sum("starved" in n for n in fl._picked()) == 3
