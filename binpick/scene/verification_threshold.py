"""The pose verification thresholds (register.max_seen_through, register.min_visible_support) of
a part, chosen on its validation scenes after training, as the clustering is.

Every validation scene goes through the scene path with verification off; each pose found is
right or wrong against the rendered truth (ADD(-S) < 0.1 d) and has its seen-through share and
its visible support (registration/visibility.py). Each threshold kept is the one that best
separates them, weighing a wrong pose kept twice as much as a right one lost (a wrong pick costs
more than a skipped one): first the seen-through cut, then the support cut on the poses it keeps.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from binpick.io.scene import SyntheticScene
from binpick.metrics.pose import scene_pose_metrics
from binpick.registration.constants import DEFAULT_MAX_SEEN_THROUGH, DEFAULT_MIN_VISIBLE_SUPPORT
from binpick.scene.process import PartModels, process
from binpick.seeding import SceneSeeds

# The threshold stays within these bounds whatever few validation scenes say. Below 0.3 it would
# drop right poses: silhouette pixels and noise at tilted views reach 0.28 on estimates within
# ADD 0.1 d (binpick bench clutter, T-joint), while a quick profile's handful of validation
# scenes may show a single wrong pose at 0.17.
THRESHOLD_RANGE = (0.3, 0.6)
# The visible support cut likewise. Right poses on the validation scenes have nearly all their
# head-on surface measured (IC-BIN cup, Kinect-class renders: 0.90-1.00), wrong ones may too (a
# cup's handle turned); on noisier, more tilted views (bench clutter) right gear-shaft poses have
# from 0.46, so the cut stays at or below 0.9 whatever a few validation scenes say. Below 0.5 it
# would keep poses with half their head-on surface in view unmeasured.
SUPPORT_RANGE = (0.5, 0.9)
WRONG_WEIGHT = 2.0


def choose_threshold(
    shares_right: Sequence[float],
    shares_wrong: Sequence[float],
    prior: float = DEFAULT_MAX_SEEN_THROUGH,
    bounds: tuple[float, float] = THRESHOLD_RANGE,
    keep_below: bool = True,
) -> float:
    """The cut t (keep poses with share <= t; >= t when not keep_below) maximising kept right
    minus WRONG_WEIGHT x kept wrong; among equally good cuts the one nearest the prior (what the
    validation scenes do not decide, the prior does); within bounds. With no wrong pose seen: the
    prior, or the cut nearest to it that keeps every right pose."""
    if not keep_below:  # keeping the largest values is keeping the smallest of their negatives
        return -choose_threshold(
            [-s for s in shares_right], [-s for s in shares_wrong], -prior, (-bounds[1], -bounds[0])
        )
    right, wrong = np.sort(np.asarray(shares_right, float)), np.sort(np.asarray(shares_wrong, float))
    lo, hi = bounds
    cuts = np.unique(np.clip(np.concatenate([right, wrong, [lo, hi, prior]]), lo, hi))
    gain = np.searchsorted(right, cuts, side="right") - WRONG_WEIGHT * np.searchsorted(wrong, cuts, side="right")
    # A cut keeps the same poses up to the next share above it: the best cuts span intervals;
    # the prior is taken when it lies in one, else the best cut nearest to it.
    order = np.concatenate([right, wrong])
    best = cuts[gain == gain.max()]
    for c in best:
        nxt = order[order > c]
        if c <= prior < (nxt.min() if len(nxt) else np.inf):
            return float(np.clip(prior, lo, hi))
    return float(np.clip(best[np.argmin(np.abs(best - prior))], lo, hi))


def calibrate_verification(
    scenes: Sequence[SyntheticScene], models: PartModels, seed: int, name: str
) -> tuple[float, float, dict[str, float]]:
    """The chosen max_seen_through and min_visible_support, and what they were chosen on
    (counts, the values' extremes)."""
    off = replace(
        models,
        register_params=models.register_params.model_copy(update={"max_seen_through": 1.0, "min_visible_support": 0.0}),
    )
    right: list[tuple[float, float]] = []
    wrong: list[tuple[float, float]] = []
    for k, scene in enumerate(scenes):
        H, W = scene.labels.shape
        result = process(scene.xyz_m.reshape(-1, 3), None, (H, W), off, SceneSeeds.of(seed, f"{name}-val-{k}"))
        poses = result.registration.poses
        T = np.array([p.T_cam_from_model for p in poses]).reshape(-1, 4, 4)
        _, per = scene_pose_metrics(
            T,
            scene.T_cam_from_model,
            scene.visible_fraction,
            models.ppf.dense_points_m,
            models.ppf.symmetries,
            models.ppf.diameter_m,
        )
        for pose, match in zip(poses, per, strict=True):
            shares = (
                pose.seen_through if pose.seen_through is not None else 0.0,
                pose.visible_support if pose.visible_support is not None else 1.0,
            )
            (right if match and match["add_ok"] else wrong).append(shares)
    t = choose_threshold([r[0] for r in right], [w[0] for w in wrong])
    # The support cut is chosen on the poses the seen-through cut keeps: the two checks together.
    s = choose_threshold(
        [r[1] for r in right if r[0] <= t],
        [w[1] for w in wrong if w[0] <= t],
        DEFAULT_MIN_VISIBLE_SUPPORT,
        SUPPORT_RANGE,
        keep_below=False,
    )
    kept_wrong = [w for w in wrong if w[0] <= t and w[1] >= s]
    return (
        t,
        s,
        {
            "n_right": float(len(right)),
            "n_wrong": float(len(wrong)),
            "right_max": max((r[0] for r in right), default=0.0),
            "wrong_min": min((w[0] for w in wrong), default=1.0),
            "right_support_min": min((r[1] for r in right), default=1.0),
            "wrong_support_max": max((w[1] for w in wrong), default=0.0),
            "kept_wrong": float(len(kept_wrong)),
            "lost_right": float(sum(r[0] > t or r[1] < s for r in right)),
        },
    )
