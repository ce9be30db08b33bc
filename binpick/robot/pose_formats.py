"""Tool poses in the robot controller's own convention, from and to our 4 x 4 matrices in metres.

What each controller wants (the frame is the robot's base, the pose the tool centre point's):
- `ur`    Universal Robots `p[x, y, z, rx, ry, rz]`: metres and a rotation vector (axis times
          angle, radians), as URScript's `movel(p[...])` takes it.
- `abb`   ABB robtarget `[[x, y, z], [q1, q2, q3, q4]]` flattened: millimetres and a unit
          quaternion, scalar first (q1 = w), q1 >= 0.
- `kuka`  KUKA `{X, Y, Z, A, B, C}`: millimetres and degrees, R = Rz(A) Ry(B) Rx(C) (Z-Y'-X'').
- `fanuc` FANUC `(X, Y, Z, W, P, R)`: millimetres and degrees, rotations about the fixed X, Y
          and Z axes in that order, so R_matrix = Rz(R) Ry(P) Rx(W): the KUKA angles reversed.
- `matrix` the 4 x 4 homogeneous matrix in metres, as the rest of binpick writes it.

Euler angles are chosen with the middle angle in [-90, 90] degrees; at +-90 (gimbal lock) the
first and last angles are not unique and any pair giving the same matrix is right.
"""

from __future__ import annotations

import warnings
from typing import Literal, get_args

import numpy as np
from scipy.spatial.transform import Rotation

PoseFormat = Literal["matrix", "ur", "abb", "kuka", "fanuc"]
POSE_FORMATS: tuple[str, ...] = get_args(PoseFormat)

# What a flat robot pose's numbers are, by format (for documents and answers).
FIELDS: dict[str, tuple[str, ...]] = {
    "ur": ("x_m", "y_m", "z_m", "rx_rad", "ry_rad", "rz_rad"),
    "abb": ("x_mm", "y_mm", "z_mm", "q1_w", "q2_x", "q3_y", "q4_z"),
    "kuka": ("X_mm", "Y_mm", "Z_mm", "A_deg", "B_deg", "C_deg"),
    "fanuc": ("X_mm", "Y_mm", "Z_mm", "W_deg", "P_deg", "R_deg"),
}

MM_PER_M = 1000.0


def _check_T(T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4):
        raise ValueError(f"a pose is a 4 x 4 matrix, got shape {T.shape}")
    return T


def to_robot(T_base_from_tcp: np.ndarray, fmt: str) -> list[float] | list[list[float]]:
    """One pose in a controller's convention (see the module's docstring).

    T_base_from_tcp: (4, 4) float, metres, robot base frame, a rigid transform. Returns the flat
    list of numbers FIELDS[fmt] names (the 4 x 4 matrix as nested lists for `matrix`).
    """
    T = _check_T(T_base_from_tcp)
    if fmt == "matrix":
        return T.tolist()
    if fmt not in FIELDS:
        raise ValueError(f"pose format {fmt!r} is not one of {', '.join(POSE_FORMATS)}")
    rotation = Rotation.from_matrix(T[:3, :3])
    t = T[:3, 3]
    if fmt == "ur":
        return [*t.tolist(), *rotation.as_rotvec().tolist()]
    t_mm = (t * MM_PER_M).tolist()
    if fmt == "abb":
        q = rotation.as_quat(scalar_first=True)
        return [*t_mm, *(q if q[0] >= 0 else -q).tolist()]
    # Intrinsic Z-Y'-X'': the angles (A, B, C) with R = Rz(A) Ry(B) Rx(C). At gimbal lock scipy
    # warns and sets the last angle to zero, one of the right answers (the module's docstring).
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        a, b, c = np.degrees(rotation.as_euler("ZYX")).tolist()
    return [*t_mm, a, b, c] if fmt == "kuka" else [*t_mm, c, b, a]


def from_robot(values: list[float] | np.ndarray, fmt: str) -> np.ndarray:
    """The (4, 4) float T_base_from_tcp, metres, from a controller's numbers (to_robot's inverse)."""
    if fmt == "matrix":
        return _check_T(np.asarray(values, dtype=float))
    if fmt not in FIELDS:
        raise ValueError(f"pose format {fmt!r} is not one of {', '.join(POSE_FORMATS)}")
    v = np.asarray(values, dtype=float).ravel()
    if v.shape != (len(FIELDS[fmt]),):
        raise ValueError(f"a {fmt} pose has {len(FIELDS[fmt])} numbers ({', '.join(FIELDS[fmt])}), got {v.size}")
    T = np.eye(4)
    if fmt == "ur":
        T[:3, 3] = v[:3]
        T[:3, :3] = Rotation.from_rotvec(v[3:]).as_matrix()
        return T
    T[:3, 3] = v[:3] / MM_PER_M
    if fmt == "abb":
        T[:3, :3] = Rotation.from_quat(v[3:], scalar_first=True).as_matrix()
    else:
        a, b, c = v[3:] if fmt == "kuka" else v[5:2:-1]
        T[:3, :3] = Rotation.from_euler("ZYX", [a, b, c], degrees=True).as_matrix()
    return T


def rounded(values: list, fmt: str) -> list:
    """A robot pose with as many digits as its units carry (micrometres, microradians, 1e-6 deg)."""
    if fmt == "matrix":
        return np.round(np.asarray(values, dtype=float), 9).tolist()
    digits = [6 if f.endswith(("_mm", "_deg")) else 9 for f in FIELDS[fmt]]
    return [round(float(x), d) + 0.0 for x, d in zip(values, digits, strict=True)]  # + 0.0: no "-0.0"
