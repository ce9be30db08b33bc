"""Blocks: spatially contiguous sets of n points (the nearest neighbours of a seed point).

Training crops and inference passes both use them, so the network always sees the point density
of the voxel grid, whatever the size of the scene.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def block_around(tree: cKDTree, n_total: int, seed_point: np.ndarray, n_points: int) -> np.ndarray:
    """Indices (min(n_points, n_total),) of the points nearest to seed_point, nearest first."""
    k = min(n_points, n_total)
    _, idx = tree.query(seed_point, k=k)
    return np.atleast_1d(idx).astype(np.int64)


def crop(points: np.ndarray, n_points: int, rng: np.random.Generator) -> np.ndarray:
    """Indices (n_points,) of a training crop: the block around a random point, or all points
    repeated at random up to n_points when the scene is smaller."""
    n = len(points)
    if n > n_points:
        return block_around(cKDTree(points), n, points[rng.integers(n)], n_points)
    return np.concatenate([np.arange(n), rng.choice(n, size=n_points - n, replace=True)]) if n < n_points else np.arange(n)


def cover(points: np.ndarray, n_points: int, rng: np.random.Generator) -> list[tuple[int, np.ndarray]]:
    """Blocks (seed index, indices) that together cover every point; seeds are drawn among the
    points not yet covered, so blocks overlap little."""
    n = len(points)
    if n <= n_points:
        return [(0, np.arange(n))]
    tree = cKDTree(points)
    covered = np.zeros(n, dtype=bool)
    blocks = []
    while not covered.all():
        seed = int(rng.choice(np.flatnonzero(~covered)))
        idx = block_around(tree, n, points[seed], n_points)
        covered[idx] = True
        blocks.append((seed, idx))
    return blocks
