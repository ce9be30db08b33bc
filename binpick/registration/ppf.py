"""Point pair feature matching (Drost, Ulrich, Navab, Ilic, CVPR 2010), vectorised in NumPy.

Model side: every ordered pair of subsampled model points gives the feature
F = (||d||, angle(n1, d), angle(n2, d), angle(n1, n2)), quantised into a key; pairs are stored
sorted by key with the reference point and the angle alpha_m. Scene side: each reference point is
paired with its neighbours within the model diameter, matching model pairs vote for
(model point, alpha), peaks become poses, poses are clustered in SE(3) with rotation AND
translation thresholds (symmetry-aware), the best clusters are re-scored against the scene and
refined with point-to-plane ICP on the exact CAD normals.

Frames: model points in the part's model frame, scene points in the camera frame, metres.
Poses are T_cam_from_model.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import open3d as o3d
import numba
from numba import njit
from scipy.spatial import cKDTree

from binpick.geometry.pointcloud import voxel_downsample_indices
from binpick.geometry.transforms import invert_T, transform_points
from binpick.params import RegisterParams

# The voting loop runs on every core through OpenMP or numba's own pool; the TBB found on some
# systems is too old for numba and would only print a warning.
numba.config.THREADING_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]

TOP_CLUSTERS = 4  # clusters refined by coarse ICP and scored per segment
FINE_CLUSTERS = 2  # of those, the best refined by fine ICP
COARSE_STRIDE = 4  # coarse ICP: every 4th dense model point is a target
FINE_STRIDE = 2  # fine ICP: every 2nd
SCORE_STRIDE = 2  # scoring: every 2nd dense model point must find a scene point
MAX_CLUSTER_CANDIDATES = 160  # per segment: the strongest accumulator peaks that are clustered
PEAKS_PER_REFERENCE = 2
SCENE_REFS_PER_CHUNK = 64  # whole-scene voting: references per accumulator
SCENE_CLUSTERS_PER_INSTANCE = 3  # whole-scene matching: clusters refined per instance sought
SCENE_MAX_SHARED_SUPPORT = 0.3  # whole-scene NMS: share of a pose's points a better pose may explain


@dataclass(frozen=True)
class PPFModel:
    """A trained PPF model.

    points_m (M, 3), normals (M, 3): subsampled model surface, model frame.
    keys (P,) int64 sorted; ref_index (P,) int32 model reference point of each pair; alpha (P,)
    float32 angle alpha_m of each pair, radians in (-pi, pi]; key_starts (K + 1,) int64: the pairs
    of key k are keys[key_starts[k]:key_starts[k + 1]] (an O(1) lookup).
    dense_points_m, dense_normals: the full surface sample, for scoring and ICP.
    symmetries (m, 4, 4): transforms of the model frame onto itself, identity first.
    """

    points_m: np.ndarray
    normals: np.ndarray
    keys: np.ndarray
    ref_index: np.ndarray
    alpha: np.ndarray
    key_starts: np.ndarray
    dense_points_m: np.ndarray
    dense_normals: np.ndarray
    symmetries: np.ndarray
    diameter_m: float
    distance_step_m: float
    angle_bins: int


@dataclass(frozen=True)
class PoseEstimate:
    """T_cam_from_model (4, 4); score in [0, 1] (share of the matched surface that agrees)."""

    T_cam_from_model: np.ndarray
    score: float
    votes: float


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


def train_ppf(
    dense_points_m: np.ndarray, dense_normals: np.ndarray, diameter_m: float, symmetries: np.ndarray, params: RegisterParams
) -> PPFModel:
    """Build the PPF table of a part from its dense surface sample (model frame, metres)."""
    if dense_points_m.ndim != 2 or dense_points_m.shape[1] != 3 or dense_normals.shape != dense_points_m.shape:
        raise ValueError("expected dense points and normals (n, 3)")
    idx = voxel_downsample_indices(dense_points_m, params.sample_step_rel * diameter_m)
    pts = dense_points_m[idx].astype(np.float64)
    nrm = dense_normals[idx].astype(np.float64)
    M = len(pts)
    i, j = np.meshgrid(np.arange(M), np.arange(M), indexing="ij")
    i, j = i[i != j], j[i != j]
    step = params.distance_step_rel * diameter_m
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
        diameter_m=float(diameter_m),
        distance_step_m=step,
        angle_bins=params.angle_bins,
    )


def _vote(model: PPFModel, pts: np.ndarray, nrm: np.ndarray, refs: np.ndarray) -> list[tuple[np.ndarray, float]]:
    """Pose candidates (T_cam_from_model, votes) from the accumulator peaks of each reference."""
    T_s = _align_to_x(pts, nrm)
    group_start, keys, alpha_s = _scene_pairs(
        pts, nrm / np.linalg.norm(nrm, axis=1, keepdims=True), np.ascontiguousarray(T_s[:, :3, :3]),
        np.ascontiguousarray(T_s[:, :3, 3]), refs.astype(np.int64), model.diameter_m, model.distance_step_m, model.angle_bins,
    )
    if len(keys) == 0:
        return []
    A = model.angle_bins
    peak_flat, peak_votes = _accumulate_peaks(
        # The table as stored (int64 / int32 / float32): a converted copy would cost more than the voting.
        group_start, keys, alpha_s, np.asarray(model.key_starts, np.int64),
        np.asarray(model.ref_index, np.int32), np.asarray(model.alpha, np.float32), len(refs), len(model.points_m), A, PEAKS_PER_REFERENCE,
        4 * numba.get_num_threads(),
    )
    valid = peak_votes > 0
    ref_rows, _ = np.nonzero(valid)
    m_r, a_bin = np.divmod(peak_flat[valid], A)
    a = -np.pi + (a_bin + 0.5) * 2 * np.pi / A
    Rx = np.zeros((len(a), 4, 4))
    Rx[:, 0, 0] = Rx[:, 3, 3] = 1.0
    Rx[:, 1, 1], Rx[:, 1, 2], Rx[:, 2, 1], Rx[:, 2, 2] = np.cos(a), -np.sin(a), np.sin(a), np.cos(a)
    T_m = _align_to_x(model.points_m, model.normals)
    poses = invert_T(T_s[refs[ref_rows]]) @ Rx @ T_m[m_r]
    return list(zip(poses, peak_votes[valid].astype(np.float64)))


@njit(cache=True, nogil=True, parallel=True)
def _scene_pairs(pts, unit_normals, R_align, t_align, refs, radius, distance_step, n_angles):  # pragma: no cover - compiled
    """Every pair (reference refs[a], other point within radius), grouped by reference: the group
    bounds (n_refs + 1,), the quantised feature key of each pair and the angle alpha that turns
    the aligned partner into the half-plane y > 0, z = 0 (the same quantities as _features,
    _keys and _alpha, in one pass without temporaries; references spread over the cores)."""
    n_refs, n = len(refs), len(pts)
    r2 = radius * radius
    counts = np.zeros(n_refs + 1, np.int64)
    for a in numba.prange(n_refs):
        i = refs[a]
        c = 0
        for j in range(n):
            dx, dy, dz = pts[j, 0] - pts[i, 0], pts[j, 1] - pts[i, 1], pts[j, 2] - pts[i, 2]
            if j != i and dx * dx + dy * dy + dz * dz <= r2:
                c += 1
        counts[a + 1] = c
    starts = np.cumsum(counts)
    keys = np.empty(starts[-1], np.int64)
    alpha = np.empty(starts[-1])
    for a in numba.prange(n_refs):
        i = refs[a]
        k = starts[a]
        for j in range(n):
            dx, dy, dz = pts[j, 0] - pts[i, 0], pts[j, 1] - pts[i, 1], pts[j, 2] - pts[i, 2]
            d2 = dx * dx + dy * dy + dz * dz
            if j == i or d2 > r2:
                continue
            dist = np.sqrt(d2)
            inv = 1.0 / max(dist, 1e-12)
            ux, uy, uz = dx * inv, dy * inv, dz * inv
            c1 = unit_normals[i, 0] * ux + unit_normals[i, 1] * uy + unit_normals[i, 2] * uz
            c2 = unit_normals[j, 0] * ux + unit_normals[j, 1] * uy + unit_normals[j, 2] * uz
            c3 = unit_normals[i, 0] * unit_normals[j, 0] + unit_normals[i, 1] * unit_normals[j, 1] + unit_normals[i, 2] * unit_normals[j, 2]
            key = np.int64(np.floor(dist / distance_step))
            for cosine in (c1, c2, c3):
                q = np.int64(np.arccos(min(max(cosine, -1.0), 1.0)) / np.pi * n_angles)
                key = key * n_angles + min(q, n_angles - 1)
            keys[k] = key
            py = R_align[i, 1, 0] * pts[j, 0] + R_align[i, 1, 1] * pts[j, 1] + R_align[i, 1, 2] * pts[j, 2] + t_align[i, 1]
            pz = R_align[i, 2, 0] * pts[j, 0] + R_align[i, 2, 1] * pts[j, 1] + R_align[i, 2, 2] * pts[j, 2] + t_align[i, 2]
            alpha[k] = np.arctan2(-pz, py)
            k += 1
    return starts, keys, alpha


@njit(cache=True, nogil=True, parallel=True)
def _accumulate_peaks(group_start, keys, alpha_s, key_starts, ref_index, alpha_m, n_refs, n_model, n_angles, n_peaks, n_chunks):  # pragma: no cover - compiled
    """The voting loop: every scene pair votes for (model reference point, alpha bin) of each
    model pair with its key; per scene reference, the n_peaks strongest accumulator cells.

    The pairs of reference r are group_start[r]:group_start[r + 1], as _scene_pairs makes them.
    References are spread over the cores in chunks, each with its own accumulator row, reset
    between references (only the touched cells), so the result does not depend on the cores.
    Returns (n_refs, n_peaks) flat cell indices (model point * n_angles + alpha bin) and votes.
    """
    peak_flat = np.zeros((n_refs, n_peaks), np.int64)
    peak_votes = np.zeros((n_refs, n_peaks), np.int32)
    n_keys = len(key_starts) - 1
    scale = n_angles / (2.0 * np.pi)
    n_chunks = min(n_chunks, n_refs)
    for c in numba.prange(n_chunks):
        acc = np.zeros(n_model * n_angles, np.int32)
        touched = np.empty(n_model * n_angles, np.int64)
        for r in range(c * n_refs // n_chunks, (c + 1) * n_refs // n_chunks):
            n_touched = 0
            for p in range(group_start[r], group_start[r + 1]):
                k = keys[p]
                if k < n_keys:
                    # bin of (alpha_m - alpha_s + pi) * scale, shifted by n_angles to be positive
                    # (truncation is then floor) and wrapped by at most two subtractions.
                    offset = (np.pi - alpha_s[p]) * scale + n_angles
                    for q in range(key_starts[k], key_starts[k + 1]):
                        b = int(alpha_m[q] * scale + offset)
                        while b >= n_angles:
                            b -= n_angles
                        cell = np.int64(ref_index[q]) * n_angles + b
                        if acc[cell] == 0:
                            touched[n_touched] = cell
                            n_touched += 1
                        acc[cell] += 1
            for t in range(n_touched):
                cell = touched[t]
                v = acc[cell]
                # insert into this reference's top list (sorted, strongest first; ties: first seen)
                for slot in range(n_peaks):
                    if v > peak_votes[r, slot]:
                        for j in range(n_peaks - 1, slot, -1):
                            peak_votes[r, j] = peak_votes[r, j - 1]
                            peak_flat[r, j] = peak_flat[r, j - 1]
                        peak_votes[r, slot] = v
                        peak_flat[r, slot] = cell
                        break
                acc[cell] = 0
    return peak_flat, peak_votes


def _cluster(
    candidates: list[tuple[np.ndarray, float]], model: PPFModel, params: RegisterParams, max_candidates: int | None = None
) -> list[tuple[np.ndarray, float]]:
    """Greedy SE(3) clustering: a pose joins the first (strongest) cluster whose best pose, or a
    symmetric twin of it, is within the rotation AND the translation threshold. Returns
    (best pose, summed votes), strongest first. max_candidates: only the strongest poses are
    clustered (weak peaks, from references on clutter or ambiguous patches, decide nothing)."""
    order = sorted(range(len(candidates)), key=lambda k: -candidates[k][1])[:max_candidates]
    if not order:
        return []
    poses = np.ascontiguousarray(np.stack([candidates[k][0] for k in order]), dtype=np.float64)
    weights = np.array([candidates[k][1] for k in order], dtype=np.float64)
    reps, votes = _greedy_clusters(
        poses, weights, np.ascontiguousarray(model.symmetries, dtype=np.float64),
        np.cos(np.radians(params.cluster_rotation_deg)), params.cluster_translation_rel * model.diameter_m,
    )
    ranked = sorted(range(len(reps)), key=lambda c: -votes[c])
    return [(poses[reps[c]], float(votes[c])) for c in ranked]


@numba.njit(cache=True)
def _greedy_clusters(poses, weights, symmetries, min_cos, max_dist):  # pragma: no cover - compiled
    """Indices of the cluster representatives (in order of creation) and each cluster's votes.

    The twins (pose @ symmetry) of each representative are made once; a pose is tested against
    a twin's translation first (three numbers) and only then its rotation: cos of the relative
    angle = (trace(R_twin^T R) - 1) / 2."""
    n, m = len(poses), len(symmetries)
    twins = np.empty((n * m, 3, 4))
    reps = np.empty(n, np.int64)
    votes = np.zeros(n)
    n_reps = 0
    d2 = max_dist * max_dist
    for k in range(n):
        T = poses[k]
        found = -1
        for c in range(n_reps):
            for s in range(m):
                W = twins[c * m + s]
                dx, dy, dz = W[0, 3] - T[0, 3], W[1, 3] - T[1, 3], W[2, 3] - T[2, 3]
                if dx * dx + dy * dy + dz * dz >= d2:
                    continue
                tr = 0.0
                for a in range(3):
                    for b in range(3):
                        tr += W[a, b] * T[a, b]
                if (tr - 1.0) / 2.0 > min_cos:
                    found = c
                    break
            if found >= 0:
                break
        if found >= 0:
            votes[found] += weights[k]
            continue
        for s in range(m):
            S = symmetries[s]
            for a in range(3):
                for b in range(4):
                    v = 0.0
                    for e in range(4):
                        v += T[a, e] * S[e, b]
                    twins[n_reps * m + s, a, b] = v
        reps[n_reps] = k
        votes[n_reps] = weights[k]
        n_reps += 1
    return reps[:n_reps], votes[:n_reps]


def score_pose(
    model: PPFModel, T_cam_from_model: np.ndarray, scene_points: np.ndarray, inlier_m: float, scene_tree: cKDTree | None = None,
    whole_scene: bool = False, stride: int = SCORE_STRIDE,
) -> float:
    """Score in [0, 1]: geometric mean of the share of camera-facing model points with a scene
    point within inlier_m, and the share of scene points within inlier_m of the model. On a
    whole scene (other parts around) only the first share counts."""
    if len(scene_points) == 0:
        return 0.0
    facing = _facing(model, T_cam_from_model, stride)
    if not facing.any():
        return 0.0
    scene_tree = scene_tree or cKDTree(scene_points)
    d_model, _ = scene_tree.query(transform_points(T_cam_from_model, model.dense_points_m[::stride][facing]), distance_upper_bound=inlier_m)
    if whole_scene:
        return float(np.mean(np.isfinite(d_model)))
    # Scene points against the model's own tree, in the model frame: built once per model.
    d_scene, _ = _model_tree(model).query(transform_points(invert_T(T_cam_from_model), scene_points), distance_upper_bound=inlier_m)
    return float(np.sqrt(np.mean(np.isfinite(d_model)) * np.mean(np.isfinite(d_scene))))


_TREES: dict[int, tuple[np.ndarray, cKDTree]] = {}


def _model_tree(model: PPFModel) -> cKDTree:
    """A kd-tree of the dense model points, cached per model (keyed by the array's identity)."""
    key = id(model.dense_points_m)
    cached = _TREES.get(key)
    if cached is None or cached[0] is not model.dense_points_m:
        _TREES.clear()  # one model at a time is the common case; keep memory bounded
        cached = (model.dense_points_m, cKDTree(model.dense_points_m))
        _TREES[key] = cached
    return cached[1]


def _facing(model: PPFModel, T_cam_from_model: np.ndarray, stride: int = 1) -> np.ndarray:
    """Mask of the dense model points (every stride-th) whose normal faces the camera (at the
    origin) at this pose."""
    pts, nrm = model.dense_points_m[::stride], model.dense_normals[::stride]
    p = pts @ T_cam_from_model[:3, :3].T + T_cam_from_model[:3, 3]
    n = nrm @ T_cam_from_model[:3, :3].T
    return np.sum(n * p, axis=1) < 0


def refine_icp(
    model: PPFModel, T_cam_from_model: np.ndarray, scene_points: np.ndarray, max_distance_m: float, iterations: int, stride: int = 1
) -> np.ndarray:
    """Point-to-plane ICP of the scene points onto the model surface (exact CAD normals).

    Only model points facing the camera at the starting pose are targets: a thin wall's inner
    surface lies within a few millimetres of its outer one, and matching the camera's view of the
    outside to the inside holds ICP in a wrong minimum.
    """
    if iterations == 0 or len(scene_points) < 6:
        return T_cam_from_model
    facing = _facing(model, T_cam_from_model, stride)
    if facing.sum() < 6:
        return T_cam_from_model
    source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(scene_points, dtype=np.float64)))
    target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(model.dense_points_m[::stride][facing]))
    target.normals = o3d.utility.Vector3dVector(model.dense_normals[::stride][facing])
    result = o3d.pipelines.registration.registration_icp(
        source,
        target,
        max_distance_m,
        invert_T(T_cam_from_model),
        o3d.pipelines.registration.TransformationEstimationPointToPlane(),
        o3d.pipelines.registration.ICPConvergenceCriteria(relative_fitness=1e-4, relative_rmse=1e-4, max_iteration=iterations),
    )
    return invert_T(np.asarray(result.transformation))


