"""The task's state at each tick, read from a LIBERO env without changing it.

What it records (lq_msgs/msg/TaskState and a geometry_msgs/PoseArray, one each per tick):

- the poses of the task's objects of interest (LIBERO's ``obj_of_interest``), of every goal predicate's
  arguments (objects, fixtures and regions: a region is a site, e.g. a drawer's ``top_region``), then of the
  scene's other movable objects;
- the gripper's contact with each of them (any gripper geom) and whether it grasps it (a geom of each finger
  pad touches it: robosuite's ``_check_grasp`` test, computed here from MuJoCo's contact arrays with precomputed
  geom ids rather than robosuite's per-contact name lookups); a region counts through its parent object's geoms;
- the truth of each goal predicate, evaluated by the env's own ``_eval_predicate`` (what LIBERO's success is
  made of);
- each object's one articulation joint (a drawer's slide, a knob's or door's hinge: what ``open`` or ``turnon``
  judge) and its position; a region takes the joint LIBERO gives it (a drawer's ``top_region``: that drawer's);
- the end effector's distance to each object's nearest surface: the axis-aligned boxes of its collision geoms in
  their own frames (for an object or region with one joint, the geoms that joint moves: the drawer with its
  handle, the knob), so a hand at a drawer's handle is near the drawer, not 13 cm from its region's site.

Everything is read from the simulator's current data: nothing is written, so the simulation stays
bit-identical with or without it.
"""

from __future__ import annotations

import numpy as np

from lq_ros.core.types import JOINT_HINGE, JOINT_NONE, JOINT_SLIDE, TaskStateSample

