"""The held-out delay study's tables (docs/design/heldout_delay_study.md): every arm's success, and the comparisons its
plan fixed before the episodes ran, paired on (task, init state, seed): the paired difference with its 95% interval (the
current method, lq_ros/scoring/intervals.paired_success_ci: the hull of the cluster-robust t interval over tasks and
Tango's score interval; the study's published intervals were made with the earlier bootstrap, see its "Deviations from
plan"), exact McNemar p-values (these tasks, other init states) and the task-level sign-flip p (``cluster_p``: other
tasks of the suite), each adjusted by Holm over the family. A comparison of identical episodes (the same arm under two
names, or the same comparison listed twice) is printed but in no family.

Usage: python benchmarks/heldout_delay_table.py [SWEEP_DIR]        (default: bags/sweeps/heldout_delay)

The sweep is ``lq sweep config/sweeps/heldout_delay.yaml`` (run in two phases, see the yaml). An arm whose episodes
are not all in yet is printed with the n it has; a comparison uses only the pairs both arms have. Errors are listed
and left out of every comparison they are in (an error is not a failure).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import lq_ros  # noqa: F401 - first: it pins OpenBLAS's kernels before numpy loads them (lq_ros/__init__.py)

# isort: split

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from lq_ros.report.sweep_report import load_episodes  # noqa: E402
from lq_ros.scoring.intervals import clustered_success_ci, wilson_interval  # noqa: E402
from lq_ros.scoring.paired_tests import compare_pairs, holm  # noqa: E402

#: Request slack K = H - 2N of the "naive + slack" arm per (family, latency label) (heldout_delay_study.md).
SLACK = {("flow", "0.2 s"): 2, ("oft", "0.2 s"): 0, ("flow", "0.1 s"): 6, ("oft", "0.1 s"): 4}
JITTER = "uniform:0.125:0.225"
ARMS = ("naive", "naive + slack", "delay", "delay + lookahead")
#: The plan's comparisons: (latency label of A, arm A, latency label of B, arm B); A - B is reported.
COMPARISONS = [
    (lat, a, lat, b)
    for lat in ("0.2 s", "0.1 s")
    for a, b in (("delay", "naive"), ("delay", "naive + slack"), ("delay + lookahead", "delay"),
                 ("delay + lookahead", "naive"))
] + [(JITTER, "delay + lookahead", JITTER, "naive"),
     (JITTER, "delay + lookahead", "0.2 s", "delay + lookahead")]  # fmt: skip
PAIR = ["task", "init", "seed"]


def arm_of(row: pd.Series) -> tuple[str, str, str]:
    """(family, latency label, arm) of an episode row, from its variant label (``oft [lookahead=1, variant=delay]``)."""
    label = str(row["policy"])
    family = label.split(" ")[0]
    dist = row.get("latency_dist") or ""
    lat = JITTER if str(dist).startswith("uniform") else f"{float(row['latency_s']):g} s"
    if "variant=delay" in label:
        return family, lat, "delay + lookahead" if "lookahead=1" in label else "delay"
    return family, lat, "naive + slack" if "request_slack=" in label else "naive"


def arm_rows(episodes: pd.DataFrame, family: str, lat: str, arm: str) -> pd.DataFrame:
    """The episodes of one arm; the naive + slack arm at K = 0 is the naive arm itself."""
    if arm == "naive + slack" and SLACK.get((family, lat)) == 0:
        arm = "naive"
    sel = episodes[(episodes.family == family) & (episodes.lat == lat) & (episodes.arm == arm)]
    return sel.set_index(PAIR)


def success_line(rows: pd.DataFrame) -> dict:
    ok = rows[rows.status.isin(["success", "failure"])]
    k, n = int((ok.status == "success").sum()), len(ok)
    lo, hi = wilson_interval(k, n) if n else (np.nan, np.nan)
    per_task = ok.groupby(level="task").status.apply(lambda s: (s == "success").to_numpy(float))
    clo, chi = clustered_success_ci(list(per_task)) if n else (np.nan, np.nan)
    return {"n": n, "errors": int((rows.status == "error").sum()), "success": k,
            "success %": f"{100 * k / n:.0f}" if n else "-", "Wilson 95%": f"[{100 * lo:.0f}, {100 * hi:.0f}]",
            "task-clustered 95%": f"[{100 * clo:.0f}, {100 * chi:.0f}]"}  # fmt: skip


def compare(a: pd.DataFrame, b: pd.DataFrame) -> dict:
    """Paired comparison of two arms' successes (lq_ros.scoring.paired_tests.compare_pairs), as table text."""
    out = compare_pairs(a.reset_index(), b.reset_index(), seed=0)
    pct = (lambda v: f"{100 * v:.0f}") if out["n_pairs"] else (lambda v: "-")
    return {"pairs": out["n_pairs"], "A only": out["a_only"], "B only": out["b_only"], "A %": pct(out["success_a"]),
            "B %": pct(out["success_b"]), "A - B (points)": pct(out["diff"]),
            "95% (task-clustered)": f"[{100 * out['diff_ci_lo']:+.0f}, {100 * out['diff_ci_hi']:+.0f}]",
            "mcnemar_p": out["mcnemar_p"], "cluster_p": out["cluster_p"], "identical": out["identical"]}  # fmt: skip


