"""Verification against what the camera saw: a pose is wrong where its surface lies in front of a
measurement, in space the sensor saw through.

For each camera-facing model point at a pose, the depth the camera measured along its ray (a
z-buffer of the capture, `DepthView`) says one of four things: a measurement at the point's depth
supports it; a measurement behind it contradicts it (the sensor saw through the surface); a
measurement in front of it hides it (neutral: another part, the bin wall); no measurement says
nothing. `seen_through_share` is contradicted / (supported + contradicted + hidden): the share of
the model's camera-facing surface that cannot be there. It means the same for every part and
sensor, so one threshold (register.max_seen_through) serves all: a right pose leaves only noise
and silhouette pixels there; a pose on a box wall or floating in front of the wall behind a desk
has most of its surface in seen-through space.

`visible_support_share` is the other side: of the surface the camera should have seen (not
hidden, measured), the share with a measured point on it (register.min_visible_support). A pose
fitted onto something that is only partly the part's shape (a lying cylinder of a shaft's girth
taking the shaft's body, its gear and steps hanging in the air a few centimetres off it, too
close to the measurements to count as seen through) has a third to a half of its visible surface
without support; a right pose, however much of it other parts hide, has nearly all of what is
left in view supported.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from binpick.geometry.camera import PinholeCamera

# The z-buffer keeps the nearest measurement per cell of this many pixels across (a coarser
# grid than the sensor's: robust to single-pixel gaps, cheap to keep in cloud.npz).
CELL_PX = 4
# Pixels the intrinsics of an organized frame are fitted to.
INTRINSICS_SAMPLE = 20000


@dataclass(frozen=True)
class DepthView:
    """depth_m (h, w) float32: the nearest measured depth (z, metres) per cell, inf where none;
    K (3, 3): pinhole intrinsics of that grid (camera frame, OpenCV convention)."""

    depth_m: np.ndarray
    K: np.ndarray

    @classmethod
    def empty(cls) -> DepthView:
        return cls(np.zeros((0, 0), np.float32), np.eye(3))

    @property
    def is_empty(self) -> bool:
        return self.depth_m.size == 0

    def points_m(self) -> np.ndarray:
        """(n, 3) camera frame: each measured cell's nearest point, at the cell's centre ray."""
        if self.is_empty:
            return np.zeros((0, 3))
        v, u = np.nonzero(np.isfinite(self.depth_m))
        z = self.depth_m[v, u].astype(np.float64)
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        return np.column_stack([(u + 0.5 - cx) * z / fx, (v + 0.5 - cy) * z / fy, z])


def fit_intrinsics(xyz_m: np.ndarray, shape: tuple[int, int]) -> PinholeCamera:
    """The pinhole camera of an organized (H, W) cloud, by least squares on u = fx x / z + cx (and v).

    xyz_m : (H * W, 3) camera frame, NaN where nothing was measured.
    """
    ok = np.flatnonzero(np.all(np.isfinite(xyz_m), axis=1) & (xyz_m[:, 2] > 0))
    return PinholeCamera.from_K(fit_intrinsics_at(xyz_m[ok], ok, shape[1]), shape[1], shape[0])


def fit_intrinsics_at(xyz_m: np.ndarray, pixel: np.ndarray, width: int) -> np.ndarray:
    """Pinhole K (3, 3) from measured points (k, 3), camera frame, z > 0, and their row-major
    pixel indices (k,) in a frame `width` pixels wide; least squares on u = fx x / z + cx (and v)."""
    if len(pixel) < 10:
        raise ValueError("too few measured pixels to fit intrinsics")
    v, u = np.divmod(np.asarray(pixel, dtype=np.int64), width)
    xyz = np.asarray(xyz_m, dtype=np.float64)
    x, y = xyz[:, 0] / xyz[:, 2], xyz[:, 1] / xyz[:, 2]
    fx, cx = np.linalg.lstsq(np.column_stack([x, np.ones_like(x)]), u, rcond=None)[0]
    fy, cy = np.linalg.lstsq(np.column_stack([y, np.ones_like(y)]), v, rcond=None)[0]
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _zbuffer(points: np.ndarray, K: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    h, w = shape
    depth = np.full(h * w, np.inf, np.float32)
    z = points[:, 2]
    ok = z > 1e-6
    uv = points[ok] @ K.T
    u = np.floor(uv[:, 0] / uv[:, 2]).astype(np.int64)
    v = np.floor(uv[:, 1] / uv[:, 2]).astype(np.int64)
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    np.minimum.at(depth, v[inside] * w + u[inside], z[ok][inside].astype(np.float32))
    return depth.reshape(h, w)


def depth_view(
    xyz_m: np.ndarray, frame_shape: tuple[int, int] | None, voxel_m: float, finite: np.ndarray | None = None
) -> DepthView:
    """The z-buffer of everything a capture measured (before any cleaning).

    Organized frames (H * W, 3): the sensor's own pixel grid at 1/CELL_PX, intrinsics fitted to
    the frame. Other clouds: a virtual pinhole at the origin whose cell is about `voxel_m` wide
    at the median depth, over the cloud's field of view. finite: (n,) bool, the points without
    NaN or inf when the caller knows them already.
    """
    xyz = np.asarray(xyz_m).reshape(-1, 3)
    valid = (np.all(np.isfinite(xyz), axis=1) if finite is None else finite) & (xyz[:, 2] > 1e-6)
    if valid.sum() < 10:
        return DepthView.empty()
    if frame_shape is not None and frame_shape[0] * frame_shape[1] == len(xyz):
        H, W = frame_shape
        # A pinhole fitted to a spread sample of the pixels is the frame's own to well below a
        # cell (and costs milliseconds instead of a fit over millions of points).
        picked = np.flatnonzero(valid)
        picked = picked[:: max(1, len(picked) // INTRINSICS_SAMPLE)]
        K = fit_intrinsics_at(xyz[picked], picked, W)
        cell = np.diag([1.0 / CELL_PX, 1.0 / CELL_PX, 1.0]) @ K
        # Each cell's nearest measurement is the least depth over its block of pixels: the
        # points of an organized frame are where their pixels are.
        h, w = int(np.ceil(H / CELL_PX)), int(np.ceil(W / CELL_PX))
        z = np.full((h * CELL_PX, w * CELL_PX), np.inf, np.float32)
        z[:H, :W] = np.where(valid, xyz[:, 2], np.inf).reshape(H, W)
        # Elementwise minima of the CELL_PX**2 strided views: the same values as a min over the
        # blocks' axes, at a tenth of the time.
        return DepthView(
            np.minimum.reduce([z[i::CELL_PX, j::CELL_PX] for i in range(CELL_PX) for j in range(CELL_PX)]), cell
        )
    pts = xyz[valid].astype(np.float64)
    f = float(np.median(pts[:, 2])) / max(voxel_m, 1e-4)
    x, y = pts[:, 0] / pts[:, 2], pts[:, 1] / pts[:, 2]
    lo_x, lo_y = float(x.min()), float(y.min())
    w = int(np.ceil((float(x.max()) - lo_x) * f)) + 1
    h = int(np.ceil((float(y.max()) - lo_y) * f)) + 1
    if h * w > 4_000_000:  # a cloud spread over a very wide view: coarser cells
        s = np.sqrt(h * w / 4_000_000)
        f, w, h = f / s, int(w / s) + 1, int(h / s) + 1
    K = np.array([[f, 0.0, -lo_x * f], [0.0, f, -lo_y * f], [0.0, 0.0, 1.0]])
    return DepthView(_zbuffer(pts, K, (h, w)), K)


def measured_depth(points_cam: np.ndarray, view: DepthView) -> np.ndarray:
    """(k,) the depth measured along the ray of each point (k, 3; camera frame): the z-buffer's
    cell it falls in; inf where nothing was measured, the point lies outside the view or behind
    the camera."""
    m = np.full(len(points_cam), np.inf)
    if view.is_empty or len(points_cam) == 0:
        return m
    h, w = view.depth_m.shape
    z = points_cam[:, 2]
    ok = np.flatnonzero(z > 1e-6)
    uv = points_cam[ok] @ view.K.T
    u = np.floor(uv[:, 0] / uv[:, 2]).astype(np.int64)
    v = np.floor(uv[:, 1] / uv[:, 2]).astype(np.int64)
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    m[ok[inside]] = view.depth_m[v[inside], u[inside]]
    return m


def seen_through_share(points_cam: np.ndarray, view: DepthView, margin_m: float) -> float:
    """Share of the posed, camera-facing model points (k, 3; camera frame) that lie in front of
    a measurement by more than margin_m, among those with a measurement along their ray."""
    measured = measured_depth(points_cam, view)
    known = np.isfinite(measured)
    if not known.any():
        return 0.0
    return float(np.mean(points_cam[known, 2] < measured[known] - margin_m))


def visible_support_share(
    points_cam: np.ndarray, supported: np.ndarray, view: DepthView, hidden_margin_m: float
) -> float:
    """Share of the posed, camera-facing model points (k, 3; camera frame) the camera should have
    seen that it did: among the points with a measurement along their ray that does not lie in
    front of them by more than hidden_margin_m (those are hidden: neutral), the share with a
    measured point near them (supported (k,) bool, the caller's nearest-neighbour test). Points
    without a measurement are neutral too (the sensor's missing data says nothing). 0 when no
    point should be seen. Without a view: the share supported among all points."""
    supported = np.asarray(supported, dtype=bool)
    if view.is_empty:
        return float(supported.mean()) if len(supported) else 0.0
    measured = measured_depth(points_cam, view)
    expected = np.isfinite(measured) & (measured >= points_cam[:, 2] - hidden_margin_m)
    return float(supported[expected].mean()) if expected.any() else 0.0
