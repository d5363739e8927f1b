"""The report's sentences: its introduction, reading notes and the per-cell findings against 0 s.

The sentences are markdown (``**bold**``); every name read from a bag goes in through escape.md_text, and
report.html takes them through escape.md_to_html."""

from __future__ import annotations

import pandas as pd

from lq_ros.core.wording import counted
from lq_ros.report.escape import md_text
from lq_ros.report.tables import count_text, outcomes_text
from lq_ros.scoring import aggregate as agg
from lq_ros.scoring.budget import budget_note
from lq_ros.scoring.intervals import CLUSTER_COVERAGE, MIN_N_INTERVAL, T_COVERAGE
from lq_ros.scoring.paired_tests import ALPHA, RMST_METRIC

#: (metric, sentence name, decimals, scale, unit) of the paired changes the report's sentences name, over the pairs
#: that succeed in both (completion time there is descriptive: the tested time change is over every pair).
PAIRED_SENTENCE = (
    ("completion_time_s", "completion time", 2, 1.0, "s"),
    ("action_ticks", "action ticks", 0, 1.0, ""),
    ("jerk_mean", "mean jerk", 2, 1.0, "m/s³"),
    ("ee_osc", "paper EE-Osc", 1, 1000.0, "mm"),
    ("ee_osc_detrended", "detrended EE-Osc", 1, 1000.0, "mm"),
    ("energy_actuator_j", "actuator energy (net of the constant overhead)", 0, 1.0, "J"),
)


def _called(r, metric: str) -> bool:
    adjusted = r.get(f"{metric}_diff_p_adjusted")
    return adjusted is not None and not pd.isna(adjusted) and adjusted < ALPHA


def _change(r, metric: str, name: str, decimals: int, scale: float, unit: str) -> str:
    text = f"{name}{f' ({unit})' if unit else ''} {agg.ci_text(r, f'{metric}_diff', decimals, scale, signed=True)}"
    tasks_p = r.get(f"{metric}_diff_cluster_p")  # the task as the unit: other tasks of the suite
    if not _called(r, metric) or tasks_p is None or pd.isna(tasks_p):
        return text
    return text + f" (task-level p {tasks_p:.2g}{': these tasks only' if tasks_p >= ALPHA else ''})"


def paired_sentences(paired: pd.DataFrame) -> list[str]:
    """The report's findings, one sentence per latency > 0 cell: success against latency 0, what decided its
    timeouts, the time to success over every pair (no survivor selection), and the paired changes over the pairs
    that succeed in both (never a comparison of success-only means over different task mixes)."""
    lines = []
    for _, r in paired.iterrows():
        latency = r.get("latency_label") or agg.cell_latency_label(r)
        text = f"**{md_text(r['policy'])} · {md_text(r['mode'])}, {md_text(latency)}** against 0 s: "
        if not r["zero_n"]:
            lines.append(text + "no zero-latency cell of this variant and protocol to compare with.")
            continue
        text += (
            f"success {count_text(r, 'cell_n_success')}/{outcomes_text(r)} against {r['zero_n_success']}/{r['zero_n']}"
        )
        note = budget_note(r)
        text += f" ({note})" if note and note != "action budget" else ""
        n_all = r.get("n_pairs_all")
        if n_all is not None and not pd.isna(n_all) and int(n_all) and r.get(f"{RMST_METRIC}_diff_n"):
            time = _change(r, RMST_METRIC, "time to success", 2, 1.0, "s")
            verdict = "changed" if _called(r, RMST_METRIC) else "not shown to change"
            every = "the 1 pair" if int(n_all) == 1 else f"all {int(n_all)} pairs"
            text += f"; over {every} (a failure at the horizon), {verdict}: {time}"
        if not r["n_pairs"]:
            lines.append(text + "; no (task, init, seed) pair succeeds in both, so there is no paired change of the "
                         "quality metrics.")  # fmt: skip
            continue
        shown, not_shown = [], []
        for metric, name, decimals, scale, unit in PAIRED_SENTENCE:
            if not r.get(f"{metric}_diff_n"):
                continue
            (shown if _called(r, metric) else not_shown).append(_change(r, metric, name, decimals, scale, unit))
        one = r["n_pairs"] == 1
        pairs = f"{int(r['n_pairs'])} pair{'' if one else 's'} that succeed{'s' if one else ''}"
        found = f"changed: {', '.join(shown)}" if shown else "no change shown"
        rest = f"; not shown to change: {', '.join(not_shown)}" if not_shown else ""
        lines.append(f"{text}; over the {pairs} in both, {found}{rest}.")
    return lines


