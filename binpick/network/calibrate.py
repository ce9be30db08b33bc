"""Clustering thresholds chosen on the validation scenes of a trained network.

The centre-score threshold and the embedding distance that separates instances depend on how a
given network spreads its outputs (measured here: P/R 0.91/0.90 at one setting and 0.39/0.86 at a
neighbouring one for the same model), so a fixed default serves some parts badly. The network's
outputs are computed once per validation scene; only the clustering is repeated over the grid.
"""

from __future__ import annotations

import numpy as np

from binpick.metrics.segmentation import SegmentationCounts, scene_counts
from binpick.network.infer import ClusterParams, Block, label_blocks, predict_blocks
from binpick.network.model import FPCC

CENTRE_GRID = (0.3, 0.4, 0.5, 0.6, 0.7)  # long parts (the gear shaft) want the higher ones
EMBEDDING_GRID_PER_EPS2 = (0.8, 0.9, 1.0, 1.07, 1.17)  # around the margin the loss pushes other instances beyond


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
    embedding_threshold, precision and recall."""
    predicted: list[list[Block]] = [predict_blocks(model, p, n, features, length_scale_m, n_points, rng) for p, n, _ in views]
    best: tuple[tuple[float, float], dict[str, float]] | None = None
    for centre in CENTRE_GRID:
        for rel in EMBEDDING_GRID_PER_EPS2:
            cp = ClusterParams(centre, nms_radius_m, rel * eps2, min_points)
            counts = SegmentationCounts()
            for (points, _, labels), blocks in zip(views, predicted):
                counts = counts.add(scene_counts(label_blocks(points, blocks, cp), labels, iou_threshold, min_points))
            s = counts.summary()
            rank = (min(s["precision"], s["recall"]), s["precision"] + s["recall"])
            if best is None or rank > best[0]:
                best = (rank, {"centre_threshold": centre, "embedding_threshold": rel * eps2, "precision": s["precision"], "recall": s["recall"]})
    assert best is not None
    return best[1]
