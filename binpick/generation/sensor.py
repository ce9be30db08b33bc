"""Sensor models: what a real 3D camera returns for a rendered scene.

The clean render (camera.py) is what a perfect depth camera would see. A structured-light or
stereo sensor differs from it in ways that follow the geometry, each its own kernel here:
- `projector_shadow`: the projector (or second camera) sits baseline_m beside the camera along
  its +x (turned by projector_angle_deg about the optical axis: the mount); surface the camera
  sees but the projector's light cannot reach returns nothing.
- `incidence_cos`, `specular_cos`: steep surfaces return less and noisier data; a shiny surface
  whose normal bisects the camera and projector directions blinds the camera with a highlight.
- `mix_edge_pixels`: a pixel on a depth edge mixes the two depths (a point in the air between them).
- `concavity`: in a concave corner the projector's light reflects off one face onto the other,
  so the range there reads long (multipath); the bias follows how much facing surface is near.
- `quantise_disparity`: a disparity measured in sub-pixel steps gives depths on a grid that
  coarsens with the squared range.
`apply_sensor_model` runs them in that order on an organized frame. Camera frame (OpenCV),
metres; organized arrays are (H, W, ...), NaN where there is no return.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
from numba import njit

from binpick.generation.camera import Render, raycasting_scene
from binpick.geometry.camera import PinholeCamera
from binpick.params import MaterialParams, SensorModelParams

# A projector ray that stops this much short of the point it was cast to is blocked: above the
# hit-distance grid and the float32 error of a ray of a metre.
SHADOW_TOLERANCE_M = 1e-4
# Neighbours sampled around a pixel for its concavity: this many directions at three radii.
CONCAVITY_DIRECTIONS = 8
# ... never farther than this many pixels (a near surface at a fine resolution spans hundreds).
CONCAVITY_MAX_PX = 12
# The concavity these samples give at the bottom of a right-angled concave corner (0.25-0.32 on
# rendered corners at 1-2 mm pixels): the point where multipath reaches its full multipath_m.
CORNER_CONCAVITY = 0.3


def intrinsics_of(model: SensorModelParams, reference_width_px: int, reference_downscale: int) -> PinholeCamera:
    """The sensor's pinhole camera rendered at about the pixel count of the reference camera at
    its downscale (never finer than the sensor itself): a Kinect-class frame renders whole, a
    5 MP Zivid frame at about the training resolution."""
    s = max(1, int(round(reference_downscale * model.width_px / reference_width_px)))
    return PinholeCamera(
        width=model.width_px // s,
        height=model.height_px // s,
        fx=model.fx_px / s,
        fy=model.fy_px / s,
        cx=(model.width_px / 2.0) / s - 0.5,
        cy=(model.height_px / 2.0) / s - 0.5,
    )


def scaled_model(model: SensorModelParams, factor: float) -> SensorModelParams:
    """The model with the size of its noise, mixing and multipath effects times `factor`."""
    return model.model_copy(
        update={
            "depth_sigma_m": model.depth_sigma_m * factor,
            "depth_sigma_per_m2": model.depth_sigma_per_m2 * factor,
            "mixed_pixel_share": min(1.0, model.mixed_pixel_share * factor),
            "multipath_m": model.multipath_m * factor,
        }
    )


def projector_shadow(
    xyz_m: np.ndarray, meshes_cam: list[tuple[np.ndarray, np.ndarray]], projector_m: np.ndarray
) -> np.ndarray:
    """(H, W) bool: points the projector's light cannot reach (its ray to them hits a mesh first).

    xyz_m : (H, W, 3) float32, camera frame, metres, NaN = no return
    meshes_cam : the scene's meshes (vertices (v, 3), faces (f, 3)), camera frame
    projector_m : (3,) the projector's centre, camera frame
    """
    if xyz_m.ndim != 3 or xyz_m.shape[2] != 3:
        raise ValueError(f"xyz_m must be (H, W, 3), got {xyz_m.shape}")
    flat = xyz_m.reshape(-1, 3).astype(np.float64)
    valid = np.flatnonzero(np.isfinite(flat).all(axis=1))
    shadow = np.zeros(len(flat), bool)
    if len(valid) == 0 or not meshes_cam:
        return shadow.reshape(xyz_m.shape[:2])
    to_point = flat[valid] - projector_m
    distance = np.linalg.norm(to_point, axis=1)
    rays = np.concatenate([np.broadcast_to(projector_m, to_point.shape), to_point / distance[:, None]], axis=1).astype(
        np.float32
    )
    t_hit = raycasting_scene(meshes_cam).cast_rays(o3d.core.Tensor(np.ascontiguousarray(rays)))["t_hit"].numpy()  # type: ignore[call-overload]
    shadow[valid] = t_hit < distance - SHADOW_TOLERANCE_M
    return shadow.reshape(xyz_m.shape[:2])


def incidence_cos(xyz_m: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(...,) cosine of the angle between the ray to each point and its surface normal (NaN where no return)."""
    ranges = np.linalg.norm(xyz_m, axis=-1)
    return -np.einsum("...i,...i->...", xyz_m, normals) / ranges


