"""Segmentation benchmark: a trained FPCC network on held-out generated scenes against a
classical baseline (DBSCAN on the same points, which plane removal has already left as parts
only), plus inference time at fixed scene sizes and training throughput."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import open3d as o3d
import torch

from binpick.io.scene import list_scenes, load_scene
from binpick.metrics.segmentation import SegmentationCounts, scene_counts
from binpick.network.evaluate import segment_and_count
from binpick.network.infer import default_device, load_segmenter
from binpick.network.loss import fpcc_loss
from binpick.network.model import input_features
from binpick.params import SegmentParams
from flows.bench import machine

SCENE_SIZES = (16384, 65536)
DBSCAN_EPS_PER_VOXEL = 2.0  # neighbours within two grid cells are one cluster


def dbscan_labels(points: np.ndarray, eps_m: float, min_points: int) -> np.ndarray:
    o3d.utility.random.seed(0)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    return np.asarray(pcd.cluster_dbscan(eps=eps_m, min_points=min_points, print_progress=False), dtype=np.int64)


def _sized(points: np.ndarray, normals: np.ndarray, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A scene of exactly n points: copies of the scene side by side (each shifted by its width)
    until there are enough, then a random n of them, so density stays that of the grid."""
    width = np.ptp(points[:, 0]) + 0.05
    copies = int(np.ceil(n / len(points)))
    P = np.concatenate([points + [k * width, 0, 0] for k in range(copies)])
    N = np.concatenate([normals] * copies)
    pick = np.sort(rng.choice(len(P), n, replace=False))
    return P[pick], N[pick]


def bench_segment(
    checkpoint: Path,
    scenes: Path,
    segment: SegmentParams,
    voxel_size_m: float,
    seed: int,
    iou_threshold: float = 0.5,
    repeats: int = 3,
) -> dict[str, object]:
    """seed and iou_threshold as in params.yaml: the network's precision and recall are then
    those of the evaluate stage on the same checkpoint and scenes (the same routine scores both)."""
    device = default_device()
    segmenter = load_segmenter(checkpoint, segment, device)
    model, settings = segmenter.network, segmenter.settings
    paths = list_scenes(scenes / "test")
    if not paths:
        raise ValueError(f"{scenes / 'test'} holds no scenes")
    ours, base = SegmentationCounts(), SegmentationCounts()
    no_part = no_part_in_segments = segments_on_no_part = 0
    for i, path in enumerate(paths):
        s = load_scene(path)
        labels, counts = segment_and_count(segmenter, s, segment, iou_threshold, seed, i)
        ours = ours.add(counts)
        # What a capture shows besides the part (distractors, rims the cleaning left): the network
        # should leave it out of every segment.
        outside = s.view_labels < 0
        no_part += int(outside.sum())
        no_part_in_segments += int((outside & (labels >= 0)).sum())
        segments_on_no_part += sum(int(outside[labels == k].mean() > 0.5) for k in np.unique(labels[labels >= 0]))
        db = dbscan_labels(s.view_points_m, DBSCAN_EPS_PER_VOXEL * voxel_size_m, 10)
        base = base.add(scene_counts(db, s.view_labels, iou_threshold, segment.min_points))
    out: dict[str, object] = {
        **{k: v for k, v in ours.summary().items()},
        "n_scenes": len(paths),
        "device": str(device),
        "no_part_points_in_segments": no_part_in_segments / no_part if no_part else 0.0,
        "segments_mostly_no_part": segments_on_no_part,
    }
    out["baseline_dbscan"] = base.summary()

    s = load_scene(paths[0])
    rng = np.random.default_rng(0)
    for n in SCENE_SIZES:
        P, N = _sized(s.view_points_m, s.view_normals, n, rng)
        segmenter.segment(P, N, rng)  # warm-up
        t = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            segmenter.segment(P, N, rng)
            t.append(time.perf_counter() - t0)
        out[f"infer_ms_per_scene_{n}"] = 1000.0 * float(np.median(t))

    # Training throughput: forward + loss + backward + step on batches of 4 crops of 4,096 points.
    tp = settings.train
    train_model = type(model)(model.config).to(device).train()
    opt = torch.optim.Adam(train_model.parameters(), lr=1e-4)
    P, N = _sized(s.view_points_m, s.view_normals, 4 * 4096, rng)
    L = np.zeros(len(P), np.int64)  # labels only shape the loss's work, not its cost
    L[: len(P) // 2] = 1
    pts = torch.as_tensor(P.reshape(4, 4096, 3), dtype=torch.float32, device=device)
    nrm = torch.as_tensor(N.reshape(4, 4096, 3), dtype=torch.float32, device=device)
    lab = torch.as_tensor(L.reshape(4, 4096), device=device)
    steps = []
    for k in range(repeats + 1):
        t0 = time.perf_counter()
        emb, ctr, fg = train_model(input_features(pts, nrm, tp.features, settings.d_max_m), pts)
        loss, _ = fpcc_loss(
            emb,
            ctr,
            pts,
            lab,
            settings.d_max_m,
            tp.eps1,
            tp.eps2,
            tp.centre_loss_weight,
            tp.centre_score_form,
            tp.loss_anchors,
            foreground_logit=fg,
        )
        opt.zero_grad()
        loss.backward()
        opt.step()
        if device.type == "cuda":  # CUDA runs the step asynchronously: wait for it before reading the clock
            torch.cuda.synchronize(device)
        if k:  # the first step warms up
            steps.append(time.perf_counter() - t0)
    out["train_samples_per_s"] = 4.0 / float(np.median(steps))
    out["train_sample_points"] = 4096
    out["model_config"] = model.config.to_dict()
    out["machine"] = machine()
    return out
