"""``lq report``: load a sweep's episodes, pool them into cells, and write the figures, tables, provenance, an HTML
and a markdown page.

Input is a sweep folder (its ``results/`` store, see lq_ros/run/sweep/store.py) or any folder of episode bags
(scored on the fly). Figures pool every task and init state of a (policy, mode, latency) cell; the
per-task aggregate table is written beside them. Aggregation rules and CIs come from lq_ros/scoring/aggregate.py;
the drawing is lq_ros/report/figures.py, the tables lq_ros/report/tables.py, the sentences lq_ros/report/prose.py.
"""

from __future__ import annotations

import html
import json
import os
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only, never a display

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from lq_ros.core.bounded_file import FileRefused  # noqa: E402
from lq_ros.core.safe_write import output_folder, save_figure, write_csv, write_text  # noqa: E402
from lq_ros.core.safe_yaml import YamlRefused, load_yaml, read_text_file  # noqa: E402
from lq_ros.report import async_figures as report_async  # noqa: E402
from lq_ros.report import episode_media as media  # noqa: E402
from lq_ros.report.escape import md_table, md_text, md_to_html  # noqa: E402
from lq_ros.report.failure_figures import fig_failure_modes  # noqa: E402
from lq_ros.report.figures import ENERGY_PARTS, FIGURE_KEYS, FIGURES, make_figures  # noqa: E402
from lq_ros.report.plot_rules import never_moved  # noqa: E402
from lq_ros.report.prose import INTRO, NOTES, comparison_sentences, paired_sentences  # noqa: E402
from lq_ros.report.runs import load_runs  # noqa: E402
from lq_ros.report.tables import (  # noqa: E402
    comparison_table,
    counted,
    episode_table,
    fmt_cell,
    paired_table,
    per_task_view,
    summary_table,
)
from lq_ros.run.sweep.record_check import read_manifest  # noqa: E402
from lq_ros.run.sweep.spec import MAX_SPEC_BYTES  # noqa: E402
from lq_ros.scoring import aggregate as agg  # noqa: E402
from lq_ros.scoring import failure_aggregate, intervals, labels, paired_tests  # noqa: E402
from lq_ros.scoring.attribution import decompose, decomposition_table  # noqa: E402
from lq_ros.scoring.decisions import AnalysisPlan, PlanError, parse_analysis  # noqa: E402
from lq_ros.scoring.row_check import row_problem  # noqa: E402

# -- data ------------------------------------------------------------------------------------


def sweep_manifest(results_dir: Path, skipped: list[str] | None = None) -> set[str] | None:
    """Episode keys of the sweep's current spec (None: not a sweep folder, or a manifest that cannot be read,
    which is named in ``skipped``)."""
    path = Path(results_dir) / "manifest.json"
    if not os.path.lexists(path):
        return None
    try:
        return read_manifest(path)
    except FileRefused as exc:
        if skipped is not None:
            skipped.append(f"{exc}; every finished episode is used")
        return None


def load_episodes(results_dir: Path, *, all_episodes: bool = False) -> pd.DataFrame:
    """The rows of :func:`load_checked_episodes` (what it skipped is left out)."""
    return load_checked_episodes(results_dir, all_episodes=all_episodes)[0]