def specular_cos(xyz_m: np.ndarray, normals: np.ndarray, projector_m: np.ndarray) -> np.ndarray:
    """(...,) cosine of the angle between each normal and the half vector of the directions from
    the point to the camera and to the projector: 1 where a mirror would send the projector's
    light straight into the camera."""
    to_cam = -xyz_m / np.linalg.norm(xyz_m, axis=-1, keepdims=True)
    to_proj = projector_m - xyz_m
    to_proj = to_proj / np.linalg.norm(to_proj, axis=-1, keepdims=True)
    half = to_cam + to_proj
    half = half / np.linalg.norm(half, axis=-1, keepdims=True)
    return np.einsum("...i,...i->...", half, normals)


def mix_edge_pixels(
    xyz_m: np.ndarray, labels: np.ndarray, jump_m: float, share: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Edge pixels (a 4-neighbour's depth differs by more than jump_m) moved along their ray to a
    depth between theirs and that neighbour's (the one farthest in depth), with probability
    `share`; a pixel moved more than halfway takes the neighbour's label. Returns copies of
    xyz_m (H, W, 3) and labels (H, W)."""
    H, W = labels.shape
    mix = rng.random((H, W)) < share
    weight = rng.random((H, W)).astype(np.float32)
    xyz, out_labels = xyz_m.copy(), labels.copy()
    _mix(xyz, out_labels, xyz_m[..., 2].copy(), labels, mix, weight, jump_m)
    return xyz, out_labels


@njit(cache=True)
def _mix(xyz, out_labels, z, labels, mix, weight, jump):  # pragma: no cover - numba
    H, W = z.shape
    for v in range(H):
        for u in range(W):
            if not mix[v, u] or not np.isfinite(z[v, u]):
                continue
            best, bv, bu = 0.0, -1, -1
            for dv, du in ((-1, 0), (1, 0), (0, -1), (0, 1)):
                nv, nu = v + dv, u + du
                if 0 <= nv < H and 0 <= nu < W and np.isfinite(z[nv, nu]):
                    d = abs(z[nv, nu] - z[v, u])
                    if d > jump and d > best:
                        best, bv, bu = d, nv, nu
            if bv < 0:
                continue
            w = weight[v, u]
            scale = (z[v, u] + w * (z[bv, bu] - z[v, u])) / z[v, u]
            xyz[v, u, 0] *= scale
            xyz[v, u, 1] *= scale
            xyz[v, u, 2] *= scale
            if w > 0.5:
                out_labels[v, u] = labels[bv, bu]


def concavity(xyz_m: np.ndarray, normals: np.ndarray, radius_m: float, fx_px: float) -> np.ndarray:
    """(H, W) float32 in [0, 1]: how much of the surface within radius_m of each point rises in
    front of its tangent plane (the mean, over neighbours sampled in the image, of the sine of
    their elevation above it, negatives counted 0). 0 on a plane and at a convex edge; about
    CORNER_CONCAVITY at the bottom of a right-angled concave corner, falling to 0 radius_m away.

    xyz_m, normals : (H, W, 3), camera frame, NaN = no return; fx_px the frame's focal length.
    """
    out = np.zeros(xyz_m.shape[:2], np.float32)
    _concavity(
        xyz_m.astype(np.float64),
        normals.astype(np.float64),
        radius_m * fx_px,
        CONCAVITY_DIRECTIONS,
        CONCAVITY_MAX_PX,
        out,
    )
    return out


@njit(cache=True)
def _concavity(xyz, normals, radius_px_m, n_dir, max_px, out):  # pragma: no cover - numba
    H, W = out.shape
    for v in range(H):
        for u in range(W):
            z = xyz[v, u, 2]
            if not np.isfinite(z):
                continue
            r = min(max_px, max(1, int(round(radius_px_m / z))))
            total, count = 0.0, 0
            for k in range(n_dir):
                a = 2.0 * np.pi * k / n_dir
                for step in (1, 2, 3):
                    rr = r * step / 3.0
                    nv, nu = v + int(round(rr * np.sin(a))), u + int(round(rr * np.cos(a)))
                    if (
                        nv < 0
                        or nv >= H
                        or nu < 0
                        or nu >= W
                        or (nv == v and nu == u)
                        or not np.isfinite(xyz[nv, nu, 2])
                    ):
                        continue
                    d0, d1, d2 = (
                        xyz[nv, nu, 0] - xyz[v, u, 0],
                        xyz[nv, nu, 1] - xyz[v, u, 1],
                        xyz[nv, nu, 2] - xyz[v, u, 2],
                    )
                    n = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
                    if n == 0.0:
                        continue
                    s = (d0 * normals[v, u, 0] + d1 * normals[v, u, 1] + d2 * normals[v, u, 2]) / n
                    total += max(0.0, s)
                    count += 1
            if count:
                out[v, u] = total / count


def quantise_disparity(z_m: np.ndarray, fx_px: float, baseline_m: float, step_px: float) -> np.ndarray:
    """Depths (any shape, metres) as a sensor measuring disparity fx * baseline / z in steps of
    step_px reports them: on the grid fx * baseline / (k * step_px). NaN stays NaN."""
    fb = fx_px * baseline_m
    steps = np.maximum(np.round(fb / z_m / step_px), 1.0)
    return (fb / (steps * step_px)).astype(z_m.dtype)


def apply_sensor_model(
    clean: Render,
    meshes_cam: list[tuple[np.ndarray, np.ndarray]],
    intr: PinholeCamera,
    model: SensorModelParams,
    part_material: MaterialParams,
    rng: np.random.Generator,
) -> Render:
    """The frame the sensor returns for a clean render (labels >= 0: the part, of part_material;
    the rest matte). meshes_cam: every mesh of the scene (for the projector's shadows).

    Order: projector shadow; dropout by incidence (ramping from dropout_start_deg to the
    material's or sensor's max_incidence_deg), random and specular dropout; multipath bias;
    mixed edge pixels; range noise (sensor std at the range, times the material's scale and the
    incidence term); quantisation. Every draw covers the whole frame, in a fixed order, so the
    same seed gives the same frame.
    """
    H, W = clean.labels.shape
    xyz, normals, labels = clean.xyz_m.copy(), clean.normals.copy(), clean.labels.astype(np.int32)
    turn = np.radians(model.projector_angle_deg)
    projector = model.baseline_m * np.array([np.cos(turn), np.sin(turn), 0.0])
    is_part = labels >= 0
    gone = np.zeros((H, W), bool)
    if model.shadows and model.baseline_m > 0:
        gone |= projector_shadow(xyz, meshes_cam, projector)

    with np.errstate(invalid="ignore"):
        angle = np.degrees(np.arccos(np.clip(incidence_cos(xyz, normals), -1.0, 1.0)))
        max_incidence = np.where(
            is_part, min(model.max_incidence_deg, part_material.max_incidence_deg), model.max_incidence_deg
        )
        start = np.minimum(model.dropout_start_deg, max_incidence)
        ramp = np.clip((angle - start) / np.maximum(max_incidence - start, 1e-6), 0.0, 1.0)
        ramp = np.where(angle > max_incidence, 1.0, ramp)
        p_drop = 1.0 - (1.0 - ramp) * (1.0 - model.dropout_fraction) * (
            1.0 - np.where(is_part, part_material.dropout_fraction, 0.0)
        )
        draw_drop = rng.random((H, W))
        gone |= ~(draw_drop >= p_drop)  # NaN (no return) counts as gone
        if part_material.specular_lobe_deg > 0:
            highlight = specular_cos(xyz, normals, projector) >= np.cos(np.radians(part_material.specular_lobe_deg))
            gone |= is_part & highlight
    xyz[gone] = np.nan
    normals[gone] = np.nan
    labels[gone] = -1

    if model.multipath_m > 0:
        # Longer range (the light took a detour): the point moves away along its ray.
        bias = (
            np.minimum(1.0, concavity(xyz, normals, model.multipath_radius_m, intr.fx) / CORNER_CONCAVITY)
            * model.multipath_m
        )
        ranges = np.linalg.norm(xyz, axis=-1)
        with np.errstate(invalid="ignore"):
            xyz *= ((ranges + bias) / ranges)[..., None].astype(np.float32)
    if model.mixed_pixel_share > 0:
        xyz, labels = mix_edge_pixels(xyz, labels, model.edge_jump_m, model.mixed_pixel_share, rng)

    ranges = np.linalg.norm(xyz, axis=-1)
    with np.errstate(invalid="ignore"):
        a = np.radians(np.clip(angle, 0.0, 89.0))
        incidence_term = 1.0 + model.incidence_noise_gain * a**2 / (np.pi / 2 - a) ** 2
        sigma = (
            (model.depth_sigma_m + model.depth_sigma_per_m2 * ranges**2)
            * np.where(is_part, part_material.noise_scale, 1.0)
            * incidence_term
        )
        draw = rng.standard_normal((H, W), dtype=np.float32)
        xyz *= (1.0 + draw * sigma / ranges)[..., None].astype(np.float32)
        if model.disparity_step_px > 0:
            z = xyz[..., 2]
            xyz *= (quantise_disparity(z, model.fx_px, model.baseline_m, model.disparity_step_px) / z)[..., None]
        if model.depth_step_m > 0:
            z = xyz[..., 2]
            xyz *= ((np.round(z / model.depth_step_m) * model.depth_step_m) / z)[..., None]
    labels[~np.isfinite(xyz[..., 2])] = -1
    return Render(xyz_m=xyz.astype(np.float32), normals=normals, labels=labels)
