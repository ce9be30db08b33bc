"""Zivid `.zdf` frames.

SDK 1.x files are NetCDF-4 (HDF5): group `data` with `pointcloud` (H, W, 3) float32 millimetres,
NaN = missing, `rgba_image` (H, W, 4) uint8 and `contrast` (or `snr`) (H, W). They are read with
h5py, no Zivid software needed. SDK 2.x files have an undocumented layout and are read through the
`zivid` package (which needs the native Zivid SDK) when it is installed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from binpick.errors import InputError, MissingDependencyError
from binpick.io.ply import PointCloudData

ZIVID_INSTALL_HINT = "install the Zivid SDK, then `pip install zivid` (or `pip install -e .[zivid]`)"


def _read_sdk1(path: Path) -> PointCloudData | None:
    import h5py

    try:
        with h5py.File(path, "r") as f:
            if "data" not in f or "pointcloud" not in f["data"]:
                return None
            xyz = np.asarray(f["data"]["pointcloud"], dtype=np.float32)
            rgba = np.asarray(f["data"]["rgba_image"]) if "rgba_image" in f["data"] else None
    except OSError:
        return None
    if xyz.ndim != 3 or xyz.shape[2] != 3:
        raise InputError(path, f"data/pointcloud has shape {xyz.shape}, expected (H, W, 3)")
    H, W, _ = xyz.shape
    rgb = rgba[..., :3].reshape(-1, 3).astype(np.uint8) if rgba is not None and rgba.shape[:2] == (H, W) else None
    return PointCloudData(xyz=xyz.reshape(-1, 3), rgb=rgb, shape=(H, W))


def _read_sdk2(path: Path) -> PointCloudData:
    try:
        import zivid  # noqa: F401
    except ImportError:
        # SDK 2.x's layout is not public, so without the SDK a file that is not HDF5 cannot be
        # told apart from random bytes: say both.
        raise MissingDependencyError(
            f"{path}: not a Zivid SDK 1.x frame (no HDF5 signature); if it is an SDK 2.x frame, reading it "
            f"needs the zivid package: {ZIVID_INSTALL_HINT}"
        ) from None
    import zivid

    app = zivid.Application()  # noqa: F841 - the SDK needs an application alive while loading
    try:
        frame = zivid.Frame(str(path))
    except RuntimeError as exc:
        raise InputError(path, f"not a Zivid frame the SDK can read ({exc})") from None
    cloud = frame.point_cloud()
    xyz = np.asarray(cloud.copy_data("xyz"), dtype=np.float32)
    rgba = np.asarray(cloud.copy_data("rgba"))
    H, W, _ = xyz.shape
    return PointCloudData(xyz=xyz.reshape(-1, 3), rgb=rgba[..., :3].reshape(-1, 3).astype(np.uint8), shape=(H, W))


def load_zdf(path: str | Path) -> PointCloudData:
    """A Zivid frame in millimetres, organized."""
    path = Path(path)
    with open(path, "rb") as fh:
        magic = fh.read(8)
    if magic.startswith(b"\x89HDF"):
        frame = _read_sdk1(path)
        if frame is None:
            raise InputError(path, "an HDF5 file without data/pointcloud: not a Zivid SDK 1.x frame")
        return frame
    return _read_sdk2(path)


def save_zdf_v1(
    path: str | Path, xyz_mm: np.ndarray, rgba: np.ndarray | None = None, contrast: np.ndarray | None = None
) -> None:
    """Write an SDK 1.x-layout frame (for tests and for converting captures): xyz_mm (H, W, 3)."""
    import h5py

    from binpick.io.atomic import atomic_path

    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        g = f.create_group("data")
        g.create_dataset("pointcloud", data=np.asarray(xyz_mm, np.float32))
        if rgba is not None:
            g.create_dataset("rgba_image", data=np.asarray(rgba, np.uint8))
        if contrast is not None:
            g.create_dataset("contrast", data=np.asarray(contrast, np.float32))