def load_checked_episodes(results_dir: Path, *, all_episodes: bool = False) -> tuple[pd.DataFrame, list[str]]:
    """Per-episode rows of a sweep folder (from its store) or of every bag below ``results_dir``, and what was
    skipped, one line each naming the file and why.

    In a sweep folder only the episodes of its current spec (manifest.json) are used, so every
    series pools the same tasks; ``all_episodes`` takes every finished record in the store. A results file that
    is not a regular file, is too large or fails a field's check (lq_ros/run/sweep/record_check.py), and a bag
    whose row cannot be placed in a cell or contradicts itself (lq_ros/scoring/row_check.py), are skipped.
    ``bag`` is kept relative to ``results_dir`` so the report's links survive moving the folder.
    """
    from lq_ros.run.sweep import ResultStore

    results_dir = Path(results_dir)
    store = ResultStore(results_dir)
    skipped: list[str] = []
    if store.results.is_dir():
        wanted = None if all_episodes else sweep_manifest(results_dir, skipped)
        rows = []
        for record in store.records():
            if wanted is not None and record["key"] not in wanted:
                continue
            row = dict(record["row"])
            row.update(bag=record.get("bag"), key=record["key"], attempts=len(record.get("attempts", [])))
            row["log"] = record["attempts"][-1].get("log") if record.get("attempts") else None
            rows.append(row)
        skipped += store.refused.values()
        for row in rows:
            versions = row.get("versions") or {}
            row["git_commit"] = versions.get("git_commit") if isinstance(versions, dict) else None
            for key in ("versions", "null_reasons", "warnings"):
                if key in row and not isinstance(row[key], str):
                    row[key] = json.dumps(row[key], sort_keys=True, default=str)
        frame = agg.episodes_frame(rows)
    else:
        rows = []
        for row in agg.score_rows(results_dir):
            row["bag"] = os.path.relpath(row["bag"], results_dir)
            problem = row_problem(row)
            if problem is None:
                rows.append(row)
            else:
                skipped.append(f"bag {row['bag']}: {problem}")
        frame = agg.episodes_frame(rows)
    if frame.empty or frame["status"].isna().all():
        why = f"; skipped: {'; '.join(skipped)}" if skipped else ""
        raise FileNotFoundError(f"no scored episodes in {results_dir} (neither results/*.json nor bags){why}")
    return add_energy_parts_per_step(frame), skipped


def add_energy_parts_per_step(episodes: pd.DataFrame) -> pd.DataFrame:
    """``<part>_per_step_j`` = part x (energy_per_step_j / energy_total_j): the scorer's own step count;
    ``energy_actuator_per_step_j`` = mechanical + electrical loss per step."""
    out = episodes.copy()
    total = pd.to_numeric(out.get("energy_total_j"), errors="coerce")
    per_step = pd.to_numeric(out.get("energy_per_step_j"), errors="coerce")
    ratio = per_step / total.where(total > 0)
    for col, _, _ in ENERGY_PARTS:
        out[col.replace("_j", "_per_step_j")] = pd.to_numeric(out.get(col), errors="coerce") * ratio
    out["energy_actuator_per_step_j"] = out["energy_mech_per_step_j"] + out["energy_elec_per_step_j"]
    # Energy net of the constant overhead: the secondary energy endpoint (the overhead is power x time, so a change
    # of the total repeats the change of completion time).
    out["energy_actuator_j"] = pd.to_numeric(out.get("energy_mech_j"), errors="coerce") + pd.to_numeric(
        out.get("energy_elec_j"), errors="coerce"
    )
    return out


def figure_aggregates(episodes: pd.DataFrame, *, n_boot: int = 2000, seed: int = 0) -> pd.DataFrame:
    """aggregate() pooled per FIGURE_KEYS, plus the per-step energy parts of Fig. 6 (over successful
    episodes, like every energy and trajectory mean; see lq_ros/scoring/aggregate.py)."""
    pooled = agg.aggregate(episodes, by=FIGURE_KEYS, n_boot=n_boot, seed=seed)
    with_outcome = episodes["status"] == "success"
    cells = [_in_cell(episodes, row) for _, row in pooled.iterrows()]
    # Episodes whose arm never moved (every tick held): figures mask a cell made only of them (plot_rules).
    idle = never_moved(episodes) & episodes["status"].isin(["success", "failure"])
    pooled["n_idle"] = [int((idle & cell).sum()) for cell in cells]
    for name in [c.replace("_j", "_per_step_j") for c, _, _ in ENERGY_PARTS] + ["energy_actuator_per_step_j"]:
        means, lows, highs = [], [], []
        for cell in cells:
            mask = with_outcome & cell
            values = pd.to_numeric(episodes.loc[mask, name], errors="coerce").to_numpy(dtype=np.float64)
            stats_ = intervals.mean_stats(values, "v")  # the t interval from MIN_N_INTERVAL values on, as every mean
            means.append(stats_["v_mean"])
            lows.append(stats_["v_ci_lo"])
            highs.append(stats_["v_ci_hi"])
        pooled[f"{name}_mean"], pooled[f"{name}_ci_lo"], pooled[f"{name}_ci_hi"] = means, lows, highs
    # The series a cell belongs to whatever its budget (Fig. 4 draws both budgets of a variant in one colour).
    series = dict(zip(episodes["policy"], labels.base_labels(episodes, ("budget_counts",)), strict=True))
    pooled["series_policy"] = pooled["policy"].map(series)
    pooled["latency_label"] = [agg.cell_latency_label(r) for _, r in pooled.iterrows()]
    return pooled


