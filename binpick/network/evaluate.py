"""Scoring a trained network on held-out generated scenes: one routine for the evaluate stage and
the segmentation benchmark, so that both report the same precision and recall."""

from __future__ import annotations

import numpy as np

from binpick.io.labelled_capture import LabelledCapture
from binpick.io.scene import SyntheticScene
from binpick.metrics.segmentation import SegmentationCounts, scene_counts
from binpick.network.infer import Segmenter
from binpick.params import SegmentParams
from binpick.seeding import derive_seed


def scene_seed(seed: int, part: str, index: int) -> np.random.SeedSequence:
    """The sampling seed of held-out scene `index` of `part`: from the scene alone, so that any
    worker, and the benchmark, segment it the same way."""
    return derive_seed(seed, "evaluate", part, index)


def segment_and_count(
    segmenter: Segmenter, scene: SyntheticScene, segment: SegmentParams, iou_threshold: float, seed: int, index: int
) -> tuple[np.ndarray, SegmentationCounts]:
    """Segment the network's view of a generated scene and match the instances against its
    labels (ground-truth instances under segment.min_points are not scored). Returns the labels
    (N,) and the counts."""
    rng = np.random.default_rng(scene_seed(seed, segmenter.settings.part, index))
    labels = segmenter.segment(scene.view_points_m, scene.view_normals, rng)
    return labels, scene_counts(labels, scene.view_labels, iou_threshold, segment.min_points)


def capture_counts(
    segmenter: Segmenter,
    capture: LabelledCapture,
    segment: SegmentParams,
    iou_threshold: float,
    rng: np.random.Generator,
) -> SegmentationCounts:
    """Segment a labelled capture's points and match the instances against its labels on the
    labelled points alone: ignored points count for neither side, so a segment on a part nobody
    posed is neither right nor wrong."""
    pred = segmenter.segment(capture.points_m, capture.normals, rng)
    known = capture.labels >= 0
    return scene_counts(pred[known], capture.labels[known].astype(np.int64), iou_threshold, segment.min_points)