def main() -> None:
    folder = Path(sys.argv[1]) if len(sys.argv) > 1 else Path("bags/sweeps/heldout_delay")
    episodes = load_episodes(folder)
    episodes = episodes[episodes.suite == "libero_object"].copy()
    labels = [arm_of(r) for _, r in episodes.iterrows()]
    episodes["family"], episodes["lat"], episodes["arm"] = (list(column) for column in zip(*labels, strict=True))
    tasks, inits = sorted(episodes.task.unique()), sorted(episodes.init.unique())
    print(
        f"held-out delay study: libero_object tasks {tasks[0]}-{tasks[-1]}, init states {inits[0]}-{inits[-1]},"
        f" seeds {sorted(episodes.seed.unique())}; async, merge replace, paper budget, lockstep in process"
    )
    lines = []
    for family in ("oft", "flow"):
        for lat in ("0.2 s", JITTER, "0.1 s"):
            for arm in ARMS:
                rows = arm_rows(episodes, family, lat, arm)
                if rows.empty:
                    continue
                name = arm if arm != "naive + slack" else f"naive + slack K={SLACK[(family, lat)]}"
                if arm == "naive + slack" and SLACK[(family, lat)] == 0:
                    name += " (= naive)"
                lines.append({"family": family, "latency": lat, "arm": name, **success_line(rows)})
    print(
        f"\nSuccess per arm. Wilson 95%: the episodes as independent draws (these tasks, other init states);"
        f" task-clustered 95%: the hull of the cluster-robust t interval over the {len(tasks)} tasks"
        f" (t with {len(tasks) - 1} df) and Wilson (other tasks of the suite; lq_ros/scoring/intervals.py)"
    )
    print(pd.DataFrame(lines).to_markdown(index=False))
    errors = episodes[episodes.status == "error"]
    for _, r in errors.iterrows():
        print(f"error: {r.family} {r.lat} {r.arm} task {r.task} init {r.init}: {r.get('error_reason')}")

    comps, seen = [], set()
    for family in ("oft", "flow"):
        for lat_a, arm_a, lat_b, arm_b in COMPARISONS:
            a, b = arm_rows(episodes, family, lat_a, arm_a), arm_rows(episodes, family, lat_b, arm_b)
            if a.empty or b.empty:
                continue
            same = arm_b == "naive + slack" and SLACK.get((family, lat_b)) == 0
            name_b = f"{arm_b} @ {lat_b}" + (" (= naive)" if same else "")
            row = compare(a, b)
            # The same pairs compared twice (B at K = 0 is the naive arm; A = delay equals naive there) count once.
            key = (family, arm_a, lat_a, tuple(b.status), tuple(b.get("completion_steps", b.status)))
            row["in family"] = not row["identical"] and key not in seen
            seen.add(key)
            comps.append({"family": family, "A": f"{arm_a} @ {lat_a}", "B": name_b, **row})
    table = pd.DataFrame(comps)
    family_rows = table["in family"].to_numpy(bool)
    for col in ("mcnemar_p", "cluster_p"):
        adjusted = np.full(len(table), np.nan)
        adjusted[family_rows] = holm(table.loc[family_rows, col].to_numpy())
        table[f"{col} Holm"] = adjusted
    table["called (these tasks)"] = np.where(table["mcnemar_p Holm"] < 0.05, "yes", "no")
    table["called (other tasks)"] = np.where(table["cluster_p Holm"] < 0.05, "yes", "no")
    for col in ("mcnemar_p", "mcnemar_p Holm", "cluster_p", "cluster_p Holm"):
        table[col] = table[col].map(lambda v: "-" if np.isnan(v) else f"{v:.2g}")
    table = table.drop(columns=["identical"])
    print(
        f"\nPlanned comparisons, paired on (task, init, seed): A - B with the hull of the cluster-robust t interval"
        f" over tasks and Tango's paired score interval; exact McNemar p (these tasks, other init states) and"
        f" task-level sign-flip p (cluster_p: other tasks of the suite), each Holm over the {int(family_rows.sum())}"
        f" in the family"
    )
    print(table.to_markdown(index=False))
    commits = sorted(set(episodes.git_commit.dropna()))
    cpus = sorted(set(episodes.cpu_class.dropna()))
    versions = json.loads(episodes.versions.dropna().iloc[0]) if episodes.versions.notna().any() else {}
    libs = ", ".join(f"{k} {versions[k]}" for k in ("mujoco", "torch", "numpy") if k in versions)
    print(f"\nepisodes {len(episodes)}; commit {', '.join(commits)}; CPU class {', '.join(cpus)}; {libs}")


if __name__ == "__main__":
    main()