def _in_cell(episodes: pd.DataFrame, row: pd.Series) -> pd.Series:
    """The episodes of the pooled cell ``row`` (FIGURE_KEYS equal; a missing value matches a missing value)."""
    mask = pd.Series(True, index=episodes.index)
    for k in FIGURE_KEYS:
        mask &= (episodes[k] == row[k]) | (episodes[k].isna() & pd.isna(row[k]))
    return mask


def policy_comparisons(
    episodes: pd.DataFrame, *, n_boot: int = 2000, seed: int = 0, plan: AnalysisPlan | None = None
) -> pd.DataFrame:
    """paired_policies.csv: every pair of policy variants (one protocol) and sync against async (one variant), per
    suite, latency and budget, over their shared (task, init, seed) episodes (lq_ros/scoring/paired_tests.py);
    ``plan``: the sweep's declared primary comparisons and equivalence margin (:func:`analysis_plan`)."""
    eps = episodes.copy()
    eps["variant"] = labels.base_labels(eps, ("budget_counts", "latency_dist"))
    return paired_tests.paired_policies(eps, arm="variant", n_boot=n_boot, seed=seed, plan=plan)


def analysis_plan(results_dir: Path) -> AnalysisPlan:
    """The ``analysis`` of the sweep's spec (``sweep.yaml``: primary comparisons, equivalence margin); nothing
    declared for a folder of bags or a spec without one."""
    path = Path(results_dir) / "sweep.yaml"
    if not path.exists():
        return AnalysisPlan()
    try:
        raw = load_yaml(read_text_file(path, MAX_SPEC_BYTES, "spec"), str(path))
        return parse_analysis(raw.get("analysis") if isinstance(raw, dict) else None)
    except (YamlRefused, PlanError) as exc:
        raise ValueError(f"{path}: {exc}") from None


def paired_aggregates(episodes: pd.DataFrame, pooled: pd.DataFrame, *, n_boot: int = 2000, seed: int = 0):
    """paired_tests.paired_differences per figure cell, with each cell's latency label and budget attribution."""
    paired = paired_tests.paired_differences(episodes, by=FIGURE_KEYS, n_boot=n_boot, seed=seed)
    if paired.empty:
        return paired
    extra = ["latency_label", "series_policy", "budget_counts", "budget_decided", "budget_mark", "budget_decided_n",
             "budget_proxy_n", "budget_twinned_n", "budget_consistent", "n_timeouts", "n_success", "n_failure",
             "n_budget_limited", "n_policy_limited", "n_budget_unattributed", "action_budget_n",
             "action_budget_success_rate"]  # fmt: skip
    cells = pooled[[*FIGURE_KEYS, *extra]].rename(columns={"n_success": "cell_n_success"})
    paired = paired.merge(cells, on=list(FIGURE_KEYS), how="left")
    # Read in order: per variant and protocol, the paper budget before the action budget, latency ascending.
    paired["_budget_order"] = (paired["budget_counts"] != "all").astype(int)
    paired["_variant"] = paired["series_policy"].astype(str).str.replace(r"(, )?latency=\w+", "", regex=True)
    order = ["_variant", "mode", "_budget_order", "latency_s", "latency_dist"]
    paired = paired.sort_values(order, kind="stable").drop(columns=["_budget_order", "_variant"])
    # Many changes against 0 s (every metric of every cell): Benjamini-Hochberg over all of them; a sentence calls
    # a change only when its adjusted p is below 0.05 (lq_ros/scoring/paired_tests.py).
    p_columns = [f"{m}_diff_p" for m in paired_tests.TESTED_METRICS if f"{m}_diff_p" in paired]
    if p_columns:
        adjusted = paired_tests.benjamini_hochberg(paired[p_columns].to_numpy(dtype=np.float64).reshape(-1))
        for k, column in enumerate(p_columns):
            paired[f"{column}_adjusted"] = adjusted.reshape(len(paired), len(p_columns))[:, k]
        paired["p_adjustment"] = paired_tests.BH_ADJUSTMENT  # the CSV says how its p-values were adjusted
    return paired.reset_index(drop=True)


