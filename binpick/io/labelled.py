"""Labelled point-cloud text scenes from other tools (one point per line: `x y z label`,
`x y z score label`, `x y z label score`, ...), so that their segmentations are evaluated with
this project's metrics. Label -1 (or any negative) means no instance."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from binpick.errors import InputError
from binpick.io.mesh import METRES_PER_UNIT
from binpick.io.text_cloud import load_text_columns

LAYOUTS = {
    "x y z label": ("x", "y", "z", "label"),
    "x y z score label": ("x", "y", "z", "score", "label"),
    "x y z label score": ("x", "y", "z", "label", "score"),
}


@dataclass(frozen=True)
class LabelledScene:
    """points_m (n, 3) float64 metres; labels (n,) int64 (-1 = none); scores (n,) or None."""

    points_m: np.ndarray
    labels: np.ndarray
    scores: np.ndarray | None


# Instance ids beyond this are not instance ids (a column of another quantity read as labels).
MAX_LABEL = 1_000_000


def load_labelled(
    path: str | Path, columns: tuple[str, ...] = LAYOUTS["x y z label"], unit: str = "m"
) -> LabelledScene:
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "labelled scene not found")
    if "label" not in columns:
        raise InputError(path, f"columns {list(columns)} name no label column")
    if unit not in METRES_PER_UNIT:
        raise InputError(path, f"unknown unit {unit!r} (use mm, m or in)")
    cols = load_text_columns(path, list(columns))
    labels = cols["label"]
    if not np.all(np.isfinite(labels)) or not np.all(labels == np.round(labels)):
        raise InputError(path, "labels must be integers")
    if len(labels) and (labels.max() > MAX_LABEL or labels.min() < -MAX_LABEL):
        raise InputError(
            path,
            f"labels must be small integers (instance ids, -1 = none); found {labels.min():.0f} to {labels.max():.0f}",
        )
    labels = labels.astype(np.int64)
    labels[labels < 0] = -1
    points = np.stack([cols["x"], cols["y"], cols["z"]], axis=1) * METRES_PER_UNIT[unit]
    bad = ~np.all(np.isfinite(points), axis=1)
    if bad.any():
        raise InputError(
            path, f"{int(bad.sum())} points have non-finite coordinates (first at row {int(np.argmax(bad)) + 1})"
        )
    return LabelledScene(points, labels, cols.get("score"))


def transfer_labels(
    source_points: np.ndarray, source_labels: np.ndarray, target_points: np.ndarray, max_distance_m: float
) -> np.ndarray:
    """Labels of target points from their nearest source point; -1 farther than max_distance_m."""
    from scipy.spatial import cKDTree

    d, i = cKDTree(source_points).query(target_points)
    return np.where(d <= max_distance_m, source_labels[i], -1)