def match_segment(
    model: PPFModel, scene_points: np.ndarray, scene_normals: np.ndarray, params: RegisterParams, rng: np.random.Generator
) -> PoseEstimate | None:
    """The best pose of the part on one segment (camera frame points and normals), or None."""
    if scene_points.ndim != 2 or scene_points.shape[1] != 3 or scene_normals.shape != scene_points.shape:
        raise ValueError("expected scene points and normals (n, 3)")
    idx = voxel_downsample_indices(scene_points, params.sample_step_rel * model.diameter_m)
    if len(idx) < 3:
        return None
    pts, nrm = scene_points[idx].astype(np.float64), scene_normals[idx].astype(np.float64)
    n_refs = max(1, int(round(params.scene_ref_fraction * len(pts))))
    refs = np.sort(rng.choice(len(pts), size=n_refs, replace=False))
    candidates = _vote(model, pts, nrm, refs)
    if not candidates:
        return None
    # Refinement and scoring work on a grid finer than the voting one but bounded, so that their
    # cost does not grow with the density of the capture.
    scene_points = scene_points[voxel_downsample_indices(scene_points, params.refine_step_rel * model.diameter_m)]
    inlier = params.score_inlier_rel * model.diameter_m
    scene_tree = cKDTree(scene_points)
    # Each strong cluster is refined by coarse ICP (on a subsample of the model) and scored;
    # comparing clusters only after ICP keeps a pose slid along a long part from winning. The
    # FINE_CLUSTERS best get the fine ICP and are scored again.
    coarse: list[tuple[float, np.ndarray, float]] = []
    for T, votes in _cluster(candidates, model, params, MAX_CLUSTER_CANDIDATES)[:TOP_CLUSTERS]:
        T = refine_icp(model, T, scene_points, 2.0 * params.sample_step_rel * model.diameter_m, params.icp_iterations, COARSE_STRIDE)
        coarse.append((score_pose(model, T, scene_points, inlier, scene_tree, stride=COARSE_STRIDE), T, votes))
    best: PoseEstimate | None = None
    for _, T, votes in sorted(coarse, key=lambda c: -c[0])[:FINE_CLUSTERS]:
        T = refine_icp(model, T, scene_points, 2.0 * inlier, params.icp_iterations, FINE_STRIDE)
        score = score_pose(model, T, scene_points, inlier, scene_tree)
        if best is None or score > best.score:
            best = PoseEstimate(T_cam_from_model=T, score=score, votes=votes)
    return best


