"""Zero-latency success (per task, Wilson 95% intervals; totals also task-clustered) and inference latency of the
learned chunk policies.

Runs the conventional LIBERO loop (``run_conventional``: infer, execute ``replan_steps`` actions,
repeat; Δt_sim = 0, no ROS) for each policy on each task of each suite over init states
``--init-start`` .. ``--init-start + --inits - 1``, and times every ``infer`` call. Each policy executes
the number of actions per chunk stored with its weights (oft chunk 8: 8, oft chunk 1: 1, flow chunk
10: 5) unless --replan-steps overrides it. The policies load the shipped weights of each suite.

Usage: python benchmarks/eval_learned.py [--suite libero_spatial --suite libero_object] [--inits 10]
       [--tasks 0 1 ...] [--workers 2] [--json out.json]
       [--policy oft --policy oft:chunk_size=1 --policy flow]   (name[:key=value,...], repeatable)
       python benchmarks/eval_learned.py --merge a.json b.json   (one table from runs split by task/policy)
       python benchmarks/eval_learned.py --merge a.json b.json --by-weights   (columns per checkpoint, see below)
       python benchmarks/eval_learned.py --from-counts 7/10 5/10 ...   (a total's intervals from a table's per-task
                                                                         counts, one per task; nothing is run)

Latency study (``--latency``): success at injected latencies Δt_sim (lockstep, in process, merge replace, the
paper's step budget: holds count) in the protocols of ``--mode``, per policy, with Wilson and task-clustered 95%
intervals. A delay-aware policy (``variant=delay``) is told the protocol it runs under (``mode=``), nothing else (it
estimates d from its own requests, see lq_ros/policies/learned/delay.py). Each policy executes its weights'
``replan_steps`` per chunk in sync; async runs the whole buffer (request threshold N).

       python benchmarks/eval_learned.py --suite libero_object --latency 0 0.1 0.2 --mode async --mode sync \
           --policy flow --policy flow:variant=delay --policy oft --policy oft:variant=delay --inits 10
       python benchmarks/eval_learned.py --merge a.json b.json   (latency rows are merged into one latency table)

``--by-weights`` pools runs by the checkpoint they ran instead of by the policy spec string: ``oft`` and
``oft:weights=/some/copy/oft_c8_libero_spatial.json`` become one column ``oft_c8`` if the two ``.pt`` files
are byte-identical (MD5; recorded in every row since it was added, else taken from the spec's ``weights=``
path, else from the shipped file, as the table says); different bytes under one name, or the same episode
twice, are refused.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import multiprocessing as mp
import sys
import time
from pathlib import Path

import lq_ros  # noqa: F401 - first: it pins OpenBLAS's kernels before numpy loads them (lq_ros/__init__.py)

# isort: split

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lq_ros.core.run_config import BUDGET_COUNTS, versions
from lq_ros.core.types import Observation, TaskInfo
from lq_ros.policies import Policy, make_policy
from lq_ros.scoring.intervals import clustered_success_ci, wilson_interval
from lq_ros.sim.libero_env import LiberoEnv
from lq_ros.training.collect import parse_spec as parse_policy_spec
from lq_ros.transport.inprocess import run_conventional

SUITES = ("libero_spatial", "libero_object")
SEED = 7
DEFAULT_POLICIES = ("oft", "oft:chunk_size=1", "flow")


def parse_spec(spec: str) -> tuple[str, dict]:
    """``name[:k=v,k=v]`` -> (name, kwargs) as ``lq collect --driver`` reads it; a bad spec ends the run in one line."""
    try:
        return parse_policy_spec(spec)
    except ValueError as exc:
        raise SystemExit(str(exc)) from None


def run_jobs(task, jobs: list, workers: int) -> list:
    """``task`` over ``jobs``: in ``workers`` spawned processes when there are several of both, else here."""
    if workers > 1 and len(jobs) > 1:
        with mp.get_context("spawn").Pool(min(workers, len(jobs))) as pool:
            return pool.map(task, jobs, chunksize=1)
    return [task(j) for j in jobs]


class Timed(Policy):
    """Delegates to a policy and records the wall time of every infer() call."""

    def __init__(self, inner: Policy) -> None:
        self.inner = inner
        self.name = inner.name
        self.times_s: list[float] = []

    def reset(self, task: TaskInfo, seed: int) -> None:
        self.inner.reset(task, seed)

    def infer(self, obs: Observation) -> np.ndarray:
        t0 = time.perf_counter()
        out = self.inner.infer(obs)
        self.times_s.append(time.perf_counter() - t0)
        return out


def eval_task(job: tuple[str, int, list[str], range, int]) -> list[dict]:
    """All policies on one task (one env), over the init states ``inits``."""
    suite, task_id, specs, inits, replan_override = job
    env = LiberoEnv(suite, task_id)
    rows = []
    try:
        for spec in specs:
            name, kwargs = parse_spec(spec)
            policy = Timed(make_policy(name, **kwargs))
            policy.reset(env.task, SEED)  # loads the suite's weights: their replan_steps
            replan = replan_override or int(policy.inner.replan_steps)
            weights = policy.inner.weights_path.name
            weights_md5 = weights_digest(policy.inner.weights_path)
            for init in inits:
                t0 = time.perf_counter()
                try:
                    res = run_conventional(env, policy, init, SEED, replan)
                    status, ticks = ("success" if res.success else "failure"), res.ticks
                except Exception as exc:  # noqa: BLE001 - counted as an error, never as a failure
                    status, ticks = f"error: {type(exc).__name__}: {exc}", 0
                rows.append({"suite": suite, "policy": spec, "task": task_id, "init": init, "status": status,
                             "ticks": ticks, "replan_steps": replan, "weights": weights, "weights_md5": weights_md5,
                             "wall_s": round(time.perf_counter() - t0, 2)})  # fmt: skip
                print(f"{suite} {spec:18s} task {task_id} init {init}: {status} {ticks}", file=sys.stderr, flush=True)
            rows.append({"suite": suite, "policy": spec, "task": task_id, "infer_s": policy.times_s})
    finally:
        env.close()
    return rows


def latency_task(job: tuple[str, int, list[str], list[str], list[float], list[int], str]) -> list[dict]:
    """Every (policy, protocol, latency, init) episode of one task through the in-process executor (one env)."""
    import shutil
    import tempfile

    from lq_ros.core.run_config import RunConfig
    from lq_ros.transport.inprocess import run_inprocess

    suite, task_id, specs, modes, latencies, inits, budget_counts = job
    env = LiberoEnv(suite, task_id)
    rows = []
    tmp = Path(tempfile.mkdtemp(prefix="lq_eval_latency_"))
    try:
        for spec in specs:
            name, kwargs = parse_spec(spec)
            for mode in modes:
                args = {**kwargs, "mode": mode} if kwargs.get("variant") == "delay" else dict(kwargs)
                policy = make_policy(name, **args)
                policy.reset(env.task, SEED)
                weights, replan = policy.weights_path.name, int(policy.replan_steps)
                for latency in latencies:
                    for init in inits:
                        cfg = RunConfig(
                            suite=suite, task=task_id, init=init, seed=SEED, mode=mode, latency_s=latency,
                            replan_steps=replan, merge="replace", policy=name, policy_args=args,
                            budget_counts=budget_counts,
                        )  # fmt: skip
                        t0 = time.perf_counter()
                        out = run_inprocess(cfg, tmp, env=env, policy=policy)
                        shutil.rmtree(out.bag_path, ignore_errors=True)
                        status = out.status if out.status != "error" else f"error: {out.reason}"
                        rows.append({"suite": suite, "policy": spec, "mode": mode, "latency_s": latency,
                                     "budget_counts": budget_counts, "task": task_id, "init": init,
                                     "status": status, "ticks": out.ticks,
                                     "replan_steps": replan, "weights": weights,
                                     "weights_md5": weights_digest(policy.weights_path),
                                     "wall_s": round(time.perf_counter() - t0, 2)})  # fmt: skip
                        print(f"{suite} {spec:18s} {mode:5s} {latency:.2f} s {budget_counts} task {task_id}"
                              f" init {init}: {status} {out.ticks}", file=sys.stderr, flush=True)  # fmt: skip
    finally:
        env.close()
        shutil.rmtree(tmp, ignore_errors=True)
    return rows


def budget_of(row: dict) -> str:
    """What the row's step budget counted (rows from before the action budget existed: ``all``, the paper's)."""
    return row.get("budget_counts", "all")


BUDGET_TITLES = {"all": "paper budget (holds count)", "action": "action budget (holds do not count)"}


def check_latency_rows(rows: list[dict]) -> list[dict]:
    """Latency-study rows of several runs, refused if one episode (or one policy spec with two different weight
    files) appears twice."""
    keys = [(r["suite"], r["policy"], r["mode"], budget_of(r), r["latency_s"], r["task"], r["init"]) for r in rows]
    if len(set(keys)) != len(keys):
        raise SystemExit("the same episode is in the merged runs twice")
    digests: dict[tuple[str, str], set[str]] = {}
    for r in rows:
        digests.setdefault((r["suite"], r["policy"]), set()).add(r["weights_md5"])
    bad = sorted(k for k, v in digests.items() if len(v) > 1)
    if bad:
        raise SystemExit(f"runs of {bad} used different weight files (md5)")
    return rows


def latency_report(rows: list[dict]) -> dict:
    """Print, per suite and budget, the success table policy x protocol x latency (k/n = % [Wilson 95%]); returns
    it as {suite: {policy: {mode: {latency: [k, n]}}}} for the paper's budget, with ``" budget=action"`` appended to
    the policy key for the action budget."""
    rows = [r for r in rows if "latency_s" in r]
    summary: dict = {}
    for suite, budget in sorted({(r["suite"], budget_of(r)) for r in rows}):
        mine = [r for r in rows if r["suite"] == suite and budget_of(r) == budget]
        lats = sorted({r["latency_s"] for r in mine})
        tasks, inits = sorted({r["task"] for r in mine}), sorted({r["init"] for r in mine})
        print(f"\n{suite}: latency study, seed={SEED}, tasks {tasks[0]}-{tasks[-1]}, inits {inits[0]}-{inits[-1]},"
              f" lockstep in process, merge replace, {BUDGET_TITLES[budget]}")  # fmt: skip
        print("success k/n = % [Wilson 95% interval | task-clustered 95% interval, %]")
        print(f"{'policy':22s} {'mode':6s}" + "".join(f"{f'{lat:g} s':>32s}" for lat in lats))
        for spec in dict.fromkeys(r["policy"] for r in mine):
            key = spec if budget == "all" else f"{spec} budget={budget}"
            for mode in ("sync", "async"):
                sel = [r for r in mine if r["policy"] == spec and r["mode"] == mode]
                if not sel:
                    continue
                line = f"{spec:22s} {mode:6s}"
                for lat in lats:
                    cell_rows = [r for r in sel if r["latency_s"] == lat]
                    ok, n = sum(r["status"] == "success" for r in cell_rows), len(cell_rows)
                    lo, hi = wilson_interval(ok, n) if n else (0.0, 0.0)
                    clustered = interval_text(*task_clustered(cell_rows)) if n else ""
                    text = f"{ok}/{n} = {100 * ok / n:.0f}% [{100 * lo:.0f}-{100 * hi:.0f} | {clustered}]" if n else "-"
                    line += f"{text:>32s}"
                    summary.setdefault(suite, {}).setdefault(key, {}).setdefault(mode, {})[f"{lat:g}"] = [ok, n]
                print(line)
        errors = sum(r["status"].startswith("error") for r in mine)
        print(f"episodes: {len(mine)}, errors: {errors}")
        for spec in dict.fromkeys(r["policy"] for r in mine):
            files = sorted({(r["weights"], r["weights_md5"]) for r in mine if r["policy"] == spec})
            print(f"  {spec}: " + ", ".join(f"{name} (md5 {md5})" for name, md5 in files))
    return summary


def weights_digest(checkpoint_json: Path) -> str:
    """MD5 of the ``.pt`` file a checkpoint JSON names (what tells two copies of a checkpoint apart)."""
    meta = json.loads(checkpoint_json.read_text())
    return hashlib.md5(checkpoint_json.with_name(meta["weights_file"]).read_bytes()).hexdigest()


def by_weights(rows: list[dict]) -> tuple[list[dict], list[str], dict[tuple[str, str], str]]:
    """Relabel rows by checkpoint base name (``oft_c8``), checking that each name has one set of bytes.

    Returns (rows, labels in first-seen order, (suite, label) -> a policy spec that loads it, for the latency).
    """
    from lq_ros.policies.learned.chunk_policy import resolve_weights

    label_of: dict[tuple[str, str], str] = {}  # (suite, spec) -> label
    digest: dict[tuple[str, str], str] = {}  # (suite, label) -> md5
    sources: dict[tuple[str, str], list[str]] = {}  # (suite, label) -> where each spec's md5 came from
    spec_of: dict[tuple[str, str], str] = {}
    for r in rows:
        if "status" not in r or (r["suite"], r["policy"]) in label_of:
            continue
        suite, spec = r["suite"], r["policy"]
        label = r["weights"].removesuffix(".json").removesuffix(f"_{suite}")
        if r.get("weights_md5"):
            md5, source = r["weights_md5"], f"{spec!r}: recorded in the run"
        else:
            weights = parse_spec(spec)[1].get("weights") or label
            path = resolve_weights(str(weights), suite)
            md5, source = weights_digest(path), f"{spec!r}: {path} now, not recorded in the run"
        if digest.setdefault((suite, label), md5) != md5:
            raise SystemExit(f"{suite} {label}: {source} is {md5}, other runs of {label} {digest[suite, label]}")
        sources.setdefault((suite, label), []).append(source)
        label_of[suite, spec] = label
        spec_of.setdefault((suite, label), spec)
    out, episodes = [], set()
    for r in rows:
        label = label_of.get((r["suite"], r["policy"]))
        if label is None:
            raise SystemExit(f"{r['suite']} {r['policy']!r}: latency rows without episodes")
        if "status" in r:
            key = (r["suite"], label, r["task"], r["init"])
            if key in episodes:
                raise SystemExit(f"episode {key} is in the merged runs twice")
            episodes.add(key)
        out.append({**r, "policy": label, "spec": r["policy"]})
    for (suite, label), md5 in digest.items():
        print(f"{suite} {label}: weights md5 {md5} ({'; '.join(sources[suite, label])})")
    return out, list(dict.fromkeys(label for _, label in spec_of)), spec_of


def isolated_latency_ms(spec: str, suite: str, repeats: int = 200) -> dict:
    """infer() on one real observation (task 0, init 0), repeated after warm-up: the model's own cost."""
    name, kwargs = parse_spec(spec)
    policy = make_policy(name, **kwargs)
    env = LiberoEnv(suite, 0)
    try:
        env.reset(0, SEED)
        policy.reset(env.task, SEED)
        obs = env.observe(with_images=False)
    finally:
        env.close()
    for _ in range(10):
        policy.infer(obs)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        policy.infer(obs)
        times.append(time.perf_counter() - t0)
    t = np.array(times) * 1e3
    return {"mean": float(t.mean()), "p50": float(np.median(t)), "p95": float(np.percentile(t, 95))}


