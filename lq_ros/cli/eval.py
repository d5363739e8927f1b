"""``lq eval``: one policy with the paper's protocol, from flags; a resumable sweep, then its report."""

from __future__ import annotations

import contextlib
import sys
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from lq_ros.cli.common import (
    BUDGETS_HELP,
    MERGE_HELP,
    POLICY_ARG_HELP,
    POLICY_HELP,
    REPLAN_STEPS_HELP,
    SUITE_HELP,
    Budgets,
    Transport,
    _out_folder,
    _parse_policy_args,
    _refuse,
    console,
    print_error_reasons,
    stdout_console,
)
from lq_ros.cli.report import print_skipped
from lq_ros.cli.sweep import _run_sweep_with_progress
from lq_ros.core.merge import Merge
from lq_ros.core.run_config import DEFAULT_CAMERA_SIZE_PX

#: ``lq eval``'s flags that set what runs, each named as the spec key it sets or mapped to it in
#: lq_ros.run.sweep.spec.FLAG_TO_SPEC_KEY (tests/test_cli_eval.py checks both). --workers and --out say how it runs.
EVAL_SPEC_FLAGS = (
    "--policy", "--policy-arg", "--suite", "--tasks", "--inits", "--latencies", "--modes", "--merge", "--replan-steps",
    "--seeds", "--camera-size", "--max-steps", "--budgets", "--budget-counts", "--transport", "--primary",
    "--equivalence-margin",
)  # fmt: skip
#: --budget-counts values: what the tick budget counts (lq_ros.core.run_config.BUDGET_COUNTS), or both (the twins).
BUDGET_CHOICES = {"all": ["all"], "action": ["action"], "both": ["all", "action"]}
#: The file ``lq eval`` writes the spec it runs to, in OUT (``lq sweep OUT/eval_spec.yaml --out OUT`` runs it again).
EVAL_SPEC_FILE = "eval_spec.yaml"
#: What the printed table's brackets and columns mean (the report says more: docs/guide/scoring.md).
EVAL_CAPTION = (
    "[lo, hi]: 95% interval (success: Wilson); success 95% (tasks): clustered by task, from {n} tasks on; "
    "(succ.): over successful episodes; (n=k): fewer than {n} values, no interval"
)
#: Columns of the report's summary table (lq_ros.report.tables.summary_table) that ``lq eval`` prints.
EVAL_COLUMNS = (
    "mode", "latency", "n", "errors", "success %", "success 95% (tasks)", "time s (succ.)", "jerk m/s³ (succ.)",
    "EE-Osc mm (succ.)", "J/step (succ.)",
)  # fmt: skip


def _csv(text: str, flag: str, kind=str) -> list:
    """``a,b,c`` -> [a, b, c] converted by ``kind``; a bad item is one line naming the flag."""
    items = [t for t in (x.strip() for x in text.split(",")) if t]
    try:
        return [kind(t if kind is str or t.isascii() else "not ASCII") for t in items]  # numbers: digits 0-9 only
    except ValueError:
        _refuse(f"{flag}: expected a comma-separated list of {kind.__name__}s, got {text!r}")
    return []


def _number_or_text(text: str) -> float | str:
    """A latency as YAML should hold it: seconds as a number, a distribution as its text."""
    try:
        return float(text if text.isascii() else "not ASCII")  # another script's digits stay text (then refused)
    except ValueError:
        return text


def eval_spec(policy: str, policy_args: dict, suite: str, tasks: str, inits: str, latencies: list, modes: list[str],
              merge: str, replan_steps: int | None, seeds: list[int], camera_size: int, max_steps: int, transport: str,
              name: str, budgets: str = "paper", primary: list | None = None,
              equivalence_margin: float = 0.0, budget_counts: list[str] | None = None) -> dict:  # fmt: skip
    """The sweep spec ``lq eval`` runs: its flags under their spec keys (docs/guide/sweeps.md). Without
    ``replan_steps`` sync executes the policy's reference protocol's (the sweep's default). ``primary``: the
    latencies at which sync against async is a declared primary comparison (``analysis.primary``)."""
    protocol = {
        "sync": {**({} if replan_steps is None else {"replan_steps": replan_steps}), "hold": "stop"},
        "async": {"merge": merge, "request_threshold": -1},
    }
    raw = {
        "name": name, "transport": transport, "suite": suite, "tasks": tasks, "inits": inits,
        "policies": [{"name": policy, "args": policy_args} if policy_args else policy], "latencies_s": latencies,
        "modes": {m: protocol[m] for m in modes}, "seeds": seeds,
    }  # fmt: skip
    raw |= {"camera_size": camera_size} if camera_size else {}
    raw |= {"budgets": budgets} if budgets != "paper" else {}
    analysis: dict = {}
    if primary:
        analysis["primary"] = [{"a": _label(policy, policy_args), "b": _label(policy, policy_args), "mode_a": "sync",
                                "mode_b": "async", "latency_s": latency} for latency in primary]  # fmt: skip
    if equivalence_margin:
        analysis["equivalence_margin"] = equivalence_margin
    raw |= {"analysis": analysis} if analysis else {}
    raw |= {"budget_counts": budget_counts} if budget_counts and budget_counts != ["all"] else {}
    return raw | ({"max_steps": max_steps} if max_steps else {})


