"""Where the arm puts the part: the tool poses that set a part, held by a grasp, at the cell's
place (params `cell.place`: a fixture, a conveyor or a drop zone). Frames: base (the robot's),
tool (the tool centre point, z the approach), model (the part's CAD frame); metres."""

from __future__ import annotations

import numpy as np

from binpick.geometry.transforms import invert_T
from binpick.params import PlaceParams

# Turns tried about the vertical at a conveyor and a drop zone.
PLACE_TURNS = 12


def place_tool_poses(place: PlaceParams, T_model_from_tool: np.ndarray, centre_m: np.ndarray) -> np.ndarray:
    """(k, 4, 4) T_base_from_tcp that put a part held by the grasp T_model_from_tool where the place
    wants it: fixture: the part at T_base_from_part exactly (T_base_from_part @ T_model_from_tool);
    conveyor: that turned about the vertical through the part's place; drop: the part's centre
    (centre_m, model frame) at the place's position, the tool straight down, any turn."""
    T_target = np.asarray(place.T_base_from_part, dtype=float)
    if place.kind == "fixture":
        return (T_target @ T_model_from_tool)[None]
    angles = 2.0 * np.pi * np.arange(PLACE_TURNS) / PLACE_TURNS
    if place.kind == "conveyor":
        out = []
        for a in angles:
            spin = np.eye(4)
            spin[:3, :3] = _rz(a)
            out.append(_about(T_target[:3, 3]) @ spin @ _about(-T_target[:3, 3]) @ T_target @ T_model_from_tool)
        return np.array(out)
    centre_tool = invert_T(T_model_from_tool)[:3, :3] @ centre_m + invert_T(T_model_from_tool)[:3, 3]
    down = np.diag([1.0, -1.0, -1.0])  # tool z along the base's -z
    out = []
    for a in angles:
        R = _rz(a) @ down
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = T_target[:3, 3] - R @ centre_tool
        out.append(T)
    return np.array(out)


def _rz(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _about(p: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = p
    return T
