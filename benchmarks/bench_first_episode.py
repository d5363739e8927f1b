"""Where a user's first `lq run` spends its seconds: one episode from a cold process, in process and through ROS.

Each phase is measured as a fresh process that stops after it, so the differences are what each phase adds
(median of ``--repeats`` runs, alternated so a change of load hits all alike):

    interpreter   python -c pass (with the ROS wheels' bootstrap, which re-executes Python once)
    imports       + import lq_ros.cli
    env           + LIBERO's imports and the task env (MuJoCo model compiled or loaded, MjSim built)
    first reset   + the episode's reset to its init state and LIBERO's 10 wait steps
    episode       `lq run --transport inprocess`: + the ticks, the bag and its scoring (the whole command)
    ROS           `lq run --transport ros`: the same episode through the four node processes (the whole command)

and, of the ROS command, its end (from the recorder's score file being written to the command's exit: the
nodes' shutdown transitions and the processes' exit) and the CPU of each of its processes (the launcher, the
five node programs, the fork server they are started from).

Every phase runs with the compiled-model cache (lq_ros.sim.model_cache) in a fresh folder that one unmeasured
run filled first (warm: the task has run on this machine before); `episode` and `ROS` are also measured with
an empty cache folder of their own (cold: the scene compiled and written to the cache, as on a machine's first
run of the task).

Then the exit of a process that built and reset the task's env: the interpreter's normal exit against the node
programs' (lq_ros.transport.processes.exit_uncollected), from the process's last statement to its end. Then the
scene's compile alone: with its image textures (what an env with cameras does), without them (1x1 flat
textures: an env that renders nothing), and its compiled model loaded from the cache's MJB file, alternated.
Then two parts of a start-up, each against what it replaced: LIBERO's import with its namespace check on whole
metadata files and on their headers (lq_ros.sim.libero_import), and how long after a node's service appears
rclpy's ``Client.wait_for_service`` and the lifecycle manager's wait notice it.

Every figure is printed twice: wall seconds, and CPU seconds (user + system of the command's whole process tree:
the node processes and what they start included). On a machine other jobs load, the wall figures grow with the
load and the CPU figures far less, so compare CPU there; the targets are wall seconds on idle cores.

``--baseline REV`` runs every phase also with the package of git revision REV of the repository the command runs
in (extracted into the benchmark's temporary folder and put first on PYTHONPATH; the same Python, packages and
model cache), the two alternated in every repetition, and prints the differences: an A/B of a change in one run,
both sides under the same load. "This tree" is the lq_ros that Python imports (PYTHONPATH's, else the installed).
The commands run in the temporary folder, and each side is checked to import lq_ros and its node programs from
one tree: started in a checkout, `python -m` would take the checkout's lq_ros for both sides.

Default episode: the scripted expert, async, Δt_sim 0.2 s, LIBERO-Spatial task 0, init state 0 (164 ticks).
Targets: in process <= 4 s; through ROS <= in process + 1.5 s (2 idle cores).

    .venv/bin/python benchmarks/bench_first_episode.py [--repeats 3] [--baseline REV]
"""

from __future__ import annotations

import argparse
import contextlib
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import lq_ros  # noqa: F401 - before numpy (compile_times): it pins OpenBLAS's kernels

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
#: Target seconds (wall, 2 idle cores): the first episode in process; what ROS may add to it.
TARGET_INPROCESS_S, TARGET_ROS_EXTRA_S = 4.0, 1.5
#: Wall seconds between two looks at the CPU of a command's processes.
SAMPLE_S = 0.05


@dataclass
class Samples:
    """One phase's runs: wall and CPU seconds of each."""

    wall: list[float] = field(default_factory=list)
    cpu: list[float] = field(default_factory=list)

    def median(self) -> tuple[float, float]:
        return statistics.median(self.wall), statistics.median(self.cpu)


def run_checked(argv: list[str], env: dict[str, str]) -> subprocess.CompletedProcess:
    """Run ``argv``; a failed command stops the benchmark with the end of its stderr."""
    proc = subprocess.run(argv, capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(argv)} failed ({proc.returncode}): {proc.stderr.strip()[-500:]}")
    return proc


