"""The report's sentences: its introduction, reading notes and the per-cell findings against 0 s."""

from __future__ import annotations

import pandas as pd

from lq_ros.report.tables import count_text, outcomes_text
from lq_ros.scoring import aggregate as agg

#: (metric, sentence name, decimals, scale, unit) of the paired changes the report's sentences name.
PAIRED_SENTENCE = (
    ("completion_time_s", "completion time", 2, 1.0, "s"),
    ("action_ticks", "action ticks", 0, 1.0, ""),
    ("jerk_mean", "mean jerk", 2, 1.0, "m/s³"),
    ("ee_osc", "paper EE-Osc", 1, 1000.0, "mm"),
    ("ee_osc_detrended", "detrended EE-Osc", 1, 1000.0, "mm"),
    ("energy_total_j", "total energy", 0, 1.0, "J"),
)


def paired_sentences(paired: pd.DataFrame) -> list[str]:
    """The report's findings, one sentence per latency > 0 cell: success against latency 0, what decided its
    timeouts, and the paired changes (never a comparison of success-only means over different task mixes)."""
    lines = []
    for _, r in paired.iterrows():
        latency = r.get("latency_label") or agg.cell_latency_label(r)
        text = f"**{r['policy']} · {r['mode']}, {latency}** against 0 s: "
        if not r["zero_n"]:
            lines.append(text + "no zero-latency cell of this variant and protocol to compare with.")
            continue
        text += (
            f"success {count_text(r, 'cell_n_success')}/{outcomes_text(r)} against {r['zero_n_success']}/{r['zero_n']}"
        )
        note = agg.budget_note(r)
        text += f" ({note})" if note and note != "action budget" else ""
        if not r["n_pairs"]:
            lines.append(text + "; no (task, init) pair succeeds in both, so there is no paired change.")
            continue
        changes = [
            f"{name}{f' ({unit})' if unit else ''} {agg.ci_text(r, f'{metric}_diff', decimals, scale, signed=True)}"
            for metric, name, decimals, scale, unit in PAIRED_SENTENCE
            if r.get(f"{metric}_diff_n")
        ]
        one = r["n_pairs"] == 1
        pairs = f"{int(r['n_pairs'])} pair{'' if one else 's'} that succeed{'s' if one else ''}"
        lines.append(f"{text}; over the {pairs} in both: {', '.join(changes)}.")
    return lines


INTRO = (
    "Pooled over tasks and init states per (policy, protocol, suite, applied Δt_sim = N × 0.05 s, sampling), never "
    "over suites; mean [95% CI]. "
    "Success: Wilson interval over episodes with an outcome (errors counted apart). Completion time, trajectory "
    "quality and energy: over successful episodes (succ.), seeded bootstrap of the mean; time (KM) is the "
    "Kaplan-Meier restricted mean up to the step budget over every episode with an outcome. The protocols differ in "
    "their replan horizon, not only in blocking: sync executes replan_steps actions of each chunk, async the H - N "
    "fresh ones (actions/chunk: measured). ⚠ / red rings: cells with degenerate-protocol episodes (async chunks no "
    "longer than N, or no chunk could overlap the old plan); × at a panel's foot: a cell whose arm never moved (no "
    "fresh action ran), its quality and energy values not drawn. Sampling: the rate of the trajectory metrics and how "
    "energy was integrated "
    "(docs/guide/scoring.md)."
)
#: The report's reading notes (after INTRO): how to read what the figures and tables attribute.
NOTES = (
    f"Few values: a metric over fewer than {agg.MIN_N_INTERVAL} episodes (or pairs) gets no bootstrap interval, "
    "which would undercover there (one value gives [v, v]); tables print the mean, n and the values, "
    "as MEAN (n=1) or MEAN (n=3: V1, V2, V3), and figures draw such a mean hollow, joined to no other, with its "
    "values as dots and no band.",
    "Paired changes: success-only means of two latencies average different task mixes whenever their success "
    "differs, so the findings compare each latency > 0 cell with the zero-latency cell of the same variant and "
    "protocol over the (task, init state, seed) pairs that succeed in both: the change per pair, its mean and its "
    "bootstrap interval over pairs.",
    "Budgets: under the paper budget (holds count) every tick, held or not, counts against the suite's step budget; "
    "under the action budget only ticks whose command came from a chunk do (hard stop at 4x the budget). Fig. 4 draws "
    "both when a sweep ran both. A timeout under the paper budget is budget-limited when the same episode under the "
    "action budget succeeded or, without that run, when it executed fewer action ticks than the same task and init "
    "state needed to succeed at 0 s; a cell is budget-decided (◇, hollow marker) when at least half of its timeouts "
    "are budget-limited: there latency made the policy slower, the budget turned slower into failed.",
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
