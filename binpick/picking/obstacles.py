"""The gripper against the obstacle points of a pick plan (picking/plan.py): what the tool, swept
along its approach or moved off it, comes near, and its clearance. Camera frame, metres.

Obstacle points carry a source: -1 the captured points, -2 the given bin, k >= 0 detected part k.
"""

from __future__ import annotations

import numpy as np

from binpick.geometry.transforms import invert_T, transform_points
from binpick.picking.gripper import covering_spheres, lowest_height, signed_distance, translated_poses

# Clearance is measured up to this far (a gripper in free space reports this).
CLEARANCE_CAP_M = 0.05
# ... by searches this wide first (then up to the cap), the nearest found in the first that finds one.
CLEARANCE_SEARCH_M = (0.01, 0.02)
# The tool's positions on a move off its own axis are checked this far apart (the margin widened
# by half of it: nothing within clearance_m of the move passes between two of them).
TOOL_STEP_M = 0.004
# Obstacle sources in reasons and counts.
CAPTURED, BIN, FLOOR = "captured points", "bin", "floor"


def source_name(s: int) -> str:
    """An obstacle's source as a cause."""
    return CAPTURED if s == -1 else BIN if s == -2 else str(int(s))


def tool_collisions(
    body, T_cam_from_tool, tree, obstacles, source, target, own, plane, clearance_m
) -> tuple[set[str], float]:
    """What the swept gripper comes within clearance_m of, and its clearance (capped; only
    computed when nothing is hit: a refused grasp's clearance is never used)."""
    hit: set[str] = set()
    clearance = CLEARANCE_CAP_M
    if plane is not None:
        low = lowest_height(body, T_cam_from_tool, plane)
        clearance = min(clearance, low)
        if low < clearance_m:
            hit.add(FLOOR)
    if tree is not None:
        # Hits first, from the few points within clearance_m of the body; the clearance, which
        # may look CLEARANCE_CAP_M far (tens of thousands of points), only for a grasp that passes.
        d, src = obstacle_distances(body, T_cam_from_tool, tree, obstacles, source, target, own, clearance_m)
        for s in np.unique(src[d < clearance_m]):
            hit.add(source_name(s))
        # The clearance by widening searches: a nearest point found within a search's margin is
        # the nearest of all (every point within the margin is gathered), so the wide, costly
        # search runs only for a grasp with nothing near it, and none beyond the floor's distance.
        if not hit:
            for margin in (*CLEARANCE_SEARCH_M, clearance):
                margin = min(margin, clearance)
                d, _ = obstacle_distances(body, T_cam_from_tool, tree, obstacles, source, target, own, margin)
                if len(d) and float(d.min()) <= margin:
                    clearance = float(d.min())
                    break
                if margin >= clearance:
                    break
    return hit, float(clearance)


def moved_tool_hits(tool, T_cam_from_tool, offset_m, tree, obstacles, source, target, own, clearance_m) -> set[str]:
    """What the tool (primitives, unswept) at T_cam_from_tool comes within clearance_m of moving
    straight by offset_m (3,, camera frame): checked at poses TOOL_STEP_M apart."""
    margin = clearance_m + TOOL_STEP_M / 2.0
    hit: set[str] = set()
    for T in translated_poses(T_cam_from_tool, offset_m, TOOL_STEP_M):
        d, src = obstacle_distances(tool, T, tree, obstacles, source, target, own, margin)
        hit.update(source_name(s) for s in np.unique(src[d < margin]))
    return hit


def obstacle_distances(
    body, T_cam_from_tool, tree, obstacles, source, target, own, margin_m
) -> tuple[np.ndarray, np.ndarray]:
    """Signed distances (k,) to the placed body of the obstacle points that may lie within
    margin_m of it (all of those, and some farther), with their sources (k,); the target's own
    points and its own model excluded."""
    centres, radii = covering_spheres(body, margin_m)
    mark = np.zeros(len(obstacles), bool)  # the union of the spheres' points
    for n in tree.query_ball_point(transform_points(T_cam_from_tool, centres), radii):
        mark[n] = True
    near = np.flatnonzero(mark)
    src = source[near]
    keep = (src != target) & ~own[near]
    near, src = near[keep], src[keep]
    if len(near) == 0:
        return np.zeros(0), src
    return signed_distance(transform_points(invert_T(T_cam_from_tool), obstacles[near]), body), src


def surface_normals(points_m: np.ndarray, planes: np.ndarray, band_m: float) -> np.ndarray:
    """(n, 3) the unit normal of the plane (k, 4: unit normal and d, n . x + d = 0) each point
    (n, 3) lies within band_m of (the nearest such), NaN for points on none; same frame, metres."""
    points = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    planes = np.asarray(planes, dtype=np.float64).reshape(-1, 4)
    out = np.full((len(points), 3), np.nan)
    if len(points) == 0 or len(planes) == 0:
        return out
    distance = np.abs(points @ planes[:, :3].T + planes[:, 3])
    nearest = np.argmin(distance, axis=1)
    on = distance[np.arange(len(points)), nearest] <= band_m
    out[on] = planes[nearest[on], :3]
    return out