def match_scene(
    model: PPFModel, scene_points: np.ndarray, scene_normals: np.ndarray, params: RegisterParams, rng: np.random.Generator,
    max_instances: int = 30, known: Sequence[np.ndarray] = (),
) -> list[PoseEstimate]:
    """Every instance of the part in a whole scene, without segments: votes from reference
    points all over the scene, the strongest pose clusters refined and scored, poses scoring
    below params.min_score dropped, then non-maximum suppression by explained points. Best first.

    scene_points, scene_normals : (n, 3) camera frame, metres; normals facing the camera.
    known : poses T_cam_from_model found already (e.g. on segments); the scene points they
            explain are taken, and only other instances are returned.
    """
    if scene_points.ndim != 2 or scene_points.shape[1] != 3 or scene_normals.shape != scene_points.shape:
        raise ValueError("expected scene points and normals (n, 3)")
    idx = voxel_downsample_indices(scene_points, params.sample_step_rel * model.diameter_m)
    if len(idx) < 3:
        return []
    pts, nrm = scene_points[idx].astype(np.float64), scene_normals[idx].astype(np.float64)
    n_refs = max(1, int(round(params.scene_ref_fraction * len(pts))))
    refs = np.sort(rng.choice(len(pts), size=n_refs, replace=False))
    candidates: list[tuple[np.ndarray, float]] = []
    # In chunks: the accumulator holds (references x model points x angle bins) counts.
    for chunk in np.array_split(refs, int(np.ceil(len(refs) / SCENE_REFS_PER_CHUNK))):
        candidates += _vote(model, pts, nrm, chunk)
    fine = scene_points[voxel_downsample_indices(scene_points, params.refine_step_rel * model.diameter_m)]
    inlier = params.score_inlier_rel * model.diameter_m
    tree = cKDTree(fine)
    estimates: list[PoseEstimate] = []
    support: list[np.ndarray] = []
    centre = model.dense_points_m.mean(axis=0)
    reach = _reach(model, params)

    def explained(T: np.ndarray) -> np.ndarray:
        return _explained(model, T, fine, tree, inlier, reach)

    for T, votes in _cluster(candidates, model, params)[: SCENE_CLUSTERS_PER_INSTANCE * max_instances]:
        # ICP and support only see the scene around the pose: the rest cannot match this part.
        near = np.asarray(tree.query_ball_point(T[:3, :3] @ centre + T[:3, 3], reach), dtype=np.int64)
        if len(near) < 6:
            continue
        local = fine[near]
        T = refine_icp(model, T, local, 2.0 * params.sample_step_rel * model.diameter_m, params.icp_iterations, COARSE_STRIDE)
        T = refine_icp(model, T, local, 2.0 * inlier, params.icp_iterations, FINE_STRIDE)
        score = score_pose(model, T, fine, inlier, tree, whole_scene=True)
        if score >= params.min_score:
            estimates.append(PoseEstimate(T_cam_from_model=T, score=score, votes=votes))
            support.append(explained(T))
    claimed = np.zeros(len(fine), bool)
    for T in known:
        claimed[explained(np.asarray(T))] = True
    return [estimates[k] for k in _suppress_by_support([e.score for e in estimates], support, claimed)][:max_instances]


