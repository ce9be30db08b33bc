"""The pose verification threshold (register.max_seen_through) of a part, chosen on its
validation scenes after training, as the clustering is.

Every validation scene goes through the scene path with verification off; each pose found is
right or wrong against the rendered truth (ADD(-S) < 0.1 d) and has its seen-through share
(registration/visibility.py). The threshold kept is the one that best separates them, weighing a
wrong pose kept twice as much as a right one lost (a wrong pick costs more than a skipped one).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from binpick.io.scene import SyntheticScene
from binpick.metrics.pose import scene_pose_metrics
from binpick.registration.constants import DEFAULT_MAX_SEEN_THROUGH
from binpick.scene_path import PartModels, SceneSeeds, process

# The threshold stays within these bounds whatever few validation scenes say. Below 0.3 it would
# drop right poses: silhouette pixels and noise at tilted views reach 0.28 on estimates within
# ADD 0.1 d (binpick bench clutter, T-joint), while a quick profile's handful of validation
# scenes may show a single wrong pose at 0.17.
THRESHOLD_RANGE = (0.3, 0.6)
WRONG_WEIGHT = 2.0


def choose_threshold(shares_right: Sequence[float], shares_wrong: Sequence[float]) -> float:
    """The cut t (keep poses with share <= t) maximising kept right minus WRONG_WEIGHT x kept
    wrong; among equally good cuts the one nearest DEFAULT_MAX_SEEN_THROUGH (what the validation
    scenes do not decide, the prior does); within THRESHOLD_RANGE. With no wrong pose seen: the
    prior."""
    right, wrong = np.sort(np.asarray(shares_right, float)), np.sort(np.asarray(shares_wrong, float))
    lo, hi = THRESHOLD_RANGE
    if len(wrong) == 0:
        return float(np.clip(DEFAULT_MAX_SEEN_THROUGH, lo, hi))
    cuts = np.unique(np.clip(np.concatenate([right, wrong, [lo, hi, DEFAULT_MAX_SEEN_THROUGH]]), lo, hi))
    gain = np.searchsorted(right, cuts, side="right") - WRONG_WEIGHT * np.searchsorted(wrong, cuts, side="right")
    # A cut keeps the same poses up to the next share above it: the best cuts span intervals;
    # the prior is taken when it lies in one, else the best cut nearest to it.
    order = np.concatenate([right, wrong])
    best = cuts[gain == gain.max()]
    for c in best:
        nxt = order[order > c]
        if c <= DEFAULT_MAX_SEEN_THROUGH < (nxt.min() if len(nxt) else np.inf):
            return float(np.clip(DEFAULT_MAX_SEEN_THROUGH, lo, hi))
    return float(np.clip(best[np.argmin(np.abs(best - DEFAULT_MAX_SEEN_THROUGH))], lo, hi))


def calibrate_seen_through(scenes: Sequence[SyntheticScene], models: PartModels, seed: int, name: str) -> tuple[float, dict[str, float]]:
    """The chosen threshold and what it was chosen on (counts, the shares' extremes)."""
    off = replace(models, register_params=models.register_params.model_copy(update={"max_seen_through": 1.0}))
    right: list[float] = []
    wrong: list[float] = []
    for k, scene in enumerate(scenes):
        H, W = scene.labels.shape
        result = process(scene.xyz_m.reshape(-1, 3), None, (H, W), off, SceneSeeds.of(seed, f"{name}-val-{k}"))
        poses = result.registration.poses
        T = np.array([p.T_cam_from_model for p in poses]).reshape(-1, 4, 4)
        _, per = scene_pose_metrics(T, scene.T_cam_from_model, scene.visible_fraction, models.ppf.dense_points_m,
                                    models.ppf.symmetries, models.ppf.diameter_m)
        for pose, match in zip(poses, per, strict=True):
            (right if match and match["add_ok"] else wrong).append(float((pose.extra or {}).get("seen_through", 0.0)))
    t = choose_threshold(right, wrong)
    return t, {"n_right": float(len(right)), "n_wrong": float(len(wrong)), "right_max": max(right, default=0.0),
               "wrong_min": min(wrong, default=1.0), "kept_wrong": float(sum(w <= t for w in wrong)),
               "lost_right": float(sum(r > t for r in right))}