def comparison_sentences(comparisons: pd.DataFrame) -> list[str]:
    """The paired_policies.csv findings: which comparisons were declared primary, one sentence per comparison whose
    Holm-adjusted McNemar p is below 0.05 (with the population each p-value speaks for), the equivalences a TOST at
    the spec's margin shows, and how many show no difference: the report never compares two arms by their separate
    intervals, and never calls two arms equal without an equivalence test."""
    lines = []
    family = comparisons["family"] if "family" in comparisons else pd.Series("exploratory", index=comparisons.index)
    n_primary = int((family == "primary").sum())
    if n_primary:
        lines.append(f"{n_primary} comparison{'s were' if n_primary > 1 else ' was'} declared primary in the sweep "
                     "spec (analysis.primary): the Holm family. Every other comparison is exploratory (Holm over the "
                     "exploratory ones alone), a lead for a new sweep rather than a finding.")  # fmt: skip
    else:
        lines.append("No primary comparison was declared (the sweep spec's analysis.primary): every comparison below "
                     "is exploratory, a lead for a new sweep rather than a finding.")  # fmt: skip
    n_none = int((family == "none").sum())
    if n_none:
        lines.append(f"{n_none} comparison{'s' if n_none > 1 else ''} set two names for identical episodes against "
                     "each other (the same outcome, steps, action ticks and energy in every pair): no information, "
                     "in no family.")  # fmt: skip
    called = comparisons[comparisons["called"].astype(bool)]
    for _, r in called.iterrows():
        lines.append(_called_sentence(r))
    for _, r in comparisons[comparisons.get("equivalent", pd.Series(dtype=object)) == True].iterrows():  # noqa: E712
        lines.append(
            f"**{_arm(r, 'a')}** and **{_arm(r, 'b')}** ({_where(r)}) are equivalent "
            f"within ±{100 * r['equivalence_margin']:.0f} points (TOST at the spec's margin, each one-sided test at "
            f"2.5%, conservative: the 95% interval {100 * r['diff']:+.0f} [{100 * r['diff_ci_lo']:+.0f}, "
            f"{100 * r['diff_ci_hi']:+.0f}] lies inside it)."
        )
    all_ = pd.Series(True, index=comparisons.index)  # a table from before the Holm family was restricted
    testable = comparisons["testable"].astype(bool) if "testable" in comparisons else all_
    in_family = testable & (family != "none")
    tested_rest, untestable = int(in_family.sum()) - len(called), int((~testable & (family != "none")).sum())
    margin = comparisons["equivalence_margin"].dropna() if "equivalence_margin" in comparisons else pd.Series()
    equal_text = ("equivalence needs a TOST at the spec's analysis.equivalence_margin, and none was stated"
                  if margin.empty else "only those named above pass the TOST at the spec's margin")  # fmt: skip
    if tested_rest:
        lines.append(
            f"{tested_rest} of the {counted(len(comparisons), 'paired comparison')} "
            f"show{'s' if tested_rest == 1 else ''} no "
            "difference at a family-wise 5% level (Holm-adjusted McNemar p >= 0.05): no difference detected, which "
            f"is not the same as equal ({equal_text}; paired_policies.csv has each one's interval)."
        )
    if untestable:
        lines.append(
            f"{untestable} comparison{' has' if untestable == 1 else 's have'} fewer than 6 discordant pairs, too few "
            "for an exact McNemar p below 0.05 whatever their direction: no difference detected."
        )
    return lines


def _where(r) -> str:
    """Where a comparison ran (suite, latency, budget), escaped for markdown."""
    return md_text(f"{r['suite']}, {agg.cell_latency_label(r)}") + (
        "" if r["budget_counts"] == "all" else f", {md_text(r['budget_counts'])} budget"
    )


def _arm(r, side: str) -> str:
    """``policy · mode`` of arm ``side`` ("a" or "b") of a comparison, escaped for markdown."""
    return f"{md_text(r[f'arm_{side}'])} · {md_text(r[f'mode_{side}'])}"


