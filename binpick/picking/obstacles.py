"""The gripper against the obstacle points of a pick plan (picking/plan.py): what the tool, swept
along its approach or moved off it, comes near, and its clearance. Camera frame, metres.

Obstacle points carry a source: -1 the captured points, -2 the bin (the given box, or the walls found
at import where the camera did not see them), k >= 0 detected part k.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

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


def unseen_walls(
    captured_m: np.ndarray,
    walls: np.ndarray,
    up: np.ndarray,
    plane: np.ndarray | None,
    band_m: float,
    spacing_m: float,
    seen_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The stretches of the bin's walls the camera did not measure, as obstacle points: on each
    wall plane, a grid spacing_m apart over the rectangle its measured points span (along the
    floor their 1st to 99th percentile; up from the support plane, or their lowest, to their
    99th percentile, the rim), where no captured point lies within seen_m. Behind a part, or
    beyond the edge of an oblique view, a wall is a wall all the same: a tool tilted 34 degrees
    toward a wall the part hid from a camera 18 degrees off the vertical went 1.1 mm into it with
    the nearest captured point 12 mm away.

    captured_m (n, 3): what the camera measured; walls (w, 4): the wall planes found at import
    (unit normals); up (3,) unit: the bin's up axis; plane (4,): the support plane with normal
    up (None: none found); band_m: a wall's points lie within this of its plane. Returns the
    points (k, 3) and their wall's unit normal (k, 3). Camera frame, metres.
    """
    captured = np.asarray(captured_m, dtype=np.float64).reshape(-1, 3)
    walls = np.asarray(walls, dtype=np.float64).reshape(-1, 4)
    up = np.asarray(up, dtype=np.float64)
    points: list[np.ndarray] = [np.zeros((0, 3))]
    normals: list[np.ndarray] = [np.zeros((0, 3))]
    if len(captured) == 0 or len(walls) == 0 or spacing_m <= 0:
        return points[0], normals[0]
    for wall in walls:
        norm = float(np.linalg.norm(wall[:3]))
        n, origin = wall[:3] / norm, -wall[3] / norm * wall[:3] / norm  # origin: the plane's point nearest the camera
        along = np.cross(up, n)
        off_plane = np.abs(captured @ n + wall[3] / norm)
        on = captured[off_plane <= band_m]
        if len(on) < 3 or np.linalg.norm(along) < 0.5:  # no points, or not standing across the floor
            continue
        along /= np.linalg.norm(along)
        rise = np.cross(n, along)  # up the wall, within its plane
        rise *= np.sign(rise @ up)
        # A point of the plane is origin + u along + v rise, u and v its dot products with them.
        u, v = on @ along, on @ rise
        u0, u1 = np.percentile(u, [1.0, 99.0])
        v1 = float(np.percentile(v, 99.0))
        # From where the wall meets the support plane (up . x + d = 0; along is level).
        v0 = float(-(plane[:3] @ origin + plane[3]) / (plane[:3] @ rise)) if plane is not None else float(np.min(v))
        if v1 <= v0 or u1 <= u0:
            continue
        U, V = np.meshgrid(
            np.linspace(u0, u1, max(2, int(np.ceil((u1 - u0) / spacing_m)) + 1)),
            np.linspace(v0, v1, max(2, int(np.ceil((v1 - v0) / spacing_m)) + 1)),
            indexing="ij",
        )
        grid = origin + U.reshape(-1, 1) * along + V.reshape(-1, 1) * rise
        # A captured point within seen_m of a grid point (on the plane) lies within seen_m of the
        # plane: only those are searched, not the whole capture.
        seen = captured[off_plane <= seen_m]
        if len(seen):
            d, _ = cKDTree(seen).query(grid, distance_upper_bound=seen_m)
            unseen = grid[~np.isfinite(d)]
        else:
            unseen = grid
        points.append(unseen)
        normals.append(np.tile(n, (len(unseen), 1)))
    return np.concatenate(points), np.concatenate(normals)
