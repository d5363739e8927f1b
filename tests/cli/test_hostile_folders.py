"""The ``lq`` commands in folders they did not make (a bag folder from anyone, a shared ``--out``): no file is written
through a link, text from a bag never starts a formula in a CSV, a busy or foreign folder is refused in one line,
numbers are ASCII digits, and a bug is one line naming the file with its traceback."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
import yaml

from lq_ros.core.executor_protocol import Command
from lq_ros.recording.episode_bag import EpisodeBagWriter
from lq_ros.run import sweep as sw
from lq_ros.wire import messages as m
from tests.run.sweep.test_spec import small_spec
from tests.scoring.test_bag_scorer import TORQUE, VELOCITY, _cubic_positions, _stamp, write_episode_bag
from tests.test_cli_errors import REPO, assert_refused, lq

SHELL = "echo mine\n"


@pytest.fixture
def outside(tmp_path):
    """A shell file outside the folders the commands write: a planted link points at it; it must never change."""
    path = tmp_path / "outside.sh"
    path.write_text(SHELL)
    return path


def bag_with_policy(path, policy: str, n_ticks: int = 40):
    """A short successful episode bag whose run metadata names ``policy`` (text chosen by the bag's author)."""
    writer = EpisodeBagWriter(path, list(m.CORE_TOPICS))
    config = {"policy": policy, "mode": "sync", "latency_s": 0.0, "suite": "s", "task": 0, "init": 0, "seed": 7}
    writer.set_run_metadata({"config": config, "versions": {"git_commit": "abc"}})
    writer.write(m.EPISODE_EVENTS, _stamp(0), m.event_msg(_stamp(0), m.EventKind.STARTED, 0))
    for i, pos in enumerate(_cubic_positions(n_ticks)):
        t_ns = _stamp(i)
        writer.write(m.EE_POSE, t_ns, m.ee_pose_msg(t_ns, pos, [0, 0, 0, 1]))
        writer.write(m.JOINT_STATES, t_ns, m.joint_state_msg(t_ns, [0.0] * 7, VELOCITY, TORQUE))
        cmd = Command(tick=i, action=[0.0] * 7, source=0, request_id=1, chunk_index=0)
        writer.write(m.COMMAND, t_ns, m.command_msg(t_ns, cmd))
    end = _stamp(n_ticks - 1)
    writer.write(m.EPISODE_EVENTS, end, m.event_msg(end, m.EventKind.SUCCESS, n_ticks - 1))
    writer.close()
    return path


# -- lq score ---------------------------------------------------------------------------------------------------


def test_lq_score_never_writes_through_a_link_planted_at_a_temporary_name(tmp_path, outside):
    """The table was written to the fixed name episodes.csv.tmp, following a link there: a bag whose policy name
    was ``$(touch FILE);#`` then overwrote a shell file the bag's author chose."""
    root = tmp_path / "bags"
    bag_with_policy(root / "ep", "$(touch pwned);#")
    for name in ("episodes.csv.tmp", "episodes.parquet.tmp", "aggregates.csv.tmp", "aggregates.parquet.tmp"):
        (root / name).symlink_to(outside)
    result = lq("score", str(root), "--n-boot", "20")
    assert result.returncode == 0, result.stderr[-2000:]
    assert outside.read_text() == SHELL
    assert pd.read_csv(root / "episodes.csv")["policy"].tolist() == ["$(touch pwned);#"]


def test_lq_score_refuses_a_link_where_a_table_goes(tmp_path, outside):
    root = tmp_path / "bags"
    write_episode_bag(root / "ep", n_ticks=40)
    (root / "episodes.csv").symlink_to(outside)
    assert_refused(lq("score", str(root), "--n-boot", "20"), "episodes.csv: a symbolic link", "not followed")
    assert outside.read_text() == SHELL and (root / "episodes.csv").is_symlink()


def test_bag_text_never_starts_a_formula_in_a_table(tmp_path):
    root = tmp_path / "bags"
    bag_with_policy(root / "ep", '=HYPERLINK("http://x","y")')
    result = lq("score", str(root), "--n-boot", "20")
    assert result.returncode == 0, result.stderr[-2000:]
    for table in ("episodes.csv", "aggregates.csv"):
        assert pd.read_csv(root / table)["policy"].tolist() == ['\'=HYPERLINK("http://x","y")'], table
    assert pd.read_parquet(root / "episodes.parquet")["policy"].tolist() == ['=HYPERLINK("http://x","y")']


# -- lq report --------------------------------------------------------------------------------------------------


def test_lq_report_does_not_write_through_links_in_its_folder(tmp_path, outside):
    root = tmp_path / "bags"
    write_episode_bag(root / "ep", n_ticks=40)
    (root / "report").mkdir()
    other = tmp_path / "other.sh"
    other.write_text(SHELL)
    (root / "report" / "report.md").symlink_to(outside)
    (root / "report" / "aggregates_pooled.csv").symlink_to(other)
    assert_refused(lq("report", str(root)), "a symbolic link where a file is written", "not followed")
    assert outside.read_text() == SHELL and other.read_text() == SHELL


def test_lq_report_refuses_a_linked_default_report_folder(tmp_path):
    root = tmp_path / "bags"
    write_episode_bag(root / "ep", n_ticks=40)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (root / "report").symlink_to(elsewhere)
    assert_refused(lq("report", str(root)), "report folder", "a symbolic link; not followed")
    assert list(elsewhere.iterdir()) == []


# -- output folders ---------------------------------------------------------------------------------------------


def _file(tmp_path):
    (tmp_path / "afile").write_text("x")
    return tmp_path / "afile", "a file, not a folder"


def _dangling(tmp_path):
    (tmp_path / "dangling").symlink_to(tmp_path / "nowhere")
    return tmp_path / "dangling", "dangling"


def _theirs(tmp_path):
    if os.getuid() != 0:
        pytest.skip("giving a folder to another user needs root")
    (tmp_path / "theirs").mkdir()
    os.chown(tmp_path / "theirs", 12345, 12345)
    return tmp_path / "theirs", "a folder of user id 12345"


OUT_CASES = {"regular file": _file, "dangling link": _dangling, "another user's folder": _theirs}
EVAL = ["eval", "--policy", "scripted", "--tasks", "0", "--inits", "0", "--latencies", "0", "--modes", "sync"]


@pytest.mark.parametrize("case", list(OUT_CASES))
@pytest.mark.parametrize("command", ["eval", "sweep", "score", "report", "run"])
def test_an_unusable_out_is_refused_in_one_line(tmp_path, case, command):
    out, expected = OUT_CASES[case](tmp_path)
    bags = tmp_path / "bags"
    write_episode_bag(bags / "ep", n_ticks=40)
    (tmp_path / "spec.yaml").write_text(yaml.safe_dump(small_spec()))
    args = {
        "eval": [*EVAL, "--transport", "inprocess"],
        "sweep": ["sweep", str(tmp_path / "spec.yaml"), "--workers", "1"],
        "score": ["score", str(bags), "--n-boot", "20"],
        "report": ["report", str(bags)],
        "run": ["run", "--transport", "inprocess", "--max-steps", "2"],
    }[command]
    assert_refused(lq(*args, "--out", str(out)), str(out), expected)
    assert not (tmp_path / "nowhere").exists()


# -- sweep folders ----------------------------------------------------------------------------------------------


def test_a_refused_lq_eval_leaves_the_running_sweeps_spec_untouched(tmp_path):
    """The spec was written before the folder's lock was taken: a second lq eval, refused, had overwritten it."""
    out = tmp_path / "eval"
    out.mkdir()
    (out / "eval_spec.yaml").write_text("the running sweep's spec\n")
    with sw.ResultStore(out).lock():  # a running sweep holds the folder
        line = assert_refused(lq(*EVAL, "--transport", "inprocess", "--out", str(out)), "another lq sweep is running")
    assert f"pid {os.getpid()}" in line
    assert (out / "eval_spec.yaml").read_text() == "the running sweep's spec\n"
    assert sorted(p.name for p in out.iterdir()) == [".lock", "eval_spec.yaml"]


def test_lq_eval_does_not_write_its_spec_through_a_link(tmp_path, outside):
    out = tmp_path / "eval"
    out.mkdir()
    (out / "eval_spec.yaml").symlink_to(outside)
    assert_refused(lq(*EVAL, "--transport", "inprocess", "--out", str(out)), "eval_spec.yaml: a symbolic link")
    assert outside.read_text() == SHELL


# -- numbers ----------------------------------------------------------------------------------------------------

ARABIC_INDIC_3 = "\u0663"  # ٣: str.isdigit() and int() take it as 3

DIGIT_CASES = {
    "eval --inits": (["--inits", ARABIC_INDIC_3], "inits: expected integers or ranges like 0-49"),
    "eval --tasks": (["--tasks", f"0-{ARABIC_INDIC_3}"], "tasks: expected integers or ranges like 0-49"),
    "eval --seeds": (["--seeds", ARABIC_INDIC_3], "--seeds: expected a comma-separated list of ints"),
    "eval --latencies": (["--latencies", f"0.{ARABIC_INDIC_3}"], "latencies_s: expected seconds or a distribution"),
    "eval superscript": (["--inits", "\u00b2"], "inits: expected integers or ranges like 0-49"),
}


@pytest.mark.parametrize("case", list(DIGIT_CASES))
def test_digits_of_another_script_are_refused_never_taken_as_numbers(tmp_path, case):
    args, expected = DIGIT_CASES[case]  # (the last of an option's values counts)
    assert_refused(lq(*EVAL, *args, "--transport", "inprocess", "--out", str(tmp_path / "o")), expected)
    assert not (tmp_path / "o").exists()


def test_lq_run_refuses_a_latency_in_another_scripts_digits(tmp_path):
    assert_refused(lq("run", "--latency", f"0.{ARABIC_INDIC_3}", "--transport", "inprocess", "--out",
                      str(tmp_path / "o")), "--latency", "expected seconds or a distribution")  # fmt: skip
    assert_refused(lq("run", "--latency", f"uniform:0:0.{ARABIC_INDIC_3}", "--transport", "inprocess", "--out",
                      str(tmp_path / "o")), "is not a number (digits 0-9)")  # fmt: skip


def test_lq_train_without_a_dataset_is_one_line(tmp_path):
    result = lq("train", "--policy", "oft", "--data", str(tmp_path / "none"), "--out", str(tmp_path / "w"))
    assert_refused(result, "not a dataset", "lq collect")


# -- a bug ------------------------------------------------------------------------------------------------------


def test_an_unexpected_exception_is_one_line_naming_the_traceback_file(tmp_path):
    """``import typer.rich_utils`` inside main() made ``typer`` a local name: any unexpected exception then ended in
    a second traceback (UnboundLocalError) instead of a message."""
    code = (
        "import sys; import lq_ros.scoring.bag_scorer as s\n"
        "def broken(path): raise KeyError('planted bug')\n"
        "s.find_bags = broken\n"
        "from lq_ros.cli import main\n"
        f"sys.argv = ['lq', 'score', {str(tmp_path)!r}]\n"
        "sys.exit(main())\n"
    )
    result = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 1 and len(lines) == 1, result.stderr
    assert "unexpected KeyError: 'planted bug'" in lines[0] and "Traceback" not in result.stderr
    log = lines[0].rsplit("the traceback: ", 1)[1].rstrip(")")
    text = Path(log).read_text()
    assert "Traceback" in text and "planted bug" in text and "lq score" in text
    os.unlink(log)
