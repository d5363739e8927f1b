"""Wall-clock ("real-time") control ticks: the schedule every node shares, and overrun accounting.

In ``--clock realtime`` runs (and against a robot) nothing waits for anything. Control tick m starts at
wall time ``tick0_ns + m * 50 ms`` on this machine's clock; ``tick0_wall_ns`` travels in the STARTED
event's detail (the real-time sim and the bridge set it :data:`START_DELAY_S` after they publish STARTED, so
every node has it before tick 0). Every managed node runs either clock (the run's ``clock`` parameter, read at
activation; nodes/*_node.py). The executor decides tick m's
command when the tick starts, giving a due chunk until :data:`COMMAND_DEADLINE_S` into the tick to
arrive (else the tick holds and the chunk applies at a later tick). The real-time sim steps tick m at
:data:`SIM_STEP_OFFSET_S` into the tick with the command of tick m if it has arrived, else the stop hold
(zero arm delta, last gripper command; absolute control: the last command), and counts that tick as a missed
command; a robot applies each command when it arrives. The sim stamps state with the ticks' scheduled wall times
(exactly 50 ms apart, so the scorer's 20 Hz series checks hold); how late each tick's work started and how long
it took is measured and counted (:class:`OverrunCounter`). A node that falls behind catches up tick by tick (every
tick is still decided and stepped, late, and counted). Such runs are not bit-reproducible: their bags
and rows say ``clock: realtime``.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field

from lq_ros.core.suite_constants import CONTROL_DT_S
from lq_ros.core.types import TickState
from lq_ros.wire import messages as m

PERIOD_NS = round(CONTROL_DT_S * 1e9)
#: The real-time sim starts tick 0 this long after it announces the episode (STARTED reaches every node first).
START_DELAY_S = 1.0
#: A chunk due at tick m that has not arrived this long after tick m started applies at a later tick.
COMMAND_DEADLINE_S = 0.025
#: The real-time sim steps tick m this long after tick m started (the executor's command is due by then).
SIM_STEP_OFFSET_S = 0.04


def now_ns() -> int:
    return time.time_ns()


@dataclass(frozen=True)
class TickClock:
    """Scheduled wall time of every control tick of one episode."""

    tick0_ns: int
    period_ns: int = PERIOD_NS

    def tick_ns(self, tick: int) -> int:
        return self.tick0_ns + tick * self.period_ns

    def tick_at(self, t_ns: int) -> int:
        """The last tick started at or before ``t_ns`` (-1 before tick 0)."""
        return (t_ns - self.tick0_ns) // self.period_ns


@dataclass
class OverrunCounter:
    """Ticks whose work did not fit in its period (recorded in the bag: terminal event and metadata).

    A tick overran when its work ended after the next tick should have started (``late_ns + work_ns >
    period``): the next tick then starts late. ``late_ns`` is how long after its scheduled time the
    work began (timer jitter, a busy CPU, the previous overrun).
    """

    period_ns: int = PERIOD_NS
    ticks: int = 0
    overruns: list[int] = field(default_factory=list)
    max_late_ns: int = 0
    max_work_ns: int = 0

    def record(self, tick: int, late_ns: int, work_ns: int) -> bool:
        self.ticks += 1
        self.max_late_ns = max(self.max_late_ns, late_ns)
        self.max_work_ns = max(self.max_work_ns, work_ns)
        over = late_ns + work_ns > self.period_ns
        if over:
            self.overruns.append(tick)
        return over

    def summary(self) -> dict:
        return {
            "ticks": self.ticks,
            "overrun_ticks": len(self.overruns),
            "overrun_tick_list": self.overruns[:200],
            "max_late_ms": round(self.max_late_ns / 1e6, 3),
            "max_work_ms": round(self.max_work_ns / 1e6, 3),
        }


def stats_json(stats: dict) -> str:
    """A node's real-time counts as they go out on /lq/realtime_stats (m.REALTIME_STATS) and into the bag."""
    return json.dumps(stats, sort_keys=True)


def tick_state_msgs(state: TickState, clock: TickClock) -> list[tuple[m.Topic, int, bytes]]:
    """The 20 Hz state of one tick (and the task's state) stamped with its scheduled wall time (no /clock, no
    physics-rate topics)."""
    t_ns = clock.tick_ns(state.tick)
    out = [
        (m.JOINT_STATES, t_ns, m.joint_state_msg(t_ns, state.joint_pos, state.joint_vel, state.joint_torque)),
        (m.EE_POSE, t_ns, m.ee_pose_msg(t_ns, state.eef_pos, state.eef_quat_xyzw)),
    ]
    if state.energy is not None:
        out.append((m.ENERGY_INTEGRALS, t_ns, m.energy_integrals_msg(t_ns, state.tick - 1, state.energy)))
    if state.task is not None:
        out += m.task_state_msgs(t_ns, state.tick, state.task)
    return out
