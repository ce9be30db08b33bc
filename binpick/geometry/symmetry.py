"""The symmetry group of a part as a finite set of transforms in its model frame."""

from __future__ import annotations

import numpy as np

from binpick.geometry.transforms import axis_angle_to_R, make_T
from binpick.params import SymmetryParams

# A revolution is sampled by this many rotations; 1 degree apart keeps the symmetric pose error
# below half a degree of discretisation.
REVOLUTION_STEPS = 360


def symmetry_transforms(symmetry: SymmetryParams, revolution_steps: int = REVOLUTION_STEPS) -> np.ndarray:
    """(m, 4, 4) float64 transforms S with model(S @ p) == model(p), identity first.

    Rotations are about `symmetry.axis` through `symmetry.origin_m` (model frame, metres).
    """
    if symmetry.kind == "none":
        return np.eye(4)[None]
    n = symmetry.order if symmetry.kind == "n_fold" else revolution_steps
    origin = np.asarray(symmetry.origin_m, dtype=np.float64)
    rotations = [axis_angle_to_R(np.asarray(symmetry.axis), 2.0 * np.pi * i / n) for i in range(n)]
    if symmetry.flip_axis is not None:
        flip = axis_angle_to_R(np.asarray(symmetry.flip_axis), np.pi)
        rotations += [R @ flip for R in rotations]
    return np.stack([make_T(R, origin - R @ origin) for R in rotations])


# A symmetry set holding a turn smaller than this is a surface of revolution (sampled): no fit
# can fix the turn about its axis.
REVOLUTION_MAX_STEP_DEG = 2.0


def revolution_axis(symmetries: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The axis (unit direction (3,), a point on it (3,); model frame, metres) of a sampled
    revolution among the symmetry transforms (m, 4, 4), or None when the part has none: the
    axis of the smallest turn, when that turn is below REVOLUTION_MAX_STEP_DEG."""
    S = np.asarray(symmetries, dtype=np.float64).reshape(-1, 4, 4)
    if len(S) < 2:
        return None
    cos = np.clip((np.trace(S[:, :3, :3], axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    cos[np.isclose(cos, 1.0, rtol=0.0, atol=1e-12)] = -np.inf  # the identity (and repeats of it)
    k = int(np.argmax(cos))
    if not np.degrees(np.arccos(cos[k])) < REVOLUTION_MAX_STEP_DEG:
        return None
    R, t = S[k, :3, :3], S[k, :3, 3]
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    axis /= np.linalg.norm(axis)
    # The turn fixes the points of its axis: (I - R) o = t, the point nearest the origin.
    origin = np.linalg.lstsq(np.eye(3) - R, t, rcond=None)[0]
    return axis, origin - (origin @ axis) * axis