def _label(policy: str, policy_args: dict) -> str:
    """The report's variant label of the policy (lq_ros.scoring.labels), as a declared comparison names its arms."""
    import pandas as pd

    from lq_ros.scoring.labels import base_labels

    row = pd.DataFrame([{"policy": policy, "policy_args": policy_args or None}])
    return str(base_labels(row, ("budget_counts", "latency_dist")).iloc[0])


def eval_(
    policy: Annotated[str, typer.Option(help=POLICY_HELP)],
    out: Annotated[
        Path,
        typer.Option(help="Folder for the spec, the episodes and the report. Run the same command again to resume."),
    ],
    policy_arg: Annotated[list[str], typer.Option(help=POLICY_ARG_HELP, metavar="KEY=VALUE")] = [],  # noqa: B006
    suite: Annotated[str, typer.Option(help=SUITE_HELP)] = "libero_spatial",
    tasks: Annotated[str, typer.Option(help="Task indices: all, or ranges and indices like 0-9 or 0-4,7.")] = "all",
    inits: Annotated[
        str, typer.Option(help="Init states: all (0-49, the paper's 50 per task), or ranges like 0-9.")
    ] = "all",
    latencies: Annotated[
        str,
        typer.Option(
            help="Injected latencies Δt_sim, comma-separated: seconds (whole 0.05 s ticks) or distributions "
            "(uniform:0.1:0.3). Spec key: latencies_s."
        ),
    ] = "0,0.1,0.2,0.4",
    modes: Annotated[
        str, typer.Option(help="Protocols, comma-separated: sync, async, or sync,async (both, paired).")
    ] = "sync,async",
    merge: Annotated[Merge, typer.Option(help=MERGE_HELP, metavar="STRATEGY")] = Merge.REPLACE,
    replan_steps: Annotated[int | None, typer.Option(help=REPLAN_STEPS_HELP)] = None,
    seeds: Annotated[str, typer.Option(help="Seeds, comma-separated: every episode once per seed (7 or 7,8,9).")] = "7",
    primary: Annotated[
        str,
        typer.Option(
            help="Latencies (s, comma-separated) where sync against async is a primary comparison: the report's Holm "
            "family; none: every comparison exploratory. Spec key: analysis.primary."
        ),
    ] = "",
    equivalence_margin: Annotated[
        float,
        typer.Option(
            help="Success difference within which sync and async may be called equivalent (TOST; 0.1 = 10 points); "
            "0: never. Spec key: analysis.equivalence_margin."
        ),
    ] = 0.0,
    camera_size: Annotated[
        int,
        typer.Option(help=f"Camera render size, px; 0: the policy's reference size, else {DEFAULT_CAMERA_SIZE_PX}."),
    ] = 0,
    max_steps: Annotated[int, typer.Option(help="Tick budget per episode; 0: the suite's (see --budgets).")] = 0,
    budgets: Annotated[Budgets, typer.Option(help=BUDGETS_HELP)] = Budgets.paper,
    budget_counts: Annotated[
        str,
        typer.Option(
            help="What the tick budget counts: all (the paper's: holds count), action (only ticks whose command came "
            "from a chunk), or both: every episode under each, the action-budget twins the report's budget "
            "attribution needs (twice the episodes; docs/guide/scoring.md).",
            metavar="all|action|both",
        ),
    ] = "all",
    overwrite: Annotated[
        bool, typer.Option(help="Replace OUT's earlier results (all its episodes run again) instead of resuming.")
    ] = False,
    workers: Annotated[int | None, typer.Option(help="Episodes run in parallel; default: CPU cores.")] = None,
    transport: Annotated[
        Transport,
        typer.Option(
            help="inprocess: one process per worker, no ROS (fastest; the same episodes); ros: the ROS nodes."
        ),
    ] = Transport.inprocess,
) -> None:
    """Evaluate one policy with the paper's protocol, without a YAML file: tasks x init states x latencies x
    protocols (sync and async), paired.

    Writes the spec it runs to OUT/eval_spec.yaml, runs it as a resumable sweep with a progress bar (run the same
    command again after any stop: finished episodes are skipped; results made by other code than what runs now are
    refused, naming the change: --overwrite replaces them), writes the report (OUT/report: report.html,
    report.md, figures, CSV tables) and prints the success table. Exits 1 if any episode was a run error; their
    reasons are printed under the table.

    Every flag is a spec key (docs/guide/sweeps.md): --suite, --tasks, --inits, --seeds, --modes, --camera-size,
    --max-steps, --budgets, --budget-counts and --transport by the same name (--budget-counts both: [all, action]);
    --latencies is latencies_s, --policy and --policy-arg are policies: [{name: P, args: {key: value}}], --merge is
    modes: {async: {merge: M}}, --replan-steps is modes: {sync: {replan_steps: K}}.
    """
    import yaml

    from lq_ros.run import sweep as sw
    from lq_ros.run.validation import did_you_mean

    if workers is not None and workers < 1:
        _refuse(f"--workers must be >= 1, got {workers}")
    mode_list = _csv(modes, "--modes")
    bad = [m for m in mode_list if m not in ("sync", "async")]
    if not mode_list or bad or len(set(mode_list)) != len(mode_list):
        hint = did_you_mean(bad[0], ("sync", "async")) if bad else ""
        _refuse(f"--modes {modes!r}: expected sync, async or sync,async{hint}")
    if budget_counts not in BUDGET_CHOICES:
        hint = did_you_mean(budget_counts, BUDGET_CHOICES)
        _refuse(f"--budget-counts {budget_counts!r}: expected all, action or both{hint}")
    raw = eval_spec(
        policy, _parse_policy_args(policy_arg), suite, tasks, inits,
        [_number_or_text(v) for v in _csv(latencies, "--latencies")], mode_list, merge.value, replan_steps,
        _csv(seeds, "--seeds", int), camera_size, max_steps, transport.value, out.resolve().name or "eval",
        budgets.value, _csv(primary, "--primary", float), equivalence_margin, BUDGET_CHOICES[budget_counts],
    )  # fmt: skip
    try:
        spec = sw.expand_spec(raw, default_name="eval")
        sw.check_policies(spec.configs)
    except sw.SpecError as exc:
        _refuse(str(exc))
    _out_folder(out)
    try:
        # The folder's lock first: a refused lq eval (another sweep runs there) writes nothing, not even the spec.
        with sw.ResultStore(out).lock():
            sw.atomic_write_text(out / EVAL_SPEC_FILE, yaml.safe_dump(raw, sort_keys=False, allow_unicode=True))
            console.print(f"{len(spec.configs)} episodes; the spec: {out / EVAL_SPEC_FILE}", highlight=False)
            summary = _run_sweep_with_progress(spec, out, workers=workers, transport=transport.value,
                                               overwrite=overwrite)  # fmt: skip
    except (sw.RayConnectError, sw.StoreError) as exc:
        _refuse(str(exc))
    from lq_ros.report.eval_info import EVAL_INFO_DIR, write_eval_info  # (matplotlib, pandas, scipy: once needed)
    from lq_ros.report.sweep_report import build_report

    with contextlib.redirect_stdout(sys.stderr):
        result = build_report(out)
    infos = write_eval_info(result.episodes, out)  # lerobot-eval's eval_info.json, one per protocol cell
    print_eval_table(result, f"{policy} on {suite}")
    print_error_reasons(result.episodes.to_dict("records"))
    print_skipped(result.skipped)
    console.print(
        f"report: {result.files['report.html']}  (markdown: {result.files['report.md'].name})", highlight=False
    )
    console.print(f"lerobot-eval's eval_info.json: {out / EVAL_INFO_DIR}/<cell>/ ({len(infos)} cells)", highlight=False)
    if summary.counts["error"]:
        raise typer.Exit(1)


def print_eval_table(result, title: str) -> None:
    """The report's summary table, the columns of EVAL_COLUMNS, on stdout: each metric with its 95% interval."""
    from lq_ros.report.tables import summary_table
    from lq_ros.scoring.intervals import MIN_N_INTERVAL

    summary = summary_table(result.pooled)
    columns = [c for c in EVAL_COLUMNS if c in summary.columns]
    from rich.markup import escape

    table = Table(title=escape(title), caption=escape(EVAL_CAPTION.format(n=MIN_N_INTERVAL)))
    for column in columns:
        table.add_column(column, justify="left" if column in ("mode", "latency") else "right")
    for _, r in summary.iterrows():
        table.add_row(*(str(r[c]) for c in columns))
    stdout_console().print(table)
