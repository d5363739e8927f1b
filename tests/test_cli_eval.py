"""``lq eval``: the paper's protocol for one policy without YAML; index ranges in specs; flags named as spec keys."""

from __future__ import annotations

import json
import re

import pytest
import yaml

from lq_ros.cli.eval import EVAL_SPEC_FILE, EVAL_SPEC_FLAGS, eval_spec
from lq_ros.core.run_config import PROTOCOL_FIELDS
from lq_ros.run.sweep.spec import FLAG_TO_SPEC_KEY, MODES, SPEC_KEYS, SpecError, expand_spec, index_list
from tests.test_cli_errors import assert_refused, lq

#: The flags whose spec key is not their own name: seconds are in the key's name (the documented mapping).
NAMED_OTHERWISE = {"--latency": "latencies_s", "--latencies": "latencies_s", "--timeout": "timeout_s",
                   "--primary": "analysis.primary", "--equivalence-margin": "analysis.equivalence_margin"}  # fmt: skip
#: Flags of lq run / lq eval that are no spec setting: where results go and how the command runs.
NOT_IN_A_SPEC = {"--out", "--overwrite", "--json", "--domain-id", "--workers", "--help"}


def flags_of(command: str) -> set[str]:
    """Every long option in ``lq COMMAND --help`` (a boolean's --no-X form aside)."""
    return set(re.findall(r"(?<![\w-])--[a-z][a-z-]*", lq(command, "--help").stdout)) - {
        f for f in re.findall(r"--no-[a-z-]+", lq(command, "--help").stdout)
    }


def test_index_ranges():
    assert index_list("0-3,7", "inits", 0, 49) == [0, 1, 2, 3, 7]
    assert index_list([1, 2], "inits", 0, 49) == [1, 2]
    for bad in ("3-1", "0-50", "a", "1,1", "-1"):
        with pytest.raises(SpecError, match="inits"):
            index_list(bad, "inits", 0, 49)


def test_a_spec_takes_ranges_and_all():
    raw = {"suites": {"libero_spatial": {"tasks": "0-1", "inits": "all"}}, "policies": ["scripted"],
           "latencies_s": [0.0], "modes": ["sync"]}  # fmt: skip
    spec = expand_spec(raw)
    assert {(c.task, c.init) for c in spec.configs} == {(t, i) for t in (0, 1) for i in range(50)}
    short = expand_spec({"suite": "libero_spatial", "tasks": "all", "inits": "3-4", "policies": ["scripted"],
                         "latencies_s": [0.0], "modes": ["sync"]})  # fmt: skip
    assert {(c.task, c.init) for c in short.configs} == {(t, i) for t in range(10) for i in (3, 4)}


@pytest.mark.parametrize("command", ["run", "eval"])
def test_every_flag_is_a_spec_key_or_mapped_to_one(command):
    """One set of names: a flag that sets an episode is its spec key (dashes for underscores, singular for one
    value) or in the documented mapping; every mapped key is one a spec takes."""
    flags = flags_of(command)
    assert "--policy" in flags and "--transport" in flags  # the help was read
    unmapped = flags - NOT_IN_A_SPEC - set(FLAG_TO_SPEC_KEY)
    assert unmapped == set(), f"lq {command} flags without a spec key: {sorted(unmapped)}"
    for flag in flags & set(FLAG_TO_SPEC_KEY):
        key = FLAG_TO_SPEC_KEY[flag]
        assert NAMED_OTHERWISE.get(flag, key) == key, (flag, key)
        head = re.split(r"[.\[]", key)[0]
        assert head in SPEC_KEYS, (flag, key)
        if key.startswith("modes."):
            _, mode, field = key.split(".")
            assert mode in MODES and field in PROTOCOL_FIELDS and field == flag[2:].replace("-", "_"), (flag, key)
        elif flag not in NAMED_OTHERWISE and "[" not in key:  # a top-level key: the flag's own name, or its plural
            assert key in (flag[2:].replace("-", "_"), flag[2:].replace("-", "_") + "s"), (flag, key)
    if command == "eval":
        assert flags - NOT_IN_A_SPEC == set(EVAL_SPEC_FLAGS)


def test_eval_writes_its_flags_under_their_spec_keys():
    raw = eval_spec("sine", {"chunk_size": 4}, "libero_object", "0-2", "all", [0.0, 0.1], ["sync", "async"], "rtc", 3,
                    [7, 8], 256, 40, "ros", "mine")  # fmt: skip
    spec = expand_spec(raw)
    assert {c.suite for c in spec.configs} == {"libero_object"} and {c.seed for c in spec.configs} == {7, 8}
    assert {c.policy_args["chunk_size"] for c in spec.configs} == {4}
    assert {(c.mode, c.merge, c.replan_steps) for c in spec.configs} >= {("async", "rtc", 5), ("sync", "replace", 3)}
    assert {c.camera_size for c in spec.configs} == {256} and {c.max_steps for c in spec.configs} == {40}
    assert len(spec.configs) == 3 * 50 * 2 * 2 * 2 and spec.transport == "ros"
    assert {c.replan_steps_source for c in spec.configs if c.mode == "sync"} == {"flag"}
    # Without --replan-steps, sync executes the policy's declared reference protocol; --budgets is the spec's budgets.
    raw = eval_spec("sine", {}, "libero_object", "0", "0", [0.0], ["sync"], "replace", None, [7], 0, 0, "inprocess",
                    "mine", "lerobot")  # fmt: skip
    assert "replan_steps" not in raw["modes"]["sync"] and raw["budgets"] == "lerobot"
    (cfg,) = expand_spec(raw).configs
    assert (cfg.replan_steps, cfg.replan_steps_source, cfg.budget) == (5, "policy", 280)