def children_cpu_s() -> float:
    """User + system seconds of this process's waited-for children (and theirs, once those waited for them)."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def process_cpu_s(pid: int) -> tuple[str, float] | None:
    """(name, user + system seconds) of a live process: its Python module (``-m``) or program; None once gone."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        argv = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return None
    fields = stat.rsplit(")", 1)[1].split()  # (the name in parentheses may hold spaces)
    names = [a.decode() for a in argv.replace(b" ", b"\0").split(b"\0") if a]  # (a forked node's title: spaces)
    name = names[names.index("-m") + 1] if "-m" in names[:-1] else Path(names[0]).name if names else ""
    return name.removeprefix("lq_ros_nodes."), (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def descendants(pid: int) -> list[int]:
    """``pid`` and every live process below it (the nodes: the launcher's children, or its fork server's)."""
    out, todo = [], [pid]
    while todo:
        out.append(todo.pop())
        with contextlib.suppress(OSError):  # (gone meanwhile)
            todo += map(int, Path(f"/proc/{out[-1]}/task/{out[-1]}/children").read_text().split())
    return out


def run_sampled(argv: list[str], env: dict[str, str], cwd: Path) -> dict[str, float]:
    """Run ``argv`` (a failure stops the benchmark); returns the CPU seconds of it and of each process below it
    (the node programs and their fork server), by name, as last seen alive: sampled every SAMPLE_S, each misses at
    most its last SAMPLE_S (its exit)."""
    last: dict[int, tuple[str, float]] = {}
    with tempfile.TemporaryFile() as err:
        proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=err, env=env, cwd=cwd)
        while proc.poll() is None:
            for pid in descendants(proc.pid):
                if (sample := process_cpu_s(pid)) is not None:  # (an exited child not yet reaped has no name)
                    last[pid] = (last[pid][0] if pid in last and not sample[0] else sample[0], sample[1])
            time.sleep(SAMPLE_S)
        if proc.returncode != 0:
            err.seek(0)
            tail = err.read().decode(errors="replace").strip()[-500:]
            raise SystemExit(f"{' '.join(argv)} failed ({proc.returncode}): {tail}")
    return {name: cpu for name, cpu in last.values()}


