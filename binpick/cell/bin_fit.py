"""Fit the bin of a cell once, from one capture, as a box the import crops every capture to.

The support plane (table or bin floor) comes first; the bin is the connected region of what
stands on it nearest to where the camera looks (the optical axis meets the plane there, as a bin
camera is mounted), and its footprint is that region's smallest enclosing rectangle. The box is
given in its own frame (`T_cam_from_bin`: origin at the footprint's centre on the plane, z up
toward the camera, x along the long side), as import_capture's region of interest takes it, for
the user to check in the recording and keep in params.yaml. Each side's wall is as high as its rim
was measured along most of the side: parts heaped over a low box's rim raise the box, not its
walls, and a heap on a table has none; the gripper is not kept off a wall that is not there.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.spatial import ConvexHull, QhullError

from binpick.cell.bin_box import BinBox
from binpick.geometry.pointcloud import plane_frame
from binpick.scene.cleaning import bin_reference_point

# Occupancy grid of what stands on the plane; gaps up to one cell join a region.
GRID_CELL_M = 0.005
# The box reaches this far above the tallest of most points of the region (percentile below).
HEIGHT_MARGIN_M = 0.02
HEIGHT_PERCENTILE = 98.0
# What a fitted box may be before it is taken for the table, the room or a wall, not a bin.
# Industrial bins and pallet boxes reach about 1.2 x 1.0 x 0.8 m (a Euro pallet box) ...
MAX_BIN_SIDE_M = 1.5
MAX_BIN_HEIGHT_M = 1.0
# ... hold a part across their shorter side and are not tens of parts long ...
MIN_PARTS_ACROSS = 1.0
MAX_PARTS_ALONG = 25.0
# ... and a bin camera looks into the bin: its up axis within this of the camera's view.
MAX_VIEW_TILT_DEG = 60.0
# A side's wall reaches the height that the points within WALL_BAND_M inside the side reach in
# WALL_MIN_COVERAGE of its WALL_STEP_M steps: a rim runs the whole side, while a heap's outline
# touches its rectangle at a few parts only (and a part over the rim only raises a step). A rim is
# also level: in WALL_MIN_LEVEL of the steps its top lies within WALL_LEVEL_M of that height; a
# row of parts along the side (cups lying end to end) rises and falls from step to step.
WALL_BAND_M = 0.02
WALL_STEP_M = 0.01
WALL_MIN_COVERAGE = 0.7
WALL_LEVEL_M = 0.005
WALL_MIN_LEVEL = 0.6


def min_area_rectangle(uv: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """Smallest rectangle around 2-D points (n, 2): (centre (2,), angle of its first side in
    radians, half sizes (2,), first side the longer). Rotating calipers over the hull's edges."""
    try:
        hull = uv[ConvexHull(uv).vertices]
    except QhullError:
        hull = uv
    best = (np.inf, 0.0, np.zeros(2), np.zeros(2))
    edges = np.diff(np.vstack([hull, hull[:1]]), axis=0)
    for angle in np.unique(np.mod(np.arctan2(edges[:, 1], edges[:, 0]), np.pi / 2)):
        c, s = np.cos(angle), np.sin(angle)
        rot = hull @ np.array([[c, -s], [s, c]])  # coordinates along the rotated axes
        lo, hi = rot.min(0), rot.max(0)
        area = float(np.prod(hi - lo))
        if area < best[0]:
            centre = ((lo + hi) / 2) @ np.array([[c, s], [-s, c]])
            best = (area, float(angle), centre, (hi - lo) / 2)
    _, angle, centre, half = best
    if half[1] > half[0]:
        angle, half = angle + np.pi / 2, half[::-1]
    return centre, angle, half


