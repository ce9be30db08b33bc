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
    segment: the instance label it was found on (-1: none, e.g. whole-scene matching).
    What verification measured (None: not measured): seen_through, the share of the camera-facing
    surface lying where the camera saw through it; visible_support, the share of the surface in
    view with a measurement on it (registration/visibility.py); turned_by_near_symmetry, whether
    the pose was turned by one of the part's near symmetries. Ground truth: visible_fraction.
    extra: any other numbers written with it. All are stored under "extra" in poses.json, rounded
    only there."""

    T_cam_from_model: np.ndarray
    score: float = 1.0
    segment: int = -1
    extra: dict | None = None
    seen_through: float | None = None
    visible_support: float | None = None
    turned_by_near_symmetry: bool = False
    visible_fraction: float | None = None

    def stored_extra(self) -> dict:
        """The "extra" object of poses.json: the typed fields rounded, then any other numbers."""
        out: dict = {}
        if self.visible_fraction is not None:
            out["visible_fraction"] = round(float(self.visible_fraction), 4)
        if self.turned_by_near_symmetry:
            out["turned_by_near_symmetry"] = 1.0
        if self.seen_through is not None:
            out["seen_through"] = round(float(self.seen_through), 4)
        if self.visible_support is not None:
            out["visible_support"] = round(float(self.visible_support), 4)
        return {**out, **(self.extra or {})}


_TYPED = ("visible_fraction", "turned_by_near_symmetry", "seen_through", "visible_support")


def _pose(p: dict) -> PartPose:
    stored = dict(p.get("extra") or {})
    typed = {k: stored.pop(k) for k in _TYPED if k in stored}
    return PartPose(
        np.asarray(p["T_cam_from_model"], dtype=np.float64).reshape(4, 4),
        float(p["score"]),
        int(p.get("segment", -1)),
        stored or None,
        seen_through=float(typed["seen_through"]) if "seen_through" in typed else None,
        visible_support=float(typed["visible_support"]) if "visible_support" in typed else None,
        turned_by_near_symmetry=bool(typed.get("turned_by_near_symmetry", False)),
        visible_fraction=float(typed["visible_fraction"]) if "visible_fraction" in typed else None,
    )


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
                **({"extra": extra} if (extra := p.stored_extra()) else {}),
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
        poses = [_pose(p) for p in doc["poses"]]
        return str(doc["part"]), poses
    except (KeyError, ValueError, TypeError) as exc:
        raise InputError(path, f"not a binpick pose file ({type(exc).__name__}: {exc})") from None
