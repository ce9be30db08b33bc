"""The network's view of a cloud: the voxel grid and the normals that both the training scenes
(generation) and the imported captures are given, so that training sees the point density and
the normals inference sees. This module is their one owner: generation and import call it.

Points are (n, 3) in the camera frame, metres; normals face the camera at the origin.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from binpick.geometry.pointcloud import estimate_normals, voxel_downsample_indices
from binpick.params import ImportCaptureParams


@dataclass(frozen=True)
class ViewParams:
    """voxel_size_m: one point kept per voxel of this size (0 = all); normal_radius_m: radius of
    the neighbourhood a normal is fitted to."""

    voxel_size_m: float
    normal_radius_m: float
    # The import step's settings: when given, a generated scene's view is its frame cleaned as the
    # import step cleans a capture (floor, walls and outliers removed; whatever else is left, a
    # distractor or a rim, stays in labelled -1, as the network meets it in a capture), else
    # the part's points alone.
    cleaning: ImportCaptureParams | None = None

    @classmethod
    def of_import(cls, params: ImportCaptureParams) -> ViewParams:
        """The view the import step gives a capture with these settings."""
        return cls(voxel_size_m=params.voxel_size_m, normal_radius_m=params.normal_radius_m, cleaning=params)


def view_grid(points: np.ndarray, view: ViewParams) -> np.ndarray:
    """Indices (m,) of the points (n, 3) kept on the view's voxel grid (the first of each voxel, sorted)."""
    return voxel_downsample_indices(points, view.voxel_size_m)


def view_normals(points: np.ndarray, view: ViewParams) -> np.ndarray:
    """(n, 3) float32 unit normals of the points (n, 3), facing the camera."""
    return estimate_normals(points, view.normal_radius_m)


def labelled_view(xyz_m: np.ndarray, labels: np.ndarray, view: ViewParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The network's view of a labelled organized frame: the labelled points on the view's grid,
    with their normals.

    xyz_m (H, W, 3) camera frame, NaN = no return; labels (H, W), -1 = not a part. Returns points
    (N, 3) float32, normals (N, 3) float32, labels (N,) int16.
    """
    flat_xyz = xyz_m.reshape(-1, 3)
    flat_lab = labels.reshape(-1)
    keep = np.isfinite(flat_xyz[:, 2]) & (flat_lab >= 0)
    pts, lab = flat_xyz[keep], flat_lab[keep]
    idx = view_grid(pts, view)
    pts, lab = pts[idx], lab[idx]
    if len(pts) == 0:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32), np.zeros(0, np.int16)
    return pts.astype(np.float32), view_normals(pts, view), lab.astype(np.int16)
