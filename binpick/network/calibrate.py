"""Clustering thresholds chosen on the validation scenes of a trained network.

The centre-score threshold and the embedding distance that separates instances depend on how a
given network spreads its outputs (measured here: P/R 0.91/0.90 at one setting and 0.39/0.86 at a
neighbouring one for the same model), so a fixed default serves some parts badly. The network's
outputs are computed once per validation scene; only the clustering is repeated over the grid.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from binpick.labels import NOT_A_PART
from binpick.metrics.segmentation import SegmentationCounts, scene_counts
from binpick.network.checkpoint import CalibratedClustering, InferenceSettings, load_network, write_with_clustering
from binpick.network.infer import (
    Block,
    ClusterParams,
    block_logits,
    cluster_params,
    default_device,
    label_blocks,
    predict_blocks,
)
from binpick.network.model import FPCC
from binpick.network.train import Views
from binpick.params import SegmentParams

CENTRE_GRID = (0.3, 0.4, 0.5, 0.6, 0.7)  # long parts (the gear shaft) want the higher ones
EMBEDDING_GRID_PER_EPS2 = (0.8, 0.9, 1.0, 1.07, 1.17)  # around the margin the loss pushes other instances beyond
# Smallest instance kept, as shares of the median visible instance of the validation scenes: most
# false instances are slivers of a part cut off at a block edge or an occlusion (on the ring
# screw's test scenes 24 of 31 were fragments of one part, median 77 points of about 760).
INSTANCE_SIZE_GRID_PER_MEDIAN = (0.0, 0.05, 0.1, 0.15, 0.2)
# The foreground head's logit cuts tried. Its loss weighs parts and no-part points alike, so on
# views that are mostly parts its logits sit low: on the T-joint's `cpu` network's validation
# views (93 % part points) the cut at 0 kept 0.92 of the part points (precision 0.99), -1.5 kept
# 0.99 (0.98); on a simulated cell's capture of 6 lone T-joints 0.56 against 0.88.
FOREGROUND_LOGIT_GRID = (-3.0, -2.5, -2.0, -1.5, -1.0, -0.5, 0.0, 0.5, 1.0)
# With fewer no-part points than this share the views cannot place the cut: it stays at 0.
MIN_NOT_A_PART_SHARE = 0.01
# The chosen values a checkpoint keeps (its CalibratedClustering).
CALIBRATED = ("centre_threshold", "embedding_threshold", "min_instance_points", "foreground_logit")


def choose_foreground_logit(
    views: list[tuple[np.ndarray, np.ndarray, np.ndarray]], predicted: list[list[Block]]
) -> float:
    """The cut of FOREGROUND_LOGIT_GRID with the best F1 of "a part's point" over the views' points
    (points (N, 3), normals, labels (N,): >= 0 a part's, NOT_A_PART not, others not scored), each
    point judged by the block whose seed is nearest, as inference judges it; ties to the cut
    nearest 0. Views with almost no no-part points (MIN_NOT_A_PART_SHARE) leave it at 0."""
    logits, parts = [], []
    for (points, _, labels), blocks in zip(views, predicted, strict=True):
        logit = block_logits(points, blocks)
        scored = np.isfinite(logit) & ((labels >= 0) | (labels == NOT_A_PART))
        logits.append(logit[scored])
        parts.append(labels[scored] >= 0)
    logit, part = np.concatenate(logits), np.concatenate(parts)
    if not len(part) or np.mean(~part) < MIN_NOT_A_PART_SHARE:
        return 0.0
    f1 = [
        2.0 * np.count_nonzero((logit > t) & part) / (np.count_nonzero(logit > t) + part.sum())
        for t in FOREGROUND_LOGIT_GRID
    ]
    top = np.flatnonzero(np.isclose(f1, max(f1)))
    return float(min((FOREGROUND_LOGIT_GRID[k] for k in top), key=abs))


def calibrate_clustering(
    model: FPCC,
    views: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
    features: str,
    length_scale_m: float,
    n_points: int,
    nms_radius_m: float,
    min_points: int,
    eps2: float,
    iou_threshold: float,
    rng: np.random.Generator,
) -> dict[str, float]:
    """The grid point with the best min(precision, recall) on the views (points (N, 3) metres,
    normals (N, 3), labels (N,)), ties to the higher sum; returns its centre_threshold,
    embedding_threshold, min_instance_points, precision and recall. Ground-truth instances with
    fewer than min_points points are not scored, and no smaller instance is kept."""
    predicted: list[list[Block]] = [
        predict_blocks(model, p, n, features, length_scale_m, n_points, rng) for p, n, _ in views
    ]
    foreground_logit = choose_foreground_logit(views, predicted)
    sizes = [np.bincount(labels[labels >= 0]) for _, _, labels in views]
    sizes_scored = np.concatenate([s[s >= min_points] for s in sizes]) if sizes else np.zeros(0)
    median_size = float(np.median(sizes_scored)) if len(sizes_scored) else 0.0
    size_grid = sorted({max(min_points, int(round(f * median_size))) for f in INSTANCE_SIZE_GRID_PER_MEDIAN})
    best: tuple[tuple[float, float], dict[str, float]] | None = None
    for centre in CENTRE_GRID:
        for rel in EMBEDDING_GRID_PER_EPS2:
            for min_size in size_grid:
                cp = ClusterParams(centre, nms_radius_m, rel * eps2, min_size, foreground_logit)
                counts = SegmentationCounts()
                for (points, _, labels), blocks in zip(views, predicted, strict=False):
                    counts = counts.add(
                        scene_counts(label_blocks(points, blocks, cp), labels, iou_threshold, min_points)
                    )
                s = counts.summary()
                rank = (min(s["precision"], s["recall"]), s["precision"] + s["recall"])
                if best is None or rank > best[0]:
                    best = (
                        rank,
                        {
                            "centre_threshold": centre,
                            "embedding_threshold": rel * eps2,
                            "min_instance_points": min_size,
                            "foreground_logit": foreground_logit,
                            "precision": s["precision"],
                            "recall": s["recall"],
                        },
                    )
    assert best is not None
    return best[1]


def calibrate_network(
    model: FPCC,
    settings: InferenceSettings,
    views: Views,
    segment: SegmentParams,
    iou_threshold: float,
    rng: np.random.Generator,
) -> dict[str, float]:
    """calibrate_clustering for a trained network with its inference settings; the suppression
    radius, block size and scored instance size from segment."""
    return calibrate_clustering(
        model,
        views.scenes(),
        settings.features,
        settings.d_max_m,
        segment.n_points,
        cluster_params(segment, settings.part_diameter_m).nms_radius_m,
        segment.min_points,
        settings.train.eps2,
        iou_threshold,
        rng,
    )


def recalibrate(
    source: str | Path,
    out: str | Path,
    views: Views,
    segment: SegmentParams,
    iou_threshold: float,
    rng: np.random.Generator,
) -> dict[str, float]:
    """Choose the clustering of the checkpoint at source on the views and write the checkpoint,
    holding it, to out (the train stage after training, `binpick calibrate` for a network trained
    elsewhere). Returns the chosen values with their validation precision and recall."""
    model, settings = load_network(source, default_device())
    chosen = calibrate_network(model, settings, views, segment, iou_threshold, rng)
    write_with_clustering(
        source,
        out,
        CalibratedClustering(
            chosen["centre_threshold"],
            chosen["embedding_threshold"],
            int(chosen["min_instance_points"]),
            chosen["foreground_logit"],
        ),
    )
    return chosen
