"""The arm against what the camera measured: a point of the arm collides where it lies behind a
measured surface along the camera's ray, or within the clearance in front of one. Space the camera
could not see behind what it measured counts as occupied (a part's hidden side, the floor under
the parts); space outside the camera's view counts as free.

Camera frame (OpenCV), metres. The z-buffer is registration.visibility.DepthView.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import minimum_filter

from binpick.registration.visibility import DepthView, measured_depth

# A window wider than this many cells is capped (a clearance of centimetres at a close wall): the
# check stays cheap, and a wider window than the cap only matters within centimetres of the camera.
MAX_WINDOW_CELLS = 129


def obstacle_view(view: DepthView, reach_m: float) -> DepthView:
    """The z-buffer with each cell holding the least depth within reach_m of it sideways (a
    window as wide as reach_m at the nearest measured depth, so wider than reach_m further
    away): a point is then within reach_m of a surface sideways when it is behind this depth."""
    if view.is_empty:
        return view
    finite = view.depth_m[np.isfinite(view.depth_m)]
    if len(finite) == 0:
        return view
    nearest_m = max(float(np.percentile(finite, 1.0)), 1e-3)
    half = int(np.ceil(reach_m * view.K[0, 0] / nearest_m))
    size = min(2 * half + 1, MAX_WINDOW_CELLS)
    return DepthView(minimum_filter(view.depth_m, size=size, mode="nearest"), view.K)


def collides(points_cam: np.ndarray, view: DepthView, clearance_m: float | np.ndarray) -> np.ndarray:
    """(n,) bool: points (n, 3) lying behind, or within clearance_m (a number, or one per point)
    in front of, the depth of `view` (an obstacle_view) along their ray."""
    measured = measured_depth(np.asarray(points_cam, dtype=np.float64).reshape(-1, 3), view)
    return np.isfinite(measured) & (points_cam[:, 2] >= measured - clearance_m)


def near_planes(points_cam: np.ndarray, planes: np.ndarray, distance_m: float) -> np.ndarray:
    """(n,) bool: points (n, 3) within distance_m of any of the planes (k, 4: unit normal n and d
    with n . x + d = 0)."""
    planes = np.asarray(planes, dtype=np.float64).reshape(-1, 4)
    if len(planes) == 0:
        return np.zeros(len(points_cam), bool)
    d = np.abs(points_cam @ planes[:, :3].T + planes[:, 3])
    return np.any(d <= distance_m, axis=1)
