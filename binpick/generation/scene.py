"""One synthetic bin scene: drop objects into the bin, render them, derive the training view."""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
import trimesh

from binpick.cell.bin_box import BinBox
from binpick.generation.bin import FLOOR_THICKNESS_M, T_bin_from_cam, bin_meshes
from binpick.generation.camera import apply_sensor_noise, camera_of, render, render_background, visible_fractions
from binpick.generation.overlap import drop_overlapping, penetration_depths_m
from binpick.generation.physics import SettleSettings, settle, settle_kinds
from binpick.generation.placement import place_objects
from binpick.generation.sensor import apply_sensor_model, intrinsics_of, scaled_model
from binpick.geometry.transforms import axis_angle_to_R, invert_T, make_T, transform_points
from binpick.io.part_model import PartModel
from binpick.io.scene import SyntheticScene
from binpick.params import CameraParams, GenerateParams, SensorModelParams
from binpick.scene.cleaning import captured_view
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
    T_bin_from_camera: np.ndarray | None = None,
    distractors: list[trimesh.Trimesh] | None = None,
    sensor: SensorModelParams | None = None,
    view_in_box: bool = False,
) -> SyntheticScene:
    """Render placed objects (poses (k, 4, 4) in the bin frame) with the bin, add sensor noise,
    measure visibility and build the network's view. T_bin_from_camera: the camera's pose
    (default: camera.distance_m straight above the bin floor centre); distractors: meshes in the
    bin frame, rendered with the bin (label -1); sensor: a sensor model (its camera and effects,
    generation/sensor.py) instead of the camera section's camera and generate.noise; view_in_box:
    the view cleaned as a capture cropped to the bin's inner box is (a cell's given box)."""
    T_cam_bin = invert_T(T_bin_from_cam(camera.distance_m) if T_bin_from_camera is None else T_bin_from_camera)
    # Poses on a 1e-12 grid: sin, cos and matrix products may differ in the last bit between CPUs
    # (numpy and BLAS dispatch by instruction set); what is rendered should not.
    T_cam_model = np.round(T_cam_bin @ T_bin_from_model, 12)
    objects = [(transform_points(T, part.mesh_vertices_m), part.mesh_faces) for T in T_cam_model]
    clutter = [
        (transform_points(T_cam_bin, np.asarray(m.vertices)), np.asarray(m.faces))
        for m in [*bin_meshes(generate.bin), *(distractors or [])]
    ]
    intr = camera_of(camera) if sensor is None else intrinsics_of(sensor, camera.width_px, camera.downscale)
    clean = render(objects, list(range(len(objects))), intr, render_background(clutter, intr))
    visible = visible_fractions(objects, clean.labels, intr)
    if sensor is None:
        noisy = apply_sensor_noise(clean, generate.noise, rng)
    else:
        noisy = apply_sensor_model(
            clean, objects + clutter, intr, sensor, generate.sensor.materials[generate.sensor.surface], rng
        )
    if view.cleaning is not None:
        cleaning = view.cleaning
        if view_in_box:
            # As high as the box a cell gives (fit-bin's reaches over the heap): parts heaped over
            # the rim stay in the view, the walls are cut at the rim.
            box = BinBox.of_generated(generate.bin, T_cam_bin, headroom_m=part.diameter_m)
            cleaning = cleaning.model_copy(update=box.as_import_settings())
        vp, vn, vl = captured_view(noisy.xyz_m, noisy.labels, cleaning)
    else:
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
    others: Sequence[PartModel] = (),
) -> SyntheticScene:
    """Place objects (count drawn from the params unless given), then render the scene. others:
    the other parts of a mixed bin (generate.clutter.parts): about clutter.parts_share of the
    objects dropped are drawn from them, rendered as distractors (label -1)."""
    rng = np.random.default_rng(seed)
    T_bin_camera, distractors = None, None
    sensor = draw_sensor(generate, stream_generator(seed, SENSOR_STREAM)) if generate.sensor.presets else None
    if sensor is not None:
        lo, hi = sensor.working_distance_m
        camera = camera.model_copy(update={"distance_m": float(np.clip(camera.distance_m, lo, hi))})
    if generate.clutter.active:
        generate, camera, T_bin_camera, distractors = draw_clutter(
            generate, camera, part.diameter_m, clutter_generator(seed)
        )
    placement = generate.placement
    if n_objects is None:
        n_objects = int(rng.integers(placement.n_objects_min, placement.n_objects_max + 1))
    if others:
        T_bin_from_model, mixed_in = _mixed_pile(
            part, others, n_objects, generate, rng, stream_generator(seed, MIX_STREAM)
        )
        distractors = [*(distractors or []), *mixed_in]
    else:
        T_bin_from_model = place_objects(part.points_m, n_objects, generate.bin, placement, rng).T_bin_from_model
        if placement.mode == "physics":
            T_bin_from_model = settle_in_bin(part, T_bin_from_model, generate, rng)
    # Drawn from a stream of its own: the scenes' other draws stay as they were.
    in_box = bool(stream_generator(seed, VIEW_BOX_STREAM).random() < generate.clutter.box_share)
    return render_scene(
        part, T_bin_from_model, generate, camera, view, rng, T_bin_camera, distractors, sensor, view_in_box=in_box
    )


