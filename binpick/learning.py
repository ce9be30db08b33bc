"""Learning from the cell: a capture whose poses passed verification with margin becomes a
labelled training scene for the part's network (pseudo-labels).

A point of the cleaned capture near a trusted pose's model surface gets that pose's instance;
every other point (near a pose that did not pass with margin, on a part nobody posed, on a
distractor) is IGNORE: it stays in the network's input, as it would at inference, but adds
nothing to the loss. It is not called background: the cell does not know what it is. What the
cell does know is the bin: a point beyond its walls or under its floor is NOT_A_PART.
"""

from __future__ import annotations

import numpy as np
from pykdtree.kdtree import KDTree
from scipy.spatial import cKDTree

from binpick.cell.bin_box import BinBox
from binpick.geometry.depth_noise import image_coordinates, local_noise_m
from binpick.geometry.transforms import invert_T, transform_points
from binpick.io.cloud import CleanCloud
from binpick.io.labelled_capture import LabelledCapture
from binpick.io.poses import PartPose
from binpick.labels import IGNORE, NOT_A_PART


def trusted(poses: list[PartPose], min_score: float, margin: float) -> np.ndarray:
    """(k,) bool: poses whose verification score clears min_score by at least margin."""
    return np.array([p.score >= min_score + margin for p in poses], dtype=bool)


def pseudo_labels(
    points_m: np.ndarray, T_cam_from_trusted: np.ndarray, model_points_m: np.ndarray, near_m: float
) -> np.ndarray:
    """Instance labels of a capture's points from trusted poses.

    points_m (N, 3): the cleaned capture, camera frame, metres; T_cam_from_trusted (k, 4, 4):
    the trusted poses, camera from model; model_points_m (M, 3): the part's surface sample,
    model frame, dense against near_m; near_m: how far from a posed surface a measured point
    may lie (the capture's noise and the pose's error, metres). Returns (N,) int16: the index
    of the nearest trusted pose whose surface lies within near_m, else IGNORE.
    """
    points_m = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    labels = np.full(len(points_m), IGNORE, np.int16)
    if not len(points_m) or not len(T_cam_from_trusted):
        return labels
    best = np.full(len(points_m), np.inf)
    for i, T in enumerate(np.asarray(T_cam_from_trusted, dtype=np.float64).reshape(-1, 4, 4)):
        surface = transform_points(T, model_points_m)
        # Only points within the posed part's reach can be near it: query those alone.
        lo, hi = surface.min(axis=0) - near_m, surface.max(axis=0) + near_m
        inside = np.flatnonzero(np.all((points_m >= lo) & (points_m <= hi), axis=1))
        if not len(inside):
            continue
        d, _ = cKDTree(surface).query(points_m[inside], distance_upper_bound=near_m)
        closer = (d <= near_m) & (d < best[inside])
        labels[inside[closer]] = i
        best[inside[closer]] = d[closer]
    return labels


def outside_bin(points_m: np.ndarray, bin_box: BinBox, near_m: float) -> np.ndarray:
    """(N,) bool: points (N, 3, camera frame, metres) farther than near_m beyond the bin's inner
    walls or under its floor, where no part of the bin can be (its rim, the table, the room).
    Above the box is not outside: parts heap over a rim."""
    q = transform_points(invert_T(np.asarray(bin_box.T_cam_from_bin, dtype=np.float64)), points_m)
    lo, hi = np.asarray(bin_box.inner_min_m, float), np.asarray(bin_box.inner_max_m, float)
    beyond_walls = np.any(q[:, :2] < lo[:2] - near_m, axis=1) | np.any(q[:, :2] > hi[:2] + near_m, axis=1)
    return beyond_walls | (q[:, 2] < lo[2] - near_m)


def near_distance_m(noise_m: float, voxel_size_m: float, diameter_m: float) -> float:
    """How far a measured point may lie from a trusted pose's surface and still be that part's:
    three times the capture's depth noise, at least one import voxel, at most 3 % of the part's
    diameter (a pose trusted with margin is that close; beyond, a neighbour's points begin)."""
    return float(min(max(3.0 * noise_m, voxel_size_m), 0.03 * diameter_m))


def label_capture(
    cloud: CleanCloud,
    poses: list[PartPose],
    dense_points_m: np.ndarray,
    diameter_m: float,
    min_score: float,
    margin: float,
    voxel_size_m: float,
    bin_box: BinBox | None = None,
) -> LabelledCapture:
    """A cleaned capture labelled from its poses (the register stage's, verified against this
    capture): poses trusted with margin label the points near them (near_distance_m of the
    noise the capture shows about its points); with the bin's box, the other points outside it
    are NOT_A_PART; every other point is IGNORE.

    dense_points_m (M, 3): the part's dense surface sample, model frame (the PPF model's);
    diameter_m: the part's; min_score: the verification threshold the poses passed;
    voxel_size_m: the import grid the cloud is on."""
    points = np.asarray(cloud.points_m, dtype=np.float64)
    keep = trusted(poses, min_score, margin)
    T_trusted = np.array([p.T_cam_from_model for p in poses], dtype=np.float64).reshape(-1, 4, 4)[keep]
    noise = local_noise_m(points, KDTree(image_coordinates(points)), points) if len(points) else 0.0
    near = near_distance_m(noise, voxel_size_m, diameter_m)
    labels = pseudo_labels(points, T_trusted, dense_points_m, near)
    if bin_box is not None and len(points):
        labels[(labels == IGNORE) & outside_bin(points, bin_box, near)] = NOT_A_PART
    return LabelledCapture(
        points_m=np.asarray(cloud.points_m, np.float32),
        normals=np.asarray(cloud.normals, np.float32),
        labels=labels,
        T_cam_from_model=T_trusted,
        scores=np.array([p.score for p in poses], dtype=np.float64)[keep],
        near_m=np.asarray(near, np.float64),
    )
