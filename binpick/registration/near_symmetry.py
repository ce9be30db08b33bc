"""Choosing between a pose and its turns by the part's near symmetries (registration/model.py:
turns that map nearly all of its surface onto itself, as a mug turned about its axis, all but the
handle). The matcher's fit and score hardly see the small part of the surface that tells such
poses apart, so a pose found may be turned by any of them; what the camera saw decides: the turn
that leaves the handle in free space is contradicted by the measurements behind it.

Model points in the part's model frame, scene points in the camera frame, metres.
"""

from __future__ import annotations

import numpy as np
from pykdtree.kdtree import KDTree
from scipy.spatial import cKDTree

from binpick.io.ppf_model import PPFModel
from binpick.registration.constants import FINE_STRIDE, Scales
from binpick.registration.verification import refine_icp, score_pose, seen_through
from binpick.registration.visibility import DepthView


def resolve(
    model: PPFModel, T_cam_from_model: np.ndarray, scene_points: np.ndarray, ball_tree: cKDTree, score_tree: KDTree, view: DepthView, scales: Scales,
    icp_iterations: int,
) -> tuple[np.ndarray, bool]:
    """The pose among T_cam_from_model and its turns by the model's near symmetries (each refined
    by fine ICP on the scene around it) that the capture supports best: the share of its
    camera-facing surface with a scene point near it, minus the share lying where the camera saw
    through it. Returns the pose and whether it is a turned one.

    scene_points : (n, 3) camera frame, on the refine grid; ball_tree / score_tree: a scipy and a
                   pykdtree tree of them.
    """
    T = np.asarray(T_cam_from_model, dtype=np.float64)
    if len(model.near_symmetries) == 0:
        return T, False
    centre = model.dense_points_m.mean(axis=0)
    near = np.asarray(ball_tree.query_ball_point(T[:3, :3] @ centre + T[:3, 3], scales.reach_m), dtype=np.int64)
    local = scene_points[near]

    def support(X: np.ndarray) -> float:
        return score_pose(model, X, scene_points, scales.inlier_m, score_tree, whole_scene=True) - seen_through(model, X, view)

    best, best_support, turned = T, support(T), False
    for S in model.near_symmetries:
        X = refine_icp(model, T @ S, local, scales.fine_icp_m, icp_iterations, FINE_STRIDE)
        value = support(X)
        if value > best_support:
            best, best_support, turned = X, value, True
    return best, turned
