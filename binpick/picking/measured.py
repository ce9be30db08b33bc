"""What the camera measured about a posed part: the capture's point spacing and its noise about
the pose, the target's own points (not obstacles to its own gripper), and whether a grasp's
contact lies on measured surface. Camera frame, metres."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pykdtree.kdtree import KDTree
from scipy.spatial import cKDTree

from binpick.params import PickParams

# Points whose nearest-neighbour distances give a point set's spacing (point_spacing_m): the
# part's surface sample (own points) and the capture (contacts on sparse captures).
SPACING_PROBES = 2000
# A grasp's contact must be measured: at least this many captured points under the suction cup
# (or between the jaw's fingers), this share of the cup's within its seal tolerance (plus the noise
# allowance below) of the contact plane. A pose off by a rotation the camera cannot tell (a pipe
# turned about its axis, its branch hidden) otherwise places grasps in the air.
SEEN_MIN_POINTS = 5
SEEN_SHARE = 0.7
SEEN_NOISE_M = 0.001
# The allowance grows with the noise the capture shows around the pose: SEEN_NOISE_SIGMAS of it
# when that exceeds SEEN_NOISE_M, so a Kinect-class sensor's 1-3 mm on a lid is not taken for a
# contact off the surface. The noise is the scatter of the captured points about their own local
# planes (local_noise_m), not about the posed model: a pose off by a turn leaves its points far
# from its surface, and that must still refuse the contact, not widen the test. Capped
# (geometry/depth_noise.py): a seal test looser than a few millimetres tests nothing on a 5 mm cup.
SEEN_NOISE_SIGMAS = 2.5
# The noise about a pose is measured at captured points within this multiple of own_points_m of
# the posed surface ...
NOISE_BAND_FACTOR = 3.0
# ... and a noisy capture's own points reach OWN_NOISE_SIGMAS of it (at least own_points_m): at
# 3 sigma, a few of a part's thousands of points stood in the gripper's way.
OWN_NOISE_SIGMAS = 4.0
# ... about where they sit off the posed surface, read from at least this many of them.
MIN_OFFSET_POINTS = 30
# ... and the plane fitted to those points must face the cup: its normal within this of the
# approach. Over a cup's few millimetres the share test alone passes a contact tilted by 30
# degrees (a pose turned the wrong way about an edge), where no cup seals; the fitted normal of
# a measured patch is a few degrees off at the sensor's noise.
SEEN_MAX_TILT_DEG = 20.0
# On a sparse capture (a VGA sensor at 0.7 m, a downsampled z-buffer: points 2-3 mm apart) a 5 mm
# cup covers one to four points; the contact is then judged over a disc of this many point
# spacings, enough to hold SEEN_MIN_POINTS and more.
SEEN_SPACINGS = 2.5
# ... measured over the cup, or over a disc of this many noise stds when wider: a 5 mm cup's
# patch at 3 mm of noise tilts by tens of degrees; 12 mm of it by a few.
TILT_PATCH_SIGMAS = 4.0


def point_spacing_m(points_m: np.ndarray, tree: KDTree | None = None) -> float:
    """The typical distance (metres) between neighbouring points (n, 3): the median
    nearest-neighbour distance of up to SPACING_PROBES evenly strided points; 0 for fewer than 2.
    tree: a k-d tree of points_m already built (else one is)."""
    if len(points_m) < 2:
        return 0.0
    probe = points_m[:: max(1, len(points_m) // SPACING_PROBES)]
    tree = KDTree(np.ascontiguousarray(points_m)) if tree is None else tree
    d, _ = tree.query(np.ascontiguousarray(probe), k=2)
    return float(np.median(d[:, 1]))


class OwnPoints:
    """Distances of points (model frame) to the part's surface. A point is its own when it lies
    within own_m of the tangent plane of its nearest sample point, that point no farther than
    own_m plus the sample's spacing.
    Asked of the distance to the nearest sample point alone, the answer would follow the sample's
    density: the ingest's 20,000 points lie 2 mm apart on the 0.44 m gear shaft, and a thinned
    sample's 8 mm left most of a target's measured surface as obstacles under the cup."""

    def __init__(self, points_m: np.ndarray, normals: np.ndarray, own_m: float) -> None:
        self.normals, self.own_m = normals, own_m
        # pykdtree: nearest-neighbour queries only, half scipy's time (a query per target part).
        tree = KDTree(np.ascontiguousarray(points_m, dtype=np.float64)) if len(points_m) else None
        self.tree, self.points_m = tree, points_m
        # The sample's spacing: an even random sample's median nearest-neighbour distance is
        # about half of it.
        self.spacing_m = 2.0 * point_spacing_m(points_m, tree)
        self.reach_m = own_m + self.spacing_m

    def distances(self, points_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For points (k, 3), model frame: (k,) the distance to the nearest sample point and (k,)
        the signed distance to its tangent plane (outward positive); both inf where the nearest
        point lies beyond own_m plus the spacing, or the plane beyond own_m."""
        nearest, plane = np.full(len(points_m), np.inf), np.full(len(points_m), np.inf)
        if self.tree is None or len(points_m) == 0:
            return nearest, plane
        d, j = self.tree.query(points_m, distance_upper_bound=self.reach_m)
        near = np.isfinite(d)
        jn = j[near]
        off = np.einsum("ij,ij->i", points_m[near] - self.points_m[jn], self.normals[jn])
        keep = np.abs(off) <= self.own_m
        idx = np.flatnonzero(near)[keep]
        nearest[idx], plane[idx] = d[near][keep], off[keep]
        return nearest, plane


