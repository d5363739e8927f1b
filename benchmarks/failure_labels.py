"""The failure-mode classifier against labels made by reading the taxonomy and watching replays.

Four steps; the labelled set they make is committed under tests/data/failure_labels/ (its check is
tests/scoring/test_failure_labels.py):

    select     pick failed episodes of a sweep, stratified by suite, protocol, latency and policy (seeded), and
               write their list (episodes.json). The classifier's output is not used to pick them.
    render     re-simulate each picked bag's commands (checked against its recorded EE poses) and render 20 ticks
               of the front and wrist cameras into a contact sheet (sheets/<episode>.png): the labeller's view of
               the replay. The sheets carry no classifier output; index.csv names each episode's task and goal.
    extract    copy what the classifier reads (events, EE pose, task state; metadata) of each picked bag into a
               small bag under tests/data/failure_labels/bags/, so the check runs without the sweep.
    agreement  score the small bags and print the confusion matrix of labels.csv against the classifier, the
               raw agreement and Cohen's kappa, each with the labelled count.

    .venv/bin/python benchmarks/failure_labels.py select bags/sweeps/failure_modes --n 48 --inits 0,1,2
    .venv/bin/python benchmarks/failure_labels.py render bags/sweeps/failure_modes --sheets /tmp/sheets
    .venv/bin/python benchmarks/failure_labels.py extract bags/sweeps/failure_modes
    .venv/bin/python benchmarks/failure_labels.py agreement

A second set, picked by the classifier's mode (the rare modes a stratified set of 48 misses), checks each mode's
precision; its steps take ``--set failure_labels_by_mode`` and ``select --modes A,B --per-mode K``.

A validation set with two blind labelling passes and an adjudication (labels_a.csv, labels_b.csv, each made
without the other or the classifier; adjudicated.csv, made after, may read the bags) is checked by

    passes     the labellers' agreement and kappa; the classifier against the adjudicated labels overall, per suite
               and per mode (precision with a Wilson interval), against the targets: agreement >= 85%, kappa >=
               0.75, LIBERO-Goal >= 80%; a mode under 70% precision is unvalidated.

    .venv/bin/python benchmarks/failure_labels.py --set failure_validation select bags/sweeps/failure_validation \
        --n 64 --inits 45,46,47,48,49 --by-suite --degenerate-per-suite 1
    .venv/bin/python benchmarks/failure_labels.py --set failure_validation render bags/sweeps/failure_validation \
        --sheets /tmp/sheets

Each labels file is a CSV with the header ``episode,label,note`` (``note`` optional): one row per picked episode,
``label`` one of the classifier's failure modes or ``no_action_executed`` (label_values()), next to episodes.json.
    .venv/bin/python benchmarks/failure_labels.py --set failure_validation extract bags/sweeps/failure_validation
    .venv/bin/python benchmarks/failure_labels.py --set failure_validation passes
"""

from __future__ import annotations

import argparse
import json
import random
from collections import defaultdict
from pathlib import Path
from types import MappingProxyType

# lq_ros first: it pins OpenBLAS's kernels before numpy loads them (lq_ros/__init__.py); imported after numpy,
# the replays here would run other kernels than the sweep did and leave its trajectories in the last bits.
import lq_ros  # noqa: F401

# isort: split
import numpy as np

REPO = Path(__file__).resolve().parents[1]
#: The labelled set the steps work on (--set): tests/data/<name>/.
DATA = REPO / "tests/data/failure_labels"
#: The stratified set; a set picked by mode leaves its episodes out.
STRATIFIED_SET = "failure_labels"
STRATA = ("suite", "mode", "latency_s", "policy")


def _rows(sweep: Path) -> list[dict]:
    return [json.loads(p.read_text())["row"] for p in sorted((sweep / "results").glob("*.json"))]


def _stratum(row: dict) -> tuple:
    """The row's STRATA values; a policy run with arguments (``scripted`` with ``chunk_size=10``) is a policy of its
    own: ``scripted{"chunk_size": 10}``."""
    policy, args = row.get("policy"), row.get("policy_args")
    if args:
        policy = f"{policy}{json.dumps(args, sort_keys=True)}"
    return tuple(policy if k == "policy" else row.get(k) for k in STRATA)


def _round_robin(strata: dict[tuple, list[str]]) -> list[str]:
    """Every episode of ``strata``, one of each stratum (sorted) in turn, each stratum's from its end."""
    queues = {key: list(names) for key, names in strata.items()}
    keys = sorted(queues, key=str)
    order: list[str] = []
    while any(queues[k] for k in keys):
        order += [queues[k].pop() for k in keys if queues[k]]
    return order


