"""Cleaned scene clouds (`cloud.npz`) and their segmentations (`segments.npz`).
Spec: data/README.md#capture-results."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from binpick.errors import InputError
from binpick.io.atomic import atomic_path
from binpick.io.npz import load_fields, save_fields


@dataclass(frozen=True)
class CleanCloud:
    """A capture after import and cleaning; camera frame, metres.

    points_m (n, 3) float32; normals (n, 3) float32 facing the camera; rgb (n, 3) uint8 (zeros
    when the capture has no colour); pixel_index (n,) int64 row-major pixel of each point in the
    organized frame, -1 when the capture is not organized; frame_shape (2,) int64 (H, W) or (0, 0);
    floor_plane (4,) float64 a, b, c, d with unit normal toward the camera, NaN when none;
    wall_planes (k, 4) float64; removed_fraction (3,) float64 shares of the valid input points
    removed as floor, walls and outliers; seen_depth_m (h, w) float32 the nearest measured depth
    per cell of everything the capture measured, before cleaning (inf = nothing; (0, 0) when
    unknown) and seen_K (3, 3) float64 the pinhole of that grid (registration/visibility.py);
    capture_digest the capture's content digest (binpick.seeding.capture_digest; '' in clouds
    written before it), which seeds the steps after import.
    """

    points_m: np.ndarray
    normals: np.ndarray
    rgb: np.ndarray
    pixel_index: np.ndarray
    frame_shape: np.ndarray
    floor_plane: np.ndarray
    wall_planes: np.ndarray
    removed_fraction: np.ndarray
    seen_depth_m: np.ndarray
    seen_K: np.ndarray
    capture_digest: str = ""


def save_cloud(path: str | Path, cloud: CleanCloud) -> None:
    save_fields(path, cloud)


def load_cloud(path: str | Path) -> CleanCloud:
    arrays = load_fields(
        path,
        CleanCloud,
        "cleaned cloud",
        "cleaned cloud not found (run the import stage first)",
        {"capture_digest": np.asarray("")},
    )
    return CleanCloud(**{**arrays, "capture_digest": str(arrays["capture_digest"])})  # type: ignore[arg-type]  # the rest are arrays


@dataclass(frozen=True)
class Segments:
    """A cloud's segmentation: labels (n,) int32 instance of each cloud point, -1 = in no
    instance; is_part (n,) bool the points the network calls a part's (all of them for a
    network without a foreground head, and in files written before it)."""

    labels: np.ndarray
    is_part: np.ndarray


def save_segments(path: str | Path, segments: Segments) -> None:
    with atomic_path(path) as tmp:
        np.savez_compressed(
            tmp, labels=np.asarray(segments.labels, dtype=np.int32), is_part=np.asarray(segments.is_part, dtype=bool)
        )


def load_segments(path: str | Path) -> Segments:
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "segments not found (run the segment stage first)")
    try:
        with np.load(path, allow_pickle=False) as z:
            labels = z["labels"]
            is_part = z["is_part"] if "is_part" in z.files else np.ones(len(labels), bool)
    except (KeyError, ValueError, OSError) as exc:
        raise InputError(path, f"not a binpick segments file ({exc})") from None
    if is_part.shape != labels.shape:
        raise InputError(path, f"has {len(is_part)} part flags for {len(labels)} labels")
    return Segments(labels, is_part.astype(bool))
