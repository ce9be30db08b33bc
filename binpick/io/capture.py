"""Captures in: the format is detected from the file's first bytes and checked against its
extension, and coordinates become metres here, once. Spec: data/README.md#captures.

Formats: PLY and PCD (organized or not, with or without colour and normals), Zivid `.zdf`
(SDK 1.x with h5py; SDK 2.x through the `zivid` package), CSV / XYZ text with configurable
columns, and 16-bit depth PNG with pinhole intrinsics.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from binpick.errors import InputError
from binpick.io.mesh import METRES_PER_UNIT

FORMATS_BY_SUFFIX = {
    ".ply": "ply",
    ".pcd": "pcd",
    ".zdf": "zdf",
    ".csv": "text",
    ".xyz": "text",
    ".txt": "text",
    ".pts": "text",
    ".png": "depth",
}
CAPTURE_SUFFIXES = tuple(FORMATS_BY_SUFFIX)
DEFAULT_TEXT_COLUMNS = ("x", "y", "z")


@dataclass(frozen=True)
class ImportOptions:
    """unit: of the coordinates (or depth values); columns: names of text columns (x, y, z, r, g,
    b, nx, ny, nz; anything else is ignored); intrinsics: JSON with fx, fy, cx, cy for depth images."""

    unit: str = "mm"
    columns: tuple[str, ...] = DEFAULT_TEXT_COLUMNS
    intrinsics: Path | None = None


@dataclass(frozen=True)
class Capture:
    """xyz_m (n, 3) float32 camera frame, metres, NaN = no return; rgb (n, 3) uint8 or None;
    shape (H, W) for organized captures (n = H * W, row-major), else None."""

    xyz_m: np.ndarray
    rgb: np.ndarray | None
    shape: tuple[int, int] | None


def sniff_format(path: Path) -> str | None:
    """The format the first bytes show, or None for text-like or unknown content."""
    with open(path, "rb") as fh:
        head = fh.read(64)
    if head.startswith(b"ply"):
        return "ply"
    if head.startswith(b"\x89HDF"):
        return "zdf"
    if head.startswith(b"\x89PNG"):
        return "depth"
    if head.lstrip().startswith((b"# .PCD", b"VERSION", b"FIELDS")):
        return "pcd"
    if head.startswith(b"ZDF") or head.startswith(b"\x00ZIV"):
        return "zdf"
    return None


def load_capture(path: str | Path, options: ImportOptions | str = ImportOptions()) -> Capture:
    if isinstance(options, str):
        options = ImportOptions(unit=options)
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "capture file not found")
    if path.stat().st_size == 0:
        raise InputError(path, "file is empty")
    if options.unit not in METRES_PER_UNIT:
        raise InputError(path, f"unknown unit {options.unit!r} (use mm, m or in)")
    by_suffix = FORMATS_BY_SUFFIX.get(path.suffix.lower())
    by_content = sniff_format(path)
    if by_suffix is None and by_content is None:
        raise InputError(path, f"unsupported capture format {path.suffix!r} (supported: {', '.join(CAPTURE_SUFFIXES)})")
    fmt = by_content or by_suffix
    if by_suffix is not None and by_content is not None and by_suffix != by_content:
        raise InputError(path, f"the extension says {by_suffix} but the content is {by_content}")
    if fmt == "text" and by_suffix != "text":
        raise InputError(path, f"unrecognised content for a {path.suffix!r} file")

    scale = np.float32(METRES_PER_UNIT[options.unit])
    rgb = None
    shape = None
    if fmt == "ply":
        from binpick.io.ply import load_ply

        data = load_ply(path)
        xyz, rgb, shape = data.xyz, data.rgb, data.shape
    elif fmt == "pcd":
        from binpick.io.pcd import load_pcd

        data = load_pcd(path)
        xyz, rgb, shape = data.xyz, data.rgb, data.shape
    elif fmt == "zdf":
        from binpick.io.zdf import load_zdf

        data = load_zdf(path)
        xyz, rgb, shape = data.xyz, data.rgb, data.shape
    elif fmt == "text":
        from binpick.io.text_cloud import load_text_columns

        cols = load_text_columns(path, list(options.columns))
        xyz = np.stack([cols["x"], cols["y"], cols["z"]], axis=1).astype(np.float32)
        if {"r", "g", "b"} <= set(cols):
            rgb = np.clip(np.stack([cols["r"], cols["g"], cols["b"]], axis=1), 0, 255).astype(np.uint8)
    else:  # depth image
        from binpick.io.depth_image import depth_metres, load_depth_png, load_intrinsics

        if options.intrinsics is None:
            raise InputError(path, "a depth image needs intrinsics (a JSON file with fx, fy, cx, cy)")
        depth = load_depth_png(path)
        xyz = load_intrinsics(options.intrinsics, depth.shape).back_project(depth_metres(depth, 1.0))
        shape = depth.shape
    if len(xyz) == 0:
        raise InputError(path, "holds no points")
    return Capture(xyz_m=xyz.astype(np.float32) * scale, rgb=rgb, shape=shape)
