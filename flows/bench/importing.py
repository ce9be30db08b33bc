"""Import benchmark: a full 1920 x 1200 organized frame read, cleaned and downsampled."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from binpick.generation.scene import generate_scene
from binpick.io.capture import ImportOptions, load_capture
from binpick.io.pcd import save_pcd
from binpick.io.ply import PointCloudData, save_ply
from binpick.io.zdf import save_zdf_v1
from binpick.params import Params
from binpick.part.model import DEFAULT_PART_NAME, T_JOINT_SYMMETRY, build_t_joint_mesh, make_part_model
from binpick.scene.cleaning import clean_capture
from binpick.view import ViewParams
from flows.bench import machine, summary, timed

N_OBJECTS = 12


def bench_import(settings: Params, repeats: int = 7, seed: int = 0) -> dict[str, object]:
    """settings: the project's params (camera, generate, import_capture)."""
    mesh = build_t_joint_mesh()
    mesh.apply_scale(1e-3)
    part = make_part_model(DEFAULT_PART_NAME, mesh, T_JOINT_SYMMETRY, 20000, np.random.default_rng(seed), "mm")
    camera = settings.camera.model_copy(update={"downscale": 1})
    scene = generate_scene(
        part, settings.generate, camera, ViewParams.of_import(settings.import_capture), seed, n_objects=N_OBJECTS
    )
    H, W = scene.labels.shape
    xyz_mm = scene.xyz_m.reshape(-1, 3) * 1000.0
    rgb = np.full((H * W, 3), 128, np.uint8)
    params = settings.import_capture
    out: dict[str, object] = {"frame": f"{W}x{H}", "n_objects": N_OBJECTS, "repeats": repeats, "machine": machine()}
    by_format: dict[str, dict[str, float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        files = {"ply": Path(tmp) / "frame.ply", "pcd": Path(tmp) / "frame.pcd", "zdf": Path(tmp) / "frame.zdf"}
        save_ply(files["ply"], PointCloudData(xyz_mm, rgb, None, (H, W)))
        save_pcd(files["pcd"], PointCloudData(xyz_mm, rgb, None, (H, W)))
        save_zdf_v1(
            files["zdf"],
            xyz_mm.reshape(H, W, 3),
            np.concatenate([rgb, np.full((H * W, 1), 255, np.uint8)], 1).reshape(H, W, 4),
        )
        for fmt, path in files.items():

            def once(path: Path = path):
                cap = load_capture(path, ImportOptions("mm"))
                return clean_capture(cap.xyz_m, cap.rgb, cap.shape, params, seed)

            once()  # warm caches and lazy imports
            seconds, cloud = timed(once, repeats)
            by_format[fmt] = {**summary(seconds, "s_per_frame"), "n_points_out": float(len(cloud.points_m))}  # type: ignore[attr-defined]
        load_s, _ = timed(lambda: load_capture(files["ply"], ImportOptions("mm")), repeats)
    out["by_format"] = by_format
    out["s_per_frame_median"] = by_format["ply"]["s_per_frame_median"]
    out["s_per_frame_p90"] = by_format["ply"]["s_per_frame_p90"]
    out["ply_read_s_median"] = float(np.median(load_s))
    out["target_s_per_frame"] = 1.0
    out["target_met"] = bool(by_format["ply"]["s_per_frame_median"] < 1.0)
    return out
