"""Synthetic scene files (`scene_NNNNNN.npz`) and their label images (`.png`).

Spec: data/README.md#scene.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from binpick.io.atomic import atomic_path
from binpick.io.npz import load_fields, save_fields
from binpick.palette import instance_colours


@dataclass(frozen=True)
class SyntheticScene:
    """A rendered scene with ground truth (spec: data/README.md#scene).

    xyz_m            : (H, W, 3) float32, camera frame, metres, NaN = no return
    labels           : (H, W) int16, instance index, -1 = bin, floor or nothing
    K                : (3, 3) float64 intrinsics of the organized frame
    T_cam_from_model : (k, 4, 4) float64, ground-truth pose of instance i at index i
    visible_fraction : (k,) float64, share of each instance's unoccluded image area that is visible
    T_cam_from_bin   : (4, 4) float64
    view_points_m    : (N, 3) float32, the network's view: every part point on the voxel grid, camera frame
    view_normals     : (N, 3) float32, normals estimated like at import, facing the camera
    view_labels      : (N,) int16, instance index of each view point
    """

    xyz_m: np.ndarray
    labels: np.ndarray
    K: np.ndarray
    T_cam_from_model: np.ndarray
    visible_fraction: np.ndarray
    T_cam_from_bin: np.ndarray
    view_points_m: np.ndarray
    view_normals: np.ndarray
    view_labels: np.ndarray


def label_image(labels: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 picture of a label image: instances coloured, -1 dark grey."""
    labels = np.asarray(labels)
    n = int(labels.max()) + 1 if labels.size and labels.max() >= 0 else 0
    palette = np.concatenate([instance_colours(n), np.full((1, 3), 40, np.uint8)])
    return palette[np.where(labels >= 0, labels, n)]


def save_scene(path: str | Path, scene: SyntheticScene, png: bool = True) -> None:
    """Write the scene (compressed npz, byte-identical for identical content) and its label PNG."""
    path = Path(path)
    save_fields(path, scene)
    if png:
        with atomic_path(path.with_suffix(".png")) as tmp:
            Image.fromarray(label_image(scene.labels)).save(tmp, format="PNG")


def load_scene(path: str | Path) -> SyntheticScene:
    return SyntheticScene(**load_fields(path, SyntheticScene, "scene", "scene file not found"))


def list_scenes(folder: str | Path) -> list[Path]:
    """Scene files of a split folder, sorted by name."""
    return sorted(Path(folder).glob("scene_*.npz"))
