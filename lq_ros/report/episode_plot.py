"""One episode at a glance, from its bag alone (no simulator): a PNG per episode for ``lq report``.

Panels: the end-effector path seen from the top and from the side, the commanded actions over time with
hold / underrun / rejected ticks shaded and chunk switches marked, the EE speed, the jerk norm, and the
instantaneous power of the paper's energy model (mechanical, electrical loss, overhead).

Trajectory and joint data come from :func:`lq_ros.scoring.bag_scorer.read_episode` (the scorer's reader, the same
samples the scores use); the commands (actions, sources, chunk ids) from :func:`lq_ros.report.replay.read_recording`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only, never a display

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from numpy.typing import ArrayLike, NDArray  # noqa: E402

from lq_ros.core.executor_protocol import Source  # noqa: E402
from lq_ros.core.safe_write import output_folder, save_figure  # noqa: E402
from lq_ros.core.suite_constants import CONTROL_DT_S, NUM_WAIT_STEPS  # noqa: E402
from lq_ros.report.replay import SOURCE_STYLE, ReplayRefused, read_recording  # noqa: E402
from lq_ros.scoring import metrics  # noqa: E402
from lq_ros.wire import messages as m  # noqa: E402

#: Panel titles, in drawing order (tests check them).
PANELS = (
    "EE path, top view (x-y)",
    "EE path, side view (x-z)",
    "commanded actions",
    "EE speed",
    "jerk norm",
    "instantaneous power",
)
ACTION_LABELS = ("dx", "dy", "dz", "dax", "day", "daz", "gripper")
DPI = 80


# -- power: the one place the energy model is evaluated over time --------------------------------------


@dataclass(frozen=True)
class PowerSeries:
    """Power of the paper's energy model (eq. 6-9) over an episode, watts, one value per interval.

    Value i covers the ``dt_s[i]`` seconds ending at control tick ``ticks[i]``, so Σ power · dt_s is the
    scorer's energy on the same data.
    """

    ticks: NDArray[np.int64]
    mech_w: NDArray[np.float64]  # positive mechanical power max(0, τ·q̇)
    elec_w: NDArray[np.float64]  # resistive loss R Kt⁻² τ·τ
    overhead_w: NDArray[np.float64]  # constant P_overhead
    dt_s: NDArray[np.float64]
    basis: str  # what the values were computed from


def instantaneous_power(
    torque_nm: ArrayLike,
    joint_vel_rad_s: ArrayLike,
    *,
    elec_coeff: float = metrics.ELEC_LOSS_COEFF_W_PER_NM2,
    overhead_w: float = metrics.OVERHEAD_POWER_W,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """(mechanical, electrical loss, overhead) power in W of (T, J) torque (N m) and velocity (rad/s) samples.

    Per sample, exactly the integrand of :func:`lq_ros.scoring.metrics.energy_terms`.
    """
    tau = np.atleast_2d(np.asarray(torque_nm, dtype=np.float64))
    qd = np.atleast_2d(np.asarray(joint_vel_rad_s, dtype=np.float64))
    if tau.shape != qd.shape:
        raise ValueError(f"torque {tau.shape} and joint velocity {qd.shape} must have equal (T, J) shapes")
    mech = np.maximum(0.0, np.einsum("tj,tj->t", tau, qd))
    elec = float(elec_coeff) * np.einsum("tj,tj->t", tau, tau)
    return mech, elec, np.full(len(tau), float(overhead_w))


def episode_power(
    view: EpisodeView,
    *,
    elec_coeff: float = metrics.ELEC_LOSS_COEFF_W_PER_NM2,
    overhead_w: float = metrics.OVERHEAD_POWER_W,
) -> PowerSeries | None:
    """The episode's power over time from the best data the bag has, as the scorer's ``auto`` energy rate.

    Per-tick substep integrals (/lq/energy_integrals) give each tick's mean power over its 25 physics
    substeps; otherwise the 20 Hz /joint_states samples give the power at each tick boundary (sampled,
    not averaged: the paper's estimate). None without either.
    """
    if len(view.energy_ticks):
        duration, work, torque_sq = view.energy.T
        return PowerSeries(view.energy_ticks, work / duration, float(elec_coeff) * torque_sq / duration,
                           np.full(len(duration), float(overhead_w)), duration,
                           "mean per tick of the 500 Hz substep integrals")  # fmt: skip
    if len(view.joint_effort):
        mech, elec, over = instantaneous_power(view.joint_effort, view.joint_vel, elec_coeff=elec_coeff,
                                               overhead_w=overhead_w)  # fmt: skip
        return PowerSeries(view.joint_ticks, mech, elec, over, np.full(len(mech), CONTROL_DT_S),
                           "20 Hz joint state samples")  # fmt: skip
    return None


# -- data -----------------------------------------------------------------------------------------------


def _tick(t_ns: NDArray[np.int64]) -> NDArray[np.int64]:
    """Control tick of sim times (the wait steps come first; tick 0 is the first policy tick)."""
    return np.rint(np.asarray(t_ns) / 1e9 / CONTROL_DT_S).astype(np.int64) - NUM_WAIT_STEPS


@dataclass
class EpisodeView:
    """What the figure draws, in control ticks."""

    name: str
    metadata: dict
    status: str  # terminal event name (success, timeout, error, stopped) or unknown
    end_tick: int | None
    ee_ticks: NDArray[np.int64]
    ee_pos: NDArray[np.float64]  # (n, 3) m
    joint_ticks: NDArray[np.int64]  # samples closing each interval after tick 0
    joint_vel: NDArray[np.float64]  # (n, J) rad/s
    joint_effort: NDArray[np.float64]  # (n, J) N m
    energy_ticks: NDArray[np.int64]  # ticks closing each /lq/energy_integrals interval
    energy: NDArray[np.float64]  # (n, 3): duration (s), positive work (J), torque² integral (N² m² s)
    command_ticks: NDArray[np.int64]
    actions: NDArray[np.float64]  # (T, 7)
    sources: NDArray[np.int64]
    switch_ticks: list[int] = field(default_factory=list)
    rejected_ticks: list[int] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    #: (tick, goal predicate, "true" | "undone") from the task state, and the episode's failure mode (None: no
    #: task state in the bag).
    predicate_events: list[tuple[int, str, str]] = field(default_factory=list)
    failure_mode: str | None = None


def load_episode_view(bag: Path) -> EpisodeView:
    """Read one bag folder into an EpisodeView (the scorer's reader for poses and joints)."""
    from lq_ros.scoring.bag_metrics import classify_episode
    from lq_ros.scoring.bag_scorer import read_episode, task_series

    bag = Path(bag)
    data = read_episode(bag)
    started = [e for e in data.events if e[0] == m.EventKind.STARTED]
    terminal = [e for e in data.events if e[0] in m.EventKind.TERMINAL]
    t0 = started[0][2] if started else None
    t1 = terminal[0][2] if terminal else None
    t_ee, pos = data.ee.arrays(t0, t1)
    # As the scorer does: joint samples strictly after the start, each closing one interval.
    t_j, jv = data.joints.arrays(None if t0 is None else t0 + 1, t1)
    energy = getattr(data, "energy", None)  # per-tick substep integrals: bags recorded since they exist
    t_e, ev = energy.arrays(None if t0 is None else t0 + 1, t1) if energy is not None else ([], np.empty((0, 3)))
    n = jv.shape[1] // 2 if jv.size else 0
    warnings = list(data.warnings)
    try:
        rec = read_recording(bag, poses=False)
        commands, switches = rec.commands, [t for t, _ in rec.chunk_switch_ticks()]
        rejected = [tick for kind, tick, _ in rec.events if kind == m.EventKind.CHUNK_REJECTED]
    except ReplayRefused as exc:
        commands, switches, rejected = [], [], []
        warnings.append(str(exc))
    series, _ = task_series(data, t0, t1)
    events, mode = [], None
    if series is not None:
        outcome = {"success": "success", "timeout": "failure"}.get(
            m.EventKind.NAMES.get(terminal[0][0], "") if terminal else "", "error"
        )
        analysis = classify_episode(series, data, outcome)  # as the scorer's row has it
        events, mode = analysis.predicate_events, analysis.failure_mode
    return EpisodeView(
        name=bag.name,
        metadata=data.metadata,
        status=m.EventKind.NAMES.get(terminal[0][0], "?") if terminal else "unknown",
        end_tick=terminal[0][1] if terminal else None,
        ee_ticks=_tick(t_ee),
        ee_pos=pos.reshape(-1, 3) if pos.size else np.empty((0, 3)),
        joint_ticks=_tick(t_j),
        joint_vel=jv[:, :n] if n else np.empty((0, 0)),
        joint_effort=jv[:, n:] if n else np.empty((0, 0)),
        energy_ticks=_tick(np.asarray(t_e, dtype=np.int64)),
        energy=ev.reshape(-1, 3) if len(t_e) else np.empty((0, 3)),
        command_ticks=np.array([c.tick for c in commands], dtype=np.int64),
        actions=np.array([c.action for c in commands]).reshape(-1, 7) if commands else np.empty((0, 7)),
        sources=np.array([c.source for c in commands], dtype=np.int64),
        switch_ticks=switches,
        rejected_ticks=rejected,
        warnings=warnings,
        predicate_events=events,
        failure_mode=mode,
    )


# -- figure ---------------------------------------------------------------------------------------------


def _rgb(colour: tuple[int, int, int]) -> tuple[float, float, float]:
    return tuple(c / 255.0 for c in colour)


def _shade_holds(ax, view: EpisodeView, legend: bool = False) -> None:
    """Shade runs of held ticks, one colour per hold reason (a command at tick k covers [k, k+1))."""
    if not len(view.sources):
        return
    labelled = set()
    start = 0
    for i in range(1, len(view.sources) + 1):
        if i < len(view.sources) and view.sources[i] == view.sources[start]:
            continue
        src = int(view.sources[start])
        if src != Source.CHUNK:
            name, colour = SOURCE_STYLE.get(src, ("hold", (128, 128, 128)))
            label = name if legend and src not in labelled else None
            labelled.add(src)
            ax.axvspan(view.command_ticks[start], view.command_ticks[i - 1] + 1, color=_rgb(colour), alpha=0.18,
                       linewidth=0, label=label)  # fmt: skip
        start = i


def _no_data(ax, text: str) -> None:
    ax.text(0.5, 0.5, text, ha="center", va="center", transform=ax.transAxes, color="0.4")


def _path(ax, view: EpisodeView, a: int, b: int, title: str) -> None:
    ax.set_title(title)
    axis = "xyz"
    ax.set_xlabel(f"{axis[a]} (m)")
    ax.set_ylabel(f"{axis[b]} (m)")
    if not len(view.ee_pos):
        _no_data(ax, "no EE pose samples")
        return
    p = view.ee_pos
    ax.plot(p[:, a], p[:, b], color="0.75", linewidth=1, zorder=1)
    sc = ax.scatter(p[:, a], p[:, b], c=view.ee_ticks, cmap="viridis", s=9, zorder=2)
    ax.plot(p[0, a], p[0, b], "o", color="black", markersize=7, label="start", zorder=3)
    end_colour = {"success": "tab:green", "timeout": "tab:orange"}.get(view.status, "tab:red")
    ax.plot(p[-1, a], p[-1, b], "*", color=end_colour, markersize=13, label=f"end ({view.status})", zorder=3)
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    plt.colorbar(sc, ax=ax, label="tick", fraction=0.046, pad=0.02)


def episode_figure(view: EpisodeView) -> plt.Figure:
    """The per-episode figure (see PANELS); time panels share the tick axis and show held ticks shaded."""
    fig = plt.figure(figsize=(12.0, 13.0), layout="constrained")
    grid = fig.add_gridspec(4, 2, height_ratios=[1.35, 1.0, 0.8, 0.9])
    ax_top, ax_side = fig.add_subplot(grid[0, 0]), fig.add_subplot(grid[0, 1])
    ax_act = fig.add_subplot(grid[1, :])
    ax_speed = fig.add_subplot(grid[2, 0], sharex=ax_act)
    ax_jerk = fig.add_subplot(grid[2, 1], sharex=ax_act)
    ax_power = fig.add_subplot(grid[3, :], sharex=ax_act)
    _path(ax_top, view, 0, 1, PANELS[0])
    _path(ax_side, view, 0, 2, PANELS[1])
    dt = CONTROL_DT_S

    # Actions: a command holds for its whole tick (steps-post).
    ax_act.set_title(PANELS[2])
    _shade_holds(ax_act, view, legend=True)
    if len(view.actions):
        x = np.append(view.command_ticks, view.command_ticks[-1] + 1)
        for i, label in enumerate(ACTION_LABELS):
            y = np.append(view.actions[:, i], view.actions[-1, i])
            ax_act.plot(x, y, drawstyle="steps-post", linewidth=1.2 if i < 6 else 1.8, label=label,
                        color="black" if i == 6 else None, linestyle="--" if i == 6 else "-")  # fmt: skip
        for k, tick in enumerate(view.switch_ticks):
            ax_act.axvline(tick, color="0.35", linestyle=":", linewidth=0.9, label="chunk switch" if k == 0 else None)
        _mark_predicates(ax_act, view)
        if view.rejected_ticks:
            ax_act.plot(view.rejected_ticks, [1.05] * len(view.rejected_ticks), "x", color="purple", markersize=8,
                        label="chunk rejected")  # fmt: skip
        ax_act.set_ylim(-1.15, 1.15)
    else:
        _no_data(ax_act, f"no commands on {m.COMMAND.name}")
    ax_act.set_ylabel("action (normalised)")
    ax_act.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.005, 1.0))
    ax_act.grid(alpha=0.3)

    ax_speed.set_title(PANELS[3])
    _shade_holds(ax_speed, view)
    if len(view.ee_pos) >= 2:
        ax_speed.plot(view.ee_ticks[1:], metrics.speed_profile(view.ee_pos, dt), color="tab:blue")
    else:
        _no_data(ax_speed, "fewer than 2 EE samples")
    ax_speed.set_ylabel("m/s (20 Hz samples)")

    ax_jerk.set_title(PANELS[4])
    _shade_holds(ax_jerk, view)
    if len(view.ee_pos) >= 4:
        jerk = metrics.jerk_norms(view.ee_pos, dt)
        ax_jerk.plot(view.ee_ticks[3:], jerk, color="tab:purple")
        ax_jerk.axhline(jerk.mean(), color="tab:purple", linestyle="--", linewidth=0.8, label=f"mean {jerk.mean():.3g}")
        ax_jerk.legend(fontsize=7, loc="upper right")
    else:
        _no_data(ax_jerk, "fewer than 4 EE samples")
    ax_jerk.set_ylabel("m/s³ (20 Hz samples)")

    ax_power.set_title(PANELS[5])
    _shade_holds(ax_power, view)
    power = episode_power(view)
    if power is not None:
        ax_power.set_title(f"{PANELS[5]} ({power.basis})")
        for series, label, colour in ((power.mech_w, "mechanical", "#4c72b0"),
                                      (power.elec_w, "electrical loss", "#dd8452"),
                                      (power.overhead_w, "overhead", "#8c8c8c")):  # fmt: skip
            # Value i covers the interval ending at ticks[i]: drawn as a step over that interval.
            ax_power.plot(power.ticks, series, drawstyle="steps-pre", color=colour,
                          label=f"{label} (Σ {float(np.sum(series * power.dt_s)):.3g} J)")  # fmt: skip
        ax_power.set_yscale("symlog", linthresh=1.0)  # the 85 W overhead would flatten the rest on a linear axis
        ax_power.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.005, 1.0))
    else:
        _no_data(ax_power, f"no energy integrals and no joint states with velocity and effort on {m.JOINT_STATES.name}")
    ax_power.set_ylabel("W (symlog)")
    ax_power.set_xlabel(f"control tick ({dt:g} s)")
    for ax in (ax_speed, ax_jerk, ax_power):
        ax.grid(alpha=0.3)
    fig.suptitle(_title(view), fontsize=10)
    return fig


