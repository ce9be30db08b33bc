"""The depth noise a capture shows about some of its points: how far a sensor's measurements
scatter along their rays. Camera frame, metres."""

from __future__ import annotations

import numpy as np
from pykdtree.kdtree import KDTree

# A capture's noise is capped here: no check that scales with it should test nothing (a seal test
# looser than a few millimetres tests nothing on a 5 mm cup).
MAX_NOISE_SIGMA_M = 0.003
# The noise is measured at up to NOISE_SAMPLE captured points near the pose, each with its
# NOISE_NEIGHBOURS nearest captured points (a few millimetres across at a capture's spacing, where
# a part's surface is flat to well under the noise) ...
NOISE_SAMPLE = 200
NOISE_NEIGHBOURS = 12
MIN_NOISE_POINTS = 30


def image_coordinates(points_m: np.ndarray) -> np.ndarray:
    """(n, 2) x / z, y / z of camera-frame points (n, 3): where they lie in the image."""
    return np.ascontiguousarray(points_m[:, :2] / points_m[:, 2:3])


def local_noise_m(points_m: np.ndarray, image_tree: KDTree | None, at_m: np.ndarray) -> float:
    """The depth noise of a capture about the points at_m (a robust std, metres, at most
    MAX_NOISE_SIGMA_M; 0 with fewer than MIN_NOISE_POINTS of them).

    points_m : (n, 3) the capture, camera frame; image_tree a k-d tree of its image_coordinates;
    at_m (k, 3) where to measure. A sensor's noise moves a point along its ray, not across the
    image, so at each of up to NOISE_SAMPLE points of at_m (evenly strided) the inverse depths
    of its NOISE_NEIGHBOURS nearest points in the image are fitted as a plane (1 / z is linear in
    x / z and y / z on a plane) and their residual std, times z^2, is the depth noise there. The
    median of the variances over the points is robust to edges.
    """
    if image_tree is None or len(at_m) < MIN_NOISE_POINTS:
        return 0.0
    probe = at_m[:: max(1, len(at_m) // NOISE_SAMPLE)]
    _, idx = image_tree.query(image_coordinates(probe), k=NOISE_NEIGHBOURS)
    nbrs = points_m[idx]  # (s, k, 3)
    inverse_depth = 1.0 / nbrs[..., 2]  # (s, k)
    design = np.concatenate(
        [np.ones_like(inverse_depth)[..., None], nbrs[..., :2] / nbrs[..., 2:3]], axis=-1
    )  # (s, k, 3)
    normal = np.einsum("ski,skj->sij", design, design)
    # Neighbours all on one image line (a one-pixel-wide strip) fit no plane.
    keep = np.abs(np.linalg.det(normal)) >= 1e-18
    design, inverse_depth, normal, probe = design[keep], inverse_depth[keep], normal[keep], probe[keep]
    if len(probe) == 0:
        return 0.0
    coef = np.linalg.solve(normal, np.einsum("ski,sk->si", design, inverse_depth)[..., None])[..., 0]
    residual = inverse_depth - np.einsum("ski,si->sk", design, coef)
    variance = np.sum(residual**2, axis=1) / (NOISE_NEIGHBOURS - 3) * probe[:, 2] ** 4
    return float(min(MAX_NOISE_SIGMA_M, np.sqrt(np.median(variance))))
