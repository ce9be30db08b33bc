"""One synthetic bin scene: drop objects into the bin, render them, derive the training view."""

from __future__ import annotations

import logging

import numpy as np

from binpick.generation.bin import T_bin_from_cam, bin_meshes
from binpick.generation.camera import Intrinsics, apply_sensor_noise, render, render_background, visible_fractions
from binpick.generation.overlap import drop_overlapping, penetration_depths_m
from binpick.generation.physics import SettleSettings, settle
from binpick.generation.placement import place_objects
from binpick.geometry.transforms import invert_T, transform_points
from binpick.io.part_model import PartModel
from binpick.io.scene import SyntheticScene
from binpick.params import CameraParams, GenerateParams
from binpick.view import ViewParams, labelled_view

log = logging.getLogger(__name__)

# Surface points per object in the physics mode's penetration check.
PENETRATION_SAMPLE = 400


def render_scene(
    part: PartModel,
    T_bin_from_model: np.ndarray,
    generate: GenerateParams,
    camera: CameraParams,
    view: ViewParams,
    rng: np.random.Generator,
) -> SyntheticScene:
    """Render placed objects (poses (k, 4, 4) in the bin frame) with the bin, add sensor noise,
    measure visibility and build the network's view."""
    T_cam_bin = invert_T(T_bin_from_cam(camera.distance_m))
    # Poses on a 1e-12 grid: sin, cos and matrix products may differ in the last bit between CPUs
    # (numpy and BLAS dispatch by instruction set); what is rendered should not.
    T_cam_model = np.round(T_cam_bin @ T_bin_from_model, 12)
    objects = [(transform_points(T, part.mesh_vertices_m), part.mesh_faces) for T in T_cam_model]
    clutter = [(transform_points(T_cam_bin, np.asarray(m.vertices)), np.asarray(m.faces)) for m in bin_meshes(generate.bin)]
    intr = Intrinsics.from_params(camera)
    clean = render(objects, list(range(len(objects))), intr, render_background(clutter, intr))
    visible = visible_fractions(objects, clean.labels, intr)
    noisy = apply_sensor_noise(clean, generate.noise, rng)
    vp, vn, vl = labelled_view(noisy.xyz_m, noisy.labels, view)
    return SyntheticScene(
        xyz_m=noisy.xyz_m,
        labels=noisy.labels.astype(np.int16),
        K=intr.K,
        T_cam_from_model=T_cam_model,
        visible_fraction=visible,
        T_cam_from_bin=T_cam_bin,
        view_points_m=vp,
        view_normals=vn,
        view_labels=vl,
    )


def generate_scene(
    part: PartModel,
    generate: GenerateParams,
    camera: CameraParams,
    view: ViewParams,
    seed: int | np.random.SeedSequence,
    n_objects: int | None = None,
) -> SyntheticScene:
    """Place objects (count drawn from the params unless given), then render the scene."""
    rng = np.random.default_rng(seed)
    placement = generate.placement
    if n_objects is None:
        n_objects = int(rng.integers(placement.n_objects_min, placement.n_objects_max + 1))
    placed = place_objects(part.points_m, n_objects, generate.bin, placement, rng)
    T_bin_from_model = placed.T_bin_from_model
    if placement.mode == "physics":
        T_bin_from_model = settle_in_bin(part, T_bin_from_model, generate, rng)
    return render_scene(part, T_bin_from_model, generate, camera, view, rng)


def settle_in_bin(part: PartModel, T_bin_from_model: np.ndarray, generate: GenerateParams, rng: np.random.Generator) -> np.ndarray:
    """The physics mode: drop-placed objects settled by simulation; objects that left the bin or
    reach deeper than placement.max_penetration_m into another are removed (logged).

    T_bin_from_model : (k, 4, 4) non-overlapping start poses, bin frame. Returns (m, 4, 4), m <= k.
    """
    placement = generate.placement
    boxes = [(m.bounds[0], m.bounds[1]) for m in bin_meshes(generate.bin)]
    half = (generate.bin.inner_x_m / 2.0, generate.bin.inner_y_m / 2.0)
    settled, inside = settle(part.mesh_vertices_m, part.mesh_faces, T_bin_from_model, boxes, SettleSettings(max_time_s=placement.settle_max_s), half)
    settled = settled[inside]
    sample = part.points_m[rng.choice(len(part.points_m), min(PENETRATION_SAMPLE, len(part.points_m)), replace=False)]
    keep = drop_overlapping(
        lambda poses: penetration_depths_m(part.mesh_vertices_m, part.mesh_faces, sample, poses, part.diameter_m),
        settled, placement.max_penetration_m,
    )
    if len(keep) < len(T_bin_from_model):
        log.info("physics: kept %d of %d objects (%d left the bin, %d overlapped)", len(keep), len(T_bin_from_model),
                 int((~inside).sum()), int(inside.sum()) - len(keep))
    return settled[keep]
