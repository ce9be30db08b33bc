"""Hand-eye calibration: where the camera is in the robot's frame, from robot flange poses and
the calibration board's pose in the capture taken at each (OpenCV's calibrateHandEye).

Two set-ups:
- eye-to-hand (the camera fixed in the cell, the board on the flange): the answer is
  T_base_from_cam, the setting every pick needs to be given in the robot's base frame;
- eye-in-hand (the camera on the flange, the board fixed in the cell): the answer is
  T_flange_from_cam.

Poses are 4 x 4, metres. A set that cannot determine the answer (fewer than 3 poses, or flange
rotations about too few distinct axes) is refused with a message saying what to add.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from binpick.errors import BinpickError
from binpick.geometry.transforms import invert_T, rigid_fit

Setup = Literal["eye_to_hand", "eye_in_hand"]
MIN_POSES = 3
# The flange must turn by at least this much between some poses, about axes at least this far
# apart: rotations about one axis leave the translation along it undetermined.
MIN_ROTATION_DEG = 10.0
MIN_AXIS_SPREAD_DEG = 15.0


@dataclass(frozen=True)
class HandEyeResult:
    """T: T_base_from_cam (eye_to_hand) or T_flange_from_cam (eye_in_hand); the board in the
    other frame (T_flange_from_target or T_base_from_target); residuals: how far each pose pair
    puts the board from where the solution says it is, median and largest, mm and degrees."""

    setup: Setup
    T: np.ndarray
    T_board: np.ndarray
    residual_mm_median: float
    residual_mm_max: float
    residual_deg_median: float
    residual_deg_max: float
    n_poses: int


def _rotation_angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def _axis(R: np.ndarray) -> np.ndarray:
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    n = np.linalg.norm(w)
    return w / n if n > 1e-12 else np.zeros(3)


def check_well_posed(T_base_from_flange: np.ndarray) -> None:
    """Refuse pose sets that cannot determine a hand-eye transform (BinpickError, one line)."""
    n = len(T_base_from_flange)
    if n < MIN_POSES:
        raise BinpickError(
            f"hand-eye calibration needs at least {MIN_POSES} robot poses, got {n}: add poses with the flange turned "
            "about different axes"
        )
    axes = []
    for i in range(n):
        for j in range(i + 1, n):
            R = (invert_T(T_base_from_flange[i]) @ T_base_from_flange[j])[:3, :3]
            if _rotation_angle_deg(R) >= MIN_ROTATION_DEG:
                axes.append(_axis(R))
    if not axes:
        raise BinpickError(
            f"ill-posed hand-eye set: the flange turns by less than {MIN_ROTATION_DEG:g} degrees between any two of "
            "the "
            f"{n} poses: turn the flange between captures"
        )
    spread = max(float(np.degrees(np.arccos(np.clip(abs(a @ b), 0.0, 1.0)))) for a in axes for b in axes)
    if spread < MIN_AXIS_SPREAD_DEG:
        raise BinpickError(
            f"ill-posed hand-eye set: the flange turns about one axis only (axes within {spread:.1f} degrees): "
            "add poses turned about a second axis"
        )


def _mean_T(Ts: np.ndarray) -> np.ndarray:
    """Mean of rigid transforms: rotations by the chordal mean (SVD), translations averaged."""
    U, _, Vt = np.linalg.svd(Ts[:, :3, :3].sum(axis=0))
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, Ts[:, :3, 3].mean(axis=0)
    return T


def solve_hand_eye(T_base_from_flange: np.ndarray, T_cam_from_target: np.ndarray, setup: Setup) -> HandEyeResult:
    """T_base_from_flange (n, 4, 4) from the robot; T_cam_from_target (n, 4, 4) from the captures."""
    import cv2

    T_bf = np.asarray(T_base_from_flange, dtype=np.float64).reshape(-1, 4, 4)
    T_ct = np.asarray(T_cam_from_target, dtype=np.float64).reshape(-1, 4, 4)
    if len(T_bf) != len(T_ct):
        raise BinpickError(f"{len(T_bf)} robot poses but {len(T_ct)} board poses: one of each per capture")
    check_well_posed(T_bf)
    # OpenCV solves the eye-in-hand form AX = XB with gripper-to-base motions; for eye-to-hand
    # the base-to-gripper poses go in and the camera-to-base transform comes out.
    moving = T_bf if setup == "eye_in_hand" else np.array([invert_T(T) for T in T_bf])
    R, t = cv2.calibrateHandEye(
        [m[:3, :3] for m in moving],
        [m[:3, 3] for m in moving],
        [c[:3, :3] for c in T_ct],
        [c[:3, 3] for c in T_ct],
        method=cv2.CALIB_HAND_EYE_PARK,
    )
    X = np.eye(4)
    X[:3, :3], X[:3, 3] = R, np.asarray(t).reshape(3)
    # The board's pose in the other frame, from every pair: their spread is the residual.
    if setup == "eye_to_hand":
        boards = np.array([invert_T(f) @ X @ c for f, c in zip(T_bf, T_ct, strict=True)])  # T_flange_from_target
    else:
        boards = np.array([f @ X @ c for f, c in zip(T_bf, T_ct, strict=True)])  # T_base_from_target
    board = _mean_T(boards)
    dist_mm = 1000.0 * np.linalg.norm(boards[:, :3, 3] - board[:3, 3], axis=1)
    ang = np.array([_rotation_angle_deg(board[:3, :3].T @ b[:3, :3]) for b in boards])
    return HandEyeResult(
        setup,
        X,
        board,
        float(np.median(dist_mm)),
        float(dist_mm.max()),
        float(np.median(ang)),
        float(ang.max()),
        len(T_bf),
    )


def board_points(pattern: tuple[int, int], square_m: float) -> np.ndarray:
    """(cols * rows, 3) inner corners of a checkerboard in its own frame (z = 0), OpenCV order."""
    cols, rows = pattern
    grid = np.stack(np.meshgrid(np.arange(cols), np.arange(rows)), axis=-1).reshape(-1, 2)
    return np.column_stack([grid * square_m, np.zeros(len(grid))]).astype(np.float64)


def board_pose(
    image: np.ndarray, pattern: tuple[int, int], square_m: float, K: np.ndarray, xyz_m: np.ndarray | None = None
) -> np.ndarray | None:
    """T_cam_from_target of a checkerboard in a colour (H, W, 3) or grey (H, W) image, None
    when the board is not found. With the organized cloud xyz_m (H, W, 3), the corners' measured
    3-D points give the pose (a rigid fit, no intrinsics error); else solvePnP with K."""
    import cv2

    grey = image if image.ndim == 2 else cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY)
    found, corners = cv2.findChessboardCorners(
        grey, pattern, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    )
    if not found:
        return None
    corners = cv2.cornerSubPix(
        grey, corners, (5, 5), (-1, -1), (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 40, 1e-3)
    ).reshape(-1, 2)
    model = board_points(pattern, square_m)
    if xyz_m is not None:
        u = np.clip(np.round(corners[:, 0]).astype(int), 0, xyz_m.shape[1] - 1)
        v = np.clip(np.round(corners[:, 1]).astype(int), 0, xyz_m.shape[0] - 1)
        measured = xyz_m[v, u]
        ok = np.all(np.isfinite(measured), axis=1)
        if ok.sum() >= 6:
            return rigid_fit(model[ok], measured[ok])
    ok_pnp, rvec, tvec = cv2.solvePnP(model, corners, K, None, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok_pnp:
        return None
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.reshape(3)
    return T
