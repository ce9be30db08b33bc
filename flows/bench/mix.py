"""Mixed-bin benchmark (`binpick bench clutter --mix a,b[,c]`): bins holding several kinds of part,
dropped together, rendered in the first part's bin and camera (name the largest part first),
each part with its own models and grids, and run through the mixed
scene path (binpick/scene/mixed.py: one cleaning, each part's segmentation and registration,
conflicts resolved, one pick list).

Per part: pose_precision and pose_recall (parts at least half visible, ADD(-S) < 0.1 d, as the
register stage counts them), wrong_part_poses (a pose of this part that is not right and whose
centre lies within half the other part's diameter of an instance of another part) and the
conflicts it lost; the same without the conflicts resolved as `baseline_*` (each part's poses
as its own registration gave them); over the mix: capture_s_median (the mixed path per capture) against
single_parts_s_median (the one-part path run for each part on the same capture, summed), both
paths warmed on the first capture before the timing.
Renderer only.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from binpick.generation.placement import place_objects
from binpick.generation.scene import render_scene
from binpick.io.part_model import PartModel
from binpick.metrics.pose import scene_pose_metrics
from binpick.params import Params
from binpick.scene.mixed import process_mixed
from binpick.scene.process import PartModels, process
from binpick.seeding import SceneSeeds
from binpick.view import ViewParams
from flows.bench import machine

log = logging.getLogger(__name__)

# Instances per bin, all kinds together, drawn in this range.
PARTS_PER_BIN = (8, 14)


def bench_mix(
    settings: Params, names: list[str], n_scenes: int, checkpoints: dict[str, Path], seed: int = 0
) -> dict[str, object]:
    """settings: the project's params; names: the parts of the mix (two or more, the first sets
    the bin, camera and grids); checkpoints: part -> trained FPCC checkpoint (without one, a part
    is registered over the whole scene)."""
    from flows.bench.mix_picking import mix_parts, mix_settings
    from flows.bench.picking import bench_models, picking_settings

    parts = mix_parts(settings, names)
    p = picking_settings(settings, parts[0])
    g = p.generate.model_copy(update={"placement": p.generate.placement.model_copy(update={"mode": "drop"})})
    # Each part's own models and grids (as its network was trained at); the bin, the camera and the
    # import settings that follow the camera (mix_settings) are the first part's.
    models = {
        part.name: bench_models(part, mix_settings(settings, part, p), checkpoints.get(part.name)) for part in parts
    }
    rows: dict[str, list[dict[str, float]]] = {part.name: [] for part in parts}
    mixed_s: list[float] = []
    single_s: list[float] = []
    for k in range(n_scenes):
        rng = np.random.default_rng(seed * 1000 + k)
        n = int(rng.integers(*PARTS_PER_BIN, endpoint=True))
        kinds = [int(x) for x in rng.integers(0, len(parts), n)]
        placed = place_objects([q.points_m for q in parts], n, g.bin, g.placement, rng, kinds)
        truth = _render_each(parts, placed, p, g, seed * 1000 + k)
        xyz, shape = truth[parts[0].name].xyz_m.reshape(-1, 3), truth[parts[0].name].labels.shape
        seeds = SceneSeeds.of(settings.seed, f"mix-{k}")
        if k == 0:
            # Both paths once untimed: the first call of either loads the compiled kernels and
            # the networks (10 s on the two-part mix), which a running service has done already.
            process_mixed(xyz, None, shape, models, seeds)
            _single_parts_s(xyz, shape, models, seeds)
        t0 = time.perf_counter()
        result = process_mixed(xyz, None, shape, models, seeds)
        mixed_s.append(time.perf_counter() - t0)
        single_s.append(_single_parts_s(xyz, shape, models, seeds))
        for part in parts:
            row = _score(part, result.poses[part.name], truth, parts, models[part.name])
            dropped = [pose for lost, pose, _ in result.conflicts if lost == part.name]
            row["conflicts_lost"] = float(len(dropped))
            # The baseline: every part's poses as its own registration gave them, no conflicts resolved.
            base = _score(part, result.poses[part.name] + dropped, truth, parts, models[part.name])
            row.update({f"baseline_{key}": v for key, v in base.items()})
            rows[part.name].append(row)
        log.info("mixed bin %d of %d: %d parts, %.2f s", k + 1, n_scenes, len(placed.T_bin_from_model), mixed_s[-1])
    per_part = {name: _sums(r) for name, r in rows.items()}
    return {
        "machine": machine(),
        "renderer_only": True,
        "mix": names,
        "n_scenes": float(n_scenes),
        "parts": per_part,
        "wrong_part_poses": float(sum(v["wrong_part_poses"] for v in per_part.values())),
        "baseline_wrong_part_poses": float(sum(v["baseline_wrong_part_poses"] for v in per_part.values())),
        "capture_s_median": float(np.median(mixed_s)),
        "single_parts_s_median": float(np.median(single_s)),
    }


def _render_each(parts: list[PartModel], placed, p: Params, g, seed: int) -> dict:
    """The bin rendered once per part: that part's instances as the objects (labels, visibility,
    truth), the other parts' as distractors; the same geometry, so one capture serves all."""
    import trimesh

    scenes = {}
    for i, part in enumerate(parts):
        mine = placed.T_bin_from_model[placed.kinds == i]
        others = []
        for j, other in enumerate(parts):
            if j == i:
                continue
            for T in placed.T_bin_from_model[placed.kinds == j]:
                mesh = trimesh.Trimesh(other.mesh_vertices_m, other.mesh_faces, process=False)
                others.append(mesh.apply_transform(T))
        # The same noise for every rendering: one seed per bin.
        scenes[part.name] = render_scene(
            part,
            mine,
            g,
            p.camera,
            ViewParams.of_import(p.import_capture),
            np.random.default_rng(seed),
            distractors=others,
        )
    return scenes


