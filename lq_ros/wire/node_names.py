"""The ROS node name of every program of the stack, by the role the launcher and the lifecycle manager use.

Parameters files, lifecycle services (``/lq_sim/change_state``) and sender checks address the nodes by these
names. Every managed node runs either clock (lockstep or real time, a parameter), so a role has one program.
"""

from __future__ import annotations

#: Role -> ROS node name of the four managed nodes of a simulated run.
MANAGED_NODE_NAMES = {"sim": "lq_sim", "policy": "lq_policy", "executor": "lq_executor", "metrics": "lq_metrics"}
#: Every program's node name by role: the managed nodes, their lifecycle manager, the robot bridge (a managed node,
#: in place of the sim for ``--robot``) and the LIBERO robot stand-in (a robot of its own, not managed).
NODE_NAMES = {**MANAGED_NODE_NAMES, "manager": "lq_manager", "bridge": "lq_bridge", "robot": "robot_standin"}


def stack_roles(robot: bool) -> tuple[str, ...]:
    """The managed nodes of a run, in activation order: the recorder before anything is published, the node that
    starts the episode (the sim, or the bridge to a robot) last."""
    return ("metrics", "policy", "executor", "bridge" if robot else "sim")


def stack_node_names(robot: bool) -> tuple[str, ...]:
    """:func:`stack_roles` as ROS node names (the lifecycle manager's ``node_names``)."""
    return tuple(NODE_NAMES[role] for role in stack_roles(robot))