#: Indexes reading a MuJoCo quaternion (w, x, y, z) as (x, y, z, w).
XYZW = np.array([1, 2, 3, 0], dtype=np.intp)


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
        self._pads_in_gripper = bool(np.all(self._gripper_mask[self._pad_masks[0] | self._pad_masks[1]]))
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
        self._joints = [self._joint_of(name) for name in self.object_names]  # (qpos address, kind) or None
        self._joint_type = np.array([j[1] if j else JOINT_NONE for j in self._joints], dtype=np.uint8)
        self._jointed = np.array([j is not None for j in self._joints], dtype=bool)
        self._joint_addresses = np.array([j[0] for j in self._joints if j], dtype=np.intp)
        # Surface geoms per object: a jointed object's moving part (the joint body's subtree), else its own geoms.
        owners, geoms = [], []
        for i, joint in enumerate(self._joints):
            mask = self._object_masks[i] & (self._subtree_geoms(joint[2]) if joint else True)
            found = np.flatnonzero(mask)
            owners += [i] * len(found)
            geoms += found.tolist()
        self._surface_geoms = np.array(geoms, dtype=np.int64)
        aabb = self._model.geom_aabb[self._surface_geoms]  # (G, 6): centre, half-size, geom frame (fixed)
        self._surface_centre, self._surface_half = aabb[:, :3], aabb[:, 3:]
        # The geoms come grouped by object, in order: each object with geoms, and where its group starts.
        self._surface_objects, self._surface_starts = np.unique(np.array(owners, dtype=np.int64), return_index=True)
        self._bodies = np.array([i for i, (kind, _) in enumerate(self._kinds) if kind == "body"], dtype=np.intp)
        self._body_ids = np.array([index for kind, index in self._kinds if kind == "body"], dtype=np.intp)
        self._sites = [(i, index) for i, (kind, index) in enumerate(self._kinds) if kind == "site"]
        self._grip_site = env.robots[0].eef_site_id
        self._bound_to = self._model

    def _joint_of(self, name: str) -> tuple[int, int, int] | None:
        """(qpos address, JOINT_SLIDE | JOINT_HINGE, body id) of the object's one articulation joint, else None."""
        import mujoco

        env, model = self._env, self._model
        state = env.object_states_dict[name]
        if getattr(state, "object_state_type", "object") == "site":
            names = getattr(env.object_sites_dict.get(name), "joints", None) or ()
        else:
            names = getattr(env.get_object(name), "joints", None) or ()
        kinds = {int(mujoco.mjtJoint.mjJNT_SLIDE): JOINT_SLIDE, int(mujoco.mjtJoint.mjJNT_HINGE): JOINT_HINGE}
        found = []
        for joint in names:
            j = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, joint)
            if j >= 0 and int(model.jnt_type[j]) in kinds:
                found.append((int(model.jnt_qposadr[j]), kinds[int(model.jnt_type[j])], int(model.jnt_bodyid[j])))
        return found[0] if len(found) == 1 else None  # several (a cabinet's drawers): no one joint to name

    def _subtree_geoms(self, body: int) -> np.ndarray:
        """Mask of the geoms on ``body`` and the bodies below it."""
        model = self._model
        inside = np.zeros(model.nbody, dtype=bool)
        inside[body] = True
        for b in range(body + 1, model.nbody):  # MuJoCo numbers a body after its parent
            inside[b] = inside[model.body_parentid[b]]
        return inside[model.geom_bodyid]

    def sample(self) -> TaskStateSample:
        import mujoco

        env = self._env
        if self._bound_to is not env.sim.model._model:
            self._bind()
        data = self._data
        k = len(self.object_names)
        if self._sites:
            pos = np.empty((k, 3))
            quat = np.empty((k, 4))
            wxyz = np.empty(4)
            pos[self._bodies] = data.xpos[self._body_ids]
            quat[self._bodies] = data.xquat[self._body_ids][:, XYZW]
            for i, index in self._sites:
                pos[i] = data.site_xpos[index]
                mujoco.mju_mat2Quat(wxyz, data.site_xmat[index])
                quat[i] = (wxyz[1], wxyz[2], wxyz[3], wxyz[0])
        else:  # bodies only (every object in order): the same values, gathered directly
            pos = data.xpos[self._body_ids]
            quat = data.xquat[self._body_ids][:, XYZW]
        ncon = data.ncon
        contacts = data.contact
        geom1 = contacts.geom1[:ncon]
        geom2 = contacts.geom2[:ncon]
        contact = np.zeros(k, dtype=bool)
        grasped = np.zeros(k, dtype=bool)
        gripper1, gripper2 = self._gripper_mask[geom1], self._gripper_mask[geom2]
        # No contact has a gripper geom (most ticks): none touches or grasps anything (the pads are gripper geoms).
        if gripper1.any() or gripper2.any() or not self._pads_in_gripper:
            masks = self._object_masks
            contact = _touch(masks, geom1, geom2, gripper1, gripper2)
            grasped = _touch(masks, geom1, geom2, self._pad_masks[0][geom1], self._pad_masks[0][geom2])
            grasped &= _touch(masks, geom1, geom2, self._pad_masks[1][geom1], self._pad_masks[1][geom2])
        values = np.array([bool(env._eval_predicate(state)) for state in self._goal], dtype=bool)
        joint_pos = np.full(k, np.nan)
        joint_pos[self._jointed] = data.qpos[self._joint_addresses]
        return TaskStateSample(
            object_names=self.object_names,
            object_pos=pos,
            object_quat_xyzw=quat,
            gripper_contact=contact,
            grasped=grasped,
            predicate_names=self.predicate_names,
            predicate_values=values,
            joint_type=self._joint_type.copy(),
            joint_position=joint_pos,
            ee_distance=self._surface_distance(),
        )

    def _surface_distance(self) -> np.ndarray:
        """Per object: the grip site's distance to the nearest of its surface geoms' boxes, m (NaN: none)."""
        data = self._data
        if not len(self._surface_geoms):
            return np.full(len(self.object_names), np.nan)
        g = self._surface_geoms
        offset = data.site_xpos[self._grip_site] - data.geom_xpos[g]  # (G, 3) world
        local = np.einsum("gji,gj->gi", data.geom_xmat[g].reshape(-1, 3, 3), offset)  # into each geom's frame
        outside = np.maximum(np.abs(local - self._surface_centre) - self._surface_half, 0.0)
        squared = np.add.reduce(outside * outside, axis=1)  # np.linalg.norm's own sum, without its checks
        # The nearest per object; its root is the nearest root (a correctly rounded root is monotonic).
        nearest = np.sqrt(np.minimum.reduceat(squared, self._surface_starts))
        if len(self._surface_objects) == len(self.object_names):  # every object has geoms
            return nearest
        out = np.full(len(self.object_names), np.nan)  # an object without geoms
        out[self._surface_objects] = nearest
        return out


def _touch(
    masks: np.ndarray, geom1: np.ndarray, geom2: np.ndarray, other1: np.ndarray, other2: np.ndarray
) -> np.ndarray:
    """Per object: some active contact pairs one of its geoms with a geom of the other group, in either order (as
    robosuite's ``check_contact`` decides it). ``masks``: (K, ngeom) each object's geoms; ``geom1``/``geom2``:
    (ncon,) each contact's geoms; ``other1``/``other2``: (ncon,) whether they are the other group's."""
    touching = np.concatenate((geom1[other2], geom2[other1]))  # the geoms paired with one of the other group
    return masks[:, touching].any(axis=1)
