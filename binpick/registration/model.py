"""The PPF model of a part (Drost, Ulrich, Navab, Ilic, CVPR 2010): every ordered pair of
subsampled model points gives the feature F = (||d||, angle(n1, d), angle(n2, d), angle(n1, n2)),
quantised into a key; pairs are stored sorted by key with the reference point and the angle
alpha_m that turns the partner into a canonical half-plane.

Frames: model points in the part's model frame, metres.
"""

from __future__ import annotations

import numpy as np
from pykdtree.kdtree import KDTree

from binpick.geometry.pointcloud import voxel_downsample_indices
from binpick.geometry.transforms import axis_angle_to_R, make_T, rigid_fit
from binpick.io.ppf_model import PPFModel
from binpick.params import RegisterParams
from binpick.registration.constants import (
    NEAR_SYMMETRY_EXACT_SHARE,
    NEAR_SYMMETRY_MIN_OVERLAP,
    NEAR_SYMMETRY_PROBE_STRIDE,
    NEAR_SYMMETRY_STEP_DEG,
)


def _align_to_x(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(n, 4, 4) transforms that move each point to the origin and turn its normal onto +x."""
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    x = np.array([1.0, 0.0, 0.0])
    axis = np.cross(n, x)  # (n, 3)
    s = np.linalg.norm(axis, axis=1)
    c = n @ x
    k = axis / np.where(s > 1e-12, s, 1.0)[:, None]
    # Normals along -x need any perpendicular axis; +x needs none.
    anti = (s <= 1e-12) & (c < 0)
    k[anti] = np.array([0.0, 0.0, 1.0])
    K = np.zeros((len(n), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    sin = np.where(anti, 0.0, s)[:, None, None]
    cos = np.where(anti, -1.0, c)[:, None, None]
    R = np.eye(3)[None] + sin * K + (1 - cos) * (K @ K)
    T = np.zeros((len(n), 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = -np.einsum("nij,nj->ni", R, points)
    T[:, 3, 3] = 1.0
    return T


def _features(p1: np.ndarray, n1: np.ndarray, p2: np.ndarray, n2: np.ndarray) -> np.ndarray:
    """(n, 4) point pair features: distance (m) and three angles (rad) in [0, pi]."""
    d = p2 - p1
    dist = np.linalg.norm(d, axis=1)
    du = d / np.maximum(dist, 1e-12)[:, None]

    def angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.arccos(np.clip(np.sum(a * b, axis=1), -1.0, 1.0))

    return np.stack([dist, angle(n1, du), angle(n2, du), angle(n1, n2)], axis=1)


def _keys(F: np.ndarray, distance_step_m: float, angle_bins: int) -> np.ndarray:
    q_d = np.floor(F[:, 0] / distance_step_m).astype(np.int64)
    q_a = np.minimum((F[:, 1:] / np.pi * angle_bins).astype(np.int64), angle_bins - 1)
    return ((q_d * angle_bins + q_a[:, 0]) * angle_bins + q_a[:, 1]) * angle_bins + q_a[:, 2]


def _alpha(T_align: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Angle about +x that brings each aligned partner point into the half-plane y > 0, z = 0."""
    p = np.einsum("nij,nj->ni", T_align[:, :3, :3], points) + T_align[:, :3, 3]
    return np.arctan2(-p[:, 2], p[:, 1])


# Refinements of the grid tried before giving up on reaching min_voting_points (each one moves
# the step by the square root of the shortfall: a surface's point count goes with 1 / step^2).
_VOTING_STEP_TRIES = 8


def voting_step(dense_points_m: np.ndarray, step_m: float, min_points: int) -> float:
    """The voting grid (metres) for a part's dense surface sample (n, 3), model frame: step_m,
    or finer until the grid holds at least min_points of the model (a long thin part: the gear
    shaft, 437 x 97 mm, has 232 points at 0.05 of its diameter, and votes between two shafts side
    by side then outnumber those within one). Never finer than the dense sample holds."""
    step = float(step_m)
    min_points = min(int(min_points), len(dense_points_m))
    for _ in range(_VOTING_STEP_TRIES):
        n = len(voxel_downsample_indices(dense_points_m, step))
        if n >= min_points:
            break
        step *= 0.98 * float(np.sqrt(n / min_points))
    return step


def train_ppf(
    dense_points_m: np.ndarray,
    dense_normals: np.ndarray,
    diameter_m: float,
    symmetries: np.ndarray,
    params: RegisterParams,
) -> PPFModel:
    """Build the PPF table of a part from its dense surface sample (model frame, metres)."""
    if dense_points_m.ndim != 2 or dense_points_m.shape[1] != 3 or dense_normals.shape != dense_points_m.shape:
        raise ValueError("expected dense points and normals (n, 3)")
    sample_step = voting_step(dense_points_m, params.sample_step_rel * diameter_m, params.min_voting_points)
    idx = voxel_downsample_indices(dense_points_m, sample_step)
    pts = dense_points_m[idx].astype(np.float64)
    nrm = dense_normals[idx].astype(np.float64)
    M = len(pts)
    i, j = np.meshgrid(np.arange(M), np.arange(M), indexing="ij")
    i, j = i[i != j], j[i != j]
    # Distance bins keep their ratio to the grid (as the params set it) when the grid is finer.
    step = params.distance_step_rel * diameter_m * (sample_step / (params.sample_step_rel * diameter_m))
    keys = _keys(_features(pts[i], nrm[i], pts[j], nrm[j]), step, params.angle_bins)
    T_align = _align_to_x(pts, nrm)
    alpha = _alpha(T_align[i], pts[j])
    order = np.argsort(keys, kind="stable")
    keys = keys[order]
    return PPFModel(
        points_m=pts,
        normals=nrm,
        keys=keys,
        key_starts=np.searchsorted(keys, np.arange(int(keys[-1]) + 2)),
        ref_index=i[order].astype(np.int32),
        alpha=alpha[order].astype(np.float32),
        dense_points_m=np.asarray(dense_points_m, dtype=np.float64),
        dense_normals=np.asarray(dense_normals, dtype=np.float64),
        symmetries=symmetries,
        near_symmetries=near_symmetries(dense_points_m, symmetries, params.score_inlier_rel * diameter_m),
        diameter_m=float(diameter_m),
        distance_step_m=step,
        sample_step_m=float(sample_step),
        angle_bins=params.angle_bins,
    )


def near_symmetries(dense_points_m: np.ndarray, symmetries: np.ndarray, inlier_m: float) -> np.ndarray:
    """(k, 4, 4) model-frame transforms: turns by multiples of NEAR_SYMMETRY_STEP_DEG about the
    principal axes of the surface sample (through its centroid) that bring at least
    NEAR_SYMMETRY_MIN_OVERLAP of it to within inlier_m of itself, leaving out the declared
    symmetries (m, 4, 4), turns equal to one found already, and undeclared exact symmetries (turns
    that bring NEAR_SYMMETRY_EXACT_SHARE of it to within 1.5 inlier_m).

    dense_points_m : (n, 3) the part's surface sample, model frame, metres.
    """
    points = np.asarray(dense_points_m, dtype=np.float64)
    if len(points) < 3:
        return np.zeros((0, 4, 4))
    centre = points.mean(axis=0)
    axes = np.linalg.svd(points - centre, full_matrices=False)[2]
    probe = np.ascontiguousarray(points[::NEAR_SYMMETRY_PROBE_STRIDE])
    moments = (probe.mean(axis=0), probe.T @ probe / len(probe))
    tree = KDTree(points)
    found: list[np.ndarray] = []
    exact: list[np.ndarray] = []
    for axis in axes:
        for k in range(1, 360 // NEAR_SYMMETRY_STEP_DEG):
            R = axis_angle_to_R(axis, np.radians(k * NEAR_SYMMETRY_STEP_DEG))
            T = make_T(R, centre - R @ centre)  # the turn about the axis through the centroid
            if any(_apart_m(T, S, moments) < inlier_m for S in (*symmetries, *exact, *found)):
                continue
            # The axis through the centroid misses the turn's own axis when the feature that
            # breaks the symmetry moves the centroid (a mug's handle): the turn is fitted first.
            T = _self_aligned(T, probe, points, tree, 3.0 * inlier_m)
            if any(_apart_m(T, S, moments) < inlier_m for S in (*symmetries, *exact, *found)):
                continue
            d, _ = tree.query(probe @ T[:3, :3].T + T[:3, 3], distance_upper_bound=1.5 * inlier_m)
            if np.mean(d < 1.5 * inlier_m) >= NEAR_SYMMETRY_EXACT_SHARE:
                exact.append(T)
            elif np.mean(d < inlier_m) >= NEAR_SYMMETRY_MIN_OVERLAP:
                found.append(T)
    return np.array(found).reshape(-1, 4, 4)


def _self_aligned(
    T: np.ndarray, probe: np.ndarray, points: np.ndarray, tree: KDTree, max_distance_m: float, iterations: int = 15
) -> np.ndarray:
    """T (4, 4) refined so that the probe points it moves land on the surface points (point to
    point ICP, pairs closer than max_distance_m)."""
    for _ in range(iterations):
        moved = probe @ T[:3, :3].T + T[:3, 3]
        d, j = tree.query(moved, distance_upper_bound=max_distance_m)
        pair = np.isfinite(d)
        if pair.sum() < 3:
            break
        T = rigid_fit(moved[pair], points[j[pair]]) @ T
    return T


def _apart_m(A: np.ndarray, B: np.ndarray, moments: tuple[np.ndarray, np.ndarray]) -> float:
    """Root mean square distance between points moved by A and by B, from the points' mean (3,)
    and second moment (3, 3): mean |D p + e|^2 = tr(D M D^T) + 2 e . D mean + |e|^2 (a
    revolution's 360 declared symmetries are compared with every turn)."""
    mean, M = moments
    D, e = A[:3, :3] - B[:3, :3], A[:3, 3] - B[:3, 3]
    return float(np.sqrt(max(0.0, np.trace(D @ M @ D.T) + 2.0 * e @ (D @ mean) + e @ e)))
