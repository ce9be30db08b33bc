"""Frames from a Zivid camera through the `zivid` Python package (optional: it builds against the
native Zivid SDK). The package is passed in, so that tests can drive the code with a fake camera."""

from __future__ import annotations

import datetime
from pathlib import Path
from types import ModuleType

import numpy as np

from binpick.errors import MissingDependencyError
from binpick.io.ply import PointCloudData, save_ply
from binpick.io.zdf import ZIVID_INSTALL_HINT
from binpick.params import ZividCameraParams


def import_zivid() -> ModuleType:
    """The zivid package, or one clear error saying what to install."""
    try:
        import zivid
    except ImportError:
        raise MissingDependencyError(f"capturing needs the zivid package: {ZIVID_INSTALL_HINT}") from None
    return zivid


def grab_frame(zivid: ModuleType, settings: ZividCameraParams) -> PointCloudData:
    """One 3D frame: organized xyz (H*W, 3) float32 in millimetres (camera frame, NaN = missing)
    and colour, shape (H, W)."""
    app = zivid.Application()
    camera = app.connect_camera(serial_number=settings.serial) if settings.serial else app.connect_camera()
    try:
        acquisition = zivid.Settings.Acquisition(
            aperture=settings.aperture,
            exposure_time=datetime.timedelta(microseconds=settings.exposure_time_us),
            brightness=settings.brightness,
            gain=settings.gain,
        )
        frame = camera.capture(zivid.Settings(acquisitions=[acquisition]))
        cloud = frame.point_cloud()
        xyz = np.asarray(cloud.copy_data("xyz"), dtype=np.float32)
        rgba = np.asarray(cloud.copy_data("rgba"), dtype=np.uint8)
    finally:
        camera.disconnect()
    if xyz.ndim != 3 or xyz.shape[2] != 3:
        raise ValueError(f"camera returned xyz of shape {xyz.shape}, expected (H, W, 3)")
    H, W, _ = xyz.shape
    return PointCloudData(xyz=xyz.reshape(-1, 3), rgb=rgba[..., :3].reshape(-1, 3), shape=(H, W))


def grab_to_file(out: str | Path, settings: ZividCameraParams, zivid: ModuleType | None = None) -> tuple[int, int]:
    """Grab one frame and save it as an organized PLY in millimetres (what `import_capture` reads);
    returns the frame's (H, W). zivid: the package, or a stand-in (default: import it)."""
    frame = grab_frame(zivid or import_zivid(), settings)
    save_ply(out, frame)
    assert frame.shape is not None  # an organized frame
    return frame.shape
