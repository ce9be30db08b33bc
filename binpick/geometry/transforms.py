"""Rigid transforms as 4x4 homogeneous matrices.

A transform is named by its frames: `T_cam_from_model @ p_model = p_cam`. Translations in metres.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Build a (4, 4) float64 transform from a (3, 3) rotation and a (3,) translation (metres)."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    if R.shape != (3, 3) or t.shape != (3,):
        raise ValueError(f"expected R (3, 3) and t (3,), got {R.shape} and {t.shape}")
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def invert_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform (or a stack (..., 4, 4) of them)."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape[-2:] != (4, 4):
        raise ValueError(f"expected (..., 4, 4), got {T.shape}")
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    inv = np.zeros_like(T)
    inv[..., :3, :3] = np.swapaxes(R, -1, -2)
    inv[..., :3, 3] = -np.einsum("...ji,...j->...i", R, t)
    inv[..., 3, 3] = 1.0
    return inv


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a (4, 4) transform to (n, 3) points; returns (n, 3) in the dtype of `points`."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"expected points (n, 3), got {points.shape}")
    T = np.asarray(T, dtype=np.float64)
    return (points @ T[:3, :3].T + T[:3, 3]).astype(points.dtype, copy=False)


def rigid_fit(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """(4, 4) T with T @ src = dst in the least-squares sense (Kabsch): src, dst (n, 3) paired points."""
    cs, cd = src.mean(0), dst.mean(0)
    U, _, Vt = np.linalg.svd((src - cs).T @ (dst - cd))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, cd - R @ cs
    return T


def axis_angle_to_R(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """(3, 3) rotation by `angle_rad` about `axis` (any length > 0)."""
    axis = np.asarray(axis, dtype=np.float64)
    norm = np.linalg.norm(axis)
    if norm < 1e-12:
        raise ValueError("rotation axis must not be zero")
    return Rotation.from_rotvec(axis / norm * angle_rad).as_matrix()


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A (3, 3) rotation drawn uniformly from SO(3): a unit quaternion from a 4-D normal (the
    draws this project's scenes were generated with; scipy's Rotation.random draws differently)."""
    q = rng.normal(size=4)
    return Rotation.from_quat(
        q[[1, 2, 3, 0]] / np.linalg.norm(q)
    ).as_matrix()  # (w, x, y, z) drawn, scipy takes (x, y, z, w)


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray:
    """Angle of the relative rotation R_a^T R_b in degrees; works on stacks (..., 3, 3)."""
    R_rel = np.swapaxes(np.asarray(R_a), -1, -2) @ np.asarray(R_b)
    cos = (np.trace(R_rel, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
