"""Turn a raw capture (camera frame, metres) into the clean scene the segmentation needs:
valid points in range and region, the support plane and optionally the bin walls removed,
optional outlier removal, a voxel grid, normals facing the camera."""

from __future__ import annotations

import logging

import numpy as np
from numba import njit, prange
from pykdtree.kdtree import KDTree

from binpick.cell.bin_box import BinBox, support_frame
from binpick.errors import BinpickError, NothingAboveTheFloor
from binpick.geometry.depth_noise import image_coordinates, local_noise_m
from binpick.geometry.pointcloud import first_in_each_voxel, fit_plane_ransac, sample_normals, statistical_outliers
from binpick.geometry.transforms import invert_T
from binpick.io.cloud import CleanCloud
from binpick.params import ImportCaptureParams
from binpick.registration.visibility import depth_view
from binpick.view import ViewParams, view_normals

log = logging.getLogger(__name__)

MIN_PLANE_FRACTION = 0.05  # a support plane holds at least this share of the points
# ... and has at most this share behind it, seen from the camera: a slab through a heap of
# objects has as many points behind it as in front.
MAX_BEHIND_FRACTION = 0.25
BEHIND_NOISE_SIGMAS = 3.0  # ... counted beyond the larger of the plane threshold and this much depth noise
WALL_MAX_COS_TO_FLOOR = 0.15  # walls stand within ~9 degrees of perpendicular to the floor
# Points whose normal is within ~45 degrees of the floor's are not searched for walls; the search
# draws from a sample of this many points (the normals of all of them cost 0.1 s a capture).
WALL_SEARCH_MAX_COS = 0.7
WALL_SEARCH_SAMPLE = 2000
MIN_POINTS = 10
WALL_INNER_SHARE = 0.8  # a bin wall has most of what is left on the bin's side
# A bin wall is longer along the floor than it stands high (a KLT box's short side: 1.4 times);
# the side of a part standing on the floor is not (a cup: 0.7, a ring screw on edge: about 1).
WALL_MIN_LENGTH_TO_HEIGHT = 1.2
# Its length is that of its longest run of points along the floor, runs split at gaps wider than
# this many voxels (the plane also passes through things far along it).
WALL_RUN_GAP_VOXELS = 5.0
# A bin is a box: each wall stands parallel or square to the first one found, within this angle
# (a plane along a diagonal row of parts is not a wall).
WALL_SQUARE_TOLERANCE_DEG = 10.0
# A wall's rim (its top face) lies within this of its inner face (a wall this thick at most), at
# the height of its top within this many plane thresholds.
WALL_RIM_M = 0.03
RIM_HEIGHT_THRESHOLDS = 3.0


def bin_reference_point(floor: np.ndarray, points: np.ndarray) -> np.ndarray:
    """A point inside the bin: where the optical axis meets the floor (the camera looks into the
    bin), or the points' centroid on the floor when the axis runs nearly parallel to it."""
    n, d = floor[:3], floor[3]
    if n[2] < -0.2:  # the normal faces the camera: the floor is ahead along +z
        return np.array([0.0, 0.0, -d / n[2]])
    c = points.mean(0)
    return c - (c @ n + d) * n


def _at_the_edge(
    others: np.ndarray, floor: np.ndarray, plane: np.ndarray, threshold_m: float, top_m: float = np.inf
) -> bool:
    """A bin wall stands at the edge of what is left: WALL_INNER_SHARE of the other points lie on
    one side of it. A plane through a heap of parts (the flank of a pile of long cylinders) has
    parts on both sides and is not a wall. The wall's own rim (top_m: the height of its top above
    the floor) lies beside its face and counts on neither side: in a bin nearly emptied the rims
    of the walls outnumbered the one part left leaning on the last wall, which was kept in the
    cloud and took the part's pose from the whole-scene pass."""
    to_plane = others @ plane[:3] + plane[3]
    rim = (np.abs(to_plane) <= WALL_RIM_M) & (
        np.abs(others @ floor[:3] + floor[3] - top_m) <= RIM_HEIGHT_THRESHOLDS * threshold_m
    )
    if rim.all():
        return True
    share = float((to_plane[~rim] > -threshold_m).mean())
    return max(share, 1.0 - share) >= WALL_INNER_SHARE


