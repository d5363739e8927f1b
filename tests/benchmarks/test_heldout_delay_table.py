"""benchmarks/heldout_delay_table.py on a synthetic store: the task-level test is printed, and a comparison of
identical episodes (oft at 0.2 s: variant=delay runs the naive arm's episodes, its slack arm is the naive arm) or a
repeat of another comparison is in no Holm family."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

_PATH = Path(__file__).resolve().parents[2] / "benchmarks" / "heldout_delay_table.py"
_SPEC = importlib.util.spec_from_file_location("heldout_delay_table", _PATH)
table = importlib.util.module_from_spec(_SPEC)
sys.modules.setdefault("heldout_delay_table", table)
_SPEC.loader.exec_module(table)

ARGS = {"naive": {}, "delay": {"variant": "delay"}, "lookahead": {"variant": "delay", "lookahead": 1}}


def _store(root: Path) -> None:
    """oft, 0.2 s, 5 tasks x 2 inits: naive and delay fail tasks 0-3 in the same episodes; the look-ahead succeeds
    everywhere."""
    (root / "results").mkdir(parents=True)
    for arm, args in ARGS.items():
        for task in range(5):
            for init in range(2):
                ok = arm == "lookahead" or task == 4
                row = {"policy": "oft", "policy_args": args, "mode": "async", "latency_s": 0.2,
                       "latency_dist": "constant", "suite": "libero_object", "task": task, "init": init, "seed": 7,
                       "status": "success" if ok else "failure", "success": ok, "completion_steps": 100 if ok else 280,
                       "completion_time_s": 5.0 if ok else 14.0, "action_ticks": 90, "energy_total_j": 500.0,
                       "step_budget": 280, "git_commit": "abc", "cpu_class": "x86", "versions": "{}"}  # fmt: skip
                key = f"{arm}-{task}-{init}"
                record = {"key": key, "status": row["status"], "row": row, "attempts": [], "bag": None}
                (root / "results" / f"{key}.json").write_text(json.dumps(record))


def test_identical_and_repeated_comparisons_are_in_no_family(tmp_path, capsys, monkeypatch):
    _store(tmp_path)
    monkeypatch.setattr(sys, "argv", ["heldout_delay_table.py", str(tmp_path)])
    table.main()
    out = capsys.readouterr().out
    comparisons = out[out.index("Planned comparisons") :]
    assert "Holm over the 1 in the family" in comparisons  # look-ahead against delay, alone
    rows = [[c.strip() for c in line.strip().strip("|").split("|")] for line in comparisons.splitlines()[1:]]
    header, rows = rows[0], [r for r in rows[2:] if len(r) == len(rows[0])]
    found = {(r["A"], r["B"]): r for r in (dict(zip(header, r, strict=True)) for r in rows)}
    assert found[("delay @ 0.2 s", "naive @ 0.2 s")]["in family"] == "False"  # identical episodes
    lookahead = found[("delay + lookahead @ 0.2 s", "delay @ 0.2 s")]
    # 8 discordant pairs in 4 tasks, one task without: the task-level p over 5 task means (4 at +1, one 0) is
    # 4/32 (the zero task's sign never matters), Holm over a family of one; McNemar 2/2^8.
    assert lookahead["in family"] == "True" and lookahead["mcnemar_p Holm"] == "0.0078"
    assert lookahead["cluster_p"] == lookahead["cluster_p Holm"] == "0.12"
    assert (lookahead["called (these tasks)"], lookahead["called (other tasks)"]) == ("yes", "no")
    assert found[("delay + lookahead @ 0.2 s", "naive @ 0.2 s")]["in family"] == "False"  # repeats the one above