def test_the_help_names_each_flags_spec_key_where_they_differ():
    help_text = " ".join(lq("eval", "--help").stdout.replace("│", " ").split())  # the words, without the box
    for words in ("latencies_s", "policies: [{name: P, args: {key: value}}]", "modes: {async: {merge: M}}",
                  "modes: {sync: {replan_steps: K}}", "current directory are importable"):  # fmt: skip
        assert words in help_text, words


def test_a_spec_key_given_by_its_flag_name_is_refused_with_the_key(tmp_path):
    spec = tmp_path / "s.yaml"
    spec.write_text("policies: [scripted]\nlatencies: [0, 0.1]\n")
    assert_refused(lq("sweep", str(spec)), "unknown key(s) ['latencies']", "did you mean 'latencies_s'?")
    spec.write_text("policies: [scripted]\nlatencies_s: [0]\npolicy_arg: {chunk_size: 4}\n")
    assert_refused(lq("sweep", str(spec)), "did you mean policies: [{name: NAME, args: {KEY: VALUE}}]?")
    spec.write_text("policies: [scripted]\nlatencies_s: [0]\nmerge: rtc\n")
    assert_refused(lq("sweep", str(spec)), "did you mean modes: {async: {merge: ...}}?")


def test_bad_modes_and_ranges_are_one_line(tmp_path):
    assert_refused(lq("eval", "--policy", "scripted", "--modes", "asynch", "--out", str(tmp_path / "a")),
                   "--modes", "sync, async", "did you mean 'async'?")  # fmt: skip
    assert_refused(
        lq("eval", "--policy", "scripted", "--inits", "0-60", "--out", str(tmp_path / "b")), "inits", "0..49"
    )
    assert_refused(lq("eval", "--policy", "scripted", "--merge", "rtx", "--out", str(tmp_path / "c")),
                   "'rtx' is not one of", "'temporal_ensemble'", "did you mean 'rtc'?")  # fmt: skip
    assert_refused(lq("eval", "--policy", "scripted", "--seeds", "7,x", "--out", str(tmp_path / "d")), "--seeds")
    assert not any((tmp_path / d).exists() for d in "abcd")


@pytest.mark.slow
@pytest.mark.sim
def test_a_tiny_evaluation_runs_writes_its_spec_and_report_and_prints_the_table(tmp_path):
    out = tmp_path / "eval"
    args = ["eval", "--policy", "scripted", "--tasks", "0", "--inits", "0", "--latencies", "0,0.2", "--modes",
            "sync,async", "--workers", "1", "--out", str(out)]  # fmt: skip
    result = lq(*args, timeout=900)
    assert result.returncode == 0, result.stderr[-3000:]
    spec = yaml.safe_load((out / EVAL_SPEC_FILE).read_text())
    assert spec["latencies_s"] == [0.0, 0.2] and (spec["suite"], spec["tasks"], spec["inits"]) == ("libero_spatial",
                                                                                                  "0", "0")  # fmt: skip
    assert set(spec["modes"]) == {"sync", "async"} and spec["policies"] == ["scripted"]
    assert len(expand_spec(spec).configs) == 4  # the written spec is the one that ran: lq sweep runs it as is
    assert (out / "report" / "report.html").exists() and (out / "report" / "paired_policies.csv").exists()
    # lerobot-eval's eval_info.json, one per protocol cell, for a LeRobot user's scripts
    cells = sorted(p.parent.name for p in (out / "eval_info").glob("*/eval_info.json"))
    assert cells == ["async_0ms", "async_200ms", "sync_0ms", "sync_200ms"], cells
    info = json.loads((out / "eval_info" / "sync_0ms" / "eval_info.json").read_text())
    assert len(info["per_episode"]) == 1 and info["overall"]["n_episodes"] == 1
    assert info["aggregated"]["pc_success"] == 100.0 * info["per_episode"][0]["success"]
    table = result.stdout
    assert "scripted on libero_spatial" in table and table.count("0.2 s (N=4)") == 2 and table.count("0 s (N=0)") == 2
    assert "success %" in table and "[Info]" not in table and "[info]" not in table  # no LIBERO chatter on stdout
    assert "4 episodes" in result.stderr and "report.html" in result.stderr
    again = lq(*args, timeout=900)  # resumable: nothing runs again
    assert again.returncode == 0 and "4 of 4 episodes already finished" in again.stderr
    assert again.stdout == table  # the same report


def test_eval_declares_its_primary_comparisons():
    """lq eval --primary 0.2 --equivalence-margin 0.1: sync against async at 0.2 s is the Holm family."""
    raw = eval_spec("flow", {"variant": "delay"}, "libero_object", "0-2", "0", [0.0, 0.2], ["sync", "async"],
                    "replace", 5, [7], 0, 0, "inprocess", "mine", primary=[0.2], equivalence_margin=0.1)  # fmt: skip
    assert raw["analysis"] == {"primary": [{"a": "flow [variant=delay]", "b": "flow [variant=delay]",
                                            "mode_a": "sync", "mode_b": "async", "latency_s": 0.2}],
                               "equivalence_margin": 0.1}  # fmt: skip
    expand_spec(raw)  # valid
    assert "analysis" not in eval_spec("flow", {}, "libero_object", "0", "0", [0.0], ["sync"], "replace", 5, [7], 0,
                                       0, "inprocess", "mine")  # fmt: skip
