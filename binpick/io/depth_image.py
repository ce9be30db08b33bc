"""Depth images (16-bit PNG, 0 = missing) with pinhole intrinsics, as written by RGB-D cameras
and data sets (BOP, IC-BIN). Intrinsics come from a JSON file with fx, fy, cx, cy in pixels."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from binpick.errors import InputError


def load_intrinsics(path: str | Path) -> tuple[float, float, float, float]:
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "intrinsics file not found")
    try:
        doc = json.loads(path.read_text())
        if "cam_K" in doc:  # BOP's camera format: a row-major 3 x 3 K
            K = np.asarray(doc["cam_K"], dtype=float).reshape(3, 3)
            return float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
        return float(doc["fx"]), float(doc["fy"]), float(doc["cx"]), float(doc["cy"])
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(path, f"needs fx, fy, cx, cy (or cam_K) in pixels ({type(exc).__name__}: {exc})") from None


def depth_to_points(depth: np.ndarray, fx: float, fy: float, cx: float, cy: float, scale: float) -> np.ndarray:
    """(H*W, 3) float32 camera-frame points from an (H, W) depth image; value * scale = depth in
    the caller's unit; 0 becomes NaN."""
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise ValueError(f"expected an (H, W) depth image, got {depth.shape}")
    H, W = depth.shape
    z = depth.astype(np.float32) * np.float32(scale)
    z[depth == 0] = np.nan
    u, v = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    return np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], axis=-1).reshape(-1, 3)


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
        raise InputError(path, f"an 8-bit image ({img.mode}); depth images are 16-bit PNGs of depth values (0 = missing)")
    if depth.ndim != 2 or depth.dtype not in (np.uint16, np.int32):
        raise InputError(path, f"expected a single-channel 16-bit depth image, got {depth.dtype} {depth.shape}")
    return depth


def check_intrinsics_fit(path: str | Path, intrinsics: tuple[float, float, float, float], shape: tuple[int, int]) -> None:
    """Refuse intrinsics that cannot belong to an image of this (H, W): the principal point must
    lie inside the image and the focal lengths be positive."""
    fx, fy, cx, cy = intrinsics
    H, W = shape
    if not (fx > 0 and fy > 0):
        raise InputError(path, f"focal lengths must be positive (fx {fx}, fy {fy})")
    if not (0.0 <= cx <= W and 0.0 <= cy <= H):
        raise InputError(path, f"principal point ({cx:g}, {cy:g}) px lies outside the {W} x {H} depth image: intrinsics of another resolution?")
