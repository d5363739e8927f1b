"""The task's state at each tick, read from a LIBERO env without changing it.

What it records (lq_msgs/msg/TaskState and a geometry_msgs/PoseArray, one each per tick):

- the poses of the task's objects of interest (LIBERO's ``obj_of_interest``), of every goal predicate's
  arguments (objects, fixtures and regions: a region is a site, e.g. a drawer's ``top_region``), then of the
  scene's other movable objects;
- the gripper's contact with each of them (any gripper geom) and whether it grasps it (a geom of each finger
  pad touches it: robosuite's ``_check_grasp`` test, computed here from MuJoCo's contact arrays with precomputed
  geom ids rather than robosuite's per-contact name lookups); a region counts through its parent object's geoms;
- the truth of each goal predicate, evaluated by the env's own ``_eval_predicate`` (what LIBERO's success is
  made of).

Everything is read from the simulator's current data: nothing is written, so the simulation stays
bit-identical with or without it.
"""

from __future__ import annotations

import numpy as np

from lq_ros.core.types import TaskStateSample


def predicate_name(state: list[str]) -> str:
    """A goal predicate as the BDDL writes it: ``["on", "bowl_1", "plate_1"]`` -> ``"(on bowl_1 plate_1)"``."""
    return "(" + " ".join(str(part) for part in state) + ")"


class TaskStateProbe:
    """Samples :class:`TaskStateSample` from a LIBERO problem env (``ControlEnv.env``) after each tick."""

    def __init__(self, env) -> None:
        self._env = env
        self._goal = [list(state) for state in env.parsed_problem["goal_state"]]
        names: list[str] = []
        # Then the scene's other movable objects: picking the wrong one (two identical bowls in LIBERO-Spatial) is
        # a failure of its own, and it is seen only if that object is tracked.
        goal_args = (arg for state in self._goal for arg in state[1:])
        for name in [*env.obj_of_interest, *goal_args, *env.objects_dict]:
            if name not in names:
                names.append(name)
        self.object_names = tuple(names)
        self.predicate_names = tuple(predicate_name(state) for state in self._goal)
        self._bound_to = None  # the MjModel the geom ids below belong to (rebound on a hard reset)

    def _bind(self) -> None:
        """Body, site and geom ids of the current model (a hard reset may build a new MjSim)."""
        env = self._env
        sim = env.sim
        model = sim.model
        self._model = model._model
        self._data = sim.data._data
        gripper = env.robots[0].gripper

        ngeom = self._model.ngeom

        def geom_mask(names) -> np.ndarray:
            mask = np.zeros(ngeom, dtype=bool)
            mask[[model.geom_name2id(n) for n in names]] = True
            return mask

        # Geom-membership masks: a tick's contacts are then classified by indexing, for every object at once.
        self._gripper_mask = geom_mask(gripper.contact_geoms)
        self._pad_masks = (
            geom_mask(gripper.important_geoms["left_fingerpad"]),
            geom_mask(gripper.important_geoms["right_fingerpad"]),
        )
        self._kinds: list[tuple[str, int]] = []  # ("body" | "site", id) per object
        object_masks = []
        for name in self.object_names:
            state = env.object_states_dict[name]
            if getattr(state, "object_state_type", "object") == "site":
                self._kinds.append(("site", model.site_name2id(name)))
                owner = env.get_object(state.parent_name)
            else:
                self._kinds.append(("body", env.obj_body_id[name]))
                owner = env.get_object(name)
            # A region whose parent LIBERO cannot name (or a model without contact geoms) has no contact to test.
            object_masks.append(geom_mask(getattr(owner, "contact_geoms", None) or ()))
        self._object_masks = np.array(object_masks).reshape(len(self.object_names), ngeom)  # (K, ngeom)
        self._bound_to = self._model

    def sample(self) -> TaskStateSample:
        import mujoco

        env = self._env
        if self._bound_to is not env.sim.model._model:
            self._bind()
        data = self._data
        k = len(self.object_names)
        pos = np.empty((k, 3))
        quat = np.empty((k, 4))
        wxyz = np.empty(4)
        for i, (kind, index) in enumerate(self._kinds):
            if kind == "body":
                pos[i] = data.xpos[index]
                wxyz[:] = data.xquat[index]
            else:
                pos[i] = data.site_xpos[index]
                mujoco.mju_mat2Quat(wxyz, data.site_xmat[index])
            quat[i] = (wxyz[1], wxyz[2], wxyz[3], wxyz[0])
        ncon = data.ncon
        geom1 = data.contact.geom1[:ncon]
        geom2 = data.contact.geom2[:ncon]
        contact = np.zeros(k, dtype=bool)
        grasped = np.zeros(k, dtype=bool)
        if ncon:
            objects1, objects2 = self._object_masks[:, geom1], self._object_masks[:, geom2]  # (K, ncon)
            contact = _touch(objects1, objects2, self._gripper_mask[geom1], self._gripper_mask[geom2])
            grasped = _touch(objects1, objects2, self._pad_masks[0][geom1], self._pad_masks[0][geom2])
            grasped &= _touch(objects1, objects2, self._pad_masks[1][geom1], self._pad_masks[1][geom2])
        values = np.array([bool(env._eval_predicate(state)) for state in self._goal], dtype=bool)
        return TaskStateSample(
            object_names=self.object_names,
            object_pos=pos,
            object_quat_xyzw=quat,
            gripper_contact=contact,
            grasped=grasped,
            predicate_names=self.predicate_names,
            predicate_values=values,
        )


def _touch(objects1: np.ndarray, objects2: np.ndarray, other1: np.ndarray, other2: np.ndarray) -> np.ndarray:
    """Per object: some active contact pairs one of its geoms with a geom of the other group, in either order (as
    robosuite's ``check_contact`` decides it). ``objects1``/``objects2``: (K, ncon) membership of each contact's
    first and second geom; ``other1``/``other2``: (ncon,) the other group's."""
    return ((objects1 & other2) | (objects2 & other1)).any(axis=1)
