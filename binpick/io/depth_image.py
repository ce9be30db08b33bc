"""Depth images (16-bit PNG, 0 = missing) with pinhole intrinsics, as written by RGB-D cameras
and data sets (BOP, IC-BIN). Intrinsics come from a JSON file with fx, fy, cx, cy in pixels."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from binpick.errors import InputError
from binpick.geometry.camera import PinholeCamera


def load_intrinsics(path: str | Path, shape: tuple[int, int]) -> PinholeCamera:
    """The pinhole camera of an (H, W) depth image from a JSON file: fx, fy, cx, cy in pixels, or
    BOP's row-major 3 x 3 `cam_K`; refused when it cannot belong to an image of that size."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "intrinsics file not found")
    try:
        doc = json.loads(path.read_text())
        if "cam_K" in doc:
            K = np.asarray(doc["cam_K"], dtype=float).reshape(3, 3)
            camera = PinholeCamera.from_K(K, shape[1], shape[0])
        else:
            camera = PinholeCamera(
                shape[1], shape[0], float(doc["fx"]), float(doc["fy"]), float(doc["cx"]), float(doc["cy"])
            )
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(path, f"needs fx, fy, cx, cy (or cam_K) in pixels ({type(exc).__name__}: {exc})") from None
    problem = camera.fits(shape)
    if problem:
        raise InputError(path, problem)
    return camera


def depth_metres(depth: np.ndarray, scale: float) -> np.ndarray:
    """(H, W) float32 depth of a depth image's values (value * scale; 0, nothing measured, NaN)."""
    z = np.asarray(depth).astype(np.float32) * np.float32(scale)
    z[np.asarray(depth) == 0] = np.nan
    return z


def load_depth_png(path: str | Path) -> np.ndarray:
    path = Path(path)
    try:
        img = Image.open(path)
        img.load()
    except (UnidentifiedImageError, OSError) as exc:
        raise InputError(path, f"not a readable image ({exc})") from None
    depth = np.asarray(img)
    if depth.dtype == np.uint8:
        # 8 bits cannot hold depth (256 levels): this is a grey or colour picture, or a preview.
        raise InputError(
            path, f"an 8-bit image ({img.mode}); depth images are 16-bit PNGs of depth values (0 = missing)"
        )
    if depth.ndim != 2 or depth.dtype not in (np.uint16, np.int32):
        raise InputError(path, f"expected a single-channel 16-bit depth image, got {depth.dtype} {depth.shape}")
    return depth
