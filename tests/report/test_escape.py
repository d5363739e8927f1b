"""Text from bags is data in report.md and report.html: a policy named ``<script>...</script> | x`` neither runs nor
splits a table, a failure reason with HTML or a link stays text, and the CSV keeps the name as it was read."""

from __future__ import annotations

import json
import re

import pandas as pd
import pytest
import yaml

from lq_ros.report import sweep_report as rp
from lq_ros.report.escape import md_link_target, md_table, md_text, md_to_html, one_line

EVIL = "<script>alert(1)</script> | x*y_[z](javascript:alert(2))"
REASON = "boom <img src=x onerror=alert(3)>\n| [click](javascript:alert(4))"


def test_md_text_escapes_every_markup_character_and_keeps_one_line():
    assert md_text("a|b*c _d_ `e<f>g[h]i\\j") == r"a\|b\*c \_d\_ \`e\<f\>g\[h\]i\\j"
    assert md_text("libero_spatial [max_steps=9]") == r"libero_spatial \[max_steps=9\]"  # inside a word: no markup
    assert md_text("two\nlines\r\n\u2028and\ttabs") == "two lines and tabs"
    assert one_line("bell\x07 escape\x1b[31m") == "bell\ufffd escape\ufffd[31m"


def test_md_table_keeps_one_cell_per_column_whatever_the_text():
    table = md_table(pd.DataFrame({"policy": [EVIL, "plain"], "n": [10, 3]}))
    rows = table.splitlines()
    assert len(rows) == 4 and "<script>" not in table
    assert {len(re.findall(r"(?<!\\)\|", row)) for row in rows} == {3}  # every row: | a | b |


def test_md_to_html_escapes_the_text_and_keeps_the_bold():
    sentence = f"**{md_text(EVIL)} · sync** against 0 s: {md_text('1 * 2')}"
    out = md_to_html(sentence)
    assert out.startswith("<b>&lt;script&gt;alert(1)&lt;/script&gt; | x*y_[z](javascript:alert(2)) · sync</b>")
    assert out.endswith("1 * 2") and "<script" not in out and "\\" not in out
    assert md_to_html("no \x00 placeholder") == "no \ufffd placeholder"


def test_md_link_target_cannot_leave_the_link_or_name_a_scheme():
    assert md_link_target("videos/a b).mp4") == "./videos/a%20b%29.mp4"
    assert md_link_target("javascript:alert(1)") == "./javascript%3Aalert%281%29"


def _row(policy: str, latency: float, task: int, init: int) -> dict:
    steps = 100 + int(200 * latency) + 5 * task + init
    fails = policy == "q" and latency > 0 and task == 4
    return {
        "policy": policy, "mode": "sync", "latency_s": latency, "suite": "libero_spatial", "task": task, "init": init,
        "seed": 7, "status": "failure" if fails else "success", "success": not fails, "completion_steps": steps,
        "completion_time_s": steps * 0.05, "action_ticks": 100 + task, "step_budget": 220, "tick_limit": 220,
        "trajectory_rate_hz": 20.0, "energy_sampling": "substep", "jerk_mean": 10.0 + latency + task / 10,
        "energy_total_j": 70.0 + 4.25 * steps, "git_commit": "abc</td><script>", "n_degenerate": 0,
    }  # fmt: skip


@pytest.fixture(scope="module")
def report(tmp_path_factory) -> rp.Report:
    out = tmp_path_factory.mktemp("escape")
    (out / "results").mkdir()
    for policy in (EVIL, "q"):
        for latency in (0.0, 0.2):
            for task in range(5):
                for init in range(2):
                    row = _row(policy, latency, task, init)
                    key = f"{'evil' if policy == EVIL else policy}-{latency}-{task}-{init}"
                    record = {"key": key, "status": row["status"], "row": row, "attempts": [], "bag": None}
                    (out / "results" / f"{key}.json").write_text(json.dumps(record))
    error = _row("q", 0.2, 0, 2) | {"status": "error", "success": None, "error_reason": REASON}
    record = {"key": "error", "status": "error", "row": error, "attempts": [], "bag": None}
    (out / "results" / "error.json").write_text(json.dumps(record))
    spec = {"name": "escape", "analysis": {"primary": [{"a": EVIL, "b": "q"}], "equivalence_margin": 0.5}}
    (out / "sweep.yaml").write_text(yaml.safe_dump(spec))
    return rp.build_report(out, n_boot=200)


def test_a_policy_named_script_is_text_in_report_md(report):
    md = report.files["report.md"].read_text()
    assert not re.search(r"(?<!\\)<(script|/script|img)|(?<!\\)\]\(javascript", md)  # only escaped: \<script\>
    assert md.count(md_text(EVIL)) >= 4  # summary, sentences, tables
    assert f"**{md_text(EVIL)} · sync, 0.2 s (N=4)** against 0 s" in md  # a sentence: bold kept, name escaped
    table = [line for line in md.splitlines() if line.startswith("|")]
    for line in table:  # no row gains a cell: each has as many unescaped | as its table's header
        assert len(re.findall(r"(?<!\\)\|", line)) in {len(re.findall(r"(?<!\\)\|", h)) for h in table}, line
    summary = md[md.index("## Summary") :].split("\n\n")[1].splitlines()
    assert len({len(re.findall(r"(?<!\\)\|", line)) for line in summary}) == 1


def test_a_policy_named_script_is_text_in_report_html(report):
    page = report.files["report.html"].read_text()
    assert "<script" not in page and "<img src=x" not in page  # (the figures are <img> of our own)
    assert "&lt;script&gt;alert(1)&lt;/script&gt;" in page
    assert "<b>&lt;script&gt;alert(1)&lt;/script&gt; | x*y_[z](javascript:alert(2)) · sync, 0.2 s (N=4)</b>" in page
    assert "boom &lt;img src=x onerror=alert(3)&gt;" in page  # the error row's reason, as text


def test_the_csv_keeps_the_name_as_read(report):
    episodes = pd.read_csv(report.files["episodes.csv"])
    assert EVIL in set(episodes["policy"])