def _top_m(on_plane: np.ndarray, floor: np.ndarray) -> float:
    """The height above the floor of a wall plane's points' top (k, 3): its 99th percentile."""
    return float(np.percentile(on_plane @ floor[:3] + floor[3], 99)) if len(on_plane) else np.inf


def _long_and_low(on_plane: np.ndarray, floor: np.ndarray, plane: np.ndarray, gap_m: float) -> bool:
    """Whether a wall plane's points (k, 3) run along the floor at least WALL_MIN_LENGTH_TO_HEIGHT
    times as far as they rise above it: the longest run along the floor (gaps wider than gap_m
    split runs) against the height span of that run's points (5th to 95th percentile)."""
    if len(on_plane) < MIN_POINTS:
        return False
    along = np.cross(floor[:3], plane[:3])
    along /= np.linalg.norm(along)
    u = on_plane @ along
    order = np.argsort(u)
    u = u[order]
    breaks = np.flatnonzero(np.diff(u) > gap_m)
    starts, ends = np.r_[0, breaks + 1], np.r_[breaks + 1, len(u)]
    k = int(np.argmax(u[ends - 1] - u[starts]))
    run = order[starts[k] : ends[k]]
    height = on_plane[run] @ floor[:3] + floor[3]
    rise = float(np.percentile(height, 95) - np.percentile(height, 5))
    return float(u[ends[k] - 1] - u[starts[k]]) >= WALL_MIN_LENGTH_TO_HEIGHT * rise


def _square_to(plane: np.ndarray, walls: list[np.ndarray]) -> bool:
    """Whether the plane's normal is parallel or perpendicular, within WALL_SQUARE_TOLERANCE_DEG,
    to every wall's found so far."""
    tol = np.sin(np.radians(WALL_SQUARE_TOLERANCE_DEG))
    return all(min(abs(plane[:3] @ w[:3]), np.sqrt(max(0.0, 1.0 - (plane[:3] @ w[:3]) ** 2))) <= tol for w in walls)


def inside_walls(points: np.ndarray, floor: np.ndarray, walls: list[np.ndarray], threshold_m: float) -> np.ndarray:
    """(n,) bool: points on the bin's side of every wall plane found (the side of
    bin_reference_point). A wall that passes within a centimetre of that point decides nothing,
    nor does a "wall" with fewer than WALL_INNER_SHARE of the points on that side: the face of a
    part standing in the middle of a table is not the edge of a bin.

    points : (n, 3) camera frame, metres; floor, walls : planes (a, b, c, d) with unit normals.
    """
    ref = bin_reference_point(floor, points) if len(points) else np.zeros(3)
    keep = np.ones(len(points), bool)
    for wall in walls:
        side = float(ref @ wall[:3] + wall[3])
        if abs(side) < 0.01:
            continue
        inner = np.sign(side) * (points @ wall[:3] + wall[3]) > -threshold_m
        if len(inner) and inner.mean() >= WALL_INNER_SHARE:
            keep &= inner
    return keep