def timed(
    argv: list[str], out: Path, cache: str, pythonpath: str | None
) -> tuple[float, float, float | None, dict[str, float]]:
    """Wall and CPU seconds of the command, of its end (from the episode's score file being written, which the
    recorder does through ROS, to the command's exit; None without a score file), and the CPU seconds of its
    processes by name (run_sampled). ``out`` is emptied first (unmeasured), so `lq run` starts without an earlier
    bag to replace, as a first run does."""
    shutil.rmtree(out, ignore_errors=True)
    argv = [*argv, "--out", str(out)] if "run" in argv else argv
    env = {**os.environ, "LQ_MODEL_CACHE": cache,
           "ROS_AUTOMATIC_DISCOVERY_RANGE": os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")}  # fmt: skip
    env.update(variant_path(pythonpath))
    cpu0, start = children_cpu_s(), time.perf_counter()
    processes = run_sampled(argv, env, out.parent)
    elapsed, ended, cpu = time.perf_counter() - start, time.time(), children_cpu_s() - cpu0
    scores = list(out.glob("*/score.json"))
    return elapsed, cpu, (ended - scores[0].stat().st_mtime if scores else None), processes


def variant_path(pythonpath: str | None) -> dict[str, str]:
    """The PYTHONPATH of a side: its tree first (None: the installed package, nothing to add)."""
    if not pythonpath:
        return {}
    return {"PYTHONPATH": os.pathsep.join(filter(None, (pythonpath, os.environ.get("PYTHONPATH"))))}


def check_variant(label: str, pythonpath: str | None, out: Path) -> None:
    """Stop unless the commands of ``label`` import lq_ros and the node programs both from its tree (PYTHONPATH's
    entry, else the installed package). The commands run in ``out``: `python -m` puts its working directory first
    on sys.path, so from a checkout's root lq_ros would come from the checkout, whatever PYTHONPATH says."""
    env = dict(os.environ)
    env.update(variant_path(pythonpath))
    code = "import lq_ros, lq_ros_nodes; print(lq_ros.__path__[0]); print(lq_ros_nodes.__path__[0])"
    found = subprocess.run([sys.executable, "-c", code], env=env, cwd=out, capture_output=True, text=True,
                           check=True).stdout.split()  # fmt: skip
    trees = {str(Path(path).resolve().parent) for path in found}
    if len(trees) != 1 or (pythonpath and trees != {str(Path(pythonpath).resolve())}):
        raise SystemExit(f"{label or 'this tree'}: lq_ros and its node programs come from {found}, not one tree")


def extract_revision(rev: str, into: Path) -> Path:
    """The source tree of git revision ``rev`` in ``into``, importable as lq_ros and lq_ros_nodes (the node
    programs' package) from PYTHONPATH; its bytecode is compiled by the unmeasured first run."""
    archive = into.with_suffix(".tar")
    with open(archive, "wb") as f:
        subprocess.run(["git", "archive", "--format=tar", rev], stdout=f, check=True)
    with tarfile.open(archive) as tar:
        tar.extractall(into, filter="data")
    archive.unlink()
    (into / "lq_ros_nodes").symlink_to(into / "nodes", target_is_directory=True)
    return into


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--baseline", metavar="REV", help="also run every phase with git revision REV, alternated")
    args = parser.parse_args()
    print(f"load average before: {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    out = Path(tempfile.mkdtemp(prefix="lq_bench_first_"))
    try:
        variants = {"": None}
        if args.baseline:
            rev = subprocess.run(["git", "rev-parse", "--short", args.baseline], text=True, capture_output=True,
                                 check=True).stdout.strip()  # fmt: skip
            variants[f"baseline {rev}"] = str(extract_revision(args.baseline, out / "baseline"))
        measure(args.repeats, out, variants)
    finally:
        shutil.rmtree(out, ignore_errors=True)  # its bags and compiled models (about 80 MB)


def measure(repeats: int, out: Path, variants: dict[str, str | None]) -> None:
    """Run and print every figure; ``out`` holds the commands' bags and the model cache. ``variants``: label ->
    PYTHONPATH entry of the package to run ("" -> None: the installed one)."""
    cache = str(out / "models")
    for label, pythonpath in variants.items():
        check_variant(label, pythonpath, out)
    for pythonpath in variants.values():  # fills the cache and compiles a baseline's bytecode (unmeasured)
        timed(PHASES["episode"], out / "warm-up", cache, pythonpath)
    runs = {**{name: (argv, cache) for name, argv in PHASES.items()},
            **{f"{name} (cold)": (PHASES[name], None) for name in ("episode", "ROS")}}  # fmt: skip
    samples = {(label, name): Samples() for label in variants for name in runs}
    ends: dict[str, list[float]] = {label: [] for label in variants}  # the ROS commands' ends, warm and cold
    per_process: dict[str, dict[str, list[float]]] = {label: {} for label in variants}  # warm ROS runs
    for _ in range(repeats):
        for name, (argv, warm_cache) in runs.items():
            for label, pythonpath in variants.items():  # alternated: a change of load hits both alike
                run_cache = warm_cache or tempfile.mkdtemp(prefix="models_", dir=out)  # cold: an empty cache
                wall, cpu, end, processes = timed(argv, out / "bags", run_cache, pythonpath)
                if warm_cache is None:
                    shutil.rmtree(run_cache)
                samples[label, name].wall.append(wall)
                samples[label, name].cpu.append(cpu)
                if name.startswith("ROS") and end is not None:
                    ends[label].append(end)
                if name == "ROS":
                    for process, seconds in processes.items():
                        per_process[label].setdefault(process, []).append(seconds)
    for label in variants:
        report(label, {name: samples[label, name].median() for name in runs}, ends[label], repeats)
        medians = ", ".join(f"{p} {statistics.median(t):.2f} s" for p, t in per_process[label].items())
        print(f"  CPU of the warm ROS command's processes (medians; each sampled every {SAMPLE_S:g} s while alive, "
              f"so without its last moments): {medians}")  # fmt: skip
    if len(variants) == 2:
        (new, base) = variants
        print(f"this tree against {base} (medians of {repeats}; negative: this tree is faster):")
        for name in runs:
            (wall, cpu), (wall0, cpu0) = samples[new, name].median(), samples[base, name].median()
            print(f"  {name:18s} wall {wall - wall0:+6.2f} s ({wall:5.2f} vs {wall0:5.2f}), "
                  f"CPU {cpu - cpu0:+6.2f} s ({cpu:5.2f} vs {cpu0:5.2f})")  # fmt: skip
    if "" in variants:
        print_exit_and_compile(repeats, cache)
        whole, headers = libero_import_cpu(5 * repeats)
        print(f"LIBERO's import (a process's CPU, median of {5 * repeats}, alternated): its namespace check on every "
              f"distribution's whole metadata {whole:.3f} s, on their headers (lq_ros.sim.libero_import) "
              f"{headers:.3f} s")  # fmt: skip
        rclpy_lag, manager_lag = service_lags(out)
        print(f"a node's service noticed after it appeared (median of {SERVICE_APPEARANCES}, each at a random moment): "
              f"by rclpy's Client.wait_for_service {rclpy_lag * 1e3:.0f} ms, by the lifecycle manager's "
              f"wait_for_service {manager_lag * 1e3:.0f} ms")  # fmt: skip
    print(f"load average after: {os.getloadavg()[0]:.2f}")


def report(label: str, median: dict[str, tuple[float, float]], ends: list[float], repeats: int) -> None:
    """The phases' medians (wall and CPU, cumulative and what each adds), the ROS end and the targets."""
    print(f"{label or 'this tree'}, warm (the task's compiled model in the cache), medians of {repeats}:")
    print(f"  {'phase':12s} {'wall':>8s} {'(adds)':>9s}   {'CPU':>7s} {'(adds)':>9s}")
    previous = (0.0, 0.0)
    for name in ("interpreter", "imports", "env", "first reset", "episode"):
        wall, cpu = median[name]
        print(f"  {name:12s} {wall:6.2f} s (+{wall - previous[0]:5.2f}) {cpu:7.2f} s (+{cpu - previous[1]:5.2f})")
        previous = (wall, cpu)
    (wall, cpu), (wall_in, cpu_in) = median["ROS"], median["episode"]
    print(f"  {'ROS':12s} {wall:6.2f} s (+{wall - wall_in:5.2f}) {cpu:7.2f} s (+{cpu - cpu_in:5.2f})  over in process")
    if ends:
        print(f"  of which the end (the recorder's score file written -> the command exited): median "
              f"{statistics.median(ends):.2f} s, longest {max(ends):.2f} s over {len(ends)} fresh stacks "
              "(warm and cold)")  # fmt: skip
    for kind, suffix in (("warm", ""), ("cold", " (cold)")):
        (wall_in, cpu_in), (wall_ros, cpu_ros) = median[f"episode{suffix}"], median[f"ROS{suffix}"]
        verdict_in = "met" if wall_in <= TARGET_INPROCESS_S else "NOT met"
        verdict_ros = "met" if wall_ros - wall_in <= TARGET_ROS_EXTRA_S else "NOT met"
        print(f"  targets, {kind}: in process {wall_in:.2f} s wall <= {TARGET_INPROCESS_S:g} s: {verdict_in} "
              f"(CPU {cpu_in:.2f} s); ROS {wall_ros:.2f} s wall <= in process + {TARGET_ROS_EXTRA_S:g} s = "
              f"{wall_in + TARGET_ROS_EXTRA_S:.2f} s: {verdict_ros} (+{wall_ros - wall_in:.2f} s; CPU {cpu_ros:.2f} s, "
              f"+{cpu_ros - cpu_in:.2f} s over in process)")  # fmt: skip
    print("  (the targets are wall seconds on idle cores: under load, read the CPU figures)")


def print_exit_and_compile(repeats: int, cache: str) -> None:
    normal, uncollected = exit_times(repeats, cache)
    print(f"exit of a process with the task's env (median of {repeats}, from its last statement to its end): "
          f"the interpreter's normal exit {normal:.2f} s, lq_ros.transport.processes.exit_uncollected "
          f"{uncollected:.2f} s (the node programs' exit)")  # fmt: skip
    textured, light, cached = compile_times(repeats, Path(cache))
    size_mb = sum(f.stat().st_size for f in Path(cache).glob("*.mjb")) / 1e6
    print(f"scene (median of {repeats}): compiled with image textures {textured:.2f} s, without "
          f"{light:.2f} s (the textures' PNG decoding: {textured - light:.2f} s); loaded from the cache "
          f"{cached:.2f} s (its file: {size_mb:.1f} MB)")  # fmt: skip


def libero_import_cpu(repeats: int) -> tuple[float, float]:
    """Median CPU seconds of a process that imports lq_ros and LIBERO: LIBERO's own import (its namespace check
    parses every installed distribution's whole metadata), then lq_ros.sim.libero_import's (headers only)."""
    programs = ("import lq_ros, libero", "import lq_ros; from lq_ros.sim.libero_import import import_libero; "
                "import_libero()")  # fmt: skip
    times: list[list[float]] = [[], []]
    for _ in range(repeats):
        for i, program in enumerate(programs):
            cpu0 = children_cpu_s()
            run_checked([sys.executable, "-c", program], dict(os.environ))
            times[i].append(children_cpu_s() - cpu0)
    return statistics.median(times[0]), statistics.median(times[1])


#: Services made to appear by service_lags, for each of the two waits.
SERVICE_APPEARANCES = 20
#: In a process of its own: how long after a service appears each wait returns (seconds, one line per wait).
SERVICE_LAG_PROGRAM = f"""
import random, threading, time
import rclpy
from lifecycle_msgs.srv import GetState
from lq_ros_nodes.manager_node import wait_for_service

rclpy.init()
caller = rclpy.create_node("lq_bench_caller")
lags, servers = {{"rclpy": [], "manager": []}}, []
for i in range({SERVICE_APPEARANCES}):
    for kind, wait in (("rclpy", lambda c: c.wait_for_service(60.0)), ("manager", lambda c: wait_for_service(c, 60.0))):
        name = f"/lq_bench_{{kind}}_{{i}}/get_state"
        client = caller.create_client(GetState, name)
        appeared = []

        def appear():
            time.sleep(random.uniform(0.05, 0.3))
            node = rclpy.create_node(f"lq_bench_{{kind}}_{{i}}")
            appeared.append(time.monotonic())
            node.create_service(GetState, name, lambda request, response: response)
            servers.append(node)  # (kept: a node no longer referenced is destroyed, its service with it)

        thread = threading.Thread(target=appear)
        thread.start()
        assert wait(client)
        noticed = time.monotonic()
        thread.join()
        lags[kind].append(noticed - appeared[0])
for kind in ("rclpy", "manager"):
    print(kind, sorted(lags[kind])[len(lags[kind]) // 2])
rclpy.shutdown()
"""


def service_lags(work: Path) -> tuple[float, float]:
    """Median seconds from a service's appearance to a wait for it returning: rclpy's own wait (it looks every
    0.25 s), then the lifecycle manager's (nodes/manager_node.py, every 5 ms), in a ROS domain of their own."""
    from lq_ros.transport.ros.stack import child_environment, reserved_domain

    with reserved_domain() as domain:
        proc = run_checked([sys.executable, "-c", SERVICE_LAG_PROGRAM], child_environment(domain.id, work / "ros_logs"))
    lags = dict(line.split() for line in proc.stdout.splitlines())
    return float(lags["rclpy"]), float(lags["manager"])


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
