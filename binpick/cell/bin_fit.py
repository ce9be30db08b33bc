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

from binpick.cell.bin_box import WALL_SIDES, BinBox
from binpick.geometry.pointcloud import fit_plane_ransac, plane_frame, voxel_downsample_indices
from binpick.geometry.transforms import transform_points
from binpick.params import ImportCaptureParams
from binpick.picking.measured import point_spacing_m
from binpick.scene.cleaning import bin_reference_point

# Occupancy grid of what stands on the plane; gaps up to one cell join a region. A cell is at
# least the capture's point spacing (a coarse sensor far away leaves 8-12 mm between points, and a
# finer grid would break a bin's rim into specks).
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
# ... or within this many times the depth noise the support plane shows, on a noisier sensor.
WALL_LEVEL_NOISE = 2.0
# A box side whose foot lies within this share of the view's extent from its edge (or beyond) is
# cut by the view: the capture ends there, not the bin.
VIEW_EDGE_SHARE = 0.01
# A region of fewer points is a speck of noise, not something standing on the plane.
MIN_REGION_POINTS = 10
# Points within this many standard deviations of the plane's scatter are the plane's, not on it.
PLANE_SCATTER_SIGMAS = 3.0


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


def valid_points(xyz_m: np.ndarray, min_range_m: float) -> np.ndarray:
    """(n,) bool: which points of a capture xyz_m (n, 3; NaN: no return), camera frame, the bin is
    fitted from: measured and at least min_range_m from the camera."""
    return np.all(np.isfinite(xyz_m), axis=1) & (np.einsum("ij,ij->i", xyz_m, xyz_m) >= min_range_m**2)


def fit_capture_bin(points_m: np.ndarray, settings: ImportCaptureParams, seed: int) -> BinBox:
    """The bin of one capture: the support plane (RANSAC with the import's plane settings) and the
    box standing on it (fit_bin_box), on a voxel grid of the points (at least 2 mm: the box does
    not need more, and a full frame would make the plane fit slow).

    points_m : (n, 3) the capture's valid points, camera frame, metres.
    Raises ValueError when no plane or nothing on it is found.
    """
    grid = points_m[voxel_downsample_indices(points_m, max(settings.voxel_size_m, 0.002))]
    floor, _ = fit_plane_ransac(
        grid,
        settings.plane_threshold_m,
        settings.plane_ransac_iterations,
        seed,
        settings.plane_ransac_confidence,
        min_distance_m=settings.min_range_m,
    )
    if floor[3] < 0:  # the normal toward the camera
        floor = -floor
    return fit_bin_box(grid, floor, settings.keep_above_plane_m)


def fit_bin_box(points_m: np.ndarray, floor: np.ndarray, keep_above_m: float) -> BinBox:
    """The bin standing on the support plane `floor` (a, b, c, d; normal toward the camera).

    points_m : (n, 3) camera frame, metres (a voxel grid of the capture is plenty).
    Raises ValueError when nothing stands on the plane.
    """
    n = floor[:3]
    height = points_m @ n + floor[3]
    on_plane = np.abs(height) <= keep_above_m
    # The plane's own scatter (a robust standard deviation, 1.4826 MAD): a coarse sensor's floor
    # (depth steps of 8-12 mm at 2 m) pokes above keep_above_m in specks that would join the bin
    # to everything around it, so what stands on the plane stands clear of that scatter too. The
    # box's floor is there as well: a crop that kept the scatter's top would hand the cleaning a
    # layer of specks to take for the floor, a few centimetres up the parts.
    noise_m = 1.4826 * float(np.median(np.abs(height[on_plane]))) if on_plane.any() else 0.0
    floor_m = max(keep_above_m, PLANE_SCATTER_SIGMAS * noise_m)
    standing = height > floor_m
    above = points_m[standing]
    if len(above) < 10:
        raise ValueError("nothing stands on the support plane")
    cell_m = max(GRID_CELL_M, point_spacing_m(points_m))
    axes, origin = plane_frame(floor)
    uv = (above - origin) @ axes.T
    lo = uv.min(0)
    cells = np.floor((uv - lo) / cell_m).astype(np.int64)
    grid = np.zeros(cells.max(0) + 1, bool)
    grid[cells[:, 0], cells[:, 1]] = True
    # A bin standing on the plane is a ring of walls: what the ring encloses (parts clear of the
    # walls, the floor between them when the plane is the bin's own floor) belongs to it.
    regions, count = ndimage.label(ndimage.binary_fill_holes(ndimage.binary_closing(grid, iterations=1) | grid))
    ref_uv = (bin_reference_point(floor, points_m) - origin) @ axes.T
    labels = regions[cells[:, 0], cells[:, 1]]
    best = _bin_region(uv, labels, count, ref_uv)
    if best == 0:
        raise ValueError("no region of points stands on the support plane")
    centre, angle, half = min_area_rectangle(uv[labels == best])
    c, s = np.cos(angle), np.sin(angle)
    # Everything within the rim's rectangle is the bin's: the parts clear of a broken ring's walls
    # and those heaped over them.
    xy = (uv - centre) @ np.array([[c, -s], [s, c]])  # along the box's x and y
    member = np.all(np.abs(xy) <= half, axis=1) | (labels == best)
    x_axis = np.cos(angle) * axes[0] + np.sin(angle) * axes[1]
    z_axis = n / np.linalg.norm(n)
    y_axis = np.cross(z_axis, x_axis)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x_axis, y_axis, z_axis])
    T[:3, 3] = origin + centre[0] * axes[0] + centre[1] * axes[1]
    member_height = height[standing][member]
    top = float(np.percentile(member_height, HEIGHT_PERCENTILE)) + HEIGHT_MARGIN_M
    walls = np.minimum(
        measured_wall_heights(
            xy[member], member_height, half, max(WALL_STEP_M, cell_m), max(WALL_LEVEL_M, WALL_LEVEL_NOISE * noise_m)
        ),
        top,
    )
    return BinBox(T, np.array([-half[0], -half[1], floor_m]), np.array([half[0], half[1], top]), np.round(walls, 4))


