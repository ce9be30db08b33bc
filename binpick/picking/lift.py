"""Whether a grasped part comes out of the heap free: the part, moved back along the approach and
then up (or, the approach tilted, straight up), must not push into anything that lies ahead of
it (a neighbour lying across it, a part hooked through it, the bin's rim over it). The gripper
check sweeps the tool; this sweeps the part it holds, which the arm's check sees only from the
lift on.

Frames: the camera's; metres.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

# A point of the part's surface leads a move when its outward normal makes at most this angle with
# the move's direction (about 80 degrees): the side walls parallel to the move do not push into a
# neighbour that merely touches them.
LEADING_COS = 0.17
# An obstacle point counts only this many of them ahead of the part: noise above a surface (a few
# stray points the part's own did not take) is not a neighbour.
MIN_BLOCKING_POINTS = 5
# A move within about 10 degrees of parallel to a known surface (a bin wall) slides along it: the
# surface's points are not run into (a part resting against a wall is lifted up along it).
SLIDE_SIN = 0.17
# An approach within this angle of the bin's down axis (cosine; about 5 degrees) leaves along the
# approach only: straight up is the same way out.
SAME_WAY_COS = 0.996
# A part resting against a bin wall leaves it at this angle at least (degrees), not along it: the
# arm's way up drifts toward the wall by a degree or so (a joint-space move, the bin's up axis
# estimated from the capture), and a part pressed between a wall and a neighbour then holds fast.
# Bench cell: a ring screw in a corner of its bin, lifted straight up along both walls, pressed
# 29 N on them with the tool 0.4 mm off its line after 16 mm and tore off its 14.5 N cup.
LEAVE_WALL_DEG = 6.0


def walls_touched(surface_m: np.ndarray, centre_m: np.ndarray, planes: np.ndarray, touch_m: float) -> np.ndarray:
    """(k, 3) unit normals, facing the part, of the planes among `planes` (w, 4: a, b, c, d with
    a x + b y + c z + d = 0; the bin's side walls) that lie within touch_m of the part's surface
    sample surface_m (n, 3), whose centre_m (3,) is inside the bin; same frame, metres."""
    planes = np.asarray(planes, dtype=np.float64).reshape(-1, 4)
    surface_m = np.asarray(surface_m, dtype=np.float64).reshape(-1, 3)
    if len(planes) == 0 or len(surface_m) == 0:
        return np.zeros((0, 3))
    planes = planes / np.linalg.norm(planes[:, :3], axis=1, keepdims=True)
    planes = planes * np.where(planes[:, :3] @ np.asarray(centre_m, float) + planes[:, 3] < 0.0, -1.0, 1.0)[:, None]
    nearest = np.min(surface_m @ planes[:, :3].T + planes[:, 3], axis=0)
    return planes[nearest <= touch_m, :3]


def way_outs(
    approach: np.ndarray, up: np.ndarray, straight_up: bool = True, walls: np.ndarray | None = None
) -> list[np.ndarray]:
    """The directions (unit, the frame of approach (3,) and up (3,)) a grasped part may leave by,
    first choice first: back along the approach, retracing the path the gripper check cleared on
    the way in; then, when straight_up and the approach is tilted, straight up the bin's axis. Pulled back along
    a tilted approach a part is dragged sideways through its neighbours: on the ring screw's
    curved faces (approaches up to 49 degrees from the vertical) every grasp of a heap of 10-20
    did, though nothing lay above the parts.

    walls (k, 3): the unit normals, facing the part, of the walls it rests against (walls_touched):
    every way out leaves them at LEAVE_WALL_DEG at least. Back along an approach that does not is
    left out (straight_up false: kept, the only way allowed), and up is tilted away from them (not
    when they face each other, a part across the bin)."""
    back = -np.asarray(approach, dtype=np.float64) / np.linalg.norm(approach)
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    if not straight_up:
        return [back]
    normals = np.zeros((0, 3)) if walls is None else np.asarray(walls, dtype=np.float64).reshape(-1, 3)
    leave_sin = np.sin(np.radians(LEAVE_WALL_DEG))
    away = np.sum(normals - np.outer(normals @ up, up), axis=0)
    if np.linalg.norm(away) > 1e-6:
        away /= np.linalg.norm(away)
        up = np.cos(np.radians(LEAVE_WALL_DEG)) * up + leave_sin * away
    # A millimetre in a metre short of the angle still leaves (the tilted up itself, rounded).
    leaves = bool(np.all(normals @ back >= leave_sin - 1e-3))
    if leaves and float(back @ up) >= SAME_WAY_COS:
        return [back]
    return [back, up] if leaves else [up]


def lift_blockers(
    surface_m: np.ndarray,
    normals: np.ndarray,
    moves: list[tuple[np.ndarray, float]],
    obstacles_m: np.ndarray,
    sources: np.ndarray,
    radius_m: float,
    contact_m: float,
    obstacle_normals: np.ndarray | None = None,
) -> dict[int, int]:
    """The sources of the obstacles the part runs into on its way out, with how many of their
    points it runs into (at least MIN_BLOCKING_POINTS each).

    surface_m (n, 3), normals (n, 3): the part's surface sample at its pose and outward normals;
    moves: (direction (3,), unit; distance m) in order, each starting where the last ended;
    obstacles_m (k, 3) with sources (k,) int: what may lie in the way (the part's own measured
    points and its own model already left out); radius_m: how close, across the move, an obstacle
    point must pass a leading surface point to be run into; contact_m: an obstacle point less than
    this ahead of the part at the start is in contact with it (parts in a heap touch) or is the
    part's own surface measured with noise (on a sloped face the surface ahead of a point rises
    within radius_m across): not run into. obstacle_normals (k, 3): the unit normal of the surface
    an obstacle point lies on (a wall's), NaN where none is known: a move within SLIDE_SIN of
    parallel to it slides along it.
    """
    surface_m = np.asarray(surface_m, dtype=np.float64).reshape(-1, 3)
    obstacles_m = np.asarray(obstacles_m, dtype=np.float64).reshape(-1, 3)
    sources = np.asarray(sources).reshape(-1)
    hit = np.zeros(len(obstacles_m), bool)
    offset = np.zeros(3)
    for direction, distance_m in moves:
        u = np.asarray(direction, dtype=np.float64) / np.linalg.norm(direction)
        leading = surface_m[np.asarray(normals) @ u >= LEADING_COS] + offset
        offset = offset + u * distance_m
        if len(leading) == 0 or len(obstacles_m) == 0 or distance_m <= 0:
            continue
        # Only what lies ahead of the part's rearmost leading point, and across the move: both
        # projected onto the plane normal to it, paired within radius_m there.
        along = obstacles_m @ u
        ahead_of_part = along > float(np.min(leading @ u)) + contact_m
        if obstacle_normals is not None:
            ahead_of_part &= ~(np.abs(np.asarray(obstacle_normals, dtype=np.float64) @ u) < SLIDE_SIN)
        candidates = np.flatnonzero(ahead_of_part)
        if len(candidates) == 0:
            continue
        basis = _across(u)
        leading_2d = leading @ basis
        candidates_2d = obstacles_m[candidates] @ basis
        across = in_footprint(leading_2d, candidates_2d, radius_m)
        candidates, candidates_2d = candidates[across], candidates_2d[across]
        if len(candidates) == 0:
            continue
        pairs = cKDTree(leading_2d).sparse_distance_matrix(cKDTree(candidates_2d), radius_m, output_type="ndarray")
        if len(pairs) == 0:
            continue
        ahead = along[candidates[pairs["j"]]] - leading[pairs["i"]] @ u
        hit[candidates[pairs["j"][(ahead > contact_m) & (ahead <= distance_m + contact_m)]]] = True
    found, counts = np.unique(sources[hit], return_counts=True)
    return {int(s): int(n) for s, n in zip(found, counts, strict=True) if n >= MIN_BLOCKING_POINTS}


def _across(u: np.ndarray) -> np.ndarray:
    """(3, 2): two unit axes perpendicular to the unit direction u (3,) and to each other; points
    times it are their coordinates in the plane across u."""
    e1 = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(u, e1)], axis=1)


def in_footprint(footprint: np.ndarray, points: np.ndarray, radius_m: float) -> np.ndarray:
    """(k,) bool: the points (k, 2) that may lie within radius_m of a footprint point (m, 2), a
    superset of those that do: cells of at least radius_m on a side, the footprint's cells and
    their neighbours. A 0.44 m gear shaft's lift met 95,000 obstacle points ahead of it, of
    which a few hundred lay across its path: a kd-tree over them all took 43 ms a lift, the
    cells 3 ms."""
    footprint = np.asarray(footprint, dtype=np.float64).reshape(-1, 2)
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if len(footprint) == 0 or len(points) == 0:
        return np.zeros(len(points), bool)
    lo = footprint.min(axis=0) - radius_m
    extent = footprint.max(axis=0) + radius_m - lo
    # At most about a million cells, whatever the part's size against the radius.
    cell = max(radius_m, float(np.max(extent)) / 1000.0, 1e-9)
    shape = np.floor(extent / cell).astype(np.int64) + 3  # one cell of margin on each side
    occupied = np.zeros(tuple(shape), bool)
    ij = np.floor((footprint - lo) / cell).astype(np.int64) + 1
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            occupied[ij[:, 0] + di, ij[:, 1] + dj] = True
    pij = np.floor((points - lo) / cell).astype(np.int64) + 1
    inside = np.all((pij >= 0) & (pij < shape), axis=1)
    out = np.zeros(len(points), bool)
    out[inside] = occupied[pij[inside, 0], pij[inside, 1]]
    return out


def across_the_way_out(surface_m: np.ndarray, up: np.ndarray, points_m: np.ndarray, reach_m: float) -> np.ndarray:
    """(k,) bool: the points (k, 3) within reach_m of the part's outline seen down the bin's up
    axis (surface_m (n, 3), the part's surface at its pose; up (3,)). A way out tilted at most a
    from up, moved d along it and then straight up, runs into nothing farther than
    (d + contact) sin a + radius from that outline (lift_blockers' contact and radius): with
    reach_m that, the points kept hold every blocker of every grasp of the part. About a gear
    shaft the 170,000 obstacle points of its 1.4 m ball fall to those along its 0.44 m outline."""
    surface = np.asarray(surface_m, dtype=np.float64).reshape(-1, 3)
    points = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    if len(surface) == 0 or len(points) == 0:
        return np.zeros(len(points), bool)
    basis = _across(np.asarray(up, dtype=np.float64) / np.linalg.norm(up))
    outline = surface @ basis
    flat = points @ basis
    # Cells at least the reach wide first (cheap, a superset), then the exact distance.
    near = in_footprint(outline, flat, reach_m)
    if near.any():
        distance, _ = cKDTree(outline).query(flat[near], distance_upper_bound=reach_m * (1.0 + 1e-9))
        near[np.flatnonzero(near)[~np.isfinite(distance)]] = False
    return near
