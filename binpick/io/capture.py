"""Captures in: the format is chosen from the extension and checked against the content, and
coordinates become metres here, once. Spec: data/README.md#captures."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from binpick.errors import InputError
from binpick.io.mesh import METRES_PER_UNIT
from binpick.io.ply import load_ply

CAPTURE_SUFFIXES = (".ply",)


@dataclass(frozen=True)
class Capture:
    """xyz_m (n, 3) float32 camera frame, metres, NaN = no return; rgb (n, 3) uint8 or None;
    shape (H, W) for organized captures (n = H * W, row-major), else None."""

    xyz_m: np.ndarray
    rgb: np.ndarray | None
    shape: tuple[int, int] | None


def load_capture(path: str | Path, unit: str) -> Capture:
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "capture file not found")
    suffix = path.suffix.lower()
    if suffix not in CAPTURE_SUFFIXES:
        raise InputError(path, f"unsupported capture format {suffix!r} (supported: {', '.join(CAPTURE_SUFFIXES)})")
    if unit not in METRES_PER_UNIT:
        raise InputError(path, f"unknown unit {unit!r} (use mm, m or in)")
    data = load_ply(path)
    if len(data.xyz) == 0:
        raise InputError(path, "holds no points")
    xyz = data.xyz.astype(np.float32) * np.float32(METRES_PER_UNIT[unit])
    return Capture(xyz_m=xyz, rgb=data.rgb, shape=data.shape)