def fit_bin_box(points_m: np.ndarray, floor: np.ndarray, keep_above_m: float) -> BinBox:
    """The bin standing on the support plane `floor` (a, b, c, d; normal toward the camera).

    points_m : (n, 3) camera frame, metres (a voxel grid of the capture is plenty).
    Raises ValueError when nothing stands on the plane.
    """
    n = floor[:3]
    height = points_m @ n + floor[3]
    above = points_m[height > keep_above_m]
    if len(above) < 10:
        raise ValueError("nothing stands on the support plane")
    axes, origin = plane_frame(floor)
    uv = (above - origin) @ axes.T
    lo = uv.min(0)
    cells = np.floor((uv - lo) / GRID_CELL_M).astype(np.int64)
    grid = np.zeros(cells.max(0) + 1, bool)
    grid[cells[:, 0], cells[:, 1]] = True
    regions, count = ndimage.label(ndimage.binary_closing(grid, iterations=1) | grid)
    ref_uv = (bin_reference_point(floor, points_m) - origin) @ axes.T
    labels = regions[cells[:, 0], cells[:, 1]]
    # The region nearest the reference point (containing it, usually).
    best, best_d = 0, np.inf
    for k in range(1, count + 1):
        member = labels == k
        if member.sum() < 10:
            continue
        d = float(np.min(np.linalg.norm(uv[member] - ref_uv, axis=1)))
        if d < best_d:
            best, best_d = k, d
    if best == 0:
        raise ValueError("no region of points stands on the support plane")
    member = labels == best
    centre, angle, half = min_area_rectangle(uv[member])
    x_axis = np.cos(angle) * axes[0] + np.sin(angle) * axes[1]
    z_axis = n / np.linalg.norm(n)
    y_axis = np.cross(z_axis, x_axis)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x_axis, y_axis, z_axis])
    T[:3, 3] = origin + centre[0] * axes[0] + centre[1] * axes[1]
    member_height = height[height > keep_above_m][member]
    top = float(np.percentile(member_height, HEIGHT_PERCENTILE)) + HEIGHT_MARGIN_M
    c, s = np.cos(angle), np.sin(angle)
    xy = (uv[member] - centre) @ np.array([[c, -s], [s, c]])  # along the box's x and y
    walls = np.minimum(measured_wall_heights(xy, member_height, half), top)
    return BinBox(
        T, np.array([-half[0], -half[1], keep_above_m]), np.array([half[0], half[1], top]), np.round(walls, 4)
    )


def measured_wall_heights(xy_m: np.ndarray, height_m: np.ndarray, half_m: np.ndarray) -> np.ndarray:
    """(4,) the height of each side's wall (order -x, +x, -y, +y), metres above the floor: what
    the points within WALL_BAND_M inside the side reach in WALL_MIN_COVERAGE of its steps, where
    WALL_MIN_LEVEL of the steps top out within WALL_LEVEL_M of it (a level rim); else 0 (no wall).

    xy_m : (n, 2) the region's points in the box's frame (centre at 0), metres; height_m : (n,)
    their heights above the floor; half_m : (2,) the box's half sizes.
    """
    heights = np.zeros(4)
    for k, (axis, sign) in enumerate(((0, -1.0), (0, 1.0), (1, -1.0), (1, 1.0))):
        along = 1 - axis
        near = sign * xy_m[:, axis] >= half_m[axis] - WALL_BAND_M
        n_steps = max(1, int(np.ceil(2 * half_m[along] / WALL_STEP_M)))
        steps = np.clip(((xy_m[near, along] + half_m[along]) / WALL_STEP_M).astype(np.int64), 0, n_steps - 1)
        step_top = np.zeros(n_steps)
        np.maximum.at(step_top, steps, height_m[near])
        height = float(np.quantile(step_top, 1.0 - WALL_MIN_COVERAGE))
        level = float(np.mean(np.abs(step_top - height) <= WALL_LEVEL_M))
        heights[k] = height if level >= WALL_MIN_LEVEL else 0.0
    return heights


def implausible(box: BinBox, part_diameter_m: float | None) -> list[str]:
    """Why a fitted box is unlikely to be the cell's bin (an empty list when nothing is): larger
    than a bin gets, too small or too long for the part (part_diameter_m; None: not checked),
    or seen from the side (the camera's view along the optical axis +z, camera frame)."""
    size = box.inner_max_m - box.inner_min_m
    side, height = float(max(size[0], size[1])), float(box.inner_max_m[2])
    problems = []
    if side > MAX_BIN_SIDE_M:
        problems.append(f"{side:.2f} m long, more than the {MAX_BIN_SIDE_M:g} m a bin gets")
    if height > MAX_BIN_HEIGHT_M:
        problems.append(f"{height:.2f} m high, more than the {MAX_BIN_HEIGHT_M:g} m a bin gets")
    if part_diameter_m is not None:
        if float(min(size[0], size[1])) < MIN_PARTS_ACROSS * part_diameter_m:
            problems.append(f"{min(size[0], size[1]):.2f} m across, narrower than the part ({part_diameter_m:.3f} m)")
        if side > MAX_PARTS_ALONG * part_diameter_m:
            problems.append(f"{side / part_diameter_m:.0f} part diameters long (at most {MAX_PARTS_ALONG:g})")
    up = box.T_cam_from_bin[:3, 2]
    tilt = float(np.degrees(np.arccos(np.clip(-up[2] / np.linalg.norm(up), -1.0, 1.0))))
    if tilt > MAX_VIEW_TILT_DEG:
        problems.append(f"its floor tilted {tilt:.0f} degrees from the camera's view (at most {MAX_VIEW_TILT_DEG:g})")
    return problems