def clean_capture(
    xyz_m: np.ndarray,
    rgb: np.ndarray | None,
    frame_shape: tuple[int, int] | None,
    params: ImportCaptureParams,
    seed: int,
) -> CleanCloud:
    """Clean a capture.

    xyz_m : (n, 3) float, camera frame, metres, NaN where nothing was measured (n = H * W for an
            organized frame of shape `frame_shape`, row-major).
    rgb   : (n, 3) uint8 or None.
    Raises BinpickError when nothing usable is left or the scene is implausibly large.
    """
    xyz = np.asarray(xyz_m)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"expected xyz (n, 3), got {xyz.shape}")
    # One pass over the frame (millions of pixels, many empty, most of the rest on the floor)
    # tests every point and keeps the first in range and region of each cell of the view grid:
    # the rest of the cleaning sees thousands of points. Numpy took six passes and four copies.
    view = ViewParams.of_import(params)
    roi = params.roi_min_m is not None and params.roi_max_m is not None
    T_roi_from_cam = (
        invert_T(np.asarray(params.T_cam_from_roi, dtype=np.float64))
        if params.T_cam_from_roi is not None
        else np.eye(4)
    )
    screen = _screen(
        xyz,
        params.min_range_m**2,
        params.max_range_m**2,
        roi,
        np.ascontiguousarray(T_roi_from_cam[:3, :3]),
        T_roi_from_cam[:3, 3].copy(),
        np.asarray(params.roi_min_m if roi else (0.0, 0.0, 0.0), np.float64),
        np.asarray(params.roi_max_m if roi else (0.0, 0.0, 0.0), np.float64),
        1.0 / view.voxel_size_m,
    )
    valid, keep, lo, hi, key_lo, key_hi, n_valid_px, n_keep = screen
    if n_valid_px == 0:
        raise BinpickError("the capture holds no valid point (all NaN or empty)")
    extent = float(np.max(hi - lo))
    if extent > params.max_scene_extent_m:
        raise BinpickError(
            f"the scene is {extent:.4g} m across, more than max_scene_extent_m={params.max_scene_extent_m}: "
            "is the unit right (millimetres read as metres)?"
        )
    # What the camera saw, before anything is removed: registration checks poses against it.
    seen = depth_view(xyz_m, frame_shape, params.voxel_size_m, valid)
    if n_keep < MIN_POINTS:
        raise BinpickError(
            f"only {n_keep} points lie within range {params.min_range_m}-{params.max_range_m} m and the region of "
            "interest"
        )
    # The voxel grid comes first: planes are fitted at the density the segmentation works at,
    # shares are shares of that, and RANSAC runs on thousands instead of millions of points.
    # It is view_grid's grid (the first point of each voxel) over the kept points.
    span = key_hi - key_lo + 1
    kept, flat = _kept_voxel_keys(xyz, keep, n_keep, key_lo, span, 1.0 / view.voxel_size_m)
    idx = kept[first_in_each_voxel(flat, int(np.prod(span)))]
    # Single precision up to here, as the range and region tests and the grid work (a float32's
    # 0.1 um at a few metres is plenty); double from here on.
    pts = xyz[idx].astype(np.float32).astype(np.float64)
    n_valid = len(pts)
    if n_valid < MIN_POINTS:
        # Identical or nearly identical points (a stuck sensor, an export of one point) collapse
        # into a few voxels: nothing to fit a plane to or segment.
        raise BinpickError(
            f"only {n_valid} distinct points at the {params.voxel_size_m * 1000:g} mm voxel grid: the capture holds "
            "no surface"
        )

    floor = np.full(4, np.nan)
    removed_floor = 0
    plane, inliers = fit_plane_ransac(
        pts,
        params.plane_threshold_m,
        params.plane_ransac_iterations,
        seed,
        params.plane_ransac_confidence,
        min_distance_m=params.min_range_m,
    )
    if plane[3] < 0:  # orient the normal toward the camera at the origin
        plane = -plane
    height = pts @ plane[:3] + plane[3]
    behind = np.mean(height < -params.plane_threshold_m)
    if behind > MAX_BEHIND_FRACTION and inliers.any():
        # A floor seen through more depth noise than the plane threshold (a camera 2 m above a
        # large bin: a band 2 cm thick) has a quarter of its own points "behind" the plane
        # RANSAC draws through it. Behind is then counted beyond the noise the capture shows on
        # the plane (3 sigmas): a slab through a heap still has its lower half there, centimetres
        # behind.
        # The cut above the floor stays keep_above_plane_m: cut as thick as the noise (6 mm at
        # 1.9 m), a lone part lying on the floor lost enough of its sides to fail the support
        # check (bench picking --mix, a T-joint in a gear shaft's bin), while the few specks the
        # thinner cut leaves found no part.
        noise_m = local_noise_m(pts, KDTree(image_coordinates(pts)), pts[inliers])
        behind_m = max(params.plane_threshold_m, BEHIND_NOISE_SIGMAS * noise_m)
        behind = np.mean(height < -behind_m)
        log.info(
            "the plane's points scatter by %.1f mm (depth noise): behind it counted beyond %.1f mm, %.1f%% of the "
            "points",
            1000 * noise_m,
            1000 * behind_m,
            100 * behind,
        )
    # |d| is the camera's distance to the plane: a plane through (or near) the camera is a fan of
    # rays (a few image rows), never a surface something rests on.
    found = inliers.mean() >= MIN_PLANE_FRACTION and behind <= MAX_BEHIND_FRACTION and plane[3] >= params.min_range_m
    box = BinBox.of_import(params)
    if box is not None:
        # The bin is given: its floor is the floor unless the plane found lies on it (within the
        # plane threshold). Cropped above its floor, the largest plane left in a box may be a
        # layer of parts lying side by side, or the top of the floor's scatter on a coarse sensor.
        given = support_frame(plane if found else np.full(4, np.nan), box, params.plane_threshold_m)[1]
        assert given is not None  # a box always gives a plane
        plane, found = given, True
    if found:
        floor = plane
        above = pts @ plane[:3] + plane[3] > params.keep_above_plane_m
        removed_floor = int((~above).sum())
        pts, idx = pts[above], idx[above]
        log.info(
            "floor plane %s removed %.1f%% of the points", np.round(plane, 4).tolist(), 100.0 * removed_floor / n_valid
        )
    else:
        log.warning(
            "no support plane found (best plane holds %.1f%% of the points, %.1f%% lie behind it, %.3f m from the "
            "camera); nothing removed",
            100 * inliers.mean(),
            100 * behind,
            plane[3],
        )

    walls: list[np.ndarray] = []
    removed_walls = 0
    if params.remove_walls and np.isfinite(floor).all():
        # Planes other than walls (the rims' tops, the top of a stack of parts) are set aside
        # from the search, not removed, and the search goes on: a few more tries than walls.
        # Only points on surfaces standing across the floor are searched, and only planes across
        # it are drawn: seen from above, a heap's floor-parallel layers (and the rims' tops)
        # outnumber the walls and took every try, and a slab of them holds a strip of each wall.
        search = np.zeros(len(pts), bool)
        if len(pts) >= MIN_POINTS:
            sample = np.sort(
                np.random.default_rng(seed).choice(len(pts), size=min(len(pts), WALL_SEARCH_SAMPLE), replace=False)
            )
            search[sample] = np.abs(sample_normals(pts, sample) @ floor[:3]) < WALL_SEARCH_MAX_COS
        for w in range(2 * params.max_walls):
            if len(walls) >= params.max_walls or search.sum() < MIN_POINTS:
                break
            plane, _ = fit_plane_ransac(
                pts[search],
                params.plane_threshold_m,
                params.plane_ransac_iterations,
                seed + 1 + w,
                params.plane_ransac_confidence,
                across=floor[:3],
                max_cos=WALL_MAX_COS_TO_FLOOR,
            )
            # The plane's points among all that are left: the wall's edges, whose normals lean,
            # belong to it too.
            in_plane = np.abs(pts @ plane[:3] + plane[3]) <= params.plane_threshold_m
            if in_plane.sum() < params.wall_min_fraction * n_valid:
                break
            inliers = in_plane
            side = None if box is None else box.wall_side(plane)
            if box is not None and side is not None:
                # A given box's wall reaches only as high as the box says (fit-bin measures it):
                # in its plane above the rim lie the sides of parts heaped over it, and at a side
                # with no wall (a heap on a table) a row of cups' sides is all there is.
                inliers = in_plane & (box.height_m(pts) <= box.wall_top_m(side) + params.plane_threshold_m)
            if (
                inliers.sum() < params.wall_min_fraction * n_valid
                or abs(plane[:3] @ floor[:3]) > WALL_MAX_COS_TO_FLOOR
                or not _at_the_edge(pts[~in_plane], floor, plane, params.plane_threshold_m, _top_m(pts[inliers], floor))
                or not _square_to(plane, walls)
                or (box is not None and (side is None or not box.has_wall(side)))
                or not _long_and_low(pts[inliers], floor, plane, WALL_RUN_GAP_VOXELS * view.voxel_size_m)
            ):
                search &= ~in_plane
                continue
            walls.append(plane)
            removed_walls += int(inliers.sum())
            pts, idx, search = pts[~inliers], idx[~inliers], search[~inliers]
        if walls:
            log.info("removed %d wall planes, %.1f%% of the points", len(walls), 100.0 * removed_walls / n_valid)
        if walls and params.crop_to_walls:
            inside = inside_walls(pts, floor, walls, params.plane_threshold_m)
            removed_walls += int((~inside).sum())
            if (~inside).any():
                log.info("%.1f%% of the points lie outside the bin walls: removed", 100.0 * (~inside).sum() / n_valid)
            pts, idx = pts[inside], idx[inside]

    removed_outliers = 0
    if params.outlier_neighbours > 0 and len(pts) > params.outlier_neighbours:
        kept = statistical_outliers(pts, params.outlier_neighbours, params.outlier_std_ratio)
        removed_outliers = int((~kept).sum())
        pts, idx = pts[kept], idx[kept]
    if len(pts) < MIN_POINTS:
        raise NothingAboveTheFloor(f"only {len(pts)} points are left after removing the floor and walls")

    normals = view_normals(pts, view)
    organized = frame_shape is not None
    return CleanCloud(
        points_m=pts.astype(np.float32),
        normals=normals,
        rgb=(np.asarray(rgb)[idx] if rgb is not None else np.zeros((len(idx), 3))).astype(np.uint8),
        pixel_index=idx.astype(np.int64) if organized else np.full(len(idx), -1, np.int64),
        frame_shape=np.asarray(frame_shape if organized else (0, 0), dtype=np.int64),
        floor_plane=floor,
        wall_planes=np.asarray(walls, dtype=np.float64).reshape(-1, 4),
        removed_fraction=np.array([removed_floor, removed_walls, removed_outliers], dtype=np.float64) / n_valid,
        seen_depth_m=seen.depth_m,
        seen_K=seen.K,
    )


