"""Blocks: spatially contiguous sets of n points (the nearest neighbours of a seed point).

Training crops and inference passes both use them, so the network always sees the point density
of the voxel grid, whatever the size of the scene.
"""

from __future__ import annotations

import numpy as np
from numba import njit
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
    return (
        np.concatenate([np.arange(n), rng.choice(n, size=n_points - n, replace=True)]) if n < n_points else np.arange(n)
    )


def cover(points: np.ndarray, n_points: int, rng: np.random.Generator) -> list[tuple[int, np.ndarray]]:
    """Blocks (seed index, indices) that together cover the points: every point lies in a
    block's ball (the n_points nearest neighbours of its seed) or less than the median point
    spacing outside one. The first block is around a random point, each next one around the
    uncovered point farthest from every block so far (the middle of the largest region left),
    so that each pass covers as much new ground as it can."""
    n = len(points)
    if n <= n_points:
        return [(0, np.arange(n))]
    tree = cKDTree(points)
    spacing = float(np.median(tree.query(points[:: max(1, n // 1000)], k=2)[0][:, 1]))
    covered = np.zeros(n, dtype=bool)
    # Each point's distance outside the nearest block, a block being the ball of its seed's
    # n_points nearest neighbours: |p - seed| - radius, at most 0 inside.
    outside = np.full(n, np.inf)
    blocks = []
    seed = int(rng.integers(n))
    while True:
        idx = block_around(tree, n, points[seed], n_points)
        covered[idx] = True
        blocks.append((seed, idx))
        radius = float(np.linalg.norm(points[idx[-1]] - points[seed]))  # nearest first: the last is the farthest
        # A point less than a point spacing outside a ball is on its rim, next to points in it:
        # it takes their labels (label_blocks) instead of a pass of its own (one that covered 1-7
        # new points in a third of the bins of 8 and 20 T-joints).
        # A seed drawn at random among the uncovered points often fell at the rim of a block,
        # and its pass (a whole network pass) covered a few hundred points, or four: 5-6 passes
        # over an 8-part T-joint bin of 11,000 points, 4-5 with this choice.
        seed = _grow(points, seed, np.array([radius], points.dtype), spacing, outside, covered)
        if seed < 0:
            return blocks


@njit(cache=True)
def _grow(points, seed, radius, spacing, outside, covered):  # pragma: no cover - compiled
    """One block's ball (points (n, 3) around points[seed], radius (1,) in the points' dtype)
    added: each point's distance outside the nearest ball (outside (n,), updated), the points
    within spacing of a ball marked covered; returns the uncovered point farthest outside every
    ball (the first of equals), or -1 when all are covered. One pass without temporaries: the
    same arithmetic in numpy had cost 3 s a part over a 1 m bin of 300,000 points."""
    best, best_i = -np.inf, -1
    r = radius[0]
    for i in range(len(points)):
        dx, dy, dz = points[i, 0] - points[seed, 0], points[i, 1] - points[seed, 1], points[i, 2] - points[seed, 2]
        d = np.sqrt(dx * dx + dy * dy + dz * dz) - r
        if d < outside[i]:
            outside[i] = d
        if outside[i] <= spacing:
            covered[i] = True
        if not covered[i] and outside[i] > best:
            best, best_i = outside[i], i
    return best_i
