"""Instance segmentation metrics on labelled points.

Main numbers: precision and recall of instances at IoU >= threshold with one-to-one matching
(Hungarian on IoU), counts pooled over scenes; mean coverage (mean over ground-truth instances of
the best IoU of any prediction). For comparison, the reference code's variant: each prediction is
a true positive if its best-IoU ground truth reaches the threshold, with no one-to-one constraint.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment


@dataclass
class SegmentationCounts:
    """Counts to pool over scenes."""

    n_pred: int = 0
    n_gt: int = 0
    tp: int = 0
    tp_reference: int = 0  # non-exclusive matching of the reference code
    coverage_sum: float = 0.0

    def add(self, other: SegmentationCounts) -> SegmentationCounts:
        return SegmentationCounts(
            self.n_pred + other.n_pred,
            self.n_gt + other.n_gt,
            self.tp + other.tp,
            self.tp_reference + other.tp_reference,
            self.coverage_sum + other.coverage_sum,
        )

    def summary(self) -> dict[str, float]:
        div = lambda a, b: float(a / b) if b else 0.0  # noqa: E731
        return {
            "precision": div(self.tp, self.n_pred),
            "recall": div(self.tp, self.n_gt),
            "mean_coverage": div(self.coverage_sum, self.n_gt),
            "precision_reference": div(self.tp_reference, self.n_pred),
            "recall_reference": div(self.tp_reference, self.n_gt),
            "n_pred": float(self.n_pred),
            "n_gt": float(self.n_gt),
        }


def iou_matrix(pred: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """IoU (P, G) between predicted and ground-truth instances, and their ids.

    pred, gt : (N,) int labels over the same points; -1 = no instance.
    """
    pred = np.asarray(pred)
    gt = np.asarray(gt)
    if pred.shape != gt.shape or pred.ndim != 1:
        raise ValueError(f"expected two (N,) label arrays, got {pred.shape} and {gt.shape}")
    p_ids = np.unique(pred[pred >= 0])
    g_ids = np.unique(gt[gt >= 0])
    if len(p_ids) == 0 or len(g_ids) == 0:
        return np.zeros((len(p_ids), len(g_ids))), p_ids, g_ids
    p_idx = np.searchsorted(p_ids, pred)
    g_idx = np.searchsorted(g_ids, gt)
    both = (pred >= 0) & (gt >= 0)
    inter = np.zeros((len(p_ids), len(g_ids)))
    np.add.at(inter, (p_idx[both], g_idx[both]), 1)
    p_size = np.bincount(p_idx[pred >= 0], minlength=len(p_ids))
    g_size = np.bincount(g_idx[gt >= 0], minlength=len(g_ids))
    union = p_size[:, None] + g_size[None, :] - inter
    return inter / np.maximum(union, 1), p_ids, g_ids


def scene_counts(pred: np.ndarray, gt: np.ndarray, iou_threshold: float, min_gt_points: int = 1) -> SegmentationCounts:
    """Counts of one scene. Ground-truth instances with fewer than min_gt_points points are
    ignored: their points count for neither side."""
    pred = np.asarray(pred).copy()
    gt = np.asarray(gt).copy()
    if min_gt_points > 1 and (gt >= 0).any():
        sizes = np.bincount(gt[gt >= 0])
        tiny = (gt >= 0) & (sizes[np.maximum(gt, 0)] < min_gt_points)
        pred, gt = pred[~tiny], gt[~tiny]
    iou, p_ids, g_ids = iou_matrix(pred, gt)
    counts = SegmentationCounts(n_pred=len(p_ids), n_gt=len(g_ids))
    if iou.size == 0:
        return counts
    rows, cols = linear_sum_assignment(-iou)
    counts.tp = int(np.sum(iou[rows, cols] >= iou_threshold))
    counts.tp_reference = int(np.sum(iou.max(axis=1) >= iou_threshold))
    counts.coverage_sum = float(iou.max(axis=0).sum())
    return counts
