"""How deep placed objects reach into each other: the check behind the no-interpenetration
promise of every placement mode."""

from __future__ import annotations

import numpy as np
import trimesh

from binpick.geometry.transforms import invert_T, transform_points


def penetration_depths_m(
    vertices_m: np.ndarray, faces: np.ndarray, sample_m: np.ndarray, T_from_model: np.ndarray, reach_m: float
) -> np.ndarray:
    """Per object, the deepest of its sample points inside any other object (0 when none).

    vertices_m, faces : the part's closed mesh, model frame, metres
    sample_m          : (n, 3) surface points of the part, model frame, metres
    T_from_model      : (k, 4, 4) object poses in one common frame
    reach_m           : objects whose origins are farther apart than this cannot touch (the diameter)
    Returns (k,) float64, metres. Exact inside tests and distances against the mesh.
    """
    mesh = trimesh.Trimesh(vertices_m, faces, process=False)
    pts = np.asarray(sample_m, np.float64)
    depth = np.zeros(len(T_from_model))
    for i, Ti in enumerate(T_from_model):
        world = transform_points(Ti, pts)
        for j, Tj in enumerate(T_from_model):
            if i == j or np.linalg.norm(Ti[:3, 3] - Tj[:3, 3]) > reach_m:
                continue
            local = transform_points(invert_T(Tj), world)
            inside = mesh.contains(local)
            if inside.any():
                _, d, _ = trimesh.proximity.closest_point(mesh, local[inside])
                depth[i] = max(depth[i], float(d.max()))
    return depth


def drop_overlapping(depths_fn, poses: np.ndarray, max_depth_m: float) -> np.ndarray:
    """Indices of the objects to keep: while any object reaches deeper than max_depth_m into
    another, the deepest one is removed. depths_fn(poses) -> (k,) depths."""
    keep = np.arange(len(poses))
    while len(keep):
        depth = depths_fn(poses[keep])
        worst = int(np.argmax(depth))
        if depth[worst] <= max_depth_m:
            break
        keep = np.delete(keep, worst)
    return keep