def _reach(model: PPFModel, params: RegisterParams) -> float:
    """Radius around a pose's centre within which scene points can belong to it."""
    return 0.5 * model.diameter_m + 2.0 * params.sample_step_rel * model.diameter_m


def _explained(model: PPFModel, T: np.ndarray, points: np.ndarray, tree: cKDTree, inlier_m: float, reach_m: float) -> np.ndarray:
    """Indices of the scene points (n, 3), in `tree`, within inlier_m of the model surface at pose T."""
    near = np.asarray(tree.query_ball_point(T[:3, :3] @ model.dense_points_m.mean(axis=0) + T[:3, 3], reach_m), dtype=np.int64)
    if len(near) == 0:
        return near
    d, _ = _model_tree(model).query(transform_points(invert_T(T), points[near]), distance_upper_bound=inlier_m)
    return near[np.isfinite(d)]


def _suppress_by_support(scores: Sequence[float], support: Sequence[np.ndarray], claimed: np.ndarray) -> list[int]:
    """Non-maximum suppression by explained points, best score first: a pose whose supporting
    scene points are mostly claimed by a better pose already (a repeat, a wrong fit on a fragment
    of a part found whole, or a fit bridging two neighbouring parts) is dropped, whatever its
    pose. claimed (n,) bool, updated in place. Returns the kept indices, best first."""
    kept: list[int] = []
    for k in sorted(range(len(scores)), key=lambda k: -scores[k]):
        if len(support[k]) == 0 or claimed[support[k]].mean() > SCENE_MAX_SHARED_SUPPORT:
            continue
        claimed[support[k]] = True
        kept.append(k)
    return kept