# -- pages -----------------------------------------------------------------------------------


ATTRIBUTION_TITLE = "Where the drop comes from: budget and rest"
ATTRIBUTION_NOTE = (
    "Cells run under both budgets, over the (task, init, seed) pairs present in each: drop = S(0) - S(paper budget) "
    "= budget + rest, with budget = S(action budget) - S(paper budget) and rest = S(0) - S(action budget), all "
    "with the paper's hold (stop); hold repeat = S(action budget, hold repeat) - S(action budget) is a sensitivity "
    "beside the sum. Percentage points with paired 95% intervals (the task as the unit, never narrower than Tango's "
    "score interval)."
)


def budget_decomposition(episodes: pd.DataFrame, *, n_boot: int = 2000, seed: int = 0) -> pd.DataFrame:
    """attribution.csv: lq_ros.scoring.attribution.decompose for the cells that ran under both budgets (the rest
    would only repeat the drop against 0 s)."""
    rows = decompose(episodes, n_boot=n_boot, seed=seed)
    if rows.empty or "drop_budget" not in rows:
        return pd.DataFrame()
    return rows[rows["drop_budget"].notna()].reset_index(drop=True)


def provenance(episodes: pd.DataFrame, results_dir: Path) -> dict[str, str]:
    """What produced these numbers: versions, commits, seeds, transports, spec."""
    out: dict[str, str] = {}
    versions: dict[str, set] = {}
    for raw in episodes.get("versions", pd.Series(dtype=object)).dropna():
        try:
            v = json.loads(raw) if isinstance(raw, str) else raw
        except (ValueError, RecursionError):
            continue
        if not isinstance(v, dict):  # (a row's versions are an object; anything else says nothing)
            continue
        for k, val in v.items():
            versions.setdefault(k, set()).add(str(val))
    for k in sorted(versions):
        out[k] = ", ".join(sorted(versions[k]))
    for col, label in (("seed", "seeds"), ("init", "init states"), ("transport", "transports"),
                       ("suite", "suites"), ("task", "tasks")):  # fmt: skip
        if col in episodes:
            vals = sorted({v for v in episodes[col].dropna()}, key=lambda v: (str(type(v)), v))
            out[label] = ", ".join(str(v) for v in vals)
    spec = Path(results_dir) / "sweep.yaml"
    if spec.exists():
        out["sweep spec"] = str(spec.name)
    out["episodes"] = str(len(episodes))
    manifest = sweep_manifest(results_dir)  # (a manifest that cannot be read is listed among the skipped files)
    if manifest is not None:
        done = set(episodes["key"].dropna()) if "key" in episodes else set()
        out["episodes of the spec not finished"] = str(len(manifest - done))
    return out


def _link(bag, prefix: str) -> str:
    return f"{prefix}{bag}/" if isinstance(bag, str) and bag else ""