def _called_sentence(r) -> str:
    """A comparison whose Holm-adjusted McNemar p is below 0.05: these tasks, other init states; whether it holds for
    other tasks of the suite is the task-level sign-flip test's (``cluster_p``) call."""
    better = r["diff"] > 0
    lo, hi = r["diff_ci_lo"], r["diff_ci_hi"]
    n_tasks = int(r["n_tasks"])
    interval = "no task-clustered interval (too few tasks)" if pd.isna(lo) or pd.isna(hi) else (
        f"[{100 * lo:+.0f}, {100 * hi:+.0f}]")  # fmt: skip
    label = "Exploratory: " if r.get("family") == "exploratory" else ""
    cluster, cluster_adj = r.get("cluster_p"), r.get("cluster_p_adjusted")
    if cluster is None or pd.isna(cluster):
        scope = "no task-level test"
    elif bool(r.get("called_tasks")):
        scope = (f"task-level sign-flip p = {cluster:.2g} (Holm {cluster_adj:.2g}): the difference speaks for other "
                 "tasks of the suite")  # fmt: skip
    else:
        floor = 2.0 / 2.0**n_tasks
        why = f", and {counted(n_tasks, 'task')} cannot give less than {floor:.2g}" if floor >= ALPHA else ""
        scope = (f"task-level sign-flip p = {cluster:.2g}{why}: shown on these tasks, not for other tasks of the "
                 "suite")  # fmt: skip
    return (
        f"{label}**{_arm(r, 'a')}** succeeds {'more' if better else 'less'} often than **{_arm(r, 'b')}** "
        f"({_where(r)}): {100 * r['success_a']:.0f}% against {100 * r['success_b']:.0f}% over "
        f"{counted(int(r['n_pairs']), 'shared episode')} of {counted(n_tasks, 'task')}; "
        f"{counted(int(r['a_only']), 'succeeds', 'succeed')} only with A and "
        f"{int(r['b_only'])} only with B; difference {100 * r['diff']:+.0f} points {interval}; McNemar p = "
        f"{r['mcnemar_p']:.2g}, Holm-adjusted p = {r['p_adjusted']:.2g} (these tasks, other init states); {scope}."
    )


INTRO = (
    "Pooled over tasks and init states per (policy, protocol, suite, applied Δt_sim = N × 0.05 s, sampling), never "
    "over suites; mean [95% CI]. "
    "Success: Wilson interval over episodes with an outcome (errors counted apart). Completion time, trajectory "
    "quality and energy: over successful episodes (succ.), Student t interval of the mean; time (KM) is the "
    "Kaplan-Meier restricted mean up to the step budget over every episode with an outcome. The protocols differ in "
    "their replan horizon, not only in blocking: sync executes replan_steps actions of each chunk, async the H - N "
    "fresh ones (actions/chunk: measured). ⚠ / red rings: cells with degenerate-protocol episodes (async chunks no "
    "longer than N, or no chunk could overlap the old plan); × at a panel's foot: a cell whose arm never moved (no "
    "fresh action ran), its quality and energy values not drawn. Sampling: the rate of the trajectory metrics and how "
    "energy was integrated "
    "(docs/guide/scoring.md)."
)


def _coverage(bounds: tuple[float, float]) -> str:
    return f"{100 * bounds[0]:.1f}-{100 * bounds[1]:.1f}%"


