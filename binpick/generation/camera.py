"""A virtual 3D camera: pinhole ray casting (Open3D/Embree) and a sensor noise model.

Organized outputs are (H, W, ...) arrays in the camera frame (OpenCV: x right, y down, z forward),
metres, NaN where the sensor returns nothing, like a Zivid frame.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import open3d as o3d
from numba import njit

from binpick.geometry.camera import PinholeCamera
from binpick.params import CameraParams, NoiseParams


def camera_of(camera: CameraParams) -> PinholeCamera:
    """The rendered camera: the configured sensor's pinhole at its downscale."""
    full = PinholeCamera(camera.width_px, camera.height_px, camera.fx_px, camera.fy_px, camera.cx_px, camera.cy_px)
    return full.downscaled(camera.downscale)


@functools.lru_cache(maxsize=4)
def _rays(camera: PinholeCamera) -> np.ndarray:
    """(H, W, 6) float32 rays (origin at the camera centre, direction with z = 1), read-only and
    cached per camera: every scene of a data set casts the same rays."""
    dirs = camera.ray_directions()
    rays = np.ascontiguousarray(np.concatenate([np.zeros_like(dirs), dirs], axis=-1))
    rays.flags.writeable = False
    return rays


# Pixels sampled per object when measuring its visible share (a share needs no more).
VISIBILITY_SAMPLES = 2000


@dataclass(frozen=True)
class Render:
    """xyz_m : (H, W, 3) float32, camera frame, NaN = no return
    normals : (H, W, 3) float32, unit, facing the camera, NaN = no return
    labels : (H, W) int32, index of the labelled mesh hit, -1 = unlabelled or nothing
    """

    xyz_m: np.ndarray
    normals: np.ndarray
    labels: np.ndarray


def raycasting_scene(meshes: list[tuple[np.ndarray, np.ndarray]]) -> o3d.t.geometry.RaycastingScene:
    """An Open3D ray-casting scene of meshes (vertices (v, 3), faces (f, 3)), in their own frame."""
    scene = o3d.t.geometry.RaycastingScene()
    for vertices, faces in meshes:
        scene.add_triangles(
            o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),  # type: ignore[call-overload]  # Open3D's stub lacks the array form
            o3d.core.Tensor(np.ascontiguousarray(faces, dtype=np.uint32)),  # type: ignore[call-overload]
        )
    return scene


def _pixel_box(vertices: np.ndarray, intr: PinholeCamera) -> tuple[int, int, int, int] | None:
    """(v0, v1, u0, u1): the pixel rows and columns the mesh's projection can cover, None when
    it covers none; the whole frame when part of it lies behind the camera."""
    v = np.asarray(vertices, dtype=np.float64)
    if (v[:, 2] <= 1e-6).any():
        return (0, intr.height, 0, intr.width) if (v[:, 2] > 1e-6).any() else None
    u = intr.fx * v[:, 0] / v[:, 2] + intr.cx
    w = intr.fy * v[:, 1] / v[:, 2] + intr.cy
    u0, u1 = int(max(np.floor(u.min()), 0)), int(min(np.ceil(u.max()) + 1, intr.width))
    v0, v1 = int(max(np.floor(w.min()), 0)), int(min(np.ceil(w.max()) + 1, intr.height))
    return (v0, v1, u0, u1) if u0 < u1 and v0 < v1 else None


HIT_GRID_M = 1e-7


def quantise(values: np.ndarray, step: float) -> np.ndarray:
    """Values rounded to a multiple of `step` (same dtype; inf and nan kept)."""
    return (np.round(values.astype(np.float64) / step) * step).astype(values.dtype)


