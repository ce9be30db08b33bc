"""A virtual 3D camera: pinhole ray casting (Open3D/Embree) and a sensor noise model.

Organized outputs are (H, W, ...) arrays in the camera frame (OpenCV: x right, y down, z forward),
metres, NaN where the sensor returns nothing, like a Zivid frame.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import open3d as o3d

from binpick.params import CameraParams, NoiseParams


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels; pixel (u, v) is column u, row v, centre of the top-left pixel at (0, 0)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @classmethod
    def from_params(cls, camera: CameraParams) -> Intrinsics:
        s = camera.downscale
        return cls(
            width=camera.width_px // s,
            height=camera.height_px // s,
            fx=camera.fx_px / s,
            fy=camera.fy_px / s,
            cx=(camera.cx_px + 0.5) / s - 0.5,
            cy=(camera.cy_px + 0.5) / s - 0.5,
        )

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def ray_directions(self) -> np.ndarray:
        """(H, W, 3) float32 ray directions with z = 1, so that a hit distance is the depth.
        Cached per camera (read-only): every scene of a data set casts the same rays."""
        return _rays(self)[..., 3:]


@functools.lru_cache(maxsize=4)
def _rays(intr: Intrinsics) -> np.ndarray:
    """(H, W, 6) float32 rays (origin at the camera centre, direction with z = 1), read-only."""
    u, v = np.meshgrid(np.arange(intr.width, dtype=np.float32), np.arange(intr.height, dtype=np.float32))
    dirs = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u)], axis=-1)
    rays = np.ascontiguousarray(np.concatenate([np.zeros_like(dirs), dirs], axis=-1))
    rays.flags.writeable = False
    return rays


VISIBILITY_STRIDE = 2


@dataclass(frozen=True)
class Render:
    """xyz_m : (H, W, 3) float32, camera frame, NaN = no return
    normals : (H, W, 3) float32, unit, facing the camera, NaN = no return
    labels : (H, W) int32, index of the labelled mesh hit, -1 = unlabelled or nothing
    """

    xyz_m: np.ndarray
    normals: np.ndarray
    labels: np.ndarray


def _scene(meshes: list[tuple[np.ndarray, np.ndarray]]) -> o3d.t.geometry.RaycastingScene:
    scene = o3d.t.geometry.RaycastingScene()
    for vertices, faces in meshes:
        scene.add_triangles(
            o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
            o3d.core.Tensor(np.ascontiguousarray(faces, dtype=np.uint32)),
        )
    return scene


def render(meshes_cam: list[tuple[np.ndarray, np.ndarray]], mesh_labels: list[int], intr: Intrinsics) -> Render:
    """Ray-cast meshes (vertices (v, 3) in the camera frame, metres; faces (f, 3)) into an organized frame.

    mesh_labels[i] is the label of the points that hit mesh i (-1 for bin, floor, clutter).
    """
    if len(meshes_cam) != len(mesh_labels):
        raise ValueError("one label per mesh is needed")
    rays = _rays(intr)
    dirs = rays[..., 3:]
    hit = _scene(meshes_cam).cast_rays(o3d.core.Tensor(rays))
    t = hit["t_hit"].numpy()
    ok = np.isfinite(t)
    # Misses carry Open3D's invalid id, clipped here onto the trailing -1 of the lookup.
    geom = np.minimum(hit["geometry_ids"].numpy(), len(mesh_labels)).astype(np.int64)
    label_of = np.asarray(list(mesh_labels) + [-1], dtype=np.int32)
    labels = label_of[geom]
    labels[~ok] = -1
    xyz = dirs * t[..., None]
    xyz[~ok] = np.nan
    normals = hit["primitive_normals"].numpy()
    # Face normals of closed meshes point outward; a visible face looks toward the camera anyway,
    # but open meshes may be hit from behind.
    normals[np.einsum("hwi,hwi->hw", normals, dirs) > 0] *= -1.0
    normals[~ok] = np.nan
    return Render(xyz_m=xyz, normals=normals, labels=labels)


def apply_sensor_noise(render_: Render, noise: NoiseParams, rng: np.random.Generator) -> Render:
    """Perturb range along each ray and drop grazing and random returns.

    Range noise std: depth_sigma_m + depth_sigma_per_m2 * range^2. A return whose incidence angle
    (between the ray and the surface normal) exceeds max_incidence_deg is dropped.
    """
    # Whole frames in float32 (the noise is far above its precision); NaN marks no return and
    # compares False, so pixels without one stay empty.
    xyz, normals = render_.xyz_m, render_.normals
    rng_m = np.sqrt(np.einsum("hwi,hwi->hw", xyz, xyz))
    ray = xyz / rng_m[..., None]
    with np.errstate(invalid="ignore"):
        keep = -np.einsum("hwi,hwi->hw", ray, normals) >= np.float32(np.cos(np.radians(noise.max_incidence_deg)))
    if noise.dropout_fraction > 0:
        keep &= rng.random(keep.shape) >= noise.dropout_fraction
    sigma = np.float32(noise.depth_sigma_m) + np.float32(noise.depth_sigma_per_m2) * rng_m * rng_m
    xyz_out = xyz + ray * (rng.standard_normal(rng_m.shape, dtype=np.float32) * sigma)[..., None]
    xyz_out[~keep] = np.nan
    normals_out = normals.copy()
    normals_out[~keep] = np.nan
    labels = np.where(keep, render_.labels, -1).astype(np.int32)
    return Render(xyz_m=xyz_out, normals=normals_out, labels=labels)


def visible_fractions(
    meshes_cam: list[tuple[np.ndarray, np.ndarray]], labels: np.ndarray, intr: Intrinsics
) -> np.ndarray:
    """(k,) share of the pixels each object would cover alone that show it in the scene.

    meshes_cam are the k objects (camera frame); labels (H, W) is the scene's label image before
    noise. Each object is cast alone only over the pixel box of its projection, on every
    VISIBILITY_STRIDE-th pixel row and column (a share of thousands of pixels needs no more).
    """
    out = np.zeros(len(meshes_cam))
    s = VISIBILITY_STRIDE
    rays_all = _rays(intr)
    for i, (vertices, faces) in enumerate(meshes_cam):
        v = np.asarray(vertices, dtype=np.float64)
        front = v[:, 2] > 1e-6
        if not front.any():
            continue
        u = intr.fx * v[front, 0] / v[front, 2] + intr.cx
        w = intr.fy * v[front, 1] / v[front, 2] + intr.cy
        u0, u1 = int(max(np.floor(u.min()), 0)), int(min(np.ceil(u.max()) + 1, intr.width))
        v0, v1 = int(max(np.floor(w.min()), 0)), int(min(np.ceil(w.max()) + 1, intr.height))
        if u0 >= u1 or v0 >= v1:
            continue
        v0, u0 = v0 + (-v0) % s, u0 + (-u0) % s  # on the strided grid of the whole frame
        rays = np.ascontiguousarray(rays_all[v0:v1:s, u0:u1:s])
        if rays.size == 0:
            continue
        alone = np.isfinite(_scene([(vertices, faces)]).cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()).sum()
        if alone:
            out[i] = min(1.0, np.count_nonzero(labels[::s, ::s] == i) / alone)
    return out