SKIPPED_TITLE = "Skipped files"
SKIPPED_NOTE = (
    "These files of the folder were left out of every figure and table, each with why: a results file or bag that "
    "is not a regular file, is too large, cannot be read, or whose fields are wrong or contradict each other."
)


FAILURE_FIGURE = "fig10_failure_modes"
FAILURE_TITLE = "Failure modes by latency"
FAILURE_NOTE = failure_aggregate.validation_note() + (
    " How each failed episode failed, read from its bag's task state (docs/guide/failure_modes.md); fractions of a "
    "cell's episodes with task state, with task-clustered 95% intervals in failure_modes.csv. The sentences say where "
    "the extra failures at a latency went; whether the rise in failures is more than chance is the paired tests' "
    "call above."
)


def write_markdown(path: Path, summary: pd.DataFrame, per_task_md: str, prov: dict, episodes: pd.DataFrame,
                   prefix: str, paired: pd.DataFrame | None = None,
                   comparisons: pd.DataFrame | None = None,
                   attribution: pd.DataFrame | None = None,
                   failures: list[str] | None = None, skipped: list[str] | None = None) -> None:  # fmt: skip
    """``failures``: the failure-mode sentences, given when the failure-mode figure was drawn; ``skipped``: the
    files left out, each with why. Results first (the summary, at most SUMMARY_LINES lines, then what was skipped),
    then the figures and tables, the methods and provenance; the per-task and per-episode tables are in the CSV files
    and report.html, not here (a sweep's would bury the page)."""
    lines = ["# LIBERO-LQ sweep report", ""] + summary_markdown(summary, paired, comparisons, failures)
    if skipped:
        lines += [f"## {SKIPPED_TITLE}", "", SKIPPED_NOTE, ""] + [f"- {md_text(line)}" for line in skipped] + [""]
    if comparisons is not None and not comparisons.empty:
        lines += ["## Policies and protocols compared (paired)", ""]
        lines += [f"- {s}" for s in comparison_sentences(comparisons)] + [""]
    if paired is not None and not paired.empty:
        lines += ["## Latency effects (paired against 0 s)", ""] + [f"- {s}" for s in paired_sentences(paired)] + [""]
    for name, title in FIGURES.items():
        lines += [f"## {title}", "", f"![{title}]({name}.png)", ""]
    if failures is not None:
        lines += [f"## {FAILURE_TITLE}", "", FAILURE_NOTE, ""] + [f"- {md_text(sentence)}" for sentence in failures]
        lines += ["", f"![{FAILURE_TITLE}]({FAILURE_FIGURE}.png)", ""]
    if paired is not None and not paired.empty:
        lines += ["## Paired changes against 0 s", "", md_table(paired_table(paired)), ""]
    if comparisons is not None and not comparisons.empty:
        lines += ["## Paired comparisons of policies and protocols", "",
                  md_table(comparison_table(comparisons)), ""]  # fmt: skip
    if attribution is not None and not attribution.empty:
        lines += [f"## {ATTRIBUTION_TITLE}", "", ATTRIBUTION_NOTE, "", md_table(attribution), ""]
    lines += ["## Methods", "", INTRO, ""] + [f"- {note}" for note in NOTES] + [""]
    lines += ["## Provenance", "", "| | |", "|---|---|"]
    lines += [f"| {md_text(k)} | {md_text(v)} |" for k, v in prov.items()] + [""]
    lines += media.videos_md(episodes, FIGURE_KEYS)
    lines += ["## Episodes", "", f"{counted(len(episodes), 'episode')}: one row each, with links to their bags and "
              "figures, in report.html and episodes.csv; per task: aggregates.csv.", ""]  # fmt: skip
    write_text(path, "\n".join(lines) + "\n")


#: The report's summary is at most this many lines (it reads in one screen); its table at most SUMMARY_ROWS rows.
SUMMARY_LINES = 60
SUMMARY_ROWS = 30
SUMMARY_NOTE = "Intervals are 95%; n is the episodes of a cell. How each number is made: Methods, below."


