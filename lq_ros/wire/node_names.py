"""The ROS node name of every program of the stack, by the role the launchers and the lifecycle manager use.

The lockstep programs (nodes/<role>_node.py) and the real-time ones (nodes/realtime_*_node.py) of a role share
its name: parameters files, lifecycle services (``/lq_sim/change_state``) and sender checks address them by it.
"""

from __future__ import annotations

#: Role -> ROS node name of the four managed nodes, in the order the launcher starts them.
MANAGED_NODE_NAMES = {"sim": "lq_sim", "policy": "lq_policy", "executor": "lq_executor", "metrics": "lq_metrics"}
#: Every program's node name by role: the managed nodes, their lifecycle manager, the robot bridge (in place of the
#: sim for ``--robot``) and the LIBERO robot stand-in.
NODE_NAMES = {**MANAGED_NODE_NAMES, "manager": "lq_manager", "bridge": "lq_bridge", "robot": "robot_standin"}
