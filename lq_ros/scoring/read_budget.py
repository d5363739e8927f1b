"""What reading one bag may cost: a budget per topic, linear in the episode's length in control ticks.

A bag's size says little about its cost: identical messages compress to almost nothing (60,000 events fit in
50 KB), so a tiny hostile bag could otherwise make the scorer decode millions of messages. Each topic may hold at
most :data:`MESSAGES_PER_TICK` messages and :data:`BYTES_PER_TICK` payload bytes per tick of the episode; what
lies beyond is damage of that topic, named and skipped (the episode is ``partial``). The episode's length is the
tick limit its run metadata gives (step budget, times the hard stop when only action ticks count), at most
:data:`MAX_EPISODE_TICKS` (also the length of a bag without one, e.g. another tool's), plus :data:`SLACK_TICKS`.
"""

from __future__ import annotations

from lq_ros.core.run_config import ACTION_BUDGET_HARD_STOP
from lq_ros.core.suite_constants import BUDGET_PRESETS, CONTROL_DT_S
from lq_ros.recording.mcap_reader import TopicBudget

#: The longest episode a bag is read for, in control ticks (5 min at 20 Hz; LIBERO's longest budget counted in
#: action ticks is 2,080): a bag without a step budget in its metadata (another tool's) is read this far.
MAX_EPISODE_TICKS = 6_000
#: Ticks a bag's topics may cover beyond the episode's limit (a robot's samples before the start, the recorder's
#: quiet period after the end).
SLACK_TICKS = 200
#: Messages and payload bytes one topic may carry per control tick, by the scorer's role for it. The stack's
#: per-tick topics carry one message (commands, energy, task poses), the physics-rate ones 25 (500 Hz); a robot's
#: own topics up to 50 (1 kHz EE pose or joint states: a 7-joint JointState at 1 kHz is ~17 KB a tick; a task
#: state up to 200 Hz). Events and chunks: about one per tick, with room for warnings, tracebacks and long chunks.
#: The bytes bound the memory of wide messages that the counts alone do not (decoded arrays are no larger than
#: their payloads): ~0.1 MB a tick over every topic, ~0.7 GB at the cap were every topic flooded.
MESSAGES_PER_TICK = {
    "ee": 50, "joints": 50, "ee_physics": 30, "joints_physics": 30, "energy": 2, "commands": 2, "requests": 2,
    "chunks": 2, "events": 4, "task": 10, "task_poses": 2,
}  # fmt: skip
BYTES_PER_TICK = {
    "ee": 8 << 10, "joints": 24 << 10, "ee_physics": 4 << 10, "joints_physics": 8 << 10, "energy": 512,
    "commands": 2 << 10, "requests": 1 << 10, "chunks": 16 << 10, "events": 16 << 10, "task": 16 << 10,
    "task_poses": 16 << 10,
}  # fmt: skip


#: Records the reader may walk one by one per tick (those of chunks without a usable message index, every topic's:
#: a Python step each, ~5 us). This stack's bags hold ~60 records a tick with the physics-rate topics.
RECORDS_PER_TICK = 256


def reindex_budget(metadata: dict) -> TopicBudget:
    """What ``lq reindex`` may walk in one bag: the scorer's records per tick of the episode (RECORDS_PER_TICK over
    :func:`episode_ticks` + SLACK_TICKS). It walks every record of every chunk to count them, so the records bound
    its time; it keeps counts only, so no topic needs a message or byte limit. A legitimate bag walks about 60
    records a tick; a flood of tiny records (millions in a few KB) is cut there and named as damage."""
    ticks, why = episode_ticks(metadata)
    return TopicBudget(messages={}, bytes={}, records=RECORDS_PER_TICK * (ticks + SLACK_TICKS), why=why,
                       walked_what="every record of every chunk, to count them")  # fmt: skip


def run_step_budget(cfg: dict) -> int | None:
    """The run's step budget from its configuration: ``max_steps``, else its preset's budget for its suite (the
    paper's for bags from before presets); None when unknown or not a positive whole number (hostile metadata)."""
    if not isinstance(cfg, dict):
        return None
    preset, suite = cfg.get("budgets", "paper"), cfg.get("suite")
    steps = cfg.get("max_steps") or (
        BUDGET_PRESETS.get(preset, {}).get(suite) if isinstance(preset, str) and isinstance(suite, str) else None
    )
    return steps if isinstance(steps, int) and not isinstance(steps, bool) and steps > 0 else None


def episode_ticks(metadata: dict) -> tuple[int, str]:
    """The ticks a bag is read for and where that comes from (the run's tick limit, else the cap)."""
    cfg = metadata.get("config") if isinstance(metadata, dict) else None
    steps = run_step_budget(cfg) if isinstance(cfg, dict) else None
    if steps is not None:
        limit = steps * (ACTION_BUDGET_HARD_STOP if cfg.get("budget_counts") == "action" else 1)
        if limit <= MAX_EPISODE_TICKS:
            return limit, f"an episode of at most {limit} ticks (its step budget)"
    minutes = MAX_EPISODE_TICKS * CONTROL_DT_S / 60
    return MAX_EPISODE_TICKS, f"an episode of at most {MAX_EPISODE_TICKS} ticks ({minutes:g} min, the scorer's cap)"


def topic_budget(roles: dict[str, str], metadata: dict) -> TopicBudget:
    """The budget of every topic read (topic -> the scorer's role for it), shared by the files of one bag."""
    ticks, why = episode_ticks(metadata)
    ticks += SLACK_TICKS
    return TopicBudget(
        messages={topic: MESSAGES_PER_TICK[role] * ticks for topic, role in roles.items()},
        bytes={topic: BYTES_PER_TICK[role] * ticks for topic, role in roles.items()},
        records=RECORDS_PER_TICK * ticks,
        why=why,
    )