def seen_offset_m(offsets_m: np.ndarray, limit_m: float) -> float:
    """Where a capture's points about a pose sit off its posed surface, metres (outward
    positive): the median of the signed offsets (k,) within limit_m of it; 0 with fewer than
    MIN_OFFSET_POINTS. The seen depth keeps each cell's nearest measurement, so its points lie
    toward the camera by about two sigmas of the sensor's noise: 1.9-2.4 mm on gear shafts 1.8 m
    from the camera, where 4 sigmas of the points' own scatter (4.3 mm) left 2-19 of every oval
    cup's ~140 footprint points as obstacles, and every grasp refused."""
    inside = offsets_m[np.abs(offsets_m) <= limit_m]
    return float(np.median(inside)) if len(inside) >= MIN_OFFSET_POINTS else 0.0


@dataclass(frozen=True)
class PosedSurface:
    """The target part's surface at its pose (T_cam_from_model (4, 4)), for judging a contact
    over a disc wider than the cup; offset_m: where the capture's points sit off it
    (seen_offset_m)."""

    own: OwnPoints
    T_cam_from_model: np.ndarray
    offset_m: float = 0.0

    def offsets(self, points_cam: np.ndarray) -> np.ndarray:
        """(k,) the signed distance (metres, outward positive) of points (k, 3; camera frame) to
        the posed surface's tangent plane, less offset_m; inf off the surface (OwnPoints)."""
        R, t = self.T_cam_from_model[:3, :3], self.T_cam_from_model[:3, 3]
        return self.own.distances((np.asarray(points_cam, float) - t) @ R)[1] - self.offset_m

    def points_near(self, at_cam: np.ndarray, radius_m: float) -> np.ndarray:
        """(k, 3) camera frame: the part's surface sample within radius_m of at_cam (3,) that
        faces the camera (the side a contact there is measured from)."""
        R, t = self.T_cam_from_model[:3, :3], self.T_cam_from_model[:3, 3]
        at_model = R.T @ (np.asarray(at_cam, float) - t)
        near = np.linalg.norm(self.own.points_m - at_model, axis=1) <= radius_m
        points = self.own.points_m[near] @ R.T + t
        facing = np.einsum("ij,ij->i", self.own.normals[near] @ R.T, points) < 0.0
        return points[facing]


def captured_near(tree: cKDTree, n_captured: int, at: np.ndarray, radius_m: float) -> np.ndarray:
    """Indices of the captured points within radius_m of `at`: the obstacle tree's first n_captured rows."""
    # Sorted: the order (which the tree's layout sets) must not change sums over these points.
    near = np.asarray(tree.query_ball_point(at, radius_m, return_sorted=True), dtype=np.int64)
    return near[near < n_captured]


