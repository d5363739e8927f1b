"""Rebuild every shipped dataset and weight file from a fresh clone: ``python -m lq_ros.training.pipeline``.

The stages are in ``config/training/shipped_weights.yaml``: each dataset is one ``lq collect`` and each weight
file one ``lq train`` (every other option at the shipped recipe's default), with the seeds the shipped files
record; tests/training/test_pipeline.py checks the file against the ``collect_config`` and ``train_config``
each shipped JSON records. Collection resumes from finished tasks, so an interrupted rebuild goes on where it
stopped when run again.

    .venv/bin/python -m lq_ros.training.pipeline --out rebuild            # every stage, timed
    .venv/bin/python -m lq_ros.training.pipeline --out rebuild --only oft_c8_libero_object
    .venv/bin/python -m lq_ros.training.pipeline --out rebuild --plan     # the commands, and the recorded times
    .venv/bin/python -m lq_ros.training.pipeline --out rebuild --only oft_c8_delay_libero_object   # a candidate

The YAML's ``candidates`` are weight files that were built and evaluated but are not shipped (the delay-aware
variants, docs/design/learned_policies.md): built only when named with ``--only``, after the weights they start from.

``--plan`` prints each stage's command and the wall time the shipped files record for it (collection: the
sum over tasks of each task's time, with ``workers`` tasks at a time; training: ``train_wall_s``).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import yaml

from lq_ros.policies.learned.chunk_policy import WEIGHTS_DIR
from lq_ros.training.collect import CollectConfig
from lq_ros.training.recipe import TrainConfig, parse_ids

PIPELINE_FILE = Path(__file__).resolve().parents[2] / "config" / "training" / "shipped_weights.yaml"
#: ``lq collect`` options a dataset entry may set, with their defaults (those of the command).
COLLECT_OPTIONS = {"suite": "libero_spatial", "tasks": "0-9", "inits": "10-29", "noise": "0,0.1,0.2", "repeats": 1,
                   "seed": 7, "workers": 2, "keep_failures": False, "latency_ticks": "", "modes": "sync,async",
                   "latency_driver": ["scripted"], "gripper_noise": 0.0}  # fmt: skip
#: ``lq train`` options a weights entry may set beyond policy, chunk and data (the delay-aware fine-tunes).
TRAIN_OPTIONS = ("steps", "lr", "delay_max", "init_from", "freeze_base", "successful_only")


@dataclass(frozen=True)
class Dataset:
    name: str
    options: dict  # lq collect options

    def config(self) -> CollectConfig:
        o = {**COLLECT_OPTIONS, **self.options}
        return CollectConfig(
            suite=o["suite"], tasks=parse_ids(o["tasks"]), inits=parse_ids(o["inits"]),
            noise_levels=tuple(float(x) for x in str(o["noise"]).split(",")), repeats=int(o["repeats"]),
            seed=int(o["seed"]), workers=int(o["workers"]), keep_failures=bool(o["keep_failures"]),
            latency_ticks=parse_ids(o["latency_ticks"]) if o["latency_ticks"] else (),
            modes=tuple(str(o["modes"]).split(",")), latency_drivers=tuple(o["latency_driver"]),
            gripper_noise=float(o["gripper_noise"]),
        )  # fmt: skip

    def command(self, out: Path) -> list[str]:
        argv = [sys.executable, "-m", "lq_ros.cli", "collect", "--out", str(out / "data" / self.name)]
        for key, value in self.options.items():
            flag = f"--{key.replace('_', '-')}"
            if isinstance(value, bool):
                argv += [flag] if value else []
            elif isinstance(value, list):
                argv += [a for v in value for a in (flag, str(v))]
            else:
                argv += [flag, str(value)]
        return argv


@dataclass(frozen=True)
class Weights:
    name: str
    policy: str
    chunk: int
    data: tuple[str, ...]
    #: Further ``lq train`` options (TRAIN_OPTIONS); ``init_from`` names another weights entry, built first.
    options: tuple[tuple[str, object], ...] = ()
    #: False for the YAML's ``candidates``: built and evaluated, not shipped (built with ``--only NAME``).
    shipped: bool = True

    def config(self) -> TrainConfig:
        return TrainConfig(policy=self.policy, horizon=self.chunk, **dict(self.options))

    def command(self, out: Path) -> list[str]:
        argv = [sys.executable, "-m", "lq_ros.cli", "train", "--policy", self.policy, "--chunk", str(self.chunk)]
        for name in self.data:
            argv += ["--data", str(out / "data" / name)]
        for key, value in self.options:
            flag = f"--{key.replace('_', '-')}"
            argv += ([flag] if value else []) if isinstance(value, bool) else [flag, str(value)]
        return argv + ["--out", str(out / "weights")]


def load_pipeline(path: Path = PIPELINE_FILE) -> tuple[dict[str, Dataset], dict[str, Weights]]:
    raw = yaml.safe_load(Path(path).read_text())
    datasets = {name: Dataset(name, dict(options)) for name, options in raw["datasets"].items()}
    weights = {
        name: Weights(
            name,
            entry["policy"],
            int(entry["chunk"]),
            tuple(entry["data"]),
            tuple((k, entry[k]) for k in TRAIN_OPTIONS if k in entry),
            shipped=section == "weights",
        )  # fmt: skip
        for section in ("weights", "candidates")
        for name, entry in (raw.get(section) or {}).items()
    }
    bad = {n: w for n, w in weights.items() if dict(w.options).get("init_from", n) not in weights}
    if bad:
        raise ValueError(f"{path}: init_from names no weights entry: {sorted(bad)}")
    unknown = {d for w in weights.values() for d in w.data} - set(datasets)
    if unknown:
        raise ValueError(f"{path}: weights use datasets that are not defined: {sorted(unknown)}")
    return datasets, weights


def recorded_times(weights: dict[str, Weights]) -> tuple[dict[str, float], dict[str, float]]:
    """Wall seconds the shipped JSONs record: per dataset (sum of its tasks' times) and per weight file."""
    collect_s, train_s = {}, {}
    for w in weights.values():
        if not w.shipped:
            continue
        meta = json.loads((WEIGHTS_DIR / f"{w.name}.json").read_text())
        train_s[w.name] = float(meta["metrics"]["train_wall_s"])
        for name, source in zip(w.data, meta["dataset"]["sources"], strict=True):
            collect_s[name] = sum(t["wall_s"] for t in source["collection"]["per_task"].values())
    return collect_s, train_s


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="folder for data/<dataset> and weights/")
    parser.add_argument("--only", nargs="*", default=None, help="weight files to build (and their datasets)")
    parser.add_argument("--plan", action="store_true", help="print the commands and the recorded times only")
    parser.add_argument("--pipeline", type=Path, default=PIPELINE_FILE)
    args = parser.parse_args(argv)
    datasets, weights = load_pipeline(args.pipeline)
    chosen = {n: w for n, w in weights.items() if (w.shipped if args.only is None else n in args.only)}
    # A fine-tune needs the weights it starts from (built first: the YAML lists them before it).
    starts = {dict(w.options).get("init_from") for w in chosen.values()} - {None}
    chosen = {n: w for n, w in weights.items() if n in chosen or n in starts}
    if args.only and set(args.only) - set(weights):
        print(f"error: unknown weights {sorted(set(args.only) - set(weights))}; known: {sorted(weights)}")
        return 2
    needed = [datasets[d] for d in dict.fromkeys(d for w in chosen.values() for d in w.data)]
    collect_s, train_s = recorded_times(weights)
    stages = [(f"collect {d.name}", d.command(args.out), collect_s.get(d.name)) for d in needed]
    stages += [(f"train {w.name}", w.command(args.out), train_s.get(w.name)) for w in chosen.values()]
    for what, command, recorded in stages:
        shown = " ".join(["lq", *command[3:]])
        print(f"{what}: {shown}  " + ("(not shipped)" if recorded is None else f"(recorded: {recorded:.0f} s)"))
        if args.plan:
            continue
        started = time.monotonic()
        done = subprocess.run(command, check=False)
        if done.returncode != 0:
            print(f"error: {what} failed (exit {done.returncode})")
            return 1
        print(f"{what}: {time.monotonic() - started:.0f} s here")
    return 0


if __name__ == "__main__":
    sys.exit(main())
