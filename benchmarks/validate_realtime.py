"""Does lockstep latency injection predict real execution? Real-time runs at L vs lockstep at Δt_sim = L.

Usage: python benchmarks/validate_realtime.py [--latencies 0.1 0.2] [--modes sync async] [--inits 20]
                                               [--task 0] [--out bags/validate_realtime] [--table-only]
                                               [--fit-from OTHER_OUT]
For each L, protocol and init state of LIBERO-Spatial task ``--task`` (seed 7):

- real time (``--clock realtime``, four processes on the wall clock): the scripted expert whose inference
  takes L of wall time (``lq_ros.policies.sleepy:SleepyPolicy sleep_s=L``), no injected latency; async
  requests the next chunk with N = L / 50 ms actions left, as lockstep's default does;
- lockstep (in process, bit-identical to the ROS stack): the scripted expert at Δt_sim = L;
- lockstep, replayed delays: the same, with the delays the paired real-time episode (same init state) really
  had between each request and its chunk taking effect, replayed per request as a ``trace:`` latency
  (written to ``OUT/traces/``), at the real-time run's request threshold. Real time pays what lockstep's
  Δt_sim leaves out (the observation waiting for the sim's step, transport), a few ms that push some chunks
  past a tick boundary; this arm tells that apart from a fault of the injection model. It is a consistency
  check, not a prediction: an episode's delays exist only after it ran.
- lockstep, fitted delays (the prediction): for the held-out second half of the init states only, the
  request-to-effect delays of the real-time episodes of the *first* half (same L and protocol), pooled into an
  ``empirical:`` latency (each request draws one of them at random; ``OUT/fits/``), at the real-time request
  threshold. A second table compares the arms on the held-out init states alone.
  With ``--fit-from OTHER_OUT`` the delays come instead from every real-time episode of a *separate* run of this
  script (another folder, run at another time: other load, other scheduling), and the fitted arm runs on every
  init state of this run: a prediction of one run from another, not of one half of a run from its other half.

Episodes are stored under their configuration, so a rerun resumes. Prints success (Wilson 95% CI) and,
over successes, completion time, jerk (20 Hz) and energy (bootstrap 95% CIs) side by side, plus the
real-time runs' overrun ticks and missed commands. Real-time results depend on the machine's load:
state it with the numbers (``uptime``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections import Counter
from functools import cache
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import lq_ros  # noqa: F401 - first: it pins OpenBLAS's kernels before numpy loads them (lq_ros/__init__.py)

# isort: split

import pandas as pd  # noqa: E402

from lq_ros.core.latency import LatencyDist  # noqa: E402
from lq_ros.core.run_config import RunConfig, versions  # noqa: E402
from lq_ros.core.suite_constants import CONTROL_DT_S  # noqa: E402
from lq_ros.recording.episode_bag import read_run_metadata, scan_mcap  # noqa: E402
from lq_ros.recording.episode_folder import SCORE_FILE  # noqa: E402
from lq_ros.run.episode import run_episode, scored_row  # noqa: E402
from lq_ros.scoring.aggregate import aggregate, ci_text  # noqa: E402
from lq_ros.wire import messages as m  # noqa: E402

SLEEPY = "lq_ros.policies.sleepy:SleepyPolicy"
FITTED = "lockstep, fitted delays"
METRICS = (("completion s (succ.)", "completion_time_s", 2), ("jerk m/s³ (succ.)", "jerk_mean", 1),
           ("energy J (succ.)", "energy_total_j", 0))  # fmt: skip


def configs(latencies: list[float], modes: list[str], inits: int, task: int, out: Path, fit_from: Path | None = None):
    """(L, arm, config) in run order; lazily: a replay config exists once its real-time bag does."""
    for lat in latencies:
        for mode in modes:
            for init in range(inits):
                common = dict(suite="libero_spatial", task=task, init=init, seed=7, mode=mode)
                # Same protocol as lockstep at N = L / 50 ms: async asks for the next chunk when N actions are
                # left (replace's default threshold is the *injected* N, which is 0 here).
                threshold = round(lat / CONTROL_DT_S) if mode == "async" else -1
                realtime = realtime_config(lat, mode, init, task)
                yield lat, "realtime", realtime
                yield lat, "lockstep", RunConfig(**common, latency_s=lat)
                trace = replay_trace(out / realtime.episode_name(), out / "traces", lat, RunConfig(**common))
                if fit_from is not None:
                    fitted = fitted_delays(fit_from, lat, mode, range(inits), task, out / "fits")
                else:
                    fitted = fitted_delays(out, lat, mode, range(inits // 2), task) if init >= inits // 2 else None
                if fitted is not None:
                    yield (
                        lat,
                        FITTED,
                        RunConfig(**common, latency_dist=f"empirical:{fitted}", request_threshold=threshold),
                    )
                if trace is not None:
                    yield (
                        lat,
                        "lockstep, replayed delays",
                        RunConfig(**common, latency_dist=f"trace:{trace}", request_threshold=threshold),
                    )


def realtime_config(lat: float, mode: str, init: int, task: int) -> RunConfig:
    threshold = round(lat / CONTROL_DT_S) if mode == "async" else -1
    return RunConfig(suite="libero_spatial", task=task, init=init, seed=7, mode=mode, clock="realtime",
                     policy=SLEEPY, policy_args={"sleep_s": lat}, request_threshold=threshold)  # fmt: skip


def fitted_delays(
    source: Path, lat: float, mode: str, inits: range, task: int, fits: Path | None = None
) -> Path | None:
    """The pooled request-to-effect delays (s) of the real-time episodes of ``inits`` stored in ``source``, as an
    ``empirical:`` latency file (in ``fits``, default ``source/fits``); None until all of them have run."""
    bags = [source / realtime_config(lat, mode, i, task).episode_name() for i in inits]
    if not bags or not all((bag / "metadata.yaml").exists() for bag in bags):
        return None
    origin = "" if fits is None else f"_from_{source.name}"
    name = f"task{task}_{mode}_{round(lat * 1000)}ms_inits{inits[0]}-{inits[-1]}{origin}.txt"
    path = (fits or source / "fits") / name
    if not path.exists():
        delays = [d for bag in bags for d in applied_delays_ticks(bag).values()]
        path.parent.mkdir(parents=True, exist_ok=True)
        header = f"# request-to-effect delays (s) of {len(bags)} real-time episodes, {mode}, L = {lat:g} s\n"
        path.write_text(header + "\n".join(f"{d * CONTROL_DT_S:.3f}" for d in delays) + "\n")
    return path


@cache  # read once per bag: the trace and the table both need it
def applied_delays_ticks(bag: Path) -> dict[int, int]:
    """Request id -> ticks from its observation request to the first command of its chunk, from a bag."""
    requested, applied = {}, {}
    for file in sorted(bag.glob("*.mcap")):
        for topic, _t, data in scan_mcap(file, keep_messages=True).messages:
            if topic == m.OBSERVATION_REQUEST.name:
                req = m.deserialize(data, m.OBSERVATION_REQUEST.msgtype)
                requested[req.request_id] = req.tick
            elif topic == m.COMMAND.name:
                cmd = m.deserialize(data, m.COMMAND.msgtype)
                if cmd.request_id and cmd.request_id not in applied:
                    applied[cmd.request_id] = cmd.tick
    return {rid: applied[rid] - tick for rid, tick in requested.items() if rid in applied}


def replay_trace(bag: Path, folder: Path, lat: float, cfg: RunConfig) -> Path | None:
    """The real-time episode's applied delays as a latency trace for the episode of ``cfg``: request k replays
    the delay of the real-time request k (L where unknown). A trace starts at a line drawn from the episode's
    latency stream (lq_ros.core.latency), which depends only on the stream and the number of lines, so the
    lines are written rotated by that offset."""
    if not (bag / "metadata.yaml").exists():
        return None
    path = folder / f"{bag.name}.txt"
    if not path.exists():
        delays = applied_delays_ticks(bag)
        nominal = round(lat / CONTROL_DT_S)
        values = [delays.get(rid, nominal) * CONTROL_DT_S for rid in range(1, max(delays, default=0) + 1)] or [lat]
        offset = LatencyDist("trace", (), tuple(values)).trace_offset(cfg.latency_stream())
        lines = [""] * len(values)
        for k, value in enumerate(values):
            lines[(offset + k) % len(values)] = f"{value:.3f}"
        folder.mkdir(parents=True, exist_ok=True)
        path.write_text(f"# request-to-chunk delays (s) of {bag.name}\n" + "\n".join(lines) + "\n")
    return path


def paired_agreement(episodes: pd.DataFrame) -> str:
    """Per (L, protocol): how often each lockstep arm agrees with the real-time episode of the same init state."""
    index = ["L_s", "mode", "init"]
    real = episodes[episodes.clock == "realtime"].set_index(index)
    lines = []
    arms = episodes.loc[episodes.clock != "realtime", ["L_s", "mode", "clock"]].drop_duplicates()
    for lat, mode, arm in sorted(arms.itertuples(index=False, name=None)):
        other = episodes[(episodes.clock == arm) & (episodes.L_s == lat) & (episodes["mode"] == mode)].set_index(index)
        both = real.join(other, how="inner", rsuffix="_arm")
        energy_close = (both.energy_total_j - both.energy_total_j_arm).abs() <= 1e-6 * both.energy_total_j.abs()
        lines.append({"L s": lat, "mode": mode, "arm vs realtime": arm, "pairs": len(both),
                      "same outcome": int((both.status == both.status_arm).sum()),
                      "same completion tick": int((both.completion_steps == both.completion_steps_arm).sum()),
                      "energy within 1e-6 rel.": int(energy_close.sum())})  # fmt: skip
    return pd.DataFrame(lines).to_markdown(index=False)


def delay_counts(episodes: pd.DataFrame) -> str:
    """Real-time chunks by how many ticks they took from request to effect, per (L, protocol)."""
    lines = []
    for (lat, mode), group in episodes[episodes.clock == "realtime"].groupby(["L_s", "mode"]):
        counts = Counter(d for delays in group.delays for d in delays)
        lines.append({"L s": lat, "mode": mode, "chunks": sum(counts.values()),
                      **{f"{k} ticks": counts[k] for k in sorted(counts)}})  # fmt: skip
    return pd.DataFrame(lines).fillna(0).to_markdown(index=False)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--latencies", type=float, nargs="+", default=[0.1, 0.2])
    ap.add_argument("--modes", nargs="+", default=["sync", "async"])
    ap.add_argument("--inits", type=int, default=20)
    ap.add_argument("--task", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("bags/validate_realtime"))
    ap.add_argument("--table-only", action="store_true", help="only tabulate the episodes already stored")
    ap.add_argument(
        "--fit-from",
        type=Path,
        default=None,
        help="fit the delays on every real-time episode of this other run's folder (a separate run)",
    )
    args = ap.parse_args()
    if args.fit_from is not None and args.fit_from.resolve() == args.out.resolve():
        raise SystemExit("--fit-from must name another run's folder than --out")

    load_start = os.getloadavg()[0]
    rows = []
    for lat, arm, cfg in configs(args.latencies, args.modes, args.inits, args.task, args.out, args.fit_from):
        bag = args.out / cfg.episode_name()
        if not (bag / SCORE_FILE).exists() and not (bag / "metadata.yaml").exists():
            if args.table_only:
                continue
            transport = "ros" if cfg.clock == "realtime" else "inprocess"
            run_episode(cfg, args.out, transport)
        row = scored_row(bag)
        row["L_s"], row["clock"] = lat, arm
        row["delays"] = delays = list(applied_delays_ticks(bag).values())
        row["late_chunks_pct"] = 100.0 * sum(d > round(lat / CONTROL_DT_S) for d in delays) / max(len(delays), 1)
        stats = (read_run_metadata(bag).get("realtime") or {}) if (bag / "metadata.yaml").exists() else {}
        row["overrun_ticks"] = sum(s.get("overrun_ticks", 0) for s in stats.values())
        row["missed_commands"] = stats.get("sim", {}).get("missed_commands", 0)
        rows.append(row)
        print(json.dumps({k: row.get(k) for k in ("clock", "mode", "L_s", "init", "status", "completion_steps")}),
              file=sys.stderr)  # fmt: skip
    episodes = pd.DataFrame(rows)
    if episodes.empty:
        raise SystemExit(f"{args.out}: no episodes stored (run without --table-only)")
    env_versions = versions()
    print(
        f"commit {env_versions.get('git_commit')}; CPU class {env_versions['cpu']['class']}; 1-min load average "
        f"{load_start:.2f} at start, {os.getloadavg()[0]:.2f} at end ({len(os.sched_getaffinity(0))} CPUs)"
    )
    print(cell_table(episodes))
    print("\nReal-time chunks by request-to-effect delay:\n" + delay_counts(episodes))
    print("\nPaired episodes (same L, protocol, init state):\n" + paired_agreement(episodes))
    held_out = episodes[episodes.init >= args.inits // 2]
    if args.fit_from is None and (held_out.clock == FITTED).any():
        print(f"\nHeld-out init states {args.inits // 2}-{args.inits - 1} only (the fitted arm's delays come from "
              f"init states 0-{args.inits // 2 - 1}):\n" + cell_table(held_out))  # fmt: skip


def cell_table(episodes: pd.DataFrame) -> str:
    """Success and metrics per (L, protocol, arm), with intervals."""
    aggs = aggregate(episodes, by=("clock", "mode", "L_s"))
    table = []
    for _, agg in aggs.iterrows():
        group = episodes[(episodes.clock == agg.clock) & (episodes["mode"] == agg["mode"]) & (episodes.L_s == agg.L_s)]
        line = {"L s": agg.L_s, "mode": agg["mode"], "clock": agg.clock, "n": int(agg.n), "errors": int(agg.n_error),
                "success %": ci_text(agg, "success", 0, 100.0)}  # fmt: skip
        for header, metric, decimals in METRICS:
            line[header] = ci_text(agg, metric, decimals)
        line["chunks late by >= 1 tick %"] = f"{group.late_chunks_pct.mean():.0f}"
        line["overrun ticks / ep"] = f"{group.overrun_ticks.mean():.1f}" if agg.clock == "realtime" else "–"
        line["missed cmds / ep"] = f"{group.missed_commands.mean():.1f}" if agg.clock == "realtime" else "–"
        table.append(line)
    return pd.DataFrame(table).sort_values(["L s", "mode", "clock"]).to_markdown(index=False)


if __name__ == "__main__":
    main()