def _score(part: PartModel, poses, truth: dict, parts: list[PartModel], m: PartModels) -> dict[str, float]:
    scene = truth[part.name]
    T = np.array([q.T_cam_from_model for q in poses]).reshape(-1, 4, 4)
    summary, per_est = scene_pose_metrics(
        T, scene.T_cam_from_model, scene.visible_fraction, m.ppf.dense_points_m, m.ppf.symmetries, part.diameter_m
    )
    centre = part.points_m.mean(axis=0)
    wrong = 0
    for T_est, err in zip(T, per_est, strict=True):
        if err and err.get("add_ok", 0.0):
            continue
        c = T_est[:3, :3] @ centre + T_est[:3, 3]
        for other in parts:
            if other.name == part.name:
                continue
            theirs = truth[other.name].T_cam_from_model
            oc = other.points_m.mean(axis=0)
            if any(np.linalg.norm(c - (Tg[:3, :3] @ oc + Tg[:3, 3])) < 0.5 * other.diameter_m for Tg in theirs):
                wrong += 1
                break
    return {
        "n_found": summary["pose_recall"] * summary["n_pickable"],
        "n_pickable": summary["n_pickable"],
        "n_ok": summary["pose_precision"] * len(T),
        "n_est": float(len(T)),
        "wrong_part_poses": float(wrong),
    }


def _sums(rows: list[dict[str, float]], prefix: str = "") -> dict[str, float]:
    n_found, n_pick = sum(r[prefix + "n_found"] for r in rows), sum(r[prefix + "n_pickable"] for r in rows)
    n_ok, n_est = sum(r[prefix + "n_ok"] for r in rows), sum(r[prefix + "n_est"] for r in rows)
    out = {
        f"{prefix}pose_precision": n_ok / n_est if n_est else 0.0,
        f"{prefix}pose_recall": n_found / n_pick if n_pick else 0.0,
        f"{prefix}wrong_part_poses": float(sum(r[prefix + "wrong_part_poses"] for r in rows)),
    }
    if not prefix:
        out.update(
            conflicts_lost=float(sum(r["conflicts_lost"] for r in rows)),
            n_pickable=float(n_pick),
            **_sums(rows, "baseline_"),
        )
    return out


def _single_parts_s(xyz: np.ndarray, shape, models: dict[str, PartModels], seeds: SceneSeeds) -> float:
    """Seconds for the one-part scene path run for each part of the mix on the same capture."""
    t0 = time.perf_counter()
    for m in models.values():
        process(xyz, None, shape, m, seeds)
    return time.perf_counter() - t0
