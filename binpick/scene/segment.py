"""Scene step `segment`: FPCC instance labels of a cleaned cloud."""

from __future__ import annotations

import numpy as np

from binpick.io.cloud import CleanCloud, Segments
from binpick.network.infer import Segmenter


def segment(cloud: CleanCloud, segmenter: Segmenter, seed: np.random.SeedSequence | int) -> Segments:
    """Instance labels of the cloud's points and the points the network calls a part's."""
    labels, is_part = segmenter.segment_parts(cloud.points_m, cloud.normals, np.random.default_rng(seed))
    return Segments(labels, is_part)