def summary_markdown(summary: pd.DataFrame, paired: pd.DataFrame | None, comparisons: pd.DataFrame | None,
                     failures: list[str] | None) -> list[str]:  # fmt: skip
    """``## Summary``: the success table (n per row), the comparisons called, the latency effects and the failure-mode
    headline, before any method text; at most SUMMARY_LINES lines, the rest pointed to."""
    shown = summary.head(SUMMARY_ROWS)
    lines = ["## Summary", "", md_table(shown), ""]
    if len(summary) > len(shown):
        lines += [f"(the first {len(shown)} of {len(summary)} cells; all: aggregates_pooled.csv and report.html)", ""]
    said = []
    if comparisons is not None and not comparisons.empty:
        called = comparisons.get("called", pd.Series(False, index=comparisons.index)).fillna(False).astype(bool)
        said.append(f"Paired comparisons: {int(called.sum())} of {len(comparisons)} called a difference (Holm-adjusted "
                    "p < 0.05; below, Policies and protocols compared).")  # fmt: skip
    if paired is not None and not paired.empty:
        said.append(f"Latency effects: {counted(len(paired), 'cell')} paired against 0 s (below, Latency effects).")
    if failures:
        said.append(f"Failure modes: {md_text(failures[0])}")
    room = SUMMARY_LINES - len(lines) - 3
    lines += [f"- {s}" for s in said[: max(0, room)]]
    lines += ["", SUMMARY_NOTE, ""]
    return lines


_CSS = """body{font-family:sans-serif;max-width:1200px;margin:2em auto;padding:0 1em}
table{border-collapse:collapse;font-size:12px}td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}
img{max-width:100%}.error{color:#b00}"""


def write_html(path: Path, summary: pd.DataFrame, per_task: pd.DataFrame, prov: dict, episodes: pd.DataFrame,
               prefix: str, paired: pd.DataFrame | None = None,
               comparisons: pd.DataFrame | None = None, attribution: pd.DataFrame | None = None,
               failures: list[str] | None = None, skipped: list[str] | None = None) -> None:  # fmt: skip
    """The page, results first (as report.md), self-contained: its figures are embedded (data URIs), so the file
    alone can be shared; only the per-episode links (bags, episode figures, videos) point beside it."""
    e = html.escape
    parts = ["<!doctype html><html><head><meta charset='utf-8'><title>LIBERO-LQ sweep report</title>",
             f"<style>{_CSS}</style></head><body><h1>LIBERO-LQ sweep report</h1>",
             "<h2>Summary</h2>" + summary.to_html(index=False, na_rep="–"), f"<p>{e(SUMMARY_NOTE)}</p>"]  # fmt: skip
    if skipped:
        parts.append(f"<h2>{e(SKIPPED_TITLE)}</h2><p>{e(SKIPPED_NOTE)}</p><ul class='error'>")
        parts += [f"<li>{e(line)}</li>" for line in skipped]
        parts.append("</ul>")
    has_paired = paired is not None and not paired.empty
    has_comparisons = comparisons is not None and not comparisons.empty
    if has_comparisons:
        parts.append("<h2>Policies and protocols compared (paired)</h2><ul>")
        parts += [f"<li>{md_to_html(sentence)}</li>" for sentence in comparison_sentences(comparisons)]
        parts.append("</ul>")
    if has_paired:
        parts.append("<h2>Latency effects (paired against 0 s)</h2><ul>")
        parts += [f"<li>{md_to_html(sentence)}</li>" for sentence in paired_sentences(paired)]
        parts.append("</ul>")
    for name, title in FIGURES.items():
        parts.append(f"<h2>{e(title)}</h2><img src='{_embedded_png(path.parent / f'{name}.png')}' alt='{e(title)}'>")
    if failures is not None:
        parts.append(f"<h2>{e(FAILURE_TITLE)}</h2><p>{e(FAILURE_NOTE)}</p><ul>")
        parts += [f"<li>{e(sentence)}</li>" for sentence in failures]
        png = _embedded_png(path.parent / f"{FAILURE_FIGURE}.png")
        parts.append(f"</ul><img src='{png}' alt='{e(FAILURE_TITLE)}'>")
    if has_paired:
        parts.append("<h2>Paired changes against 0 s</h2>" + paired_table(paired).to_html(index=False, na_rep="–"))
    if has_comparisons:
        table = comparison_table(comparisons).to_html(index=False, na_rep="–")
        parts.append("<h2>Paired comparisons of policies and protocols</h2>" + table)
    if attribution is not None and not attribution.empty:
        parts.append(f"<h2>{e(ATTRIBUTION_TITLE)}</h2><p>{e(ATTRIBUTION_NOTE)}</p>" + attribution.to_html(index=False))
    parts.append("<h2>Per task</h2>" + per_task.to_html(index=False, na_rep="–", float_format=lambda v: f"{v:.4g}"))
    parts += ["<h2>Methods</h2>", f"<p>{e(INTRO)}</p>", "<ul>", *(f"<li>{e(n)}</li>" for n in NOTES), "</ul>"]
    parts.append("<h2>Provenance</h2><table>")
    parts += [f"<tr><th>{e(k)}</th><td style='text-align:left'>{e(v)}</td></tr>" for k, v in prov.items()]
    parts.append("</table>" + media.videos_html(episodes, FIGURE_KEYS) + "<h2>Episodes</h2><table><tr>")
    table = episode_table(episodes)
    header = [c for c in table.columns if c != "bag" and c not in media.MEDIA_COLUMNS]
    parts += [f"<th>{e(c)}</th>" for c in [*header, "bag", *media.link_headers(table)]]
    parts.append("</tr>")
    for _, r in table.iterrows():
        cls = " class='error'" if r.get("status") == "error" else ""
        cells = "".join(f"<td>{e(fmt_cell(r[c]))}</td>" for c in header)
        bag = r["bag"]
        link = (
            f"<a href='{e(_link(bag, prefix))}'>{e(str(bag).rsplit('/', 1)[-1])}</a>" if isinstance(bag, str) else "–"
        )
        parts.append(f"<tr{cls}>{cells}<td style='text-align:left'>{link}</td>{media.html_cells(r)}</tr>")
    parts.append("</table></body></html>")
    write_text(path, "\n".join(parts))