def contact_seen(
    T_cam_from_tool: np.ndarray,
    kind: str,
    width_m: float,
    captured: np.ndarray,
    tree: cKDTree | None,
    params: PickParams,
    noise_m: float = 0.0,
    spacing_m: float = 0.0,
    surface: PosedSurface | None = None,
) -> bool:
    """Whether the captured points show the surface the grasp's contact needs (see the module's
    docstring); noise_m: the capture's noise about the pose (local_noise_m), which widens the
    seal tolerance and the tilt a measured patch may show; spacing_m: the capture's point
    spacing, which widens a suction contact's disc on a sparse capture (SEEN_SPACINGS);
    surface: the posed part's, which a disc so widened is judged against (None: its plane)."""
    if tree is None or len(captured) == 0:
        return False
    c = T_cam_from_tool[:3, 3]
    if kind == "suction":
        reach = max(params.suction.cup_radius_m, SEEN_SPACINGS * spacing_m)
    else:
        # Between the fingers, from their tips back to the palm: the camera sees a shaft gripped
        # by pads at its axis on its top, a radius behind them. Across the fingers the band is
        # widened on a sparse capture, as the cup's disc is.
        j = params.jaw
        half_y = max(j.finger_width_m / 2.0, SEEN_SPACINGS * spacing_m / 2.0)
        reach = float(np.sqrt((width_m / 2) ** 2 + half_y**2 + max(j.palm_from_tcp_m, j.pad_m / 2) ** 2))
    near = captured_near(tree, len(captured), c, reach)
    if len(near) < SEEN_MIN_POINTS:
        return False
    local = (captured[near] - c) @ T_cam_from_tool[:3, :3]
    if kind == "suction":
        seal_m = params.suction.max_deviation_m + max(SEEN_NOISE_M, SEEN_NOISE_SIGMAS * noise_m)
        if surface is not None and reach > params.suction.cup_radius_m:
            return _seen_on_surface(captured[near], c, reach, seal_m, noise_m, surface)
        if np.mean(np.abs(local[:, 2]) <= seal_m) < SEEN_SHARE:
            return False
        # The measured patch, its points within the seal tolerance, must face the cup. Noise
        # tilts it (_faces_within_tilt), so on a noisy capture the patch is taken wider than the cup.
        patch_m = max(reach, TILT_PATCH_SIGMAS * noise_m)
        if patch_m > reach:
            near = captured_near(tree, len(captured), c, patch_m)
            local = (captured[near] - c) @ T_cam_from_tool[:3, :3]
        local = local[np.abs(local[:, 2]) <= seal_m]
        if len(local) < SEEN_MIN_POINTS:
            return False
        return _faces_within_tilt(local, np.array([0.0, 0.0, 1.0]), noise_m, patch_m)
    between = (
        (np.abs(local[:, 0]) < width_m / 2)
        & (np.abs(local[:, 1]) < half_y)
        & (local[:, 2] > -j.palm_from_tcp_m)
        & (local[:, 2] < j.pad_m / 2)
    )
    return int(between.sum()) >= SEEN_MIN_POINTS


def _seen_on_surface(
    disc: np.ndarray, c: np.ndarray, reach_m: float, seal_m: float, noise_m: float, surface: PosedSurface
) -> bool:
    """A suction contact at c (3,) judged over a disc wider than its cup (the captured points
    disc (k, 3) within reach_m; camera frame): over that disc the part's own shape lies off the
    contact's plane (a cup's lid: a 6-9 mm recess round a 12 mm plateau, inside the 15 mm disc of
    a VGA frame's cloud), so SEEN_SHARE of the points must lie within seal_m of the posed
    surface instead, and the plane fitted to them must face as the posed surface's own over the
    disc does (a pose turned about an edge leaves the points' plane tilted from its surface's).
    The cup's own patch was checked flat when the grasp was made (the grasps stage)."""
    on = np.abs(surface.offsets(disc)) <= seal_m
    if on.mean() < SEEN_SHARE or on.sum() < SEEN_MIN_POINTS:
        return False
    model = surface.points_near(c, reach_m)
    if len(model) < SEEN_MIN_POINTS:
        return False
    return _faces_within_tilt(disc[on], _plane_normal(model), noise_m, reach_m)


def _plane_normal(points: np.ndarray) -> np.ndarray:
    """(3,) unit: the normal of the plane fitted to points (k, 3), their direction of least spread."""
    return np.linalg.svd(points - points.mean(axis=0), full_matrices=False)[2][2]


def _faces_within_tilt(points: np.ndarray, axis: np.ndarray, noise_m: float, patch_m: float) -> bool:
    """Whether the plane fitted to points (k, 3) faces along axis (3,) unit (either way) within
    SEEN_MAX_TILT_DEG, plus what noise_m tilts it: a plane fitted to k points over a disc of
    radius patch_m has a slope std of 2 sigma / (r sqrt(k)), and SEEN_NOISE_SIGMAS of it is allowed."""
    tilt_noise_deg = np.degrees(np.arctan(SEEN_NOISE_SIGMAS * 2.0 * noise_m / (patch_m * np.sqrt(len(points)))))
    return bool(abs(_plane_normal(points) @ axis) >= np.cos(np.radians(SEEN_MAX_TILT_DEG + tilt_noise_deg)))
