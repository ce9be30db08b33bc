"""Scene step `clean`: a capture's points to the cleaned cloud the network and the matcher use."""

from __future__ import annotations

import numpy as np

from binpick.io.cloud import CleanCloud
from binpick.params import ImportCaptureParams
from binpick.scene.cleaning import clean_capture


def clean(
    xyz_m: np.ndarray,
    rgb: np.ndarray | None,
    frame_shape: tuple[int, int] | None,
    params: ImportCaptureParams,
    seed: int,
) -> CleanCloud:
    """The cleaned cloud of a capture: xyz_m (n, 3) camera frame, metres, NaN = no return
    (n = H * W, row-major, for an organized frame of shape frame_shape); rgb (n, 3) uint8 or None."""
    return clean_capture(xyz_m, rgb, frame_shape, params, seed)