def task_clustered(rows: list[dict]) -> tuple[float, float]:
    """The success rate's task-clustered 95% interval over ``rows`` (whole tasks resampled, the Wilson interval's
    hull: lq_ros.scoring.intervals.clustered_success_ci); NaN below its minimum number of tasks."""
    by_task: dict[int, list[float]] = {}
    for r in rows:
        by_task.setdefault(r["task"], []).append(float(r["status"] == "success"))
    return clustered_success_ci(list(by_task.values()))


def total_from_counts(counts: list[str]) -> str:
    """``k/n = p% [Wilson | task-clustered]`` of the total of per-task counts ``k/n`` (one per task), computed as the
    table of a run computes it (the clustered interval depends on each task's k and n only). ValueError naming a
    count that is not ``k/n`` with 0 <= k <= n and n > 0."""
    rows = []
    for task, count in enumerate(counts):
        k, _, n = count.partition("/")
        if not (k.isdigit() and n.isdigit() and 0 < int(n) and int(k) <= int(n)):
            raise ValueError(f"--from-counts: {count!r} is not k/n with 0 <= k <= n and n > 0 (e.g. 7/10)")
        rows += [{"task": task, "status": "success" if i < int(k) else "failure"} for i in range(int(n))]
    ok = sum(r["status"] == "success" for r in rows)
    lo, hi = wilson_interval(ok, len(rows))
    clustered = interval_text(*task_clustered(rows))
    return f"{ok}/{len(rows)} = {100 * ok / len(rows):.0f}% [{100 * lo:.0f}-{100 * hi:.0f} | {clustered}]"