#: The report's reading notes (after INTRO): how to read what the figures and tables attribute.
NOTES = (
    f"Intervals: success carries the Wilson interval over episodes (these tasks, other init states) and, for a cell "
    f"of at least {MIN_N_INTERVAL} tasks, the task-clustered interval (the task as the unit, never narrower than "
    "Wilson; success clusters by task, so this is the one that speaks for other tasks of this kind; Fig. 4's band is "
    "it wherever every cell of a line has it, else the hatched Wilson band); the mean of a metric "
    "carries the Student t interval, a paired success difference the task-clustered interval never narrower than "
    "Tango's. Simulated at 5-10 tasks (benchmarks/interval_coverage.py, docs/design/statistics.md), the nominal 95% "
    f"intervals cover {_coverage(CLUSTER_COVERAGE['success'])} (success), {_coverage(CLUSTER_COVERAGE['paired'])} "
    f"(paired differences) and {_coverage(T_COVERAGE)} (means of 5-9 values). Few values: a metric over fewer than "
    f"{MIN_N_INTERVAL} episodes (or pairs) gets no interval; tables print the mean, n and the values, "
    "as MEAN (n=1) or MEAN (n=3: V1, V2, V3), and figures draw such a mean hollow, joined to no other, with its "
    "values as dots and no band.",
    "Comparisons: two policies (one protocol) or two protocols (one policy) are compared only on the episodes both "
    "ran (same task, init state and seed): the discordant pairs, the paired difference with a task-clustered "
    "interval and two tests that speak for two populations. The exact McNemar test counts the pairs as independent: "
    "it speaks for these tasks at other init states. The task-level sign-flip test (cluster_p: each task's mean "
    "difference, its sign flipped at random) takes the task as the unit: it speaks for other tasks of the suite, and "
    "a claim about a method in general rests on it (with k tasks it cannot go below 2/2^k: 0.0625 at 5 tasks). "
    "Success is the primary endpoint. The Holm family is the comparisons the sweep spec declares primary "
    "(analysis.primary, paired_policies.csv column primary); the rest are exploratory, Holm-adjusted among "
    "themselves over those with at least 6 discordant pairs, the fewest that can reach p < 0.05; two names for "
    "identical episodes are in no family. Two arms are called equivalent only when a TOST at the spec's "
    "analysis.equivalence_margin passes (the 95% interval inside the margin: each one-sided test at 2.5%, "
    "conservative against the usual 5% TOST, which takes the 90% interval); otherwise a non-significant comparison "
    'is "no difference detected", with '
    "its interval. The changes against 0 s are secondary: Benjamini-Hochberg adjusted over completion time, action "
    "ticks, the trajectory metrics and the actuator energy (energy net of the constant 85 W overhead, whose change "
    "would repeat the change of time; the totals stay in the tables, untested), called (and starred in the paired "
    "table) only when the adjusted p is below 0.05.",
    "Paired changes: success-only means of two latencies average different task mixes whenever their success "
    "differs, so the findings compare each latency > 0 cell with the zero-latency cell of the same variant and "
    "protocol over the (task, init state, seed) pairs that succeed in both: the change per pair, its mean and its "
    "t interval over pairs. Restricting to pairs that succeed in both selects the survivors; the restricted-mean "
    "time to success of paired_policies.csv counts every pair (a failure at the budget).",
    "Budgets: under the paper budget (holds count) every tick, held or not, counts against the suite's step budget; "
    "under the action budget only ticks whose command came from a chunk do (hard stop at 4x the budget). Fig. 4 draws "
    "both when a sweep ran both. A cell is budget-decided (◇, hollow marker) only from its action-budget twins: the "
    "same episodes run again under the action budget; it needs at least 5 timeouts, and the fraction that succeeds "
    "there (a timeout without a twin counts as not) above half with its whole Wilson 95% interval: latency made the "
    "policy slower and the budget turned slower into failed. A fraction of at least half whose interval reaches "
    "below half is only consistent with that, and the note says so; every note gives the rescued fraction with its "
    "interval. Without a twin, a cell of at least 5 timeouts that executed fewer "
    "action ticks than the same episodes needed at 0 s gets the weaker proxy mark (◌, dotted ring): a hint, not a "
    "finding; a cell where any twin ran gets no proxy mark. The proxy is never applied to an arm that received no "
    "fresh action or whose buffer ran dry.",
    "Fig. 9 separates slower from failing: the fraction succeeded by t, in sim seconds and in action ticks, with "
    "failures censored at their end and a pointwise 95% Greenwood band (log-log); a slower cell rises later, a "
    "failing cell levels off lower.",
    "Latency labels: a distribution cell is named by its distribution and the mean Δt_sim its chunks actually got "
    "(realised mean, pooled over the cell's chunks); a constant cell by Δt_sim and N.",
    "EE-Osc: the paper's (A.3) is the spread of the last 10 positions (0.5 s) about their mean, so an arm still "
    "travelling at the end scores high; the detrended EE-Osc is the spread about the window's straight line, the "
    "back-and-forth alone. Fig. 5 shows both on one scale; a paper EE-Osc falling with latency while the detrended "
    "one stays flat means the arm arrives slower, not steadier.",
    "Async best case: in lockstep with no request slack the next chunk is requested N actions before the buffer "
    "empties and lands exactly as it does (constant latency, N ticks): no tick holds. Any jitter (a latency "
    "distribution, the real-time clock) makes the chunk land late, and every late tick is an underrun hold; a request "
    "slack of K actions requests K actions earlier and trades those holds for K stale actions.",
)
