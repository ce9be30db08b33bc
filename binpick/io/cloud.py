"""Cleaned scene clouds (`cloud.npz`), their segmentations (`segments.npz`) and pose lists
(`poses.json`, also used for ground truth). Spec: data/README.md#capture-results."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from binpick.errors import InputError
from binpick.io.atomic import atomic_path, write_text
from binpick.io.npz import load_fields, save_fields


@dataclass(frozen=True)
class CleanCloud:
    """A capture after import and cleaning; camera frame, metres.

    points_m (n, 3) float32; normals (n, 3) float32 facing the camera; rgb (n, 3) uint8 (zeros
    when the capture has no colour); pixel_index (n,) int64 row-major pixel of each point in the
    organized frame, -1 when the capture is not organized; frame_shape (2,) int64 (H, W) or (0, 0);
    floor_plane (4,) float64 a, b, c, d with unit normal toward the camera, NaN when none;
    wall_planes (k, 4) float64; removed_fraction (3,) float64 shares of the valid input points
    removed as floor, walls and outliers.
    """

    points_m: np.ndarray
    normals: np.ndarray
    rgb: np.ndarray
    pixel_index: np.ndarray
    frame_shape: np.ndarray
    floor_plane: np.ndarray
    wall_planes: np.ndarray
    removed_fraction: np.ndarray


def save_cloud(path: str | Path, cloud: CleanCloud) -> None:
    save_fields(path, cloud)


def load_cloud(path: str | Path) -> CleanCloud:
    return CleanCloud(**load_fields(path, CleanCloud, "cleaned cloud", "cleaned cloud not found (run the import stage first)"))


def save_segments(path: str | Path, labels: np.ndarray) -> None:
    """labels (n,) int32 instance of each cloud point, -1 = none."""
    with atomic_path(path) as tmp:
        np.savez_compressed(tmp, labels=np.asarray(labels, dtype=np.int32))


def load_segments(path: str | Path) -> np.ndarray:
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "segments not found (run the segment stage first)")
    try:
        with np.load(path, allow_pickle=False) as z:
            return z["labels"]
    except (KeyError, ValueError, OSError) as exc:
        raise InputError(path, f"not a binpick segments file ({exc})") from None


@dataclass(frozen=True)
class PoseRecord:
    """One part in a scene: T_cam_from_model (4, 4) metres; score in [0, 1] (1 for ground truth);
    segment: the instance label it came from (-1 if none); extra numbers (visible fraction, ...)."""

    T_cam_from_model: np.ndarray
    score: float = 1.0
    segment: int = -1
    extra: dict | None = None


def save_poses(path: str | Path, part: str, poses: list[PoseRecord]) -> None:
    doc = {
        "part": part,
        "unit": "m",
        "frame": "camera",
        "poses": [
            {
                "T_cam_from_model": np.asarray(p.T_cam_from_model, dtype=float).round(9).tolist(),
                "score": round(float(p.score), 6),
                "segment": int(p.segment),
                **({"extra": p.extra} if p.extra else {}),
            }
            for p in poses
        ],
    }
    write_text(path, json.dumps(doc, indent=1) + "\n")


def load_poses(path: str | Path) -> tuple[str, list[PoseRecord]]:
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "pose file not found")
    try:
        doc = json.loads(path.read_text())
        poses = [
            PoseRecord(np.asarray(p["T_cam_from_model"], dtype=np.float64).reshape(4, 4), float(p["score"]), int(p.get("segment", -1)), p.get("extra"))
            for p in doc["poses"]
        ]
        return str(doc["part"]), poses
    except (KeyError, ValueError, TypeError) as exc:
        raise InputError(path, f"not a binpick pose file ({type(exc).__name__}: {exc})") from None