def select(
    sweep: Path, n: int, seed: int, inits: set[int] | None = None, by_suite: bool = False, degenerate: int = -1
) -> None:
    """Round-robin over the strata (sorted), a seeded random failed episode of each in turn, until ``n``; only
    ``inits``' episodes when given (the sweep as it was when a set was picked). ``by_suite``: the suites take turns
    (as many of each as its failures allow), each round-robin over its own strata, so a suite with fewer strata
    (one policy) gets as many episodes as one with three policies. ``degenerate`` >= 0 (with ``by_suite``): at most
    that many of a suite's episodes from a degenerate protocol (async chunks no longer than the latency: no fresh
    action can run; the row's ``degenerate_protocol``, from the configuration), the others only once every suite's
    other failures are taken: a starved arm is the protocol's failure, not one of the policy's modes."""
    failed = [r for r in _rows(sweep) if r.get("status") == "failure" and (inits is None or r.get("init") in inits)]
    strata: dict[tuple, list[str]] = defaultdict(list)
    for row in failed:
        strata[_stratum(row)].append(row["episode"])
    rng = random.Random(seed)
    for names in strata.values():
        names.sort()
        rng.shuffle(names)
    if by_suite:  # STRATA[0] is the suite
        starved = {r["episode"] for r in failed if r.get("degenerate_protocol")} if degenerate >= 0 else set()
        first: dict[tuple, list[str]] = {}
        later: dict[tuple, list[str]] = {}
        for suite in {key[0] for key in strata}:
            queue = _round_robin({k: v for k, v in strata.items() if k[0] == suite})
            deferred = set([name for name in queue if name in starved][degenerate:]) if degenerate >= 0 else set()
            # (reversed: _round_robin takes each queue from its end)
            first[(suite,)] = [name for name in reversed(queue) if name not in deferred]
            later[(suite,)] = [name for name in reversed(queue) if name in deferred]
        order = _round_robin(first) + _round_robin(later)
    else:
        order = _round_robin(strata)
    picked = order[:n]
    DATA.mkdir(parents=True, exist_ok=True)
    out = {"sweep": sweep.name, "seed": seed, "strata": list(STRATA), "episodes": sorted(picked)}
    if by_suite:
        out["balanced_by"] = "suite"
    if by_suite and degenerate >= 0:
        out["degenerate_per_suite"] = degenerate
    (DATA / "episodes.json").write_text(json.dumps(out, indent=1) + "\n")
    print(f"{len(picked)} of {len(failed)} failed episodes in {len(strata)} strata -> {DATA / 'episodes.json'}")


def select_by_mode(sweep: Path, modes: list[str], per_mode: int, seed: int) -> None:
    """Up to ``per_mode`` seeded random failed episodes the classifier puts in each of ``modes`` (the rare ones a
    stratified set misses), none of the stratified set's: a check of each mode's precision (of the episodes the
    classifier calls X, how many a labeller calls X), not of how often modes occur."""
    taken = set(json.loads((REPO / "tests/data" / STRATIFIED_SET / "episodes.json").read_text())["episodes"])
    rows = [r for r in _rows(sweep) if r.get("status") == "failure" and r["episode"] not in taken]
    rng = random.Random(seed)
    picked: list[str] = []
    for mode in modes:
        names = sorted(r["episode"] for r in rows if r.get("failure_mode") == mode)
        rng.shuffle(names)
        picked += names[:per_mode]
        print(f"{mode}: {min(per_mode, len(names))} of {len(names)}")
    DATA.mkdir(parents=True, exist_ok=True)
    out = {"sweep": sweep.name, "seed": seed, "selected_by": "classifier mode", "modes": modes,
           "per_mode": per_mode, "episodes": sorted(picked)}  # fmt: skip
    (DATA / "episodes.json").write_text(json.dumps(out, indent=1) + "\n")
    print(f"{len(picked)} failed episodes -> {DATA / 'episodes.json'}")


def _picked() -> list[str]:
    return json.loads((DATA / "episodes.json").read_text())["episodes"]


#: How far (m) a replayed EE position may be from the bag's for a contact sheet: far below a pixel of it.
DRAWING_TOLERANCE_M = 1e-6