def _close(A: np.ndarray, B: np.ndarray, rotation_deg: float, translation_m: float) -> np.ndarray:
    """(a, b) mask: pose A[i] within translation_m AND rotation_deg of pose B[j]; A (a, 4, 4), B (b, 4, 4)."""
    close_t = np.linalg.norm(A[:, None, :3, 3] - B[None, :, :3, 3], axis=2) < translation_m
    # cos of the relative angle: (trace(R_a^T R_b) - 1) / 2
    cos = (np.einsum("aij,bij->ab", A[:, :3, :3], B[:, :3, :3]) - 1.0) / 2.0
    return close_t & (cos > np.cos(np.radians(rotation_deg)))


def _near(poses: np.ndarray, T: np.ndarray, rotation_deg: float, translation_m: float) -> np.ndarray:
    """(n,) mask of the poses (n, 4, 4) within translation_m AND rotation_deg of T."""
    return _close(poses, T[None], rotation_deg, translation_m)[:, 0]


def same_pose(model: PPFModel, T_a: np.ndarray, T_b: np.ndarray, rotation_deg: float, translation_m: float) -> bool:
    """Whether two poses of the part agree within the thresholds, up to the part's symmetries."""
    return bool(_near(T_a[None] @ model.symmetries, T_b, rotation_deg, translation_m).any())


