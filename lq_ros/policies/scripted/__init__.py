"""Scripted privileged-state experts behind the one policy name ``scripted`` (docs/design/scripted_experts.md).

``machine``      the shared machinery: state machine, chunk rollout on an arm model, parameters
``scene``        object collision boxes and the fixed LIBERO-Goal fixtures
``bowl``         rim grasp of a bowl: LIBERO-Spatial, and the Goal bowl tasks
``pick_place``   top-down grasp of boxes, cans, bottles: LIBERO-Object, Goal objects
``knob``         Goal: turn on the stove
``drawer``       Goal: open the middle drawer
``facade``       ``ScriptedExpert``, the registered policy: picks the expert at reset (``expert_for``)
"""

from lq_ros.policies.scripted.facade import GOAL_UNCOVERED, ScriptedExpert, expert_for
from lq_ros.policies.scripted.machine import Expert, ExpertParams

__all__ = ["GOAL_UNCOVERED", "Expert", "ExpertParams", "ScriptedExpert", "expert_for"]