def render(sweep: Path, sheets: Path, frames: int = 20, columns: int = 4, size_px: int = 224) -> None:
    """Re-simulate each picked bag's commands (an env without cameras, as the bag was recorded: its EE position must
    be the bag's at every rendered tick, to within DRAWING_TOLERANCE_M) and render ``frames`` ticks (evenly spaced,
    the last included) from the front and wrist cameras into one contact sheet. The pictures come from a second env
    of the task with cameras, set to the replay's positions at each picked tick. The tolerance admits the bags
    recorded on LIBERO-Object scenes before every env ran the forward pass of an env with a renderer
    (lq_ros/sim/renderer_passes.py): they replay apart in the last bits, which no picture shows; a sheet that is
    not exact says so."""
    import mujoco
    from PIL import Image, ImageDraw

    from lq_ros.report.replay import check_replayable, read_recording
    from lq_ros.sim.libero_env import LiberoEnv

    sheets.mkdir(parents=True, exist_ok=True)
    cameras = ("agentview", "robot0_eye_in_hand")
    by_task: dict[tuple[str, int], list] = defaultdict(list)
    for name in _picked():
        if not (sheets / f"{name}.png").exists():
            rec = read_recording(sweep / "bags" / name)
            cfg = check_replayable(rec)
            by_task[(cfg.suite, cfg.task)].append((name, rec, cfg))
    for (suite, task), episodes in sorted(by_task.items()):
        # First every replay of the task, in an env without cameras (created first: the states to draw)...
        env = LiberoEnv(suite, task)
        states = {}
        for name, rec, cfg in episodes:
            env.reset(cfg.init, cfg.seed)
            picks = set(np.linspace(0, rec.ticks, frames).round().astype(int).tolist())
            states[name] = []
            for tick in range(rec.ticks + 1):
                if tick in picks:
                    recorded = rec.poses.get(tick)
                    gap = 0.0 if recorded is None else float(np.linalg.norm(env._tick_state().eef_pos - recorded[0]))
                    if gap > DRAWING_TOLERANCE_M:
                        raise SystemExit(f"{name}: the replay left the recorded trajectory at tick {tick}")
                    if gap:
                        print(f"{name}: tick {tick} replayed {gap:.1e} m from the bag (drawn all the same)")
                    states[name].append((tick, env._data.qpos.copy(), env._data.qvel.copy()))
                if tick < rec.ticks:
                    env.step(rec.commands[tick].action)
        goal = " and ".join("(" + " ".join(g) + ")" for g in env.task.goal)
        instruction = env.task.instruction
        env.close()
        # ... then the pictures, from an env with cameras set to those states.
        painter = LiberoEnv(suite, task, camera_names=cameras, camera_size=size_px)
        painter.reset(0, 0)
        for name, rec, _ in episodes:
            tiles = []
            for tick, qpos, qvel in states[name]:
                painter._data.qpos[:] = qpos
                painter._data.qvel[:] = qvel
                mujoco.mj_forward(painter._model, painter._data)
                images = [painter._sim.render(camera_name=c, width=size_px, height=size_px)[::-1] for c in cameras]
                tiles.append((tick, np.hstack(images)))
            out = sheets / f"{name}.png"
            h, w = tiles[0][1].shape[:2]
            rows = -(-len(tiles) // columns)
            sheet = Image.new("RGB", (columns * w, rows * (h + 16)), "white")
            draw = ImageDraw.Draw(sheet)
            for i, (tick, image) in enumerate(tiles):
                x, y = (i % columns) * w, (i // columns) * (h + 16)
                sheet.paste(Image.fromarray(np.ascontiguousarray(image)), (x, y + 16))
                draw.text((x + 3, y + 2), f"tick {tick} of {rec.ticks}  (left: front, right: wrist)", fill="black")
            sheet.save(out)
            index_csv = sheets / "index.csv"  # what the labeller is told: the task, nothing scored
            with index_csv.open("a") as index:
                if index_csv.stat().st_size == 0:
                    index.write("episode,instruction,goal\n")
                index.write(f'{name},"{instruction}","{goal}"\n')
            print(f"{name}: {out}")
        painter.close()


def extract(sweep: Path) -> None:
    from lq_ros.recording.bag_compare import bag_messages
    from lq_ros.recording.episode_bag import EpisodeBagWriter, read_run_metadata
    from lq_ros.wire import messages as m

    # Commands too: whether any fresh action ran, and whether the gripper was closed beside the target.
    topics = [m.EPISODE_EVENTS, m.EE_POSE, m.COMMAND, m.TASK_STATE, m.TASK_OBJECT_POSES]
    for name in _picked():
        source = sweep / "bags" / name
        target = DATA / "bags" / name
        if target.exists():
            continue
        messages = bag_messages(source)
        writer = EpisodeBagWriter(target, topics)
        writer.set_run_metadata(read_run_metadata(source))
        for topic in topics:
            for t_ns, raw in messages.get(topic.name, []):
                writer.write(topic, t_ns, raw)
        writer.close()
    size = sum(p.stat().st_size for p in (DATA / "bags").rglob("*") if p.is_file())
    print(f"{len(_picked())} bags, {size / 1e6:.1f} MB in {DATA / 'bags'}")


def agreement() -> dict:
    """Labels against the classifier: confusion matrix (rows: label, columns: classifier), agreement, kappa."""
    import csv

    from lq_ros.scoring.bag_scorer import score_bag
    from lq_ros.scoring.failure_aggregate import label_agreement

    with (DATA / "labels.csv").open() as f:
        labels = {r["episode"]: r["label"] for r in csv.DictReader(f)}
    predicted = {name: score_bag(DATA / "bags" / name)["failure_mode"] for name in labels}
    out = label_agreement(labels, predicted)
    modes, matrix = out["modes"], out["matrix"]
    width = max(len(m) for m in modes)
    print(f"{out['n']} labelled failed episodes; rows: label, columns: classifier (numbered as the rows)")
    print(" " * width + "      " + " ".join(f"{i:>3}" for i in range(len(modes))))
    for i, mode in enumerate(modes):
        print(f"{mode:>{width}} ({i}) " + " ".join(f"{v:>3}" for v in matrix[i]))
    print(f"agreement {out['agreement']:.1%} ({out['agreed']} of {out['n']}), Cohen's kappa {out['kappa']:.2f}")
    for j, mode in enumerate(modes):  # precision: of the episodes the classifier calls a mode, the labeller's share
        called = int(matrix[:, j].sum())
        if called:
            print(f"  classifier {mode}: labeller agrees on {matrix[j, j]} of {called}")
    for name in sorted(labels):
        if labels[name] != predicted[name]:
            print(f"  {name}: label {labels[name]}, classifier {predicted[name]}")
    return out


#: What a validation set must reach against its adjudicated labels (agreement, kappa, LIBERO-Goal's agreement), and
#: the precision under which a mode stays unvalidated. Frozen before the set picked from
#: config/sweeps/failure_validation.yaml was labelled: a change needs a new set (tests/benchmarks pins the values).
TARGETS = MappingProxyType({"agreement": 0.85, "kappa": 0.75, "libero_goal": 0.80, "precision": 0.70})


def label_values() -> tuple[str, ...]:
    """What a label may be: the classifier's failure modes and ``no_action_executed`` (not success, not error)."""
    from lq_ros.scoring.failure_modes import MODES

    return tuple(m for m in MODES if m not in ("none", "error"))


def _labels(name: str) -> dict[str, str]:
    """``episode -> label`` of a labels file (columns ``episode,label``, more such as ``note`` ignored); one line
    naming the file and the problem for a missing file or column, an episode labelled twice or an unknown label."""
    import csv

    path = DATA / name
    if not path.exists():
        raise SystemExit(f"{path}: missing (passes needs labels_a.csv, labels_b.csv and adjudicated.csv)")
    valid = label_values()
    out: dict[str, str] = {}
    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        if not {"episode", "label"} <= set(reader.fieldnames or ()):
            raise SystemExit(f"{path}: needs a header with the columns episode and label (and optionally note)")
        for row in reader:
            episode, label = (row["episode"] or "").strip(), (row["label"] or "").strip()
            if episode in out:
                raise SystemExit(f"{path}: {episode} is labelled twice")
            if label not in valid:
                raise SystemExit(f"{path}: {episode}: unknown label {label!r}; valid: {', '.join(valid)}")
            out[episode] = label
    return out


def passes() -> dict:
    """Two blind passes and their adjudication: the labellers' kappa, then the classifier against the adjudicated
    labels, overall, per suite and per mode, each with its count and a Wilson interval, against TARGETS."""
    from lq_ros.scoring.bag_scorer import score_bag
    from lq_ros.scoring.failure_aggregate import label_agreement
    from lq_ros.scoring.intervals import wilson_interval

    print(f"targets (frozen before labelling): {dict(TARGETS)}")
    files = ("labels_a.csv", "labels_b.csv", "adjudicated.csv")
    first, second, truth = (_labels(name) for name in files)
    picked = set(_picked())
    for name, labels in zip(files, (first, second, truth), strict=True):
        if set(labels) != picked:
            missing, extra = sorted(picked - set(labels)), sorted(set(labels) - picked)
            raise SystemExit(
                f"{DATA / name}: must label each of the {len(picked)} picked episodes (episodes.json) once: "
                f"{len(missing)} missing (first: {missing[:1]}), {len(extra)} not picked (first: {extra[:1]})"
            )
    between = label_agreement(first, second)
    print(f"labellers: {between['agreed']} of {between['n']} agree, Cohen's kappa {between['kappa']:.2f}")
    rows = {name: score_bag(DATA / "bags" / name) for name in truth}
    predicted = {name: row["failure_mode"] for name, row in rows.items()}
    out = label_agreement(truth, predicted)

    def share(agreed: int, n: int) -> str:
        low, high = wilson_interval(agreed, n)
        return f"{agreed} of {n} ({agreed / n:.0%}, 95% CI {low:.0%}-{high:.0%})" if n else "none"

    print(f"classifier vs adjudicated: {share(out['agreed'], out['n'])}, Cohen's kappa {out['kappa']:.2f}")
    for name, labels in zip(files[:2], (first, second), strict=True):
        blind = label_agreement(labels, predicted)
        print(f"  classifier vs {name} (blind, from sheets): {share(blind['agreed'], blind['n'])}, "
              f"Cohen's kappa {blind['kappa']:.2f}")  # fmt: skip
    both = [n for n in truth if first[n] == second[n]]
    by_classifier, by_adjudication = (sum(given[n] == first[n] for n in both) for given in (predicted, truth))
    print(f"  where the blind passes agree ({len(both)}): the classifier agrees with them on {by_classifier}, "
          f"the adjudication on {by_adjudication}")  # fmt: skip
    met = {"agreement": out["agreement"] >= TARGETS["agreement"], "kappa": out["kappa"] >= TARGETS["kappa"]}
    for suite in sorted({str(row.get("suite")) for row in rows.values()}):
        names = [n for n, row in rows.items() if str(row.get("suite")) == suite]
        agreed = sum(truth[n] == predicted[n] for n in names)
        print(f"  {suite}: {share(agreed, len(names))}")
        if suite == "libero_goal":
            met["libero_goal"] = agreed >= TARGETS["libero_goal"] * len(names)
    unvalidated = []
    for mode in sorted(set(predicted.values())):
        names = [n for n in truth if predicted[n] == mode]
        agreed = sum(truth[n] == mode for n in names)
        print(f"  classifier {mode}: the adjudicated label agrees on {share(agreed, len(names))}")
        if agreed < TARGETS["precision"] * len(names):
            unvalidated.append(mode)
    print(f"targets met: {met}; unvalidated modes (precision under {TARGETS['precision']:.0%}): {unvalidated}")
    return {"between": between, "classifier": out, "met": met, "unvalidated": unvalidated}


def main() -> None:
    global DATA
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--set", default=STRATIFIED_SET, help="the labelled set: tests/data/<set>/")
    sub = parser.add_subparsers(dest="step", required=True)
    p = sub.add_parser("select")
    p.add_argument("sweep", type=Path)
    p.add_argument("--n", type=int, default=48)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--modes", default="", help="comma-separated: pick by the classifier's mode instead of strata")
    p.add_argument("--per-mode", type=int, default=6)
    p.add_argument("--inits", default="", help="comma-separated init states to pick from (default: all)")
    p.add_argument("--by-suite", action="store_true", help="the suites take turns, each over its own strata")
    p.add_argument(
        "--degenerate-per-suite", type=int, default=-1,
        help="with --by-suite: at most K of a suite's picks from a degenerate protocol before all suites' other "
        "failures are taken (default: no limit)",
    )  # fmt: skip
    p = sub.add_parser("render")
    p.add_argument("sweep", type=Path)
    p.add_argument("--sheets", type=Path, required=True)
    p = sub.add_parser("extract")
    p.add_argument("sweep", type=Path)
    sub.add_parser("agreement")
    sub.add_parser("passes", help="two blind passes and their adjudication against the classifier")
    args = parser.parse_args()
    DATA = REPO / "tests/data" / args.set
    if args.step == "select" and args.modes:
        select_by_mode(args.sweep, args.modes.split(","), args.per_mode, args.seed)
    elif args.step == "select":
        inits = {int(i) for i in args.inits.split(",")} if args.inits else None
        select(args.sweep, args.n, args.seed, inits, args.by_suite, args.degenerate_per_suite)
    elif args.step == "render":
        render(args.sweep, args.sheets)
    elif args.step == "extract":
        extract(args.sweep)
    elif args.step == "passes":
        passes()
    else:
        agreement()


if __name__ == "__main__":
    main()
