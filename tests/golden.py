"""The golden scene: one small rendered bin of the built-in part, recorded once, so that a test
can tell whether generation on this machine gives what it gave where it was recorded.

Re-record (after a deliberate change to generation): `python -m tests.golden`.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from binpick.params import CameraParams, GenerateParams
from flows.bench import cpu_model

GOLDEN = Path(__file__).resolve().parent / "data" / "golden_scene.npz"
SEED = 20261201
N_OBJECTS = 6
# Fixed here, not read from params.yaml: the recording must not depend on the project's settings.
CAMERA = {
    "width_px": 1920,
    "height_px": 1200,
    "fx_px": 2660.0,
    "fy_px": 2660.0,
    "cx_px": 960.0,
    "cy_px": 600.0,
    "downscale": 12,
    "distance_m": 0.5,
}
GENERATE = {
    "n_train": 1,
    "n_val": 1,
    "n_test": 1,
    "placement": {
        "n_objects_min": N_OBJECTS,
        "n_objects_max": N_OBJECTS,
        "orientation": "uniform",
        "heightmap_cell_m": 0.001,
        "candidates_per_object": 8,
        "max_pile_height_m": 0.25,
        "heights": "pile",
        "height_levels_m": [0.0],
        "mode": "drop",
        "settle_max_s": 2.0,
        "max_penetration_m": 0.001,
    },
    "bin": {"inner_x_m": 0.30, "inner_y_m": 0.20, "wall_height_m": 0.08, "wall_thickness_m": 0.01},
    "noise": {
        "depth_sigma_m": 0.0002,
        "depth_sigma_per_m2": 0.0004,
        "max_incidence_deg": 80.0,
        "dropout_fraction": 0.01,
    },
    "clutter": {
        "n_distractors_max": 0,
        "distractor_size_rel": [0.3, 1.2],
        "outside_share": 0.5,
        "bin_scale": [1.0, 1.0],
        "wall_height_scale": [1.0, 1.0],
        "camera_tilt_deg_max": 0.0,
        "camera_distance_scale": [1.0, 1.0],
        "noise_scale": [1.0, 1.0],
    },
    "sensor": {
        "presets": [],
        "effect_scale": [1.0, 1.0],
        "baseline_scale": [1.0, 1.0],
        "projector_angle_deg": [0.0, 0.0],
        "surface": "matte",
        "models": {},
        "materials": {},
    },
}


def render_golden() -> dict[str, np.ndarray]:
    """Render the golden scene on this machine: depth (H, W) float32 metres (nan = no return),
    labels (H, W) int16, poses (k, 4, 4) float64 camera frame."""
    from binpick.generation.scene import generate_scene
    from binpick.part.model import T_JOINT_SYMMETRY, build_t_joint_mesh, make_part_model
    from binpick.view import ViewParams

    mesh = build_t_joint_mesh()
    mesh.apply_scale(1e-3)
    part = make_part_model("t_joint", mesh, T_JOINT_SYMMETRY, 20000, np.random.default_rng(SEED), "mm")
    view = ViewParams(voxel_size_m=0.002, normal_radius_m=0.006)
    scene = generate_scene(
        part, GenerateParams.model_validate(GENERATE), CameraParams.model_validate(CAMERA), view, SEED
    )
    return {
        "depth_m": scene.xyz_m[..., 2].astype(np.float32),
        "labels": scene.labels.astype(np.int16),
        "T_cam_from_model": scene.T_cam_from_model.astype(np.float64),
    }


def main() -> None:
    golden = render_golden()
    GOLDEN.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(GOLDEN, **golden, recorded_on=np.array(json.dumps({"cpu": cpu_model()})))
    print(f"wrote {GOLDEN}")  # noqa: T201 - a maintainer's script


if __name__ == "__main__":
    main()
