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
