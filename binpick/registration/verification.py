"""Verification of a pose against the scene: point-to-plane ICP on the exact CAD normals,
the score, the scene points a pose explains, and non-maximum suppression by those points.
Model points in the model frame, scene points in the camera frame, metres."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from pykdtree.kdtree import KDTree
from scipy.spatial import cKDTree

from binpick.geometry.icp import point_to_plane_icp
from binpick.geometry.transforms import invert_T, transform_points
from binpick.io.ppf_model import PPFModel
from binpick.registration.constants import (
    FINE_STRIDE,
    ICP_RELATIVE_CHANGE,
    MAX_BELOW_FLOOR_REL,
    MAX_SHARED_SUPPORT,
    MIN_MEASURED_SHARE,
    SCORE_STRIDE,
    SEEN_THROUGH_MARGIN_MIN_M,
    SEEN_THROUGH_MARGIN_REL,
    SUPPORT_MAX_INCIDENCE_DEG,
    SUPPORT_NOISE_RELIEF,
)
from binpick.registration.visibility import DepthView, measured_depth, seen_through_share, visible_support_share


def score_pose(
    model: PPFModel,
    T_cam_from_model: np.ndarray,
    scene_points: np.ndarray,
    inlier_m: float,
    scene_tree: KDTree | None = None,
    whole_scene: bool = False,
    stride: int = SCORE_STRIDE,
    view: DepthView | None = None,
) -> float:
    """Score in [0, 1]: geometric mean of the share of camera-facing model points with a scene
    point within inlier_m, and the share of scene points within inlier_m of the model. On a
    whole scene (other parts around) only the first share counts, and with the capture's view
    a facing point on whose ray the sensor measured nothing does not count against the pose
    (whole_scene_share). scene_tree: a pykdtree of scene_points (nearest-neighbour queries take
    half scipy's time), built here when None."""
    if len(scene_points) == 0:
        return 0.0
    facing = _posed_facing_points(model, T_cam_from_model, stride)
    if len(facing) == 0:
        return 0.0
    scene_tree = scene_tree or KDTree(np.ascontiguousarray(scene_points, dtype=np.float64))
    d_model, _ = scene_tree.query(facing, distance_upper_bound=inlier_m)
    if whole_scene:
        return whole_scene_share(facing, np.isfinite(d_model), view)
    # Scene points against the model's own tree, in the model frame: built once per model.
    d_scene, _ = model.dense_tree.query(
        transform_points(invert_T(T_cam_from_model), scene_points), distance_upper_bound=inlier_m
    )
    return float(np.sqrt(np.mean(np.isfinite(d_model)) * np.mean(np.isfinite(d_scene))))


def whole_scene_share(facing_cam: np.ndarray, supported: np.ndarray, view: DepthView | None) -> float:
    """The whole-scene score of a pose: the share of its camera-facing model points (k, 3;
    camera frame) with a scene point near them (supported (k,) bool), among those on whose ray
    the sensor measured something (view; all points without one), and never fewer than
    MIN_MEASURED_SHARE of them.

    A segment's score has a second factor, the share of its points the pose explains, which a
    correct pose keeps near 1 when the sensor leaves half its surface unmeasured; the whole
    scene has no such factor, so the same gap (a wide-baseline projector's shadow across the
    part) pulled a right pose's whole-scene score below min_score (PhoXi-class captures at 41
    degrees: 0.14-0.29 against 0.37-0.54 on the same parts' segments). The floor keeps a pose
    on a few measured points in a region the sensor barely saw from scoring high."""
    supported = np.asarray(supported, bool)
    if len(supported) == 0:
        return 0.0
    if view is None or view.is_empty:
        return float(supported.mean())
    measured = np.isfinite(measured_depth(facing_cam, view))
    return float(supported[measured].sum() / max(int(measured.sum()), MIN_MEASURED_SHARE * len(supported)))


def below_floor_share(model: PPFModel, T_cam_from_model: np.ndarray, floor_plane: np.ndarray) -> float:
    """How far the posed surface reaches below the support plane, in part diameters (<= 0: not
    at all). floor_plane (4,): a, b, c, d, unit normal toward the camera (CleanCloud.floor_plane);
    0 when there is none (NaN)."""
    plane = np.asarray(floor_plane, dtype=np.float64)
    if plane.shape != (4,) or not np.all(np.isfinite(plane)):
        return 0.0
    height = transform_points(T_cam_from_model, model.dense_points_m[::SCORE_STRIDE]) @ plane[:3] + plane[3]
    return float(-height.min() / model.diameter_m)


def in_the_floor(model: PPFModel, T_cam_from_model: np.ndarray, floor_plane: np.ndarray) -> bool:
    """The pose reaches more than MAX_BELOW_FLOOR_REL of the part's diameter below the support plane."""
    return below_floor_share(model, T_cam_from_model, floor_plane) > MAX_BELOW_FLOOR_REL


def seen_through(model: PPFModel, T_cam_from_model: np.ndarray, view: DepthView, stride: int = SCORE_STRIDE) -> float:
    """Share of the pose's camera-facing surface lying in space the camera saw through
    (visibility.py); 0 when the view is unknown."""
    points = _posed_facing_points(model, T_cam_from_model, stride)
    margin = max(SEEN_THROUGH_MARGIN_REL * model.diameter_m, SEEN_THROUGH_MARGIN_MIN_M)
    return seen_through_share(points, view, margin)


def visible_support(
    model: PPFModel,
    T_cam_from_model: np.ndarray,
    view: DepthView,
    scene_tree: KDTree,
    inlier_m: float,
    stride: int = SCORE_STRIDE,
    max_incidence_deg: float = SUPPORT_MAX_INCIDENCE_DEG,
) -> float:
    """Share of the pose's camera-facing surface the camera should have seen (visibility.py)
    with a scene point of scene_tree (a pykdtree of the cleaned cloud) within inlier_m. Hidden
    means a measurement more than inlier_m in front of the surface. Only surface whose normal is
    within max_incidence_deg of the ray to the camera counts (constants.py says why)."""
    facing = _facing(model, T_cam_from_model, stride)
    points = transform_points(T_cam_from_model, model.dense_points_m[::stride][facing])
    normals = model.dense_normals[::stride][facing] @ T_cam_from_model[:3, :3].T
    # cos(incidence) = n . (-p) / |p|, the camera at the origin.
    head_on = -np.einsum("ij,ij->i", normals, points) >= np.cos(np.radians(max_incidence_deg)) * np.linalg.norm(
        points, axis=1
    )
    points = points[head_on]
    if len(points) == 0:
        return 0.0
    d, _ = scene_tree.query(points, distance_upper_bound=inlier_m)
    return visible_support_share(points, np.isfinite(d), view, inlier_m)


def support_cut(least: float, noise_m: float, inlier_m: float) -> float:
    """The visible support a pose needs on a capture with noise_m of depth noise about it: least,
    lowered by SUPPORT_NOISE_RELIEF as the noise grows from 0.5 to 1.5 inlier distances."""
    return least - SUPPORT_NOISE_RELIEF * float(np.clip(noise_m / inlier_m - 0.5, 0.0, 1.0))


def part_share(
    model: PPFModel,
    T_cam_from_model: np.ndarray,
    scene_tree: KDTree,
    is_part: np.ndarray,
    inlier_m: float,
    stride: int = SCORE_STRIDE,
) -> float:
    """Share of the scene points on the pose (the nearest cloud point of scene_tree, a pykdtree of
    the cleaned cloud, within inlier_m of each camera-facing model point) that the network calls a
    part's (is_part (n,) bool, per point of that cloud); 1 when no point lies on it."""
    points = _posed_facing_points(model, T_cam_from_model, stride)
    if len(points) == 0:
        return 1.0
    d, nearest = scene_tree.query(points, distance_upper_bound=inlier_m)
    on_pose = np.unique(nearest[np.isfinite(d)])
    return float(np.mean(is_part[on_pose])) if len(on_pose) else 1.0


def _posed_facing_points(model: PPFModel, T_cam_from_model: np.ndarray, stride: int) -> np.ndarray:
    """(k, 3) camera frame, metres: the dense model points (every stride-th) facing the camera at
    this pose, moved to it."""
    return transform_points(T_cam_from_model, model.dense_points_m[::stride][_facing(model, T_cam_from_model, stride)])


def _facing(model: PPFModel, T_cam_from_model: np.ndarray, stride: int = 1) -> np.ndarray:
    """Mask of the dense model points (every stride-th) whose normal faces the camera (at the
    origin) at this pose."""
    # (R n) . (R p + t) = n . p + n . (R^T t): one product per point instead of moving them all.
    R, t = T_cam_from_model[:3, :3], T_cam_from_model[:3, 3]
    return model.dense_normal_dot_point[::stride] + model.dense_normals[::stride] @ (R.T @ t) < 0


def refine_icp(
    model: PPFModel,
    T_cam_from_model: np.ndarray,
    scene_points: np.ndarray,
    max_distance_m: float,
    iterations: int,
    stride: int = 1,
) -> np.ndarray:
    """Point-to-plane ICP of the scene points onto the model surface (exact CAD normals).

    Only model points facing the camera at the starting pose are targets: a thin wall's inner
    surface lies within a few millimetres of its outer one, and matching the camera's view of the
    outside to the inside holds ICP in a wrong minimum. On a part declared with a revolution
    symmetry the turn about its axis is left as the start pose has it (no fit can fix it).
    """
    if iterations == 0 or len(scene_points) < 6:
        return T_cam_from_model
    facing = _facing(model, T_cam_from_model, stride)
    if facing.sum() < 6:
        return T_cam_from_model
    T_model_from_cam = point_to_plane_icp(
        scene_points,
        model.dense_points_m[::stride][facing],
        model.dense_normals[::stride][facing],
        invert_T(T_cam_from_model),
        max_distance_m,
        iterations,
        ICP_RELATIVE_CHANGE,
        model.revolution_axis,
    )
    return invert_T(T_model_from_cam)


def refine_along_rays(
    model: PPFModel, T_cam_from_model: np.ndarray, scene_points: np.ndarray, max_distance_m: float, iterations: int
) -> np.ndarray:
    """Point-to-plane ICP of the scene points (n, 3, camera frame, metres; the camera at the
    origin) onto the model surface facing the camera, each point paired with the model point on
    its camera ray (geometry/icp.py, ray_pairing_rad): the pose without the pull toward the camera
    that nearest-point pairing gives a curved part under depth noise (refine_icp; 1.4-1.8 mm on
    gear shafts 2 m from a Kinect-class sensor, our renderer). A ray pairs within two of the dense
    sample's spacings at the points' median range; the sample is taken every FINE_STRIDE-th
    point, as the fine ICP takes it (half the time, the same poses to 0.01 mm on a shaft)."""
    facing = _facing(model, T_cam_from_model, FINE_STRIDE)
    if iterations == 0 or len(scene_points) < 6 or facing.sum() < 6:
        return T_cam_from_model
    target = model.dense_points_m[::FINE_STRIDE][facing]
    spacing_m = float(np.median(KDTree(target).query(target[:: max(1, len(target) // 500)], k=2)[0][:, 1]))
    range_m = float(np.median(np.linalg.norm(scene_points, axis=1)))
    T_model_from_cam = point_to_plane_icp(
        scene_points,
        target,
        model.dense_normals[::FINE_STRIDE][facing],
        invert_T(T_cam_from_model),
        max_distance_m,
        iterations,
        ICP_RELATIVE_CHANGE,
        model.revolution_axis,
        ray_pairing_rad=2.0 * spacing_m / range_m,
    )
    return invert_T(T_model_from_cam)


def explained_points(
    model: PPFModel, T: np.ndarray, points: np.ndarray, tree: cKDTree, inlier_m: float, reach_m: float
) -> np.ndarray:
    """Indices of the scene points (n, 3), in `tree`, within inlier_m of the model surface at pose T."""
    near = np.asarray(
        tree.query_ball_point(T[:3, :3] @ model.dense_points_m.mean(axis=0) + T[:3, 3], reach_m), dtype=np.int64
    )
    if len(near) == 0:
        return near
    d, _ = model.dense_tree.query(transform_points(invert_T(T), points[near]), distance_upper_bound=inlier_m)
    return near[np.isfinite(d)]


def suppress_by_support(scores: Sequence[float], support: Sequence[np.ndarray], claimed: np.ndarray) -> list[int]:
    """Non-maximum suppression by explained points, best score first: a pose whose supporting
    scene points are mostly claimed by a better pose already (a repeat, a wrong fit on a fragment
    of a part found whole, or a fit bridging two neighbouring parts) is dropped, whatever its
    pose. claimed (n,) bool, updated in place. Returns the kept indices, best first."""
    kept: list[int] = []
    for k in sorted(range(len(scores)), key=lambda k: -scores[k]):
        if len(support[k]) == 0 or claimed[support[k]].mean() > MAX_SHARED_SUPPORT:
            continue
        claimed[support[k]] = True
        kept.append(k)
    return kept
