"""Labelled captures (`data/real/<part>/<capture>.npz`): a real capture's cleaned points
labelled from the poses the cell trusted (binpick.learning). Spec: data/README.md#labelled-capture.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from binpick.io.npz import load_fields, save_fields


@dataclass(frozen=True)
class LabelledCapture:
    """One capture labelled from its trusted poses; camera frame, metres.

    points_m         : (N, 3) float32, the cleaned capture (the network's input at inference)
    normals          : (N, 3) float32, facing the camera
    labels           : (N,) int16, index of the trusted pose a point belongs to; NOT_A_PART (-1)
                       beyond the bin; IGNORE (-2) for every other point (left out of the loss
                       and the scoring, not background)
    T_cam_from_model : (k, 4, 4) float64, the trusted poses
    scores           : (k,) float64, their verification scores
    near_m           : () float64, how far from a posed surface a point was still labelled
    """

    points_m: np.ndarray
    normals: np.ndarray
    labels: np.ndarray
    T_cam_from_model: np.ndarray
    scores: np.ndarray
    near_m: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.points_m)
        if self.normals.shape != (n, 3) or self.labels.shape != (n,) or self.T_cam_from_model.shape[1:] != (4, 4):
            raise ValueError("points, normals and labels must hold one row per point, the poses be 4 x 4")


def save_labelled_capture(path: str | Path, capture: LabelledCapture) -> None:
    """Write atomically; the same content gives the same bytes."""
    save_fields(path, capture)


def load_labelled_capture(path: str | Path) -> LabelledCapture:
    return LabelledCapture(
        **load_fields(path, LabelledCapture, "labelled capture", "labelled capture not found (run the label stage)")
    )


def list_labelled_captures(folder: str | Path) -> list[Path]:
    """The labelled captures of a part's folder, sorted by name."""
    return sorted(Path(folder).glob("*.npz"))
