"""Scene step `segment`: FPCC instance labels of a cleaned cloud."""

from __future__ import annotations

import numpy as np

from binpick.io.cloud import CleanCloud
from binpick.network.infer import Segmenter


def segment(cloud: CleanCloud, segmenter: Segmenter, seed: np.random.SeedSequence | int) -> np.ndarray:
    """Instance labels (n,) int32 of the cloud's points, -1 = not a part."""
    return segmenter.segment(cloud.points_m, cloud.normals, np.random.default_rng(seed))