def interval_text(low: float, high: float) -> str:
    """``lo-hi`` in percent, ``n/a`` for an interval that is not defined (too few tasks)."""
    return "n/a" if np.isnan(low) else f"{100 * low:.0f}-{100 * high:.0f}"


def cell(ok: int, n: int) -> str:
    """``k/n [lo-hi]`` with the Wilson 95% interval in percent."""
    if n == 0:
        return "-"
    lo, hi = wilson_interval(ok, n)
    return f"{ok}/{n} [{100 * lo:.0f}-{100 * hi:.0f}]"


def report(
    rows: list[dict], specs: list[str], isolated: bool, spec_of: dict[tuple[str, str], str] | None = None
) -> dict:
    """Print, per suite, the per-task success table (Wilson 95% CIs) and latency; returns the summary.

    ``specs`` are the column labels (the rows' ``policy``); ``spec_of`` maps (suite, label) to the policy spec
    the isolated latency is measured with (default: the label itself)."""
    episodes = [r for r in rows if "status" in r]
    summary: dict = {}
    for suite in sorted({r["suite"] for r in episodes}, key=lambda s: (s not in SUITES, s)):
        mine = [r for r in episodes if r["suite"] == suite]
        tasks = sorted({r["task"] for r in mine})
        inits = sorted({r["init"] for r in mine})
        print(
            f"\n{suite}: seed={SEED} inits={inits[0]}-{inits[-1]} ({len(inits)} per task) Δt_sim=0 (conventional loop)"
        )
        print("success k/n [Wilson 95% interval, %]")
        width = 19
        print("task   " + "".join(f"{s:>{width}s}" for s in specs))
        for t in tasks:
            line = f"t{t:<6d}"
            for spec in specs:
                sel = [r for r in mine if r["policy"] == spec and r["task"] == t]
                line += f"{cell(sum(r['status'] == 'success' for r in sel), len(sel)):>{width}s}"
            print(line)
        line = "total  "
        for spec in specs:
            sel = [r for r in mine if r["policy"] == spec]
            line += f"{cell(sum(r['status'] == 'success' for r in sel), len(sel)):>{width}s}"
        print(line)
        # The total's Wilson interval treats the episodes as independent; success clusters by task.
        clustered = {spec: task_clustered(sel) for spec in specs if (sel := [r for r in mine if r["policy"] == spec])}
        line = "tasks  "
        for spec in specs:
            line += f"{f'[{interval_text(*clustered[spec])}]' if spec in clustered else '-':>{width}s}"
        print(line + f"   <- the total's task-clustered 95% interval, % ({len(tasks)} tasks)")
        summary[suite] = {}
        for spec in specs:
            sel = [r for r in mine if r["policy"] == spec]
            if not sel:
                continue
            n_ok = sum(r["status"] == "success" for r in sel)
            n_err = sum(r["status"].startswith("error") for r in sel)
            steps = [r["ticks"] for r in sel if r["status"] == "success"]
            infer = np.concatenate(
                [r["infer_s"] for r in rows if r.get("policy") == spec and r.get("suite") == suite and "infer_s" in r]
            )
            infer_ms = infer * 1e3
            lo, hi = wilson_interval(n_ok, len(sel))
            s = summary[suite][spec] = {
                "success": n_ok,
                "episodes": len(sel),
                "wilson95": [lo, hi],
                "task_clustered95": list(clustered[spec]),
                "errors": n_err,
                "per_task": {
                    t: [sum(r["status"] == "success" for r in sel if r["task"] == t), sum(r["task"] == t for r in sel)]
                    for t in tasks
                },
                "mean_steps_success": float(np.mean(steps)) if steps else None,
                "infer_ms_in_loop_mean": float(infer_ms.mean()) if len(infer_ms) else None,
                "infer_ms_in_loop_p50": float(np.median(infer_ms)) if len(infer_ms) else None,
                "infer_calls": len(infer_ms),
                "replan_steps": sel[0]["replan_steps"],
                "weights": sel[0].get("weights"),
            }
            print(
                f"  {spec:18s} {s['weights'] or ''}: replan {s['replan_steps']}, {100 * n_ok / len(sel):.0f}%"
                f" [{100 * lo:.0f}-{100 * hi:.0f}],"
                f" mean steps (successes) {s['mean_steps_success'] or float('nan'):.1f},"
                f" infer in loop mean {s['infer_ms_in_loop_mean']:.2f} ms p50 {s['infer_ms_in_loop_p50']:.2f}"
                f" (n={len(infer_ms)})" + (f", errors: {n_err}" if n_err else "")
            )
        if isolated:
            print("  isolated infer latency (task 0 init 0 observation, 200 calls after warm-up, 1 torch thread):")
            for spec in specs:
                if spec not in summary[suite]:
                    continue
                lat = isolated_latency_ms((spec_of or {}).get((suite, spec), spec), suite)
                summary[suite][spec]["infer_ms_isolated"] = lat
                print(f"  {spec:18s} mean {lat['mean']:.2f} ms  p50 {lat['p50']:.2f}  p95 {lat['p95']:.2f}")
    return summary


