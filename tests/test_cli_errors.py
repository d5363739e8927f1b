"""A user's mistake is one line naming the problem and the valid values, exit code 2, no traceback, no bag.

Every case runs the real ``lq`` command line in a subprocess, as a user would.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]


def lq(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "lq_ros.cli", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout)  # fmt: skip


def assert_refused(result: subprocess.CompletedProcess, *expected: str) -> str:
    """Exit code 2 and exactly one line on stderr that contains every ``expected`` piece."""
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2, (result.returncode, result.stderr[-2000:])
    assert len(lines) == 1, result.stderr
    assert "Traceback" not in result.stdout + result.stderr
    for piece in expected:
        assert piece in lines[0], (piece, lines[0])
    return lines[0]


# -- lq run --------------------------------------------------------------------------------------------------

RUN_CASES = {
    "unknown suite": (["--suite", "libero_nosuch"], ["unknown suite 'libero_nosuch'", "libero_spatial", "libero_90"]),
    "task out of range": (["--task", "12"], ["task 12", "libero_spatial has tasks 0..9"]),
    "task of libero_90": (["--suite", "libero_90", "--task", "90"], ["task 90", "libero_90 has tasks 0..89"]),
    "negative task": (["--task", "-1"], ["task -1", "0..9"]),
    "init out of range": (["--init", "999"], ["init state 999", "0..49"]),
    "unknown policy": (["--policy", "nosuch"], ["unknown policy 'nosuch'", "scripted", "sine", "module:Class"]),
    "policy module missing": (["--policy", "nosuch_pkg.mod:Cls"], ["cannot import module 'nosuch_pkg.mod'"]),
    "argument not taken": (
        ["--policy", "sine", "--policy-arg", "chunk=4"],
        ["policy 'sine' takes no argument 'chunk'", "chunk_size: int = 8"],
    ),
    "argument of the wrong type": (
        ["--policy", "sine", "--policy-arg", "chunk_size=abc"],
        ["chunk_size='abc' is a str, not int", "chunk_size: int = 8"],
    ),
    "argument value refused": (
        ["--policy", "sine", "--policy-arg", "chunk_size=0"],
        ["policy 'sine' refuses chunk_size=0", "chunk_size must be >= 1"],
    ),
    "malformed policy argument": (["--policy-arg", "chunk_size"], ["--policy-arg expects key=value"]),
    "not an integer": (["--task", "abc"], ["Invalid value for '--task'"]),
    "unknown option": (["--tsk", "1"], ["No such option: --tsk"]),
    "latency between ticks": (["--latency", "0.075"], ["not a whole number", "0.05 s or 0.1 s"]),
    "negative timeout": (["--timeout", "-1"], ["--timeout: expected a number of seconds > 0, got -1.0"]),
    "camera size beyond a spec's": (["--camera-size", "100000"], ["--camera-size: expected 0", "1..1024 px"]),
}


@pytest.mark.parametrize("case", list(RUN_CASES))
def test_lq_run_refuses_in_one_line(tmp_path, case):
    args, expected = RUN_CASES[case]
    out = tmp_path / "bags"
    assert_refused(lq("run", *args, "--transport", "inprocess", "--out", str(out)), *expected)
    assert not out.exists(), "nothing may start: no bag folder"


@pytest.mark.slow
@pytest.mark.sim
def test_an_unknown_node_executor_is_refused_in_one_line(tmp_path, monkeypatch):
    monkeypatch.setenv("LQ_RCLPY_EXECUTOR", "multi")
    out = tmp_path / "bags"
    assert_refused(lq("run", "--out", str(out)), "LQ_RCLPY_EXECUTOR must be events or single_threaded, got 'multi'")
    assert not out.exists()


def test_an_unknown_sim_cpu_choice_is_refused_in_one_line(tmp_path, monkeypatch):
    monkeypatch.setenv("LQ_SIM_CPU", "3")
    out = tmp_path / "bags"
    assert_refused(lq("run", "--out", str(out)), "LQ_SIM_CPU must be auto or off, got '3'")
    assert not out.exists()


def test_an_unknown_node_forks_choice_is_refused_in_one_line(tmp_path, monkeypatch):
    monkeypatch.setenv("LQ_NODE_FORKS", "maybe")
    out = tmp_path / "bags"
    assert_refused(lq("run", "--out", str(out)), "LQ_NODE_FORKS must be on or off, got 'maybe'")
    assert not out.exists()


def test_a_bad_model_cache_limit_is_refused_in_one_line(tmp_path, monkeypatch):
    monkeypatch.setenv("LQ_MODEL_CACHE_MB", "-1")
    out = tmp_path / "bags"
    assert_refused(lq("run", "--transport", "inprocess", "--out", str(out)), "LQ_MODEL_CACHE_MB='-1'", "megabytes")
    assert not out.exists()


def test_rerun_into_the_same_out_is_refused_unless_overwrite(tmp_path):
    args = ["run", "--policy", "sine", "--max-steps", "3", "--transport", "inprocess", "--out", str(tmp_path)]
    first = lq(*args)
    assert first.returncode == 0, first.stderr[-2000:]
    (bag,) = [p for p in tmp_path.iterdir() if p.is_dir()]
    (bag / "marker").write_text("first run")
    line = assert_refused(lq(*args), "already exists", str(bag), "--overwrite")
    assert "another --out" in line
    assert (bag / "marker").exists(), "the refused rerun must not touch the first bag"
    again = lq(*args, "--overwrite")
    assert again.returncode == 0, again.stderr[-2000:]
    assert not (bag / "marker").exists() and (bag / "metadata.yaml").exists()  # a fresh episode folder


# -- lq sweep ------------------------------------------------------------------------------------------------

GOOD_SPEC = {"transport": "inprocess", "tasks": [0], "inits": [0], "policies": ["sine"], "latencies_s": [0.1],
             "modes": ["async"], "max_steps": 4}  # fmt: skip
SWEEP_CASES = {
    "unknown suite": ({"suite": "libero_nosuch"}, ["unknown suite", "libero_spatial"]),
    "task out of range": ({"tasks": [10]}, ["tasks: 10 is outside 0..9"]),
    "init out of range": ({"inits": [50]}, ["inits: 50 is outside 0..49"]),
    "unknown policy": ({"policies": ["nosuch"]}, ["unknown policy 'nosuch'", "sine"]),
    "argument not taken": (
        {"policies": [{"name": "sine", "args": {"chunk": 4}}]},
        ["policy 'sine' takes no argument 'chunk'", "chunk_size: int = 8"],
    ),
    "argument of the wrong type": (
        {"policies": [{"name": "sine", "args": {"chunk_size": "abc"}}]},
        ["chunk_size='abc' is a str, not int"],
    ),
    "unknown key": ({"latency": [0.1]}, ["unknown key(s) ['latency']"]),
}


@pytest.mark.parametrize("case", list(SWEEP_CASES))
def test_lq_sweep_refuses_a_bad_spec_in_one_line(tmp_path, case):
    change, expected = SWEEP_CASES[case]
    spec = tmp_path / "spec.yaml"
    spec.write_text(yaml.safe_dump({**GOOD_SPEC, **change}))
    out = tmp_path / "sweep"
    assert_refused(lq("sweep", str(spec), "--out", str(out)), str(spec), *expected)
    assert not out.exists()


def test_lq_sweep_refuses_an_unreadable_spec(tmp_path):
    assert_refused(lq("sweep", str(tmp_path / "missing.yaml")), "missing.yaml: cannot read")
    broken = tmp_path / "broken.yaml"
    broken.write_text("policies: [sine\n  latencies_s: {")
    assert_refused(lq("sweep", str(broken), "--out", str(tmp_path / "o")), "broken.yaml: not valid YAML")
    assert not (tmp_path / "o").exists()


def test_lq_reindex_of_a_folder_without_a_bag_is_refused(tmp_path):
    assert_refused(lq("reindex", str(tmp_path)), "no .mcap file")


# -- lq score: options are checked before any bag is read -----------------------------------------------------

SCORE_CASES = {
    "zero EE-Osc window": (["--osc-window", "0"], ["--osc-window must be >= 1", "got 0"]),
    "zero bootstrap resamples": (["--n-boot", "0"], ["--n-boot must be 1..100000", "got 0"]),
    "too many bootstrap resamples": (["--n-boot", "100000000"], ["--n-boot must be 1..100000"]),
    "negative seed": (["--seed", "-1"], ["--seed must be >= 0"]),
    "zero jobs": (["--jobs", "0"], ["--jobs must be >= 1"]),
    "negative overhead power": (["--overhead-w", "-5"], ["--overhead-w must be a finite number >= 0"]),
}


@pytest.mark.parametrize("case", list(SCORE_CASES))
def test_lq_score_refuses_a_bad_option_before_scoring(tmp_path, case):
    from tests.scoring.test_bag_scorer import write_episode_bag

    args, expected = SCORE_CASES[case]
    root = tmp_path / "bags"
    write_episode_bag(root / "ep", n_ticks=20)
    write_episode_bag(root / "ep2", n_ticks=20)
    assert_refused(lq("score", str(root), *args), *expected)
    assert not (root / "episodes.csv").exists()  # nothing was scored or written


# -- enumerated options: the choices in --help and in the refusal, with the closest one -------------------------

CHOICE_CASES = {
    # command, option, a typo, the choices, the suggestion
    "mode": ("run", "--mode", "asynch", ["'sync', 'async'"], "did you mean 'async'?"),
    "hold": ("run", "--hold", "repaet", ["'stop', 'repeat'"], "did you mean 'repeat'?"),
    "merge": ("run", "--merge", "rtx", ["'replace'", "'temporal_ensemble'", "'rtc_hard'"], "did you mean 'rtc'?"),
    "clock": ("run", "--clock", "realtim", ["'lockstep', 'realtime'"], "did you mean 'realtime'?"),
    "transport": ("run", "--transport", "inproc", ["'ros', 'inprocess'"], "did you mean 'inprocess'?"),
    "budget": ("run", "--budget-counts", "actions", ["'all', 'action'"], "did you mean 'action'?"),
    "rounding": ("run", "--latency-rounding", "nearst", ["'exact', 'nearest'"], "did you mean 'nearest'?"),
    "backend": ("sweep", "--backend", "rey", ["'local', 'ray'"], "did you mean 'ray'?"),
    "rate": ("score", "--rate", "ctrl", ["'auto', 'control', 'physics', 'native'"], "did you mean 'control'?"),
    "energy rate": ("score", "--energy-rate", "substeps", ["'substep'", "'native'"], "did you mean 'substep'?"),
}


@pytest.mark.parametrize("case", list(CHOICE_CASES))
def test_an_enumerated_option_lists_its_choices_in_help_and_refusal(tmp_path, case):
    command, option, typo, choices, hint = CHOICE_CASES[case]
    before = {"sweep": [str(tmp_path / "s.yaml")], "score": [str(tmp_path)]}.get(command, [])
    line = assert_refused(lq(command, *before, option, typo), f"Invalid value for '{option}': '{typo}' is not one of",
                          *choices, hint)  # fmt: skip
    assert "Value error" not in line
    help_text = " ".join(lq(command, "--help").stdout.replace("│", " ").split())
    bare = [c.replace("'", "").replace(", ", "|") for c in choices]
    if option == "--merge":  # too many for the option's column: the help text names them
        assert "replace, latest_only, weighted_average, average, conservative, temporal_ensemble, rtc, rtc_hard" in (
            help_text
        )
    else:
        assert any(f"<{b}" in help_text or f"{b}>" in help_text for b in bare), (option, bare)


def test_the_literal_choices_are_the_modules_own():
    from lq_ros.cli import common as cli
    from lq_ros.core.suite_constants import STEP_BUDGETS
    from lq_ros.run.sweep import BACKENDS

    assert cli.SUITE_HELP.endswith(": " + ", ".join(STEP_BUDGETS) + ".")
    from lq_ros.scoring.bag_scorer import ENERGY_RATES, TRAJECTORY_RATES

    assert tuple(b.value for b in cli.Backend) == BACKENDS
    assert tuple(r.value for r in cli.TrajectoryRate) == TRAJECTORY_RATES
    assert tuple(r.value for r in cli.EnergyRate) == ENERGY_RATES


@pytest.mark.parametrize(
    "args, expected",
    [
        (["--suite", "libero_spatail"], ["unknown suite 'libero_spatail' (did you mean 'libero_spatial'?)"]),
        (["--policy", "scriptd"], ["unknown policy 'scriptd' (did you mean 'scripted'?)", "module:Class"]),
        (["--policy", "openpie"], ["(did you mean 'openpi'?)"]),
    ],
)
def test_a_mistyped_suite_or_policy_gets_the_closest_name(tmp_path, args, expected):
    assert_refused(lq("run", *args, "--transport", "inprocess", "--out", str(tmp_path / "b")), *expected)
    assert not (tmp_path / "b").exists()


def test_a_mistyped_spec_key_policy_or_suite_gets_the_closest_name(tmp_path):
    spec = tmp_path / "spec.yaml"
    for change, hint in (({"sedes": [1]}, "did you mean 'seeds'?"), ({"policies": ["sien"]}, "did you mean 'sine'?"),
                         ({"suite": "libero_gaol"}, "did you mean 'libero_goal'?")):  # fmt: skip
        spec.write_text(yaml.safe_dump({**GOOD_SPEC, **change}))
        assert_refused(lq("sweep", str(spec), "--out", str(tmp_path / "o")), hint)


# -- what lq prints: results on stdout, nothing else; reasons under the table; paths whole ----------------------


@pytest.mark.sim
def test_a_run_error_prints_its_reason_under_the_table_and_stdout_holds_only_the_table(tmp_path):
    out = tmp_path / ("a_long_folder_name_" * 6)  # longer than any terminal: a piped path is never wrapped
    result = lq("run", "--policy", "faulty", "--policy-arg", "fault=raise", "--policy-arg", "at_requests=[1]",
                "--max-steps", "5", "--transport", "inprocess", "--out", str(out))  # fmt: skip
    assert result.returncode == 1, result.stderr[-2000:]
    assert " error │" in result.stdout and "constant" in result.stdout  # the row, no column cut short
    assert "[info]" not in result.stdout and "Applying task order" not in result.stdout
    (bag,) = [p for p in out.iterdir() if p.is_dir() and not p.name.endswith("logs")]
    lines = result.stderr.splitlines()
    trace = bag / "logs" / "episode.log"  # the error line names where its traceback is
    assert f"error: {bag.name}: PolicyError: injected failure on request 1 (traceback: {trace})" in lines
    assert "injected failure on request 1" in trace.read_text()
    assert f"bag: {bag}" in lines  # one line, whole
    assert not any("macro file" in line for line in lines)  # robosuite's private-macro advice is silenced


@pytest.mark.sim
def test_lq_score_of_a_folder_with_one_bag_writes_the_aggregates(tmp_path):
    from tests.scoring.test_bag_scorer import write_episode_bag

    root = tmp_path / "bags"
    write_episode_bag(root / "ep", n_ticks=20)
    folder = lq("score", str(root))
    assert folder.returncode == 0, folder.stderr[-2000:]
    assert (root / "episodes.csv").exists() and (root / "aggregates.csv").exists()
    assert "| policy" in folder.stdout or "policy |" in folder.stdout  # the markdown aggregate table
    (root / "episodes.csv").unlink()
    (root / "aggregates.csv").unlink()
    one = lq("score", str(root / "ep"))  # the bag itself: its row, no tables
    assert one.returncode == 0 and "steps" in one.stdout and not (root / "episodes.csv").exists()
