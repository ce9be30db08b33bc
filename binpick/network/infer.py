"""FPCC inference: centre candidates, non-maximum suppression, nearest-centre assignment,
and labels for every point of a scene of any size."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

from binpick.network.blocks import cover
from binpick.network.checkpoint import CalibratedClustering, InferenceSettings, load_network
from binpick.network.model import FPCC, input_features
from binpick.params import SegmentParams

# Share of a block instance's points that must already belong to one instance for the two to merge.
MERGE_OVERLAP = 0.3


@dataclass(frozen=True)
class ClusterParams:
    """centre_threshold: score above which a point may be a centre; nms_radius_m: candidates this
    close (metres) to a chosen centre are suppressed, as are candidates closer than
    embedding_threshold in embedding space; points farther than embedding_threshold from every
    centre are noise; instances smaller than min_points become noise; foreground_logit: a point
    whose foreground logit is not above it is no part's."""

    centre_threshold: float
    nms_radius_m: float
    embedding_threshold: float
    min_points: int
    foreground_logit: float = 0.0


def cluster(
    points: np.ndarray,
    embedding: np.ndarray,
    centre: np.ndarray,
    params: ClusterParams,
    foreground: np.ndarray | None = None,
) -> np.ndarray:
    """Instance labels (N,) int32, -1 = noise.

    points (N, 3) metres; embedding (N, D); centre (N,) predicted centre scores in [0, 1];
    foreground (N,) bool, the points the network calls a part's (default: all): the others are
    noise and never a centre.
    """
    N = len(points)
    if N == 0:
        return np.zeros(0, np.int32)
    part = np.ones(N, bool) if foreground is None else np.asarray(foreground, bool)
    order = np.argsort(-centre, kind="stable")
    candidates = order[(centre[order] > params.centre_threshold) & part[order]]
    cand_xyz, cand_emb = points[candidates], embedding[candidates]
    cand_sq = np.einsum("ij,ij->i", cand_emb, cand_emb)
    r_xyz_sq, r_emb_sq = params.nms_radius_m**2, params.embedding_threshold**2
    alive = np.ones(len(candidates), dtype=bool)
    centres: list[int] = []
    i = 0
    while i < len(candidates):  # candidates by falling score; a centre suppresses its neighbourhood
        centres.append(int(candidates[i]))
        dxyz = cand_xyz - cand_xyz[i]
        near_xyz = np.einsum("ij,ij->i", dxyz, dxyz) < r_xyz_sq
        near_emb = cand_sq - 2.0 * (cand_emb @ cand_emb[i]) + cand_sq[i] < r_emb_sq
        alive &= ~(near_xyz | near_emb)
        alive[i] = False
        nxt = np.flatnonzero(alive[i:])
        i = i + int(nxt[0]) if len(nxt) else len(candidates)
    if not centres:
        return np.full(N, -1, np.int32)
    # Squared embedding distances (N, C) by the product form: no (N, C, D) difference array.
    ce = embedding[centres]
    d_sq = (
        np.einsum("ij,ij->i", embedding, embedding)[:, None]
        - 2.0 * (embedding @ ce.T)
        + np.einsum("ij,ij->i", ce, ce)[None, :]
    )
    labels = d_sq.argmin(axis=1).astype(np.int32)
    labels[(d_sq.min(axis=1) > r_emb_sq) | ~part] = -1
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
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One network pass: points (N, 3) metres, normals (N, 3) -> embedding (N, D), centre scores
    (N,) and foreground logits (N,) (a point is a part's above ClusterParams.foreground_logit)."""
    device = next(model.parameters()).device
    p = torch.as_tensor(points, dtype=torch.float32, device=device)[None]
    n = torch.as_tensor(normals, dtype=torch.float32, device=device)[None]
    emb, ctr, fg = model(input_features(p, n, features, length_scale_m), p)
    return emb[0].cpu().numpy(), ctr[0].cpu().numpy(), fg[0].cpu().numpy()


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
    """Labels (M,) int32 for every one of the M scene points (camera frame, metres, on the voxel
    grid the network was trained at): predict_blocks, then label_blocks."""
    return label_blocks(points, predict_blocks(model, points, normals, features, length_scale_m, n_points, rng), params)


# Seed point, point indices, embeddings, centre scores, foreground logits.
Block = tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def predict_blocks(
    model: FPCC,
    points: np.ndarray,
    normals: np.ndarray,
    features: str,
    length_scale_m: float,
    n_points: int,
    rng: np.random.Generator,
) -> list[Block]:
    """The network's outputs on a cover of the scene: scenes larger than n_points are covered by
    blocks of n_points neighbours (see blocks.cover)."""
    if len(points) == 0:
        return []
    blocks = []
    for seed, idx in cover(points, n_points, rng):
        emb, ctr, fg = predict(model, points[idx], normals[idx], features, length_scale_m)
        blocks.append((seed, idx, emb, ctr, fg))
    return blocks


def block_logits(points: np.ndarray, blocks: list[Block]) -> np.ndarray:
    """(M,) the foreground logit of each scene point from the block whose seed is nearest to it
    (where it had the most context), as label_blocks labels it; NaN for a point in no block."""
    logits = np.full(len(points), np.nan)
    best_dist = np.full(len(points), np.inf)
    for seed, idx, _, _, fg in blocks:
        dist = np.linalg.norm(points[idx] - points[seed], axis=1)
        closer = dist < best_dist[idx]
        logits[idx[closer]] = fg[closer]
        best_dist[idx[closer]] = dist[closer]
    return logits


def part_points(points: np.ndarray, blocks: list[Block], foreground_logit: float = 0.0) -> np.ndarray:
    """(M,) bool: the scene points the network calls a part's (its foreground head's logit above
    foreground_logit; every point for a network without one), each judged by the block whose
    seed is nearest (block_logits); a point in no block takes its nearest neighbour's judgement."""
    logits = block_logits(points, blocks)
    inside = np.isfinite(logits)
    is_part = np.ones(len(points), bool)
    is_part[inside] = logits[inside] > foreground_logit
    if inside.any() and not inside.all():
        _, nearest = cKDTree(points[inside]).query(points[~inside])
        is_part[~inside] = is_part[np.flatnonzero(inside)[nearest]]
    return is_part


def label_blocks(points: np.ndarray, blocks: list[Block], params: ClusterParams) -> np.ndarray:
    """Labels (M,) int32 of the M scene points from the clustered blocks.

    Each point keeps the label of the block whose seed is nearest to it (where it had the most
    context) among those that label it: a block that holds a point but not its part's centre
    leaves it unlabelled (-1 only when no block labels it). An instance of a block joins the
    instance that already holds most of its points (MERGE_OVERLAP of them or more), else it is
    new. A point in no block (on a block's rim: blocks.cover) takes the label of the nearest
    point in one.
    """
    M = len(points)
    labels = np.full(M, -1, np.int32)
    best_dist = np.full(M, np.inf)  # to the seed of the block that gave the label
    seen = np.zeros(M, bool)  # in a block
    n_instances = 0
    for seed, idx, emb, ctr, fg in blocks:
        local = cluster(points[idx], emb, ctr, params, fg > params.foreground_logit)
        mapping = np.full(int(local.max()) + 2, -1, np.int32)  # local id -> global id; last slot: noise
        for j in range(int(local.max()) + 1):
            before = labels[idx[local == j]]
            before = before[before >= 0]
            if len(before) >= MERGE_OVERLAP * np.count_nonzero(local == j):
                mapping[j] = np.bincount(before).argmax()
            else:
                mapping[j] = n_instances
                n_instances += 1
        dist = np.linalg.norm(points[idx] - points[seed], axis=1)
        closer = (dist < best_dist[idx]) & (local >= 0)
        labels[idx[closer]] = mapping[local[closer]]
        best_dist[idx[closer]] = dist[closer]
        seen[idx] = True
    # A point on a block's rim but in no block (blocks.cover) takes its nearest neighbour's label.
    rim = np.flatnonzero(~seen)
    if len(rim) and len(rim) < M:
        inside = np.flatnonzero(seen)
        _, nearest = cKDTree(points[inside]).query(points[rim])
        labels[rim] = labels[inside[nearest]]
    # Renumber 0..k-1 (a merged or fully overwritten instance leaves a gap).
    present = np.unique(labels[labels >= 0])
    remap = np.full(n_instances + 1, -1, np.int32)
    remap[present] = np.arange(len(present), dtype=np.int32)
    return np.where(labels >= 0, remap[np.maximum(labels, 0)], -1).astype(np.int32)


# The paper ties the suppression radius to object size; a quarter diameter keeps two touching
# parts apart while the candidates of one part (within 0.2 diameters of its centre at the
# default threshold) fall inside one radius or one embedding neighbourhood.
NMS_RADIUS_PER_DIAMETER = 0.25


# Used where neither params.yaml nor the checkpoint sets them (a checkpoint from before
# calibration, or the sample predictions during training).
DEFAULT_CENTRE_THRESHOLD = 0.3
DEFAULT_EMBEDDING_THRESHOLD = 1.5


def cluster_params(
    segment: SegmentParams, diameter_m: float, calibrated: CalibratedClustering | None = None
) -> ClusterParams:
    """Clustering settings: the segment params where set, else the values calibrated on the
    validation scenes at training (the checkpoint's), else the defaults (smallest instance:
    segment.min_points); the suppression radius defaults to a share of the part's diameter."""

    def pick(value: float | None, calibrated_value: float | None, default: float) -> float:
        return (
            float(value) if value is not None else float(calibrated_value if calibrated_value is not None else default)
        )

    c = calibrated
    return ClusterParams(
        centre_threshold=pick(segment.centre_threshold, c.centre_threshold if c else None, DEFAULT_CENTRE_THRESHOLD),
        nms_radius_m=segment.nms_radius_m if segment.nms_radius_m is not None else NMS_RADIUS_PER_DIAMETER * diameter_m,
        embedding_threshold=pick(
            segment.embedding_threshold, c.embedding_threshold if c else None, DEFAULT_EMBEDDING_THRESHOLD
        ),
        min_points=max(
            segment.min_points,
            int(pick(segment.min_instance_points, c.min_instance_points if c else None, segment.min_points)),
        ),
        foreground_logit=pick(segment.foreground_logit, c.foreground_logit if c else None, 0.0),
    )


@dataclass(frozen=True)
class Segmenter:
    """A trained network ready to segment scenes of its part: the network (eval mode), its
    inference settings, the points per network pass and the clustering settings in force."""

    network: FPCC
    settings: InferenceSettings
    n_points: int
    clustering: ClusterParams

    def predict_blocks(self, points: np.ndarray, normals: np.ndarray, rng: np.random.Generator) -> list[Block]:
        return predict_blocks(
            self.network, points, normals, self.settings.features, self.settings.d_max_m, self.n_points, rng
        )

    def segment(self, points: np.ndarray, normals: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Labels (M,) int32 of the M scene points (camera frame, metres, on the voxel grid the
        network was trained at; normals facing the camera), -1 = in no instance."""
        return label_blocks(points, self.predict_blocks(points, normals, rng), self.clustering)

    def segment_parts(
        self, points: np.ndarray, normals: np.ndarray, rng: np.random.Generator
    ) -> tuple[np.ndarray, np.ndarray]:
        """segment's labels (M,) int32 and part_points' (M,) bool from one pass of the network."""
        blocks = self.predict_blocks(points, normals, rng)
        return label_blocks(points, blocks, self.clustering), part_points(
            points, blocks, self.clustering.foreground_logit
        )


def make_segmenter(network: FPCC, settings: InferenceSettings, segment: SegmentParams) -> Segmenter:
    return Segmenter(
        network, settings, segment.n_points, cluster_params(segment, settings.part_diameter_m, settings.clustering)
    )


def load_segmenter(path: str | Path, segment: SegmentParams, device: str | torch.device | None = None) -> Segmenter:
    """The checkpoint at `path` as a ready segmenter (on the GPU when there is one), with the
    segment params applied over its calibrated clustering."""
    network, settings = load_network(path, device if device is not None else default_device())
    return make_segmenter(network, settings, segment)


def default_device() -> torch.device:
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")