def _bin_region(uv: np.ndarray, labels: np.ndarray, count: int, ref_uv: np.ndarray) -> int:
    """The label (1..count; 0: none) of the bin among the regions standing on the plane: the one
    whose smallest rectangle around it is largest among those holding the reference point (a
    ring of walls, even broken into pieces, holds the point the camera looks at; a part clear of
    the walls near that point does not enclose it), else the region nearest the point (a heap on
    a table). uv : (n, 2) the points on the plane; labels : (n,) their regions (0: none)."""
    best, best_area = 0, 0.0
    nearest, nearest_d = 0, np.inf
    for k in range(1, count + 1):
        member = labels == k
        if member.sum() < MIN_REGION_POINTS:
            continue
        d = float(np.min(np.linalg.norm(uv[member] - ref_uv, axis=1)))
        if d < nearest_d:
            nearest, nearest_d = k, d
        centre, angle, half = min_area_rectangle(uv[member])
        c, s = np.cos(angle), np.sin(angle)
        if np.all(np.abs((ref_uv - centre) @ np.array([[c, -s], [s, c]])) <= half) and np.prod(half) > best_area:
            best, best_area = k, float(np.prod(half))
    return best if best else nearest


def measured_wall_heights(
    xy_m: np.ndarray,
    height_m: np.ndarray,
    half_m: np.ndarray,
    step_m: float = WALL_STEP_M,
    level_m: float = WALL_LEVEL_M,
) -> np.ndarray:
    """(4,) the height of each side's wall (order -x, +x, -y, +y), metres above the floor: what
    the points within WALL_BAND_M inside the side reach in WALL_MIN_COVERAGE of its steps (step_m
    long), where WALL_MIN_LEVEL of the steps top out within level_m of it (a level rim); else 0
    (no wall).

    xy_m : (n, 2) the region's points in the box's frame (centre at 0), metres; height_m : (n,)
    their heights above the floor; half_m : (2,) the box's half sizes.
    """
    heights = np.zeros(4)
    for k, (axis, sign) in enumerate(((0, -1.0), (0, 1.0), (1, -1.0), (1, 1.0))):
        along = 1 - axis
        near = sign * xy_m[:, axis] >= half_m[axis] - WALL_BAND_M
        n_steps = max(1, int(np.ceil(2 * half_m[along] / step_m)))
        steps = np.clip(((xy_m[near, along] + half_m[along]) / step_m).astype(np.int64), 0, n_steps - 1)
        step_top = np.zeros(n_steps)
        np.maximum.at(step_top, steps, height_m[near])
        height = float(np.quantile(step_top, 1.0 - WALL_MIN_COVERAGE))
        level = float(np.mean(np.abs(step_top - height) <= level_m))
        heights[k] = height if level >= WALL_MIN_LEVEL else 0.0
    return heights


def sides_out_of_view(box: BinBox, points_m: np.ndarray) -> list[str]:
    """The box's sides (WALL_SIDES names) that reach the edge of the camera's view: the view cuts
    the bin there, and the box ends where the capture does, not at the bin's rim.

    points_m : (n, 3) the capture's valid points, camera frame (optical axis +z), metres; the view
    is their extent in x/z and y/z, less VIEW_EDGE_SHARE of it.
    """
    ahead = points_m[points_m[:, 2] > 0]
    if len(ahead) == 0:
        return []
    slopes = ahead[:, :2] / ahead[:, 2:3]
    lo, hi = slopes.min(0), slopes.max(0)
    margin = VIEW_EDGE_SHARE * (hi - lo)
    lo, hi = lo + margin, hi - margin
    a, b = np.asarray(box.inner_min_m, float), np.asarray(box.inner_max_m, float)
    steps = np.linspace(0.0, 1.0, 11)
    out = []
    for k, (axis, at) in enumerate(((0, a[0]), (0, b[0]), (1, a[1]), (1, b[1]))):
        along = 1 - axis
        edge = np.zeros((len(steps), 3))
        edge[:, axis] = at
        edge[:, along] = a[along] + steps * (b[along] - a[along])  # the side's foot on the floor
        cam = transform_points(box.T_cam_from_bin, edge)
        cam = cam[cam[:, 2] > 0]
        s = cam[:, :2] / cam[:, 2:3]
        if len(s) < len(steps) or np.any((s < lo) | (s > hi)):
            out.append(WALL_SIDES[k])
    return out


def implausible(box: BinBox, part_diameter_m: float | None, points_m: np.ndarray | None = None) -> list[str]:
    """Why a fitted box is unlikely to be the cell's bin (an empty list when nothing is): larger
    than a bin gets, too small or too long for the part (part_diameter_m; None: not checked),
    seen from the side (the camera's view along the optical axis +z, camera frame), or, given the
    capture's valid points (n, 3), ending at the edge of the view (sides_out_of_view)."""
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
    cut = sides_out_of_view(box, points_m) if points_m is not None else []
    if cut:
        problems.append(f"the camera's view ends at its {', '.join(cut)} side (the rim there is not in the capture)")
    return problems
