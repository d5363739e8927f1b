"""``lq eval``: the paper's protocol for one policy without YAML; index ranges in specs; flags named as spec keys."""

from __future__ import annotations

import re

import pytest
import yaml

from lq_ros.cli import EVAL_FLAG_TO_SPEC_KEY
from lq_ros.run.sweep.spec import SpecError, expand_spec, index_list
from tests.test_cli_errors import assert_refused, lq


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


def test_every_flag_maps_to_a_spec_key_and_is_in_the_help():
    help_text = lq("eval", "--help").stdout
    spec_keys = {"name", "transport", "suites", "tasks", "inits", "seeds", "policies", "latencies_s", "modes"}
    for flag, key in EVAL_FLAG_TO_SPEC_KEY.items():
        assert flag in help_text, flag
        assert re.split(r"[.\[]", key)[0] in spec_keys, key
    # Where the names differ, the help says which spec key a flag is.
    assert "latencies_s" in help_text and "args" in help_text


def test_bad_modes_and_ranges_are_one_line(tmp_path):
    assert_refused(lq("eval", "--policy", "scripted", "--modes", "asynch", "--out", str(tmp_path / "a")),
                   "--modes", "sync, async")  # fmt: skip
    assert_refused(
        lq("eval", "--policy", "scripted", "--inits", "0-60", "--out", str(tmp_path / "b")), "inits", "0..49"
    )
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


@pytest.mark.slow
@pytest.mark.sim
def test_a_tiny_evaluation_runs_writes_its_spec_and_report_and_prints_the_table(tmp_path):
    out = tmp_path / "eval"
    args = ["eval", "--policy", "scripted", "--tasks", "0", "--inits", "0", "--latencies", "0,0.2", "--modes",
            "async", "--workers", "1", "--out", str(out)]  # fmt: skip
    result = lq(*args, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    spec = yaml.safe_load((out / "eval_spec.yaml").read_text())
    assert spec["latencies_s"] == [0.0, 0.2] and spec["suites"] == {"libero_spatial": {"tasks": "0", "inits": "0"}}
    assert (out / "report" / "report.html").exists() and (out / "report" / "paired_policies.csv").exists()
    assert "scripted on libero_spatial" in result.stdout and "0.2 s (N=4)" in result.stdout
    again = lq(*args, timeout=600)  # resumable: nothing runs again
    assert again.returncode == 0 and "2 of 2 episodes already finished" in again.stderr