def _mark_predicates(ax, view: EpisodeView) -> None:
    """A goal predicate becoming true (green) or undone (red, dashed) at its tick, named at the panel's top."""
    labelled = set()
    for tick, name, change in view.predicate_events:
        colour, style = ("tab:green", "-") if change == "true" else ("tab:red", "--")
        label = f"goal predicate {change}" if change not in labelled else None
        labelled.add(change)
        ax.axvline(tick, color=colour, linestyle=style, linewidth=1.4, label=label)
        ax.annotate(name, (tick, 1.0), xycoords=("data", "axes fraction"), rotation=90, fontsize=6, color=colour,
                    ha="right", va="top")  # fmt: skip


def _title(view: EpisodeView) -> str:
    cfg = view.metadata.get("config") or {}
    parts = [str(cfg.get(k)) for k in ("policy", "mode") if cfg.get(k) is not None]
    if cfg.get("latency_s") is not None:
        parts.append(f"Δt_sim {cfg['latency_s']:g} s")
    if cfg.get("suite") is not None:
        parts.append(f"{cfg['suite']} task {cfg.get('task')} init {cfg.get('init')} seed {cfg.get('seed')}")
    end = f"{view.status}" + (f" at tick {view.end_tick}" if view.end_tick is not None else "")
    if view.failure_mode not in (None, "none"):
        end += f" · failure mode: {view.failure_mode.replace('_', ' ')}"
    return f"{view.name}\n{' · '.join(parts + [end])}"


def write_episode_figure(bag: Path, path: Path, dpi: int = DPI) -> Path:
    """Draw ``bag``'s figure into ``path`` (PNG); returns the path."""
    fig = episode_figure(load_episode_view(bag))
    try:
        output_folder(Path(path).parent, "figure folder", follow=False)  # (in a report folder: never a link)
        save_figure(fig, path, dpi=dpi)
    finally:
        plt.close(fig)
    return Path(path)
