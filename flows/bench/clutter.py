"""Clutter benchmark: bins with distractors in and around them, seen by a tilted camera, through
the real scene path (import and cleaning, segmentation when the part has a trained network,
registration with verification), against the scoring without the checks this benchmark is for
(`baseline_*`: no crop to the bin walls, no verification against what the camera saw: neither
seen-through nor visible support).

Per part: pose_precision and pose_recall (parts at least half visible, ADD(-S) < 0.1 d, as the
register stage counts them), pose_recall_measured (over the parts the capture measured at least
half of: a part in the projector's shadow or out of the sensor's range is visible, not
measured), false_poses_outside_bin (wrong poses whose centre lies outside the
bin's inner footprint), n_scenes; then the same over all parts, and over all parts per band of
the camera's tilt from the bin's up axis (`by_tilt`: 0-15, 15-30, 30-45 degrees, ...): the
camera is tilted up to `tilt_deg_max` (45 by default), as a cell camera mounted beside the bin is.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import numpy as np

from binpick.errors import BinpickError
from binpick.generation.camera import visible_fractions
from binpick.generation.scene import generate_scene
from binpick.geometry.camera import PinholeCamera
from binpick.geometry.symmetry import symmetry_transforms
from binpick.geometry.transforms import invert_T, transform_points
from binpick.io.part_model import PartModel
from binpick.layout import Layout
from binpick.metrics.pose import MIN_VISIBLE_FRACTION, scene_pose_metrics
from binpick.params import BinParams, Params
from binpick.registration.model import train_ppf
from binpick.scene.process import PartModels, chosen_verification, process
from binpick.scene.register import with_verification
from binpick.seeding import SceneSeeds
from binpick.view import ViewParams
from flows.bench import BENCH_PARTS, machine

log = logging.getLogger(__name__)
Group = TypeVar("Group")
Figures = TypeVar("Figures")

CUP = "icbin_coffee_cup"
DEFAULT_PARTS = (*BENCH_PARTS, CUP)
NOISE_SCALE_MAX = 2.0
CLUTTER: dict[str, object] = {
    "n_distractors_max": 8,
    "distractor_size_rel": (0.3, 1.2),
    "outside_share": 0.5,
    "bin_scale": (0.9, 1.2),
    "wall_height_scale": (0.6, 1.4),
    "camera_tilt_deg_max": 20.0,
    "camera_distance_scale": (0.95, 1.2),
    "noise_scale": (0.5, NOISE_SCALE_MAX),
}
# Oblique views as cells mount cameras: beside the bin, looking in at up to 45 degrees.
TILT_DEG_MAX = 45.0
TILT_BAND_DEG = 15.0


def _cup(n_points: int) -> PartModel | None:
    from binpick.io.mesh import load_mesh
    from binpick.params import SymmetryParams
    from binpick.part.model import make_part_model
    from flows.bench.parts import shared_parts_folder

    parts = shared_parts_folder()
    path = parts.parent / "scans" / "icbin_scene1" / "coffee_cup_model.ply" if parts else None
    if path is None or not path.is_file():
        log.warning("skipping %s: ../shared/data/scans/icbin_scene1/coffee_cup_model.ply not found", CUP)
        return None
    mesh, unit = load_mesh(path, "mm")
    return make_part_model(CUP, mesh, SymmetryParams(), n_points, np.random.default_rng(0), unit)


def scaled_settings(settings: Params, part: PartModel, tilt_deg_max: float | None = None) -> Params:
    """The project's settings with the bin, camera distance and grids scaled to a part larger than
    the default bin was made for (the gear shaft is 0.44 m long), and clutter on, the camera
    tilted up to tilt_deg_max (default: CLUTTER's)."""
    g, cam, imp = settings.generate, settings.camera.model_copy(update={"downscale": 2}), settings.import_capture
    d = part.diameter_m
    inner_x = max(g.bin.inner_x_m, 2.2 * d)
    inner_y = max(g.bin.inner_y_m, 1.6 * d)
    # The camera sees the bin and a margin around it.
    distance = max(
        cam.distance_m, 1.25 * inner_x * cam.fx_px / cam.width_px, 1.25 * inner_y * cam.fy_px / cam.height_px
    )
    voxel = max(imp.voxel_size_m, d / 35.0)
    # Plane fits at three times the depth noise at that distance, at the noisiest clutter draws.
    sigma = (g.noise.depth_sigma_m + g.noise.depth_sigma_per_m2 * (1.2 * distance) ** 2) * NOISE_SCALE_MAX
    plane_threshold = max(imp.plane_threshold_m, 3.0 * sigma)
    generate = g.model_copy(
        update={
            "bin": g.bin.model_copy(
                update={"inner_x_m": inner_x, "inner_y_m": inner_y, "wall_height_m": max(g.bin.wall_height_m, 0.4 * d)}
            ),
            "clutter": g.clutter.model_copy(
                update={**CLUTTER, **({} if tilt_deg_max is None else {"camera_tilt_deg_max": tilt_deg_max})}
            ),
        }
    )
    return settings.model_copy(
        update={
            "generate": generate,
            "camera": cam.model_copy(update={"distance_m": distance}),
            "import_capture": imp.model_copy(
                update={
                    "voxel_size_m": voxel,
                    "normal_radius_m": 3.0 * voxel,
                    "plane_threshold_m": plane_threshold,
                    "keep_above_plane_m": max(imp.keep_above_plane_m, 1.3 * plane_threshold),
                    "max_range_m": max(imp.max_range_m, 2.0 * distance),
                }
            ),
        }
    )


def _outside_bin(
    T_cam_from_model: np.ndarray, centre_m: np.ndarray, T_cam_from_bin: np.ndarray, inner_x: float, inner_y: float
) -> bool:
    c = transform_points(
        invert_T(T_cam_from_bin), (T_cam_from_model[:3, :3] @ centre_m + T_cam_from_model[:3, 3])[None]
    )[0]
    return bool(abs(c[0]) > inner_x / 2 or abs(c[1]) > inner_y / 2)


def measured_fractions(scene, part: PartModel) -> np.ndarray:
    """(k,) share of the pixels each of the scene's parts would cover alone that the capture
    measured on it: visible_fraction after the sensor's shadows, dropouts and range limits (the
    scene's label image is the captured one)."""
    H, W = scene.labels.shape
    objects = [(transform_points(T, part.mesh_vertices_m), part.mesh_faces) for T in scene.T_cam_from_model]
    return visible_fractions(objects, scene.labels, PinholeCamera.from_K(scene.K, W, H))


def _score(poses, scene, ppf, part, inner_x, inner_y) -> dict[str, float]:
    T_est = np.array([p.T_cam_from_model for p in poses]).reshape(-1, 4, 4)

    def scored(visible: np.ndarray) -> tuple[dict[str, float], list[dict[str, float]]]:
        return scene_pose_metrics(
            T_est, scene.T_cam_from_model, visible, ppf.dense_points_m, ppf.symmetries, ppf.diameter_m
        )

    summary, per_est = scored(scene.visible_fraction)
    false = [i for i, m in enumerate(per_est) if not m or not m["add_ok"]]
    outside = sum(_outside_bin(T_est[i], part.centre_m, scene.T_cam_from_bin, inner_x, inner_y) for i in false)
    # The matching does not depend on which parts count; only the recall's parts do.
    measured, _ = scored(np.minimum(scene.visible_fraction, measured_fractions(scene, part)))
    n_pickable, n_found = summary["n_pickable"], summary["pose_recall"] * summary["n_pickable"]
    n_measured, n_found_measured = measured["n_pickable"], measured["pose_recall"] * measured["n_pickable"]
    return {
        "n_est": float(len(poses)),
        "n_ok": float(len(poses) - len(false)),
        "n_pickable": n_pickable,
        "n_found": n_found,
        "n_measured": n_measured,
        "n_found_measured": n_found_measured,
        "outside": float(outside),
    }


def _summary(rows: list[dict[str, float]]) -> dict[str, float]:
    n_est, n_ok = sum(r["n_est"] for r in rows), sum(r["n_ok"] for r in rows)
    n_pick, n_found = sum(r["n_pickable"] for r in rows), sum(r["n_found"] for r in rows)
    n_measured, n_found_measured = sum(r["n_measured"] for r in rows), sum(r["n_found_measured"] for r in rows)
    return {
        "pose_precision": n_ok / n_est if n_est else 0.0,
        "pose_recall": n_found / n_pick if n_pick else 0.0,
        "pose_recall_measured": n_found_measured / n_measured if n_measured else 0.0,
        "false_poses_outside_bin": sum(r["outside"] for r in rows),
        "n_scenes": float(len(rows)),
    }


def bench_clutter(
    settings: Params,
    names: list[str] | None,
    n_scenes: int,
    checkpoints: dict[str, Path],
    seed: int = 0,
    tilt_deg_max: float = TILT_DEG_MAX,
    part_settings: dict[str, Params] | None = None,
) -> dict[str, object]:
    """settings: the project's params; checkpoints: part -> trained FPCC checkpoint (parts
    without one are registered over the whole scene, no network); tilt_deg_max: the camera's
    largest tilt from the bin's up axis, degrees; part_settings: the params resolved for a part
    the project lists (its entry's overrides), used for that part."""
    from flows.bench.parts import bench_parts

    wanted = list(names or DEFAULT_PARTS)
    others = [n for n in wanted if n != CUP]
    # (An empty list would mean every part to bench_parts: `--part icbin_coffee_cup` alone ran them all.)
    parts = bench_parts(others, n_points=settings.ingest.n_surface_points) if others else []
    if CUP in wanted and (cup := _cup(settings.ingest.n_surface_points)) is not None:
        parts.append(cup)
    per_part: dict[str, dict[str, float]] = {}
    all_new: list[dict[str, float]] = []
    all_base: list[dict[str, float]] = []
    by_band: dict[str, list[dict[str, float]]] = {}
    for part in parts:
        p = scaled_settings((part_settings or {}).get(part.name, settings), part, tilt_deg_max)
        ppf = train_ppf(
            part.points_m, part.normals, part.diameter_m, symmetry_transforms(part.symmetry), p.registration
        )
        segmenter = None
        if part.name in checkpoints and checkpoints[part.name].is_file():
            from binpick.network.infer import load_segmenter

            segmenter = load_segmenter(checkpoints[part.name], p.segment)
        mode = p.registration.mode if segmenter is not None else "whole_scene"
        chosen = chosen_verification(
            Layout.verification_of(checkpoints[part.name]) if segmenter is not None else None, segmenter
        )
        new = PartModels(
            part,
            ppf,
            segmenter,
            p.import_capture,
            with_verification(p.registration.model_copy(update={"mode": mode}), chosen),
        )
        base = PartModels(
            part,
            ppf,
            segmenter,
            p.import_capture.model_copy(update={"crop_to_walls": False}),
            p.registration.model_copy(update={"mode": mode, "max_seen_through": 1.0, "min_visible_support": 0.0}),
        )
        rows_new: list[dict[str, float]] = []
        rows_base: list[dict[str, float]] = []
        for k in range(n_scenes):
            scene = generate_scene(
                part,
                p.generate,
                p.camera,
                ViewParams.of_import(p.import_capture),
                seed * 1000 + k,
                n_objects=int(np.random.default_rng(k).integers(6, 11)),
            )
            H, W = scene.labels.shape
            xyz = scene.xyz_m.reshape(-1, 3)
            # The bin actually drawn for this scene (clutter scales it): the one in the scene's frame.
            drawn, tilt_deg = drawn_bin(p, part, seed * 1000 + k)
            inner_x, inner_y = drawn.inner_x_m, drawn.inner_y_m
            for models, rows in ((new, rows_new), (base, rows_base)):
                try:
                    poses = process(
                        xyz, None, (H, W), models, SceneSeeds.of(seed, f"clutter-{part.name}-{k}")
                    ).registration.poses
                except BinpickError as exc:  # the scene path refused the capture: no poses, counted
                    log.warning("%s scene %d: %s", part.name, k, exc)
                    poses = []
                rows.append(_score(poses, scene, ppf, part, inner_x, inner_y))
            by_band.setdefault(tilt_band(tilt_deg), []).append(rows_new[-1])
        per_part[part.name] = {
            **_summary(rows_new),
            **{f"baseline_{k}": v for k, v in _summary(rows_base).items()},
            "segmentation": 1.0 if segmenter is not None else 0.0,
            "diameter_mm": 1000.0 * part.diameter_m,
        }
        all_new += rows_new
        all_base += rows_base
        log.info("%s: %s", part.name, {k: round(v, 3) for k, v in per_part[part.name].items()})
    return {
        "machine": machine(),
        "parts": per_part,
        **_summary(all_new),
        **{f"baseline_{k}": v for k, v in _summary(all_base).items()},
        "by_tilt": per_band(by_band, _summary),
        "min_visible_fraction": MIN_VISIBLE_FRACTION,
        "clutter": {k: list(v) if isinstance(v, tuple) else v for k, v in CLUTTER.items()},
    }


def drawn_bin(p: Params, part: PartModel, seed: int | np.random.SeedSequence) -> tuple[BinParams, float]:
    """The bin generate_scene drew for this seed (it draws clutter from its own stream) and the
    camera's tilt from the bin's up axis, degrees."""
    from binpick.generation.scene import clutter_generator, draw_clutter

    generate, _, T_bin_camera, _ = draw_clutter(p.generate, p.camera, part.diameter_m, clutter_generator(seed))
    return generate.bin, camera_tilt_deg(T_bin_camera)


def camera_tilt_deg(T_bin_from_camera: np.ndarray) -> float:
    """Degrees between the camera's viewing axis (its +z) and straight down the bin's up axis."""
    return float(np.degrees(np.arccos(np.clip(-T_bin_from_camera[2, 2], -1.0, 1.0))))


def tilt_band(tilt_deg: float) -> str:
    """The band of TILT_BAND_DEG a tilt falls in, as "lo-hi" degrees ("0-15", "15-30", ...)."""
    lo = int(tilt_deg // TILT_BAND_DEG) * int(TILT_BAND_DEG)
    return f"{lo}-{lo + int(TILT_BAND_DEG)}"


def per_band(groups: dict[str, Group], summarise: Callable[[Group], Figures]) -> dict[str, Figures]:
    """Each band's figures (summarise of its group), the bands in order of tilt."""
    return {band: summarise(group) for band, group in sorted(groups.items(), key=lambda kv: int(kv[0].split("-")[0]))}