def _mixed_pile(
    part: PartModel,
    others: Sequence[PartModel],
    n_objects: int,
    generate: GenerateParams,
    rng: np.random.Generator,
    kinds_rng: np.random.Generator,
) -> tuple[np.ndarray, list[trimesh.Trimesh]]:
    """A pile of the part with the other parts mixed in: the part's poses (k, 4, 4), bin frame,
    and the other parts' instances as meshes in the bin frame. Each object is another part with
    probability clutter.parts_share (which one: uniform), drawn from kinds_rng."""
    every = [part, *others]
    other = kinds_rng.random(n_objects) < generate.clutter.parts_share
    kinds = np.where(other, 1 + kinds_rng.integers(0, len(others), n_objects), 0)
    placed = place_objects(
        [q.points_m for q in every], n_objects, generate.bin, generate.placement, rng, kinds.tolist()
    )
    T, placed_kinds = placed.T_bin_from_model, np.asarray(placed.kinds, dtype=np.int64)
    if generate.placement.mode == "physics":
        boxes = [(m.bounds[0], m.bounds[1]) for m in bin_meshes(generate.bin)]
        half = (generate.bin.inner_x_m / 2.0, generate.bin.inner_y_m / 2.0)
        meshes = [(q.mesh_vertices_m, q.mesh_faces) for q in every]
        settings = SettleSettings(max_time_s=generate.placement.settle_max_s)
        T, inside = settle_kinds(meshes, placed_kinds, T, boxes, settings, half)
        T, placed_kinds = T[inside], placed_kinds[inside]
    mixed_in = [
        trimesh.Trimesh(every[k].mesh_vertices_m, every[k].mesh_faces, process=False).apply_transform(T_k)
        for T_k, k in zip(T, placed_kinds, strict=True)
        if k > 0
    ]
    return T[placed_kinds == 0], mixed_in


CLUTTER_STREAM = 7_777
SENSOR_STREAM = 7_778
MIX_STREAM = 7_779
VIEW_BOX_STREAM = 7_780


def stream_generator(seed: int | np.random.SeedSequence, stream: int) -> np.random.Generator:
    """A random stream of a scene's own, beside the scene's: turning clutter or sensor models on
    changes no other draw (and a caller can redraw the same clutter)."""
    seq = np.random.default_rng(seed).bit_generator.seed_seq
    return np.random.default_rng(np.random.SeedSequence(seq.entropy, spawn_key=(*seq.spawn_key, stream)))  # type: ignore[attr-defined]


def clutter_generator(seed: int | np.random.SeedSequence) -> np.random.Generator:
    """The random stream a scene's clutter is drawn from."""
    return stream_generator(seed, CLUTTER_STREAM)


def draw_sensor(generate: GenerateParams, rng: np.random.Generator) -> SensorModelParams:
    """One scene's sensor: a preset of generate.sensor.presets, its effects scaled by a factor
    drawn from generate.sensor.effect_scale, its baseline by one from baseline_scale, its
    projector turned about the optical axis by an angle from projector_angle_deg (a fixed range
    draws nothing: the scenes of a seed stay the same)."""
    s = generate.sensor
    name = s.presets[int(rng.integers(0, len(s.presets)))]
    model = scaled_model(s.models[name], _scaled(s.effect_scale, rng))
    return model.model_copy(
        update={
            "baseline_m": model.baseline_m * _scaled(s.baseline_scale, rng),
            "projector_angle_deg": model.projector_angle_deg + _scaled(s.projector_angle_deg, rng),
        }
    )


def _scaled(lo_hi: tuple[float, float], rng: np.random.Generator) -> float:
    lo, hi = lo_hi
    return float(rng.uniform(lo, hi)) if hi > lo else float(lo)


def tilted_camera(distance_m: float, tilt_rad: float, heading_rad: float) -> np.ndarray:
    """T_bin_from_camera (4, 4): the camera distance_m from the bin floor centre, looking at it,
    its axis tilted by tilt_rad from straight down, about the horizontal axis at heading_rad
    (bin frame, from +x towards +y)."""
    R = axis_angle_to_R(np.array([np.cos(heading_rad), np.sin(heading_rad), 0.0]), tilt_rad)
    return make_T(R, np.zeros(3)) @ T_bin_from_cam(distance_m)