def _embedded_png(png: Path) -> str:
    """A PNG as a data URI (the page carries its figures); its file name when it was not drawn."""
    import base64

    try:
        return "data:image/png;base64," + base64.b64encode(png.read_bytes()).decode("ascii")
    except OSError:
        return png.name


@dataclass
class Report:
    out_dir: Path
    files: dict[str, Path]
    episodes: pd.DataFrame
    pooled: pd.DataFrame
    figures: dict[str, plt.Figure]
    #: Per-episode figures and replay videos that could not be made, and replays that differ from their bag.
    media_warnings: list[str] | None = None
    #: Paired changes of every latency > 0 cell against its zero-latency cell (paired_aggregates).
    paired: pd.DataFrame | None = None
    #: Files of the folder left out (damaged, foreign or contradictory), one line each naming the file and why.
    skipped: list[str] | None = None


def build_report(results_dir: Path | list[Path], out_dir: Path | None = None, *, n_boot: int = 2000, seed: int = 0,
                 keep_figures: bool = False, all_episodes: bool = False, videos: int = 0,
                 progress: media.Progress | None = None) -> Report:  # fmt: skip
    """Write figures, tables, report.html and report.md for ``results_dir`` (a folder, or a list of run folders
    to compare) into ``out_dir`` (default ``results_dir/report``; required for several). ``keep_figures`` leaves
    the matplotlib figures open (tests); ``all_episodes``: see load_episodes. Every episode gets a figure;
    ``videos``: replay videos per (policy, protocol, Δt_sim) cell (lq_ros/report/episode_media.py);
    ``progress(stage, done, total)`` follows both."""
    dirs = [Path(results_dir)] if isinstance(results_dir, str | Path) else [Path(d) for d in results_dir]
    if len(dirs) > 1 and out_dir is None:
        raise ValueError("several run folders need an output folder (--out)")
    # A folder of this user's; the default one inside RESULTS_DIR (which may come from anyone) never a link.
    out_dir = output_folder(out_dir, "--out") if out_dir else output_folder(dirs[0] / "report", "report folder",
                                                                          follow=False)  # fmt: skip
    # Several folders: one report comparing their runs (lq_ros/report/runs.py); links relative to their parent.
    skipped: list[str] = []

    def load(folder: Path) -> pd.DataFrame:
        frame, lost = load_checked_episodes(folder, all_episodes=all_episodes)
        skipped.extend(lost)
        return frame

    episodes, results_dir = load_runs(dirs, load)
    pooled = figure_aggregates(episodes, n_boot=n_boot, seed=seed)
    per_task = agg.aggregate(episodes, n_boot=n_boot, seed=seed)
    files = agg.write_tables(episodes, per_task, out_dir)
    pooled_csv = out_dir / "aggregates_pooled.csv"
    write_csv(pooled, pooled_csv)
    files["aggregates_pooled.csv"] = pooled_csv
    paired = paired_aggregates(episodes, pooled, n_boot=n_boot, seed=seed)
    paired_csv = out_dir / "paired_vs_zero_latency.csv"
    write_csv(paired, paired_csv)
    files[paired_csv.name] = paired_csv
    plan = analysis_plan(results_dir)
    comparisons = policy_comparisons(episodes, n_boot=n_boot, seed=seed, plan=plan)
    comparisons_csv = out_dir / "paired_policies.csv"
    write_csv(comparisons, comparisons_csv)
    files[comparisons_csv.name] = comparisons_csv
    attribution = budget_decomposition(episodes, n_boot=n_boot, seed=seed)
    if not attribution.empty:
        attribution_csv = out_dir / "attribution.csv"
        write_csv(attribution, attribution_csv)
        files[attribution_csv.name] = attribution_csv
    fractions = failure_aggregate.mode_fractions(episodes, FIGURE_KEYS, n_boot=n_boot, seed=seed)
    failures = None
    if not fractions.empty:
        fractions_csv = out_dir / "failure_modes.csv"
        write_csv(fractions, fractions_csv)
        files[fractions_csv.name] = fractions_csv
    figures = make_figures(pooled, episodes) | report_async.make_boundary_figures(episodes, n_boot=n_boot, seed=seed)
    failure_figure = fig_failure_modes(fractions)
    if failure_figure is not None:
        figures[FAILURE_FIGURE] = failure_figure
        failures = failure_aggregate.shift_sentences(fractions, ("suite", "policy", "mode"), episodes=episodes)
    for name, fig in figures.items():
        path = out_dir / f"{name}.png"
        save_figure(fig, path, dpi=110)
        files[path.name] = path
        if not keep_figures:
            plt.close(fig)
    episodes, media_warnings = media.add_episode_media(episodes, results_dir, out_dir, videos=videos,
                                                       cell_keys=FIGURE_KEYS, progress=progress)  # fmt: skip
    prov = provenance(episodes, results_dir)
    prefix = os.path.relpath(results_dir, out_dir).rstrip("/") + "/"
    summary = summary_table(pooled)
    files["report.md"] = out_dir / "report.md"
    attribution_view = decomposition_table(attribution)
    write_markdown(files["report.md"], summary, agg.markdown_table(per_task), prov, episodes, prefix, paired,
                   comparisons, attribution_view, failures, skipped)  # fmt: skip
    files["report.html"] = out_dir / "report.html"
    write_html(files["report.html"], summary, per_task_view(per_task), prov, episodes, prefix, paired, comparisons,
               attribution_view, failures, skipped)  # fmt: skip
    return Report(out_dir, files, episodes, pooled, figures if keep_figures else {}, media_warnings, paired, skipped)
