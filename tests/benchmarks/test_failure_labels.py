"""benchmarks/failure_labels.py passes: two blind labelling passes and their adjudication against the classifier,
on the committed labelled set's bags (the labellers here: its labels, one of them changed)."""

from __future__ import annotations

import csv
import importlib.util
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