def render(
    meshes_cam: list[tuple[np.ndarray, np.ndarray]],
    mesh_labels: list[int],
    intr: PinholeCamera,
    background: Render | None = None,
) -> Render:
    """Ray-cast meshes (vertices (v, 3) in the camera frame, metres; faces (f, 3)) into an organized frame.

    mesh_labels[i] is the label of the points that hit mesh i (-1 for bin, floor, clutter).
    background: a render of static geometry (the bin, see render_background) at these intrinsics;
    then only the rays that can reach one of the meshes are cast, and the nearer hit wins, which
    is what casting the meshes together with the static geometry gives.
    """
    if len(meshes_cam) != len(mesh_labels):
        raise ValueError("one label per mesh is needed")
    H, W = intr.height, intr.width
    if background is None:
        xyz = np.full((H * W, 3), np.nan, np.float32)
        normals = np.full((H * W, 3), np.nan, np.float32)
        labels = np.full(H * W, -1, np.int32)
        sel = np.arange(H * W)
    else:
        if background.labels.shape != (H, W):
            raise ValueError("the background was rendered at other intrinsics")
        xyz, normals = background.xyz_m.reshape(-1, 3).copy(), background.normals.reshape(-1, 3).copy()
        labels = background.labels.reshape(-1).astype(np.int32)
        mask = np.zeros((H, W), dtype=bool)
        for vertices, _ in meshes_cam:
            box = _pixel_box(vertices, intr)
            if box is not None:
                mask[box[0] : box[1], box[2] : box[3]] = True
        sel = np.flatnonzero(mask)
    if len(sel) and meshes_cam:
        rays = _rays(intr).reshape(-1, 6)
        hit = raycasting_scene(meshes_cam).cast_rays(o3d.core.Tensor(rays if len(sel) == H * W else rays[sel]))  # type: ignore[call-overload]
        label_of = np.asarray(list(mesh_labels) + [-1], dtype=np.int32)
        # Embree picks its kernels by CPU instruction set, so hit distances may differ in their
        # last bits between CPUs; a 0.1 micrometre grid (far below any sensor's noise) makes them
        # the same except where a hit lies within rounding of a grid line.
        t_hit = quantise(hit["t_hit"].numpy(), HIT_GRID_M)
        _composite(
            sel,
            t_hit,
            hit["geometry_ids"].numpy(),
            hit["primitive_normals"].numpy(),
            rays[:, 3:],
            label_of,
            xyz,
            normals,
            labels,
        )
    return Render(xyz_m=xyz.reshape(H, W, 3), normals=normals.reshape(H, W, 3), labels=labels.reshape(H, W))


@njit(cache=True)
def _composite(sel, t, geom, prim_normals, dirs, label_of, xyz, normals, labels):  # pragma: no cover - numba
    """Write each hit of ray sel[k] into the flat frame (xyz (HW, 3), normals, labels) where it is
    nearer than what is there (NaN there = nothing). Normals are turned toward the camera; a
    geometry id past label_of (Open3D's invalid id) cannot occur for a finite hit."""
    for k in range(len(sel)):
        tk = t[k]
        if not np.isfinite(tk):
            continue
        i = sel[k]
        if xyz[i, 2] <= tk:
            continue
        d0, d1, d2 = dirs[i, 0], dirs[i, 1], dirs[i, 2]
        n0, n1, n2 = prim_normals[k, 0], prim_normals[k, 1], prim_normals[k, 2]
        if n0 * d0 + n1 * d1 + n2 * d2 > 0:
            n0, n1, n2 = -n0, -n1, -n2
        xyz[i, 0], xyz[i, 1], xyz[i, 2] = d0 * tk, d1 * tk, d2 * tk
        normals[i, 0], normals[i, 1], normals[i, 2] = n0, n1, n2
        labels[i] = label_of[geom[k]]


@functools.lru_cache(maxsize=4)
def _background(intr: PinholeCamera, meshes: tuple[tuple[bytes, bytes], ...]) -> Render:
    arrays = [
        (np.frombuffer(v, np.float64).reshape(-1, 3), np.frombuffer(f, np.int64).reshape(-1, 3)) for v, f in meshes
    ]
    r = render(arrays, [-1] * len(arrays), intr)
    for a in (r.xyz_m, r.normals, r.labels):
        a.flags.writeable = False
    return r


