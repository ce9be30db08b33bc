"""Point-cloud kernels on arrays; Open3D and SciPy are used inside and never leak out.

All points are (n, 3) float32/float64 in metres, in whatever frame the caller uses; normals are
(n, 3) unit vectors in the same frame.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
from numba import njit, prange
from pykdtree.kdtree import KDTree


def _check_points(points: np.ndarray, name: str = "points") -> np.ndarray:
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"expected {name} (n, 3), got {points.shape}")
    return points


def _o3d_cloud(points: np.ndarray, normals: np.ndarray | None = None) -> o3d.geometry.PointCloud:
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    if normals is not None:
        pcd.normals = o3d.utility.Vector3dVector(np.asarray(normals, dtype=np.float64))
    return pcd


# Voxel grids up to this many cells are marked in a dense array (one linear pass); larger ones
# sort their keys instead.
DENSE_VOXEL_CELLS = 1 << 24


def voxel_downsample_indices(points: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """Indices (m,) of one point per occupied voxel: the first point of each voxel, sorted.

    Keeping real points (not voxel means) keeps their labels, colours and pixel positions exact.
    """
    points = _check_points(points)
    if voxel_size_m <= 0 or len(points) == 0:
        return np.arange(len(points))
    return first_in_each_voxel(*_voxel_keys(points, 1.0 / voxel_size_m))


def first_in_each_voxel(flat: np.ndarray, n_cells: int) -> np.ndarray:
    """Indices (m,), sorted, of the first entry of each distinct flat voxel key (n,) int64 in [0, n_cells)."""
    if n_cells <= DENSE_VOXEL_CELLS:
        return _first_in_cell(flat, n_cells)
    _, first = np.unique(flat, return_index=True)
    return np.sort(first)


@njit(cache=True)
def _voxel_keys(points, inv_size):  # pragma: no cover - numba
    """Flat voxel index of each point (x varies fastest, so neighbouring pixels of a frame fall in
    neighbouring cells) and the number of cells of the occupied box. Two passes that recompute
    the cell of each point, instead of an (n, 3) array of them: memory traffic is the cost."""
    n = len(points)
    lo = np.full(3, np.iinfo(np.int64).max)
    hi = np.full(3, np.iinfo(np.int64).min)
    for i in range(n):
        for a in range(3):
            k = np.int64(np.floor(points[i, a] * inv_size))
            lo[a] = min(lo[a], k)
            hi[a] = max(hi[a], k)
    span = hi - lo + 1
    flat = np.empty(n, np.int64)
    for i in range(n):
        kx = np.int64(np.floor(points[i, 0] * inv_size)) - lo[0]
        ky = np.int64(np.floor(points[i, 1] * inv_size)) - lo[1]
        kz = np.int64(np.floor(points[i, 2] * inv_size)) - lo[2]
        flat[i] = (kz * span[1] + ky) * span[0] + kx
    return flat, span[0] * span[1] * span[2]


@njit(cache=True)
def _first_in_cell(flat, n_cells):  # pragma: no cover - numba
    seen = np.zeros(n_cells, np.bool_)
    out = np.empty(len(flat), np.int64)
    m = 0
    for i in range(len(flat)):
        if not seen[flat[i]]:
            seen[flat[i]] = True
            out[m] = i
            m += 1
    return out[:m]


def estimate_normals(
    points: np.ndarray, radius_m: float, viewpoint: np.ndarray | None = None, max_nn: int = 30
) -> np.ndarray:
    """(n, 3) float32 unit normals from local PCA, oriented toward `viewpoint` (default: origin,
    the camera centre in the camera frame)."""
    points = _check_points(points)
    if len(points) == 0:
        return np.zeros((0, 3), np.float32)
    pcd = _o3d_cloud(points)
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius_m, max_nn=max_nn))
    n = np.asarray(pcd.normals)
    vp = np.zeros(3) if viewpoint is None else np.asarray(viewpoint, dtype=np.float64)
    flip = np.sum(n * (vp - points), axis=1) < 0
    n[flip] *= -1
    return n.astype(np.float32)


def sample_normals(points: np.ndarray, index: np.ndarray, k: int = 12) -> np.ndarray:
    """(m, 3) unit normals, unoriented, of points[index] (index (m,) int): the direction of least
    spread of each one's k nearest neighbours among all the points (n, 3). For a sample of a
    cloud, without estimating every point's normal."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    index = np.asarray(index, dtype=np.int64)
    if len(index) == 0:
        return np.zeros((0, 3))
    _, near = KDTree(points).query(points[index], k=min(k, len(points)))
    near = np.asarray(near).reshape(len(index), -1)
    local = points[near]
    local -= local.mean(axis=1, keepdims=True)
    return np.linalg.eigh(np.matmul(local.transpose(0, 2, 1), local))[1][:, :, 0]


# RANSAC scores its hypotheses on at most this many points; inliers and the final fit use all.
RANSAC_MAX_POINTS = 5000
# Hypotheses drawn and scored together (one (points x batch) distance matrix); the stopping rule
# is checked after each batch.
RANSAC_BATCH = 64