def print_provenance(runs: list[dict | None]) -> None:
    """The commits, CPU classes and library versions the runs recorded (a run from before they were: unknown)."""
    known = [p for p in runs if p]
    commits = sorted({p["git_commit"] for p in known}) + (["unknown"] if len(known) < len(runs) else [])
    classes = sorted({p["cpu"]["class"] for p in known})
    libs = sorted({f"mujoco {p['mujoco']}, torch {p['torch']}, numpy {p['numpy']}" for p in known})
    print(f"commit {', '.join(commits)}; CPU class {', '.join(classes) or 'unknown'}; {'; '.join(libs)}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--suite", action="append", choices=SUITES, help="repeatable; default: both")
    ap.add_argument("--inits", type=int, default=10, help="N init states per task")
    ap.add_argument("--init-start", type=int, default=0, help="first init state (to split a run; see --merge)")
    ap.add_argument("--tasks", type=int, nargs="*", default=list(range(10)))
    ap.add_argument("--policy", action="append", help="name[:key=value,...] (repeatable)")
    ap.add_argument("--replan-steps", type=int, default=0, help="override the weights' replan_steps")
    ap.add_argument("--workers", type=int, default=2, help="processes (one task each at a time)")
    ap.add_argument("--json", type=Path, help="also write every episode row here")
    ap.add_argument("--merge", type=Path, nargs="+", help="only print the table of these --json files together")
    ap.add_argument("--by-weights", action="store_true", help="--merge: one column per checkpoint (see above)")
    ap.add_argument("--from-counts", nargs="+", metavar="K/N", help="only print a total's intervals from task counts")
    ap.add_argument("--no-isolated", action="store_true", help="skip the isolated latency measurement")
    ap.add_argument("--latency", type=float, nargs="+", help="latency study: injected Δt_sim values, s")
    ap.add_argument("--mode", action="append", choices=("sync", "async"), help="latency study protocols (repeatable)")
    ap.add_argument(
        "--budget", choices=BUDGET_COUNTS, default="all",
        help="latency study: what the step budget counts (all ticks: the paper's; action ticks only)",
    )  # fmt: skip
    args = ap.parse_args()

    if args.from_counts:
        try:
            print("success k/n = % [Wilson 95% interval | task-clustered 95% interval, %]")
            print(total_from_counts(args.from_counts))
        except ValueError as exc:
            ap.error(str(exc))
        return
    if args.merge:
        loaded = [json.loads(path.read_text()) for path in args.merge]
        rows = [r for run in loaded for r in run["rows"]]
        if any("latency_s" in r for r in rows):
            summary = latency_report(check_latency_rows(rows))
            print_provenance([run.get("provenance") for run in loaded])
            if args.json:
                args.json.write_text(json.dumps({"latency": summary, "merged": [str(p) for p in args.merge]}))
            return
        spec_of = None
        if args.by_weights:
            rows, specs, spec_of = by_weights(rows)
        else:
            specs = list(dict.fromkeys(r["policy"] for r in rows))
        summary = report(rows, specs, isolated=not args.no_isolated, spec_of=spec_of)
        print_provenance([run.get("provenance") for run in loaded])
        if args.json:
            args.json.write_text(json.dumps({"summary": summary, "merged": [str(p) for p in args.merge]}, indent=1))
        return
    specs = args.policy or list(DEFAULT_POLICIES)
    suites = args.suite or list(SUITES)
    provenance = versions()
    started = time.perf_counter()
    inits = range(args.init_start, args.init_start + args.inits)
    if args.latency:
        modes = args.mode or ["async"]
        jobs = [(s, t, specs, modes, args.latency, list(inits), args.budget) for s in suites for t in args.tasks]
        results = run_jobs(latency_task, jobs, args.workers)
        rows = [r for res in results for r in res]
        summary = latency_report(rows)
        print_provenance([provenance])
        print(f"wall time {time.perf_counter() - started:.0f} s with {args.workers} workers")
        if args.json:
            args.json.write_text(json.dumps({"latency": summary, "rows": rows, "provenance": provenance}, indent=1))
        return
    jobs = [(s, t, specs, inits, args.replan_steps) for s in suites for t in args.tasks]
    results = run_jobs(eval_task, jobs, args.workers)
    rows = [r for res in results for r in res]
    wall = time.perf_counter() - started
    if args.json:
        args.json.write_text(json.dumps({"rows": rows, "provenance": provenance}, indent=1))
    summary = report(rows, specs, isolated=not args.no_isolated)
    print_provenance([provenance])
    print(f"wall time {wall:.0f} s with {args.workers} workers (episodes only)")
    if args.json:
        args.json.write_text(json.dumps({"summary": summary, "rows": rows, "provenance": provenance}, indent=1))


if __name__ == "__main__":
    main()