def render_background(meshes_cam: list[tuple[np.ndarray, np.ndarray]], intr: PinholeCamera) -> Render:
    """The render of static, unlabelled geometry (bin, floor), cached by content: every scene of a
    data set shares it, so each scene casts only the rays that can reach its objects."""
    meshes = tuple(
        (np.ascontiguousarray(v, np.float64).tobytes(), np.ascontiguousarray(f, np.int64).tobytes())
        for v, f in meshes_cam
    )
    return _background(intr, meshes)


def apply_sensor_noise(render_: Render, noise: NoiseParams, rng: np.random.Generator) -> Render:
    """Perturb range along each ray and drop grazing and random returns.

    Range noise std: depth_sigma_m + depth_sigma_per_m2 * range^2. A return whose incidence angle
    (between the ray and the surface normal) exceeds max_incidence_deg is dropped.
    """
    shape = render_.labels.shape
    # One draw per pixel, in a fixed order, whatever the pixel holds: the same seed gives the same frame.
    dropped = rng.random(shape) < noise.dropout_fraction if noise.dropout_fraction > 0 else np.zeros(shape, bool)
    draw = rng.standard_normal(shape, dtype=np.float32)
    xyz, normals, labels = render_.xyz_m.copy(), render_.normals.copy(), render_.labels.astype(np.int32)
    _noise(
        xyz.reshape(-1, 3),
        normals.reshape(-1, 3),
        labels.reshape(-1),
        draw.reshape(-1),
        dropped.reshape(-1),
        np.cos(np.radians(noise.max_incidence_deg)),
        noise.depth_sigma_m,
        noise.depth_sigma_per_m2,
    )
    return Render(xyz_m=xyz, normals=normals, labels=labels)


@njit(cache=True)
def _noise(xyz, normals, labels, draw, dropped, min_cos, sigma0, sigma2):  # pragma: no cover - numba
    """In place on flat frames: returns seen at a grazing angle or dropped become NaN / -1, the
    others move along their ray by draw * (sigma0 + sigma2 * range^2)."""
    for i in range(len(labels)):
        x, y, z = xyz[i, 0], xyz[i, 1], xyz[i, 2]
        r = np.sqrt(x * x + y * y + z * z)
        cos = -(x * normals[i, 0] + y * normals[i, 1] + z * normals[i, 2]) / r
        if not (cos >= min_cos) or dropped[i]:  # NaN (no return) fails the test too
            xyz[i, 0] = xyz[i, 1] = xyz[i, 2] = np.nan
            normals[i, 0] = normals[i, 1] = normals[i, 2] = np.nan
            labels[i] = -1
            continue
        scale = 1.0 + draw[i] * (sigma0 + sigma2 * r * r) / r
        xyz[i, 0], xyz[i, 1], xyz[i, 2] = x * scale, y * scale, z * scale


def visible_fractions(
    meshes_cam: list[tuple[np.ndarray, np.ndarray]], labels: np.ndarray, intr: PinholeCamera
) -> np.ndarray:
    """(k,) share of the pixels each object would cover alone that show it in the scene.

    meshes_cam are the k objects (camera frame); labels (H, W) is the scene's label image before
    noise. Each object is cast alone only over the pixel box of its projection, on a pixel grid
    with about VISIBILITY_SAMPLES nodes in that box.
    """
    out = np.zeros(len(meshes_cam))
    rays_all = _rays(intr)
    for i, (vertices, faces) in enumerate(meshes_cam):
        box = _pixel_box(vertices, intr)
        if box is None:
            continue
        v0, v1, u0, u1 = box
        s = max(1, int(np.sqrt((v1 - v0) * (u1 - u0) / VISIBILITY_SAMPLES)))
        rays = np.ascontiguousarray(rays_all[v0:v1:s, u0:u1:s])
        hit = raycasting_scene([(vertices, faces)]).cast_rays(o3d.core.Tensor(rays))  # type: ignore[call-overload]
        alone = np.isfinite(hit["t_hit"].numpy()).sum()
        if alone:
            out[i] = min(1.0, np.count_nonzero(labels[v0:v1:s, u0:u1:s] == i) / alone)
    return out
