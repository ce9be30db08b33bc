"""PLY point clouds, organized or not (Zivid Studio / SDK exports, PCL, Open3D).

An organized cloud is stored row-major with every pixel present (NaN where nothing was measured)
and its size in the header as PCL does: `obj_info num_cols W` and `obj_info num_rows H`.
Coordinates are stored in the file's unit (Zivid: millimetres); conversion is the caller's.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement, PlyParseError

from binpick.errors import InputError
from binpick.io.atomic import atomic_path


@dataclass(frozen=True)
class PointCloudData:
    """xyz (n, 3) float32 in the file's unit (NaN allowed); rgb (n, 3) uint8 or None; normals
    (n, 3) float32 or None; shape (H, W) when organized (n == H * W), else None."""

    xyz: np.ndarray
    rgb: np.ndarray | None = None
    normals: np.ndarray | None = None
    shape: tuple[int, int] | None = None


def save_ply(path: str | Path, cloud: PointCloudData, text: bool = False) -> None:
    """Write a (binary little-endian) PLY; organized clouds get their size in obj_info lines."""
    xyz = np.asarray(cloud.xyz, dtype=np.float32).reshape(-1, 3)
    fields = [("x", "f4"), ("y", "f4"), ("z", "f4")]
    if cloud.normals is not None:
        fields += [("nx", "f4"), ("ny", "f4"), ("nz", "f4")]
    if cloud.rgb is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    vertex = np.empty(len(xyz), dtype=fields)
    vertex["x"], vertex["y"], vertex["z"] = xyz.T
    if cloud.normals is not None:
        nrm = np.asarray(cloud.normals, dtype=np.float32).reshape(-1, 3)
        vertex["nx"], vertex["ny"], vertex["nz"] = nrm.T
    if cloud.rgb is not None:
        rgb = np.asarray(cloud.rgb, dtype=np.uint8).reshape(-1, 3)
        vertex["red"], vertex["green"], vertex["blue"] = rgb.T
    obj_info = []
    if cloud.shape is not None:
        H, W = cloud.shape
        if H * W != len(xyz):
            raise ValueError(f"organized shape {cloud.shape} does not match {len(xyz)} points")
        obj_info = [f"num_cols {W}", f"num_rows {H}"]
    data = PlyData([PlyElement.describe(vertex, "vertex")], text=text, byte_order="<", obj_info=obj_info)
    with atomic_path(path) as tmp:
        data.write(str(tmp))


def _organized_shape(ply: PlyData, n: int) -> tuple[int, int] | None:
    info = {}
    for line in ply.obj_info:
        parts = str(line).split()
        if len(parts) == 2 and parts[0] in ("num_cols", "num_rows", "width", "height") and parts[1].isdigit():
            info[parts[0]] = int(parts[1])
    W = info.get("num_cols", info.get("width"))
    H = info.get("num_rows", info.get("height"))
    if W and H and W * H == n:
        return (H, W)
    return None


def load_ply(path: str | Path) -> PointCloudData:
    """Read the vertices of a PLY file; InputError for a missing, truncated or non-point file."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "file not found")
    try:
        ply = PlyData.read(str(path))
        vertex = ply["vertex"].data
    except (PlyParseError, KeyError, ValueError, EOFError, OSError) as exc:
        raise InputError(
            path, f"not a readable PLY point cloud ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})"
        ) from None
    names = vertex.dtype.names or ()
    if not {"x", "y", "z"} <= set(names):
        raise InputError(path, "PLY vertices have no x, y, z properties")
    xyz = np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=1).astype(np.float32)
    rgb = None
    if {"red", "green", "blue"} <= set(names):
        rgb = np.stack([vertex["red"], vertex["green"], vertex["blue"]], axis=1).astype(np.uint8)
    normals = None
    if {"nx", "ny", "nz"} <= set(names):
        normals = np.stack([vertex["nx"], vertex["ny"], vertex["nz"]], axis=1).astype(np.float32)
    return PointCloudData(xyz=xyz, rgb=rgb, normals=normals, shape=_organized_shape(ply, len(xyz)))
