"""Where a user's first `lq run` spends its seconds: one episode from a cold process, in process and through ROS.

Each phase is measured as a fresh process that stops after it, so the differences are what each phase adds
(median of ``--repeats`` runs, alternated so a change of load hits all alike):

    interpreter   python -c pass (with the ROS wheels' bootstrap, which re-executes Python once)
    imports       + import lq_ros.cli
    env           + LIBERO's imports and the task env (MuJoCo model compiled or loaded, MjSim built)
    first reset   + the episode's reset to its init state and LIBERO's 10 wait steps
    episode       `lq run --transport inprocess`: + the ticks, the bag and its scoring (the whole command)
    ROS           `lq run --transport ros`: the same episode through the four node processes (the whole command)

and, of the ROS command, its end: from the recorder's score file being written to the command's exit (the
nodes' shutdown transitions and the processes' exit).

Every phase runs with the compiled-model cache (lq_ros.sim.model_cache) in a fresh folder that one unmeasured
run filled first (warm: the task has run on this machine before); `episode` and `ROS` are also measured with
an empty cache folder of their own (cold: the scene compiled and written to the cache, as on a machine's first
run of the task).

Then the exit of a process that built and reset the task's env: the interpreter's normal exit against the node
programs' (lq_ros.transport.processes.exit_uncollected), from the process's last statement to its end. Then the
scene's compile alone: with its image textures (what an env with cameras does), without them (1x1 flat
textures: an env that renders nothing), and its compiled model loaded from the cache's MJB file, alternated.

Default episode: the scripted expert, async, Δt_sim 0.2 s, LIBERO-Spatial task 0, init state 0 (164 ticks).
Targets: in process <= 4 s; through ROS <= in process + 1.5 s (2 idle cores).

    .venv/bin/python benchmarks/bench_first_episode.py [--repeats 3]
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

RUN_ARGS = ["--suite", "libero_spatial", "--task", "0", "--init", "0", "--mode", "async", "--latency", "0.2",
            "--policy", "scripted"]  # fmt: skip
ENV = "from lq_ros.sim.libero_env import LiberoEnv; env = LiberoEnv('libero_spatial', 0)"
PHASES = {
    "interpreter": [sys.executable, "-c", "pass"],
    "imports": [sys.executable, "-c", "import lq_ros.cli"],
    "env": [sys.executable, "-c", ENV],
    "first reset": [sys.executable, "-c", f"{ENV}; env.reset(0, 7)"],
    "episode": [sys.executable, "-m", "lq_ros.cli", "run", *RUN_ARGS, "--transport", "inprocess"],
    "ROS": [sys.executable, "-m", "lq_ros.cli", "run", *RUN_ARGS, "--transport", "ros"],
}


def run_checked(argv: list[str], env: dict[str, str]) -> subprocess.CompletedProcess:
    """Run ``argv``; a failed command stops the benchmark with the end of its stderr."""
    proc = subprocess.run(argv, capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(argv)} failed ({proc.returncode}): {proc.stderr.strip()[-500:]}")
    return proc


def wall_s(argv: list[str], out: Path, cache: str) -> tuple[float, float | None]:
    """Wall seconds of the command, and of its end: from the episode's score file being written (the recorder
    writes one through ROS) to the command's exit; None without a score file."""
    start = time.perf_counter()
    argv = [*argv, "--out", str(out), "--overwrite"] if "run" in argv else argv
    env = {**os.environ, "LQ_MODEL_CACHE": cache,
           "ROS_AUTOMATIC_DISCOVERY_RANGE": os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")}  # fmt: skip
    run_checked(argv, env)
    elapsed, ended = time.perf_counter() - start, time.time()
    scores = list(out.glob("*/score.json"))
    return elapsed, (ended - scores[0].stat().st_mtime if scores else None)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    print(f"load average before: {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    out = Path(tempfile.mkdtemp(prefix="lq_bench_first_"))
    try:
        measure(args.repeats, out)
    finally:
        shutil.rmtree(out, ignore_errors=True)  # its bags and compiled models (about 80 MB)


def measure(repeats: int, out: Path) -> None:
    """Run and print every figure; ``out`` holds the commands' bags and the model cache."""
    cache = str(out / "models")
    wall_s(PHASES["env"], out, cache)  # fills the cache (unmeasured)
    runs = {**{name: (argv, cache) for name, argv in PHASES.items()},
            **{f"{name} (cold)": (PHASES[name], None) for name in ("episode", "ROS")}}  # fmt: skip
    times: dict[str, list[float]] = {name: [] for name in runs}
    ends: list[float] = []  # the ROS commands' ends (score file written -> exit), warm and cold
    for _ in range(repeats):
        for name, (argv, warm_cache) in runs.items():  # (a cold run: an empty cache folder of its own)
            run_cache = warm_cache or tempfile.mkdtemp(prefix="models_", dir=out)
            elapsed, end = wall_s(argv, out / name.replace(" ", "_").strip("()"), run_cache)
            if warm_cache is None:
                shutil.rmtree(run_cache)
            times[name].append(elapsed)
            if name.startswith("ROS") and end is not None:
                ends.append(end)
    median = {name: statistics.median(t) for name, t in times.items()}
    previous = 0.0
    print("warm (the task's compiled model in the cache):")
    for name in ("interpreter", "imports", "env", "first reset", "episode"):
        print(f"  {name:12s} {median[name]:6.2f} s cumulative  (+{median[name] - previous:5.2f} s)")
        previous = median[name]
    print(f"  {'ROS':12s} {median['ROS']:6.2f} s  (+{median['ROS'] - median['episode']:5.2f} s over in process)")
    print(
        f"  of which the end (the recorder's score file written -> the command exited): median "
        f"{statistics.median(ends):.2f} s, longest {max(ends):.2f} s over {len(ends)} fresh stacks (warm and cold)"
    )
    for label, suffix in (("warm", ""), ("cold", " (cold)")):
        episode, ros = median[f"episode{suffix}"], median[f"ROS{suffix}"]
        print(f"targets, {label}: in process {episode:.2f} s <= 4 s; ROS {ros:.2f} s <= in process + 1.5 s = "
              f"{episode + 1.5:.2f} s (+{ros - episode:.2f} s)  (medians of {repeats})")  # fmt: skip
    normal, uncollected = exit_times(repeats, cache)
    print(f"exit of a process with the task's env (median of {repeats}, from its last statement to its end): "
          f"the interpreter's normal exit {normal:.2f} s, lq_ros.transport.processes.exit_uncollected "
          f"{uncollected:.2f} s (the node programs' exit)")  # fmt: skip
    textured, light, cached = compile_times(repeats, Path(cache))
    size_mb = sum(f.stat().st_size for f in Path(cache).glob("*.mjb")) / 1e6
    print(f"scene (median of {repeats}): compiled with image textures {textured:.2f} s, without "
          f"{light:.2f} s (the textures' PNG decoding: {textured - light:.2f} s); loaded from the cache "
          f"{cached:.2f} s (its file: {size_mb:.1f} MB)")  # fmt: skip
    print(f"load average after: {os.getloadavg()[0]:.2f}")


def exit_times(repeats: int, cache: str) -> tuple[float, float]:
    """Median wall seconds from a process's last statement to its end, with the task's env built and reset: the
    interpreter's normal exit against exit_uncollected (alternated)."""
    env = {**os.environ, "LQ_MODEL_CACHE": cache}
    script = f"import sys, time; {ENV}; env.reset(0, 7); env.close(); print(time.time(), flush=True); "
    exits = {"normal": "sys.exit(0)",
             "uncollected": "from lq_ros.transport.processes import exit_uncollected; exit_uncollected(0)"}  # fmt: skip
    times: dict[str, list[float]] = {kind: [] for kind in exits}
    for _ in range(repeats):
        for kind, leave in exits.items():
            proc = run_checked([sys.executable, "-c", script + leave], env)
            ended = time.time()
            times[kind].append(ended - float(proc.stdout.split()[-1]))
    return statistics.median(times["normal"]), statistics.median(times["uncollected"])


def compile_times(repeats: int, cache: Path) -> tuple[float, float, float]:
    """Median wall seconds of LIBERO-Spatial task 0's scene compiled with and without its image textures, and of
    its texture-less model loaded from the cache's MJB file."""
    import mujoco

    from lq_ros.sim import libero_env, model_cache

    os.environ["LQ_MODEL_CACHE"] = "off"
    env = libero_env.LiberoEnv("libero_spatial", 0)  # (camera-less: its XML is the key of the kept model)
    ((xml, _),) = libero_env._compiled_models
    env.close()
    light_xml = libero_env.without_image_textures(xml)
    mjb = cache / f"{model_cache.model_key(light_xml, mujoco.__version__)}{model_cache.SUFFIX}"
    if not mjb.is_file():
        raise SystemExit(f"{mjb}: not in the cache the episodes filled")
    times: dict[str, list[float]] = {"textures": [], "light": [], "cached": []}
    for _ in range(repeats):
        for kind in times:
            start = time.perf_counter()
            if kind == "cached":
                mujoco.MjModel.from_binary_path(str(mjb))
            else:
                mujoco.MjModel.from_xml_string(xml if kind == "textures" else light_xml)
            times[kind].append(time.perf_counter() - start)
    return tuple(statistics.median(t) for t in times.values())


if __name__ == "__main__":
    main()