def captured_view(
    xyz_m: np.ndarray, labels: np.ndarray, params: ImportCaptureParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The network's view of a labelled organized frame as a capture of it would give it: the
    frame cleaned as the import step cleans one (seed 0), each point keeping its pixel's label.

    xyz_m (H, W, 3) camera frame, NaN = no return; labels (H, W) int, -1 = not a part. Returns
    points (N, 3) float32, normals (N, 3) float32, labels (N,) int16; empty when the cleaning
    leaves nothing (a frame that shows no surface above its floor).
    """
    h, w = labels.shape
    try:
        cloud = clean_capture(xyz_m.reshape(-1, 3), None, (h, w), params, 0)
    except BinpickError:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32), np.zeros(0, np.int16)
    return cloud.points_m, cloud.normals, labels.reshape(-1)[cloud.pixel_index].astype(np.int16)


# _screen's chunks of the frame, spread over the cores (a fixed number: the result is the same
# whatever the cores, as minima, maxima and counts do not depend on the order they are taken in).
SCREEN_CHUNKS = 16


@njit(cache=True, parallel=True)
def _screen(
    xyz, range2_min, range2_max, use_roi, R_roi_from_cam, t_roi_from_cam, roi_min, roi_max, inv_voxel
):  # pragma: no cover - numba
    """One pass over a capture's points (n, 3), camera frame, metres: valid (n,) bool (all three
    coordinates finite); keep (n,) bool (valid, range squared within [range2_min, range2_max]
    and, with use_roi, inside the box [roi_min, roi_max] of the ROI frame); the extent of the
    valid points (lo, hi per axis); the voxel key bounds (per axis) of the kept points; the
    number of valid and kept points. Tests and keys in single precision (see clean_capture)."""
    n = len(xyz)
    valid = np.zeros(n, np.bool_)
    keep = np.zeros(n, np.bool_)
    lo_c = np.full((SCREEN_CHUNKS, 3), np.inf)
    hi_c = np.full((SCREEN_CHUNKS, 3), -np.inf)
    key_lo_c = np.full((SCREEN_CHUNKS, 3), np.iinfo(np.int64).max)
    key_hi_c = np.full((SCREEN_CHUNKS, 3), np.iinfo(np.int64).min)
    n_valid_c = np.zeros(SCREEN_CHUNKS, np.int64)
    n_keep_c = np.zeros(SCREEN_CHUNKS, np.int64)
    for c in prange(SCREEN_CHUNKS):
        p = np.empty(3, np.float32)
        for i in range(c * n // SCREEN_CHUNKS, (c + 1) * n // SCREEN_CHUNKS):
            if not np.isfinite(xyz[i, 0] + xyz[i, 1] + xyz[i, 2]):
                continue
            valid[i] = True
            n_valid_c[c] += 1
            for a in range(3):
                p[a] = np.float32(xyz[i, a])
                lo_c[c, a] = min(lo_c[c, a], np.float64(p[a]))
                hi_c[c, a] = max(hi_c[c, a], np.float64(p[a]))
            range2 = p[0] * p[0] + p[1] * p[1] + p[2] * p[2]
            if range2 < range2_min or range2 > range2_max:
                continue
            if use_roi:
                inside = True
                for a in range(3):
                    v = (
                        R_roi_from_cam[a, 0] * np.float64(p[0])
                        + R_roi_from_cam[a, 1] * np.float64(p[1])
                        + R_roi_from_cam[a, 2] * np.float64(p[2])
                        + t_roi_from_cam[a]
                    )
                    if v < roi_min[a] or v > roi_max[a]:
                        inside = False
                if not inside:
                    continue
            keep[i] = True
            n_keep_c[c] += 1
            for a in range(3):
                k = np.int64(np.floor(np.float64(p[a]) * inv_voxel))
                key_lo_c[c, a] = min(key_lo_c[c, a], k)
                key_hi_c[c, a] = max(key_hi_c[c, a], k)
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    key_lo = np.full(3, np.iinfo(np.int64).max)
    key_hi = np.full(3, np.iinfo(np.int64).min)
    for c in range(SCREEN_CHUNKS):
        for a in range(3):
            lo[a] = min(lo[a], lo_c[c, a])
            hi[a] = max(hi[a], hi_c[c, a])
            key_lo[a] = min(key_lo[a], key_lo_c[c, a])
            key_hi[a] = max(key_hi[a], key_hi_c[c, a])
    return valid, keep, lo, hi, key_lo, key_hi, n_valid_c.sum(), n_keep_c.sum()


@njit(cache=True)
def _kept_voxel_keys(xyz, keep, n_keep, key_lo, span, inv_voxel):  # pragma: no cover - numba
    """The indices (n_keep,) of the kept points and their flat voxel keys (x fastest), as
    geometry.pointcloud keys them, from the single-precision coordinates."""
    kept = np.empty(n_keep, np.int64)
    flat = np.empty(n_keep, np.int64)
    m = 0
    for i in range(len(xyz)):
        if keep[i]:
            kx = np.int64(np.floor(np.float64(np.float32(xyz[i, 0])) * inv_voxel)) - key_lo[0]
            ky = np.int64(np.floor(np.float64(np.float32(xyz[i, 1])) * inv_voxel)) - key_lo[1]
            kz = np.int64(np.floor(np.float64(np.float32(xyz[i, 2])) * inv_voxel)) - key_lo[2]
            kept[m] = i
            flat[m] = (kz * span[1] + ky) * span[0] + kx
            m += 1
    return kept, flat
