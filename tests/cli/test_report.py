"""``lq report DIR1 DIR2 --out OUT``: several runs in one report; without --out, one line."""

from __future__ import annotations

from tests.report.test_runs import write_run
from tests.test_cli_errors import assert_refused, lq


def test_two_folders_need_an_output_folder(tmp_path):
    write_run(tmp_path / "a", successes=2)
    write_run(tmp_path / "b", successes=2)
    assert_refused(lq("report", str(tmp_path / "a"), str(tmp_path / "b")), "2 run folders", "--out")
    assert_refused(lq("report", str(tmp_path / "a"), str(tmp_path / "nope"), "--out", str(tmp_path / "r")),
                   "nope: no such folder")  # fmt: skip
