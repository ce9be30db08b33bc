"""Whether a simulated gripper holds a part, and whether the part arrived: kernels on the part's
true mesh (binpick/cell/simulation.py asks them; the cup's seal: picking/seal.py). Model frame of
the part, metres."""

from __future__ import annotations

import numpy as np
import trimesh

from binpick.params import PlaceParams
from binpick.picking.seal import CONTACT_TOLERANCE_M


def jaws_touch(mesh: trimesh.Trimesh, pads_model: np.ndarray) -> bool:
    """Whether both jaw pads' centres (2, 3), model frame, lie within CONTACT_TOLERANCE_M of the
    part's true surface."""
    _, distance, _ = trimesh.proximity.closest_point(mesh, pads_model)
    return bool(np.all(distance <= CONTACT_TOLERANCE_M))


def arrived(T_base_from_model: np.ndarray, centre_model_m: np.ndarray, place: PlaceParams) -> bool:
    """Whether a part at T_base_from_model (4, 4, base frame, metres) is where the place wants it:
    `drop` its box's centre (centre_model_m, model frame) within tolerance_m of the place's
    position; `conveyor` its position within tolerance_m and its z within tolerance_deg;
    `fixture` its position and whole turn within tolerance."""
    T = np.asarray(T_base_from_model, dtype=float)
    T_target = np.asarray(place.T_base_from_part, dtype=float)
    if place.kind == "drop":
        centre = T[:3, :3] @ centre_model_m + T[:3, 3]
        return bool(np.linalg.norm(centre - T_target[:3, 3]) <= place.tolerance_m)
    if np.linalg.norm(T[:3, 3] - T_target[:3, 3]) > place.tolerance_m:
        return False
    if place.kind == "conveyor":
        tilt = np.degrees(np.arccos(np.clip(T[:3, 2] @ T_target[:3, 2], -1.0, 1.0)))
        return bool(tilt <= place.tolerance_deg)
    R = T[:3, :3].T @ T_target[:3, :3]
    angle = np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))
    return bool(angle <= place.tolerance_deg)