def suppress_duplicates(
    model: PPFModel, estimates: list[PoseEstimate], params: RegisterParams, scene_points: np.ndarray | None = None
) -> list[int]:
    """Indices of the estimates kept by non-maximum suppression, best score first: an estimate
    that repeats the pose of a better one (one part split into two segments) is dropped; with
    the whole scene's points (n, 3), so is one whose supporting points a better one explains
    (a wrong fit on the fragment of a part that another segment gave whole)."""
    order = sorted(range(len(estimates)), key=lambda k: -estimates[k].score)
    kept: list[int] = []
    trans_thr = params.cluster_translation_rel * model.diameter_m
    for k in order:
        T = estimates[k].T_cam_from_model
        if not any(same_pose(model, estimates[j].T_cam_from_model, T, params.cluster_rotation_deg, trans_thr) for j in kept):
            kept.append(k)
    if scene_points is None or len(kept) < 2:
        return kept
    fine = scene_points[voxel_downsample_indices(scene_points, params.refine_step_rel * model.diameter_m)]
    tree = cKDTree(fine)
    inlier, reach = params.score_inlier_rel * model.diameter_m, _reach(model, params)
    support = [_explained(model, estimates[k].T_cam_from_model, fine, tree, inlier, reach) for k in kept]
    by_support = _suppress_by_support([estimates[k].score for k in kept], support, np.zeros(len(fine), bool))
    return [kept[i] for i in by_support]
