"""Pose lists (`poses.json`: estimated poses and ground truth) and their type.
Spec: data/README.md#capture-results."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from binpick.errors import InputError
from binpick.io.atomic import write_text


@dataclass(frozen=True)
class PartPose:
    """One part in a scene: T_cam_from_model (4, 4) metres; score in [0, 1] (1 for ground truth);
    segment: the instance label it was found on (-1: none, e.g. whole-scene matching); extra:
    numbers written with it (the visible fraction of a ground-truth part, ...)."""

    T_cam_from_model: np.ndarray
    score: float = 1.0
    segment: int = -1
    extra: dict | None = None


def save_poses(path: str | Path, part: str, poses: list[PartPose]) -> None:
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


def load_poses(path: str | Path) -> tuple[str, list[PartPose]]:
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "pose file not found")
    try:
        doc = json.loads(path.read_text())
        poses = [
            PartPose(np.asarray(p["T_cam_from_model"], dtype=np.float64).reshape(4, 4), float(p["score"]), int(p.get("segment", -1)), p.get("extra"))
            for p in doc["poses"]
        ]
        return str(doc["part"]), poses
    except (KeyError, ValueError, TypeError) as exc:
        raise InputError(path, f"not a binpick pose file ({type(exc).__name__}: {exc})") from None
