"""The pinhole camera: one type for the renderer, depth images, fitted frames and overlays.

Camera frame OpenCV (x right, y down, z forward), metres. Pixel (u, v) is column u, row v, with the
centre of the top-left pixel at (0, 0): a point (x, y, z) projects to u = fx x / z + cx,
v = fy y / z + cy.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class PinholeCamera:
    """Pinhole intrinsics in pixels of a width x height frame."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @classmethod
    def from_K(cls, K: np.ndarray, width: int, height: int) -> PinholeCamera:
        """From a (3, 3) intrinsic matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]."""
        K = np.asarray(K, dtype=float)
        return cls(
            width=int(width),
            height=int(height),
            fx=float(K[0, 0]),
            fy=float(K[1, 1]),
            cx=float(K[0, 2]),
            cy=float(K[1, 2]),
        )

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W), the order of an image array."""
        return self.height, self.width

    def downscaled(self, factor: int) -> PinholeCamera:
        """The same camera with factor x factor pixels binned into one (pixel centres move with
        the binning: the new pixel (0, 0) is the centre of the old block)."""
        return PinholeCamera(
            width=self.width // factor,
            height=self.height // factor,
            fx=self.fx / factor,
            fy=self.fy / factor,
            cx=(self.cx + 0.5) / factor - 0.5,
            cy=(self.cy + 0.5) / factor - 0.5,
        )

    def fits(self, shape: tuple[int, int]) -> str | None:
        """Why these intrinsics cannot belong to an image of this (H, W) (the principal point
        outside it, a focal length not positive), None when they can."""
        H, W = shape
        if not (self.fx > 0 and self.fy > 0):
            return f"focal lengths must be positive (fx {self.fx}, fy {self.fy})"
        if not (0.0 <= self.cx <= W and 0.0 <= self.cy <= H):
            return (
                f"principal point ({self.cx:g}, {self.cy:g}) px lies outside the {W} x {H} image: "
                "intrinsics of another resolution?"
            )
        return None

    def back_project(self, depth_m: np.ndarray) -> np.ndarray:
        """(H * W, 3) float32 camera-frame points of an (H, W) depth image (z per pixel, any
        unit; NaN stays NaN), row-major like the image."""
        z = np.asarray(depth_m, dtype=np.float32)
        if z.ndim != 2:
            raise ValueError(f"expected an (H, W) depth image, got {z.shape}")
        H, W = z.shape
        u, v = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
        return np.stack([(u - self.cx) / self.fx * z, (v - self.cy) / self.fy * z, z], axis=-1).reshape(-1, 3)

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """(n, 2) pixel coordinates (u, v) of camera-frame points (n, 3) in front of the camera
        (z > 0; others come out as NaN)."""
        p = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(p[:, 2] > 0, p[:, 2], np.nan)
            return np.column_stack([self.fx * p[:, 0] / z + self.cx, self.fy * p[:, 1] / z + self.cy])

    def ray_directions(self) -> np.ndarray:
        """(H, W, 3) float32 ray directions with z = 1 through each pixel's centre, so that a hit
        distance along one is the depth."""
        u, v = np.meshgrid(np.arange(self.width, dtype=np.float32), np.arange(self.height, dtype=np.float32))
        return np.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fy, np.ones_like(u)], axis=-1)


def in_view_of(camera: PinholeCamera, T_cam_from_bin: np.ndarray) -> Callable[[np.ndarray], bool]:
    """Whether any of some points (n, 3), bin frame, lies in the camera's image (in front of it)."""

    def in_view(points_bin: np.ndarray) -> bool:
        uv = camera.project(points_bin @ T_cam_from_bin[:3, :3].T + T_cam_from_bin[:3, 3])
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)
        return bool(np.any(inside))

    return in_view
