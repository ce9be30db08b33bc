"""FPCC inference: centre candidates, non-maximum suppression, nearest-centre assignment,
and labels for every point of a scene of any size."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from binpick.geometry.pointcloud import nearest_neighbours
from binpick.network.model import FPCC, input_features
from binpick.params import SegmentParams


@dataclass(frozen=True)
class ClusterParams:
    """centre_threshold: score above which a point may be a centre; nms_radius_m: candidates this
    close (metres) to a chosen centre are suppressed, as are candidates closer than
    embedding_threshold in embedding space; points farther than embedding_threshold from every
    centre are noise; instances smaller than min_points become noise."""

    centre_threshold: float
    nms_radius_m: float
    embedding_threshold: float
    min_points: int


def cluster(points: np.ndarray, embedding: np.ndarray, centre: np.ndarray, params: ClusterParams) -> np.ndarray:
    """Instance labels (N,) int32, -1 = noise.

    points (N, 3) metres; embedding (N, D); centre (N,) predicted centre scores in [0, 1].
    """
    N = len(points)
    if N == 0:
        return np.zeros(0, np.int32)
    order = np.argsort(-centre, kind="stable")
    candidates = order[centre[order] > params.centre_threshold]
    alive = np.ones(len(candidates), dtype=bool)
    centres: list[int] = []
    for i, c in enumerate(candidates):
        if not alive[i]:
            continue
        centres.append(int(c))
        near_xyz = np.linalg.norm(points[candidates] - points[c], axis=1) < params.nms_radius_m
        near_emb = np.linalg.norm(embedding[candidates] - embedding[c], axis=1) < params.embedding_threshold
        alive &= ~(near_xyz | near_emb)
    if not centres:
        return np.full(N, -1, np.int32)
    d = np.linalg.norm(embedding[:, None, :] - embedding[centres][None, :, :], axis=2)  # (N, C)
    labels = d.argmin(axis=1).astype(np.int32)
    labels[d.min(axis=1) > params.embedding_threshold] = -1
    sizes = np.bincount(labels[labels >= 0], minlength=len(centres))
    small = sizes < params.min_points
    labels[(labels >= 0) & small[np.maximum(labels, 0)]] = -1
    # Renumber to 0..k-1 in order of appearance of the centres.
    kept = np.flatnonzero(~small)
    remap = np.full(len(centres), -1, np.int32)
    remap[kept] = np.arange(len(kept), dtype=np.int32)
    return np.where(labels >= 0, remap[np.maximum(labels, 0)], -1).astype(np.int32)


@torch.no_grad()
def predict(
    model: FPCC, points: np.ndarray, normals: np.ndarray, features: str, length_scale_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """One network pass: points (N, 3) metres, normals (N, 3) -> embedding (N, D), centre scores (N,)."""
    device = next(model.parameters()).device
    p = torch.as_tensor(points, dtype=torch.float32, device=device)[None]
    n = torch.as_tensor(normals, dtype=torch.float32, device=device)[None]
    emb, ctr = model(input_features(p, n, features, length_scale_m), p)
    return emb[0].cpu().numpy(), ctr[0].cpu().numpy()


def segment_scene(
    model: FPCC,
    points: np.ndarray,
    normals: np.ndarray,
    features: str,
    length_scale_m: float,
    n_points: int,
    params: ClusterParams,
    rng: np.random.Generator,
) -> np.ndarray:
    """Labels (M,) int32 for every one of the M scene points (camera frame, metres).

    The network sees n_points of them drawn at random; every other point takes the label of its
    nearest seen point (label propagation), so no point is left out.
    """
    M = len(points)
    if M == 0:
        return np.zeros(0, np.int32)
    pick = np.sort(rng.choice(M, size=n_points, replace=False)) if M > n_points else np.arange(M)
    emb, ctr = predict(model, points[pick], normals[pick], features, length_scale_m)
    seen = cluster(points[pick], emb, ctr, params)
    if len(pick) == M:
        return seen
    _, nearest = nearest_neighbours(points[pick], points, k=1)
    return seen[nearest]


# The paper ties the suppression radius to object size; a quarter diameter keeps two touching
# parts apart while the candidates of one part (within 0.2 diameters of its centre at the
# default threshold) fall inside one radius or one embedding neighbourhood.
NMS_RADIUS_PER_DIAMETER = 0.25


def cluster_params(segment: SegmentParams, diameter_m: float) -> ClusterParams:
    """Clustering settings from the segment params, with size-derived defaults filled in."""
    return ClusterParams(
        centre_threshold=segment.centre_threshold,
        nms_radius_m=segment.nms_radius_m if segment.nms_radius_m is not None else NMS_RADIUS_PER_DIAMETER * diameter_m,
        embedding_threshold=segment.embedding_threshold,
        min_points=segment.min_points,
    )