def draw_clutter(
    generate: GenerateParams, camera: CameraParams, diameter_m: float, rng: np.random.Generator
) -> tuple[GenerateParams, CameraParams, np.ndarray, list[trimesh.Trimesh]]:
    """One scene's variation (generate.clutter): the bin and noise settings, the camera's pose
    (bin frame: tilted about a horizontal axis through the bin floor centre, at a scaled height)
    and the distractor meshes (bin frame, metres) standing on the bin floor or on the table."""
    c = generate.clutter
    b = generate.bin
    bin_params = b.model_copy(
        update={
            "inner_x_m": b.inner_x_m * _scaled(c.bin_scale, rng),
            "inner_y_m": b.inner_y_m * _scaled(c.bin_scale, rng),
            "wall_height_m": b.wall_height_m * _scaled(c.wall_height_scale, rng),
        }
    )
    k = _scaled(c.noise_scale, rng)
    noise = generate.noise.model_copy(
        update={
            "depth_sigma_m": generate.noise.depth_sigma_m * k,
            "depth_sigma_per_m2": generate.noise.depth_sigma_per_m2 * k,
        }
    )
    distance = camera.distance_m * _scaled(c.camera_distance_scale, rng)
    camera = camera.model_copy(update={"distance_m": distance})
    tilt = np.radians(float(rng.uniform(0.0, c.camera_tilt_deg_max))) if c.camera_tilt_deg_max > 0 else 0.0
    T_bin_camera = tilted_camera(distance, tilt, float(rng.uniform(0.0, 2.0 * np.pi)))
    meshes = []
    n = int(rng.integers(0, c.n_distractors_max + 1)) if c.n_distractors_max else 0
    X, Y, W = bin_params.inner_x_m, bin_params.inner_y_m, bin_params.wall_thickness_m
    for _ in range(n):
        size = _scaled(c.distractor_size_rel, rng) * diameter_m
        kind = int(rng.integers(0, 3))
        if kind == 0:  # a box
            mesh = trimesh.creation.box(extents=size * rng.uniform(0.3, 1.0, 3))
        elif kind == 1:  # a cylinder standing or lying
            mesh = trimesh.creation.cylinder(radius=size * float(rng.uniform(0.15, 0.35)), height=size, sections=24)
            if rng.random() < 0.5:
                mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
        else:  # a thin plate
            mesh = trimesh.creation.box(extents=[size, size * float(rng.uniform(0.4, 1.0)), max(0.002, 0.04 * size)])
        mesh.apply_transform(trimesh.transformations.rotation_matrix(float(rng.uniform(0, 2 * np.pi)), [0, 0, 1]))
        half = (mesh.bounds[1] - mesh.bounds[0]) / 2.0
        if rng.random() < c.outside_share:  # on the table beside the bin
            side = int(rng.integers(0, 4))
            gap = float(rng.uniform(0.01, 0.08))
            along = float(rng.uniform(-0.5, 0.5))
            x = (X / 2 + W + gap + half[0]) * (1 if side == 0 else -1) if side < 2 else along * X
            y = (Y / 2 + W + gap + half[1]) * (1 if side == 2 else -1) if side >= 2 else along * Y
            z0 = -FLOOR_THICKNESS_M
        else:  # on the bin floor
            x = float(rng.uniform(-1, 1)) * max(X / 2 - half[0], 0.0)
            y = float(rng.uniform(-1, 1)) * max(Y / 2 - half[1], 0.0)
            z0 = 0.0
        mesh.apply_translation(np.array([x, y, z0 + half[2]]) - (mesh.bounds[0] + mesh.bounds[1]) / 2.0)
        meshes.append(mesh)
    return generate.model_copy(update={"bin": bin_params, "noise": noise}), camera, T_bin_camera, meshes


def settle_in_bin(
    part: PartModel, T_bin_from_model: np.ndarray, generate: GenerateParams, rng: np.random.Generator
) -> np.ndarray:
    """The physics mode: drop-placed objects settled by simulation; objects that left the bin or
    reach deeper than placement.max_penetration_m into another are removed (logged).

    T_bin_from_model : (k, 4, 4) non-overlapping start poses, bin frame. Returns (m, 4, 4), m <= k.
    """
    placement = generate.placement
    boxes = [(m.bounds[0], m.bounds[1]) for m in bin_meshes(generate.bin)]
    half = (generate.bin.inner_x_m / 2.0, generate.bin.inner_y_m / 2.0)
    settled, inside = settle(
        part.mesh_vertices_m,
        part.mesh_faces,
        T_bin_from_model,
        boxes,
        SettleSettings(max_time_s=placement.settle_max_s),
        half,
    )
    settled = settled[inside]
    sample = part.points_m[rng.choice(len(part.points_m), min(PENETRATION_SAMPLE, len(part.points_m)), replace=False)]
    keep = drop_overlapping(
        lambda poses: penetration_depths_m(part.mesh_vertices_m, part.mesh_faces, sample, poses, part.diameter_m),
        settled,
        placement.max_penetration_m,
    )
    if len(keep) < len(T_bin_from_model):
        log.info(
            "physics: kept %d of %d objects (%d left the bin, %d overlapped)",
            len(keep),
            len(T_bin_from_model),
            int((~inside).sum()),
            int(inside.sum()) - len(keep),
        )
    return settled[keep]