def fit_plane_ransac(
    points: np.ndarray,
    threshold_m: float,
    iterations: int,
    seed: int,
    confidence: float = 0.9999,
    across: np.ndarray | None = None,
    max_cos: float = 1.0,
    min_distance_m: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """RANSAC plane on a random subset of at most RANSAC_MAX_POINTS points, stopping once
    `confidence` is reached (at most `iterations` hypotheses), refined by least squares on its
    inliers among all points. Returns (plane (4,) a, b, c, d with unit normal and
    a x + b y + c z + d = 0, inlier mask (n,)). With `across` (3,), a unit vector, only planes
    whose normal makes |cos| <= max_cos with it are drawn (walls across a floor). With
    min_distance_m, only planes at least that far from the origin (the camera) are drawn: the
    points of one image row lie on a plane through the camera, and in a full frame such a fan
    of rows can hold nearly as many points as the floor and end the search before the floor is
    drawn (a full bin of 20 T-joints, one seed in five).

    Written here rather than taken from Open3D: its segment_plane scores hypotheses on parallel
    threads and stops early when one thread's best says so, so the plane it returns depended on
    the machine's load (the IC-BIN frame's floor came out as the desk on a busy machine). Here the
    hypotheses, their order and the stopping point follow the seed alone.
    """
    points = _check_points(points)
    if len(points) < 3:
        raise ValueError("a plane needs at least 3 points")
    rng = np.random.default_rng(seed)
    subset = (
        points
        if len(points) <= RANSAC_MAX_POINTS
        else points[rng.choice(len(points), RANSAC_MAX_POINTS, replace=False)]
    )
    plane = _ransac_plane(subset, threshold_m, iterations, confidence, rng, across, max_cos, min_distance_m)
    inl = np.asarray(points[np.abs(points @ plane[:3] + plane[3]) <= threshold_m], dtype=np.float64)
    if len(inl) >= 3:
        centre = inl.mean(axis=0)
        normal = np.linalg.svd(inl - centre, full_matrices=False)[2][2]
        normal *= np.sign(normal @ plane[:3]) or 1.0
        plane = np.append(normal, -normal @ centre)
    mask = np.abs(points @ plane[:3] + plane[3]) <= threshold_m
    return plane, mask


def _ransac_plane(
    points: np.ndarray,
    threshold_m: float,
    iterations: int,
    confidence: float,
    rng: np.random.Generator,
    across: np.ndarray | None = None,
    max_cos: float = 1.0,
    min_distance_m: float = 0.0,
) -> np.ndarray:
    """The hypothesis (4,) with the most inliers among points (n, 3) (ties: the smaller inlier
    error, then the earlier drawn), drawn RANSAC_BATCH at a time until `iterations` are drawn or
    the standard bound says `confidence` is reached: log(1 - confidence) / log(1 - w^3) for the
    best inlier share w so far. across / max_cos / min_distance_m: as fit_plane_ransac."""
    n = len(points)
    best, best_count, best_err = np.array([0.0, 0.0, 1.0, 0.0]), -1, np.inf
    needed, drawn = iterations, 0
    while drawn < needed:
        k = min(RANSAC_BATCH, needed - drawn)
        a, b, c = (points[rng.integers(0, n, size=k)] for _ in range(3))
        normal = np.cross(b - a, c - a)
        length = np.linalg.norm(normal, axis=1)
        drawn += k
        ok = length > 1e-12  # three distinct, non-collinear points
        if across is not None:
            ok &= np.abs(normal @ across) <= max_cos * length
        if min_distance_m > 0.0:
            ok &= np.abs(np.einsum("ij,ij->i", normal, a)) >= min_distance_m * length
        if not ok.any():
            continue
        normal = normal[ok] / length[ok, None]
        d = -np.einsum("ij,ij->i", normal, a[ok])
        count = _count_inliers(points, np.ascontiguousarray(normal), d, threshold_m)
        top = int(count.max())
        if top < best_count:
            continue
        # The inlier error (the tie-break) only for the hypotheses with the most inliers.
        tied = np.flatnonzero(count == top)
        dist = np.abs(points @ normal[tied].T + d[tied])
        err = np.array([dist[:, k][dist[:, k] <= threshold_m].mean() for k in range(len(tied))])
        j = int(tied[int(np.argmin(err))])
        if top > best_count or err.min() < best_err:
            best, best_count, best_err = np.append(normal[j], d[j]), top, float(err.min())
            share = best_count / n
            if share >= 1.0:
                break
            if share**3 > 1e-12 and confidence < 1.0:
                bound = np.log(1.0 - confidence) / np.log1p(-(share**3))
                needed = min(iterations, max(drawn, int(np.ceil(bound))))
    return best


@njit(cache=True, parallel=True)
def _count_inliers(points, normals, d, threshold_m):  # pragma: no cover - numba
    """(k,) int64: for each plane (normals (k, 3), d (k,)) the points (n, 3) within threshold_m.
    One pass per plane, no (n, k) matrix (a third of numpy's time on 5,000 points); the planes
    spread over the cores, each counted whole, so the counts do not depend on them."""
    k = normals.shape[0]
    out = np.zeros(k, np.int64)
    for j in prange(k):
        a, b, c, e = normals[j, 0], normals[j, 1], normals[j, 2], d[j]
        count = 0
        for i in range(points.shape[0]):
            if abs(a * points[i, 0] + b * points[i, 1] + c * points[i, 2] + e) <= threshold_m:
                count += 1
        out[j] = count
    return out


def statistical_outliers(points: np.ndarray, neighbours: int, std_ratio: float) -> np.ndarray:
    """(n,) bool mask of points kept by statistical outlier removal (Open3D)."""
    points = _check_points(points)
    _, kept = _o3d_cloud(points).remove_statistical_outlier(nb_neighbors=neighbours, std_ratio=std_ratio)
    mask = np.zeros(len(points), dtype=bool)
    mask[np.asarray(kept, dtype=np.int64)] = True
    return mask


def plane_frame(plane: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two orthonormal vectors (2, 3) spanning the plane (a, b, c, d; unit normal) and the point
    (3,) of the plane nearest the origin; (axes, origin) with n, axes[0], axes[1] right-handed."""
    n = np.asarray(plane[:3], dtype=np.float64)
    u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(n, u)]), -float(plane[3]) * n
