"""The bin and the camera above it.

Bin frame: origin at the centre of the inner bin floor, z up, x along the long side.
Camera frame (OpenCV): x right, y down, z along the optical axis.
"""

from __future__ import annotations

import numpy as np
import trimesh

from binpick.geometry.transforms import make_T
from binpick.params import BinParams

FLOOR_THICKNESS_M = 0.005
GROUND_MARGIN_M = 0.25  # the ground plane reaches this far beyond the bin on every side


def bin_meshes(bin_params: BinParams) -> list[trimesh.Trimesh]:
    """Ground, bin floor and four walls as closed boxes, bin frame, metres."""
    X, Y, H, W = bin_params.inner_x_m, bin_params.inner_y_m, bin_params.wall_height_m, bin_params.wall_thickness_m
    F = FLOOR_THICKNESS_M

    def box(lo: tuple[float, float, float], hi: tuple[float, float, float]) -> trimesh.Trimesh:
        lo_a, hi_a = np.asarray(lo), np.asarray(hi)
        b = trimesh.creation.box(extents=hi_a - lo_a)
        b.apply_translation((lo_a + hi_a) / 2.0)
        return b

    g = GROUND_MARGIN_M
    meshes = [
        box((-X / 2 - W - g, -Y / 2 - W - g, -F - 0.01), (X / 2 + W + g, Y / 2 + W + g, -F)),  # ground
        box((-X / 2 - W, -Y / 2 - W, -F), (X / 2 + W, Y / 2 + W, 0.0)),  # bin floor
    ]
    if H > 0:
        meshes += [
            box((-X / 2 - W, -Y / 2 - W, 0.0), (-X / 2, Y / 2 + W, H)),
            box((X / 2, -Y / 2 - W, 0.0), (X / 2 + W, Y / 2 + W, H)),
            box((-X / 2, -Y / 2 - W, 0.0), (X / 2, -Y / 2, H)),
            box((-X / 2, Y / 2, 0.0), (X / 2, Y / 2 + W, H)),
        ]
    return meshes


def T_bin_from_cam(distance_m: float) -> np.ndarray:
    """Camera `distance_m` above the bin floor centre, looking straight down, image x along bin x."""
    R = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # columns: cam axes in bin frame
    return make_T(R, np.array([0.0, 0.0, distance_m]))
