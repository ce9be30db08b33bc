"""Point-to-plane ICP onto a target with known normals, repeatable to the last bit.

Open3D's `registration_icp` sums its normal equations in parallel and returns different last bits
on identical input (12-16 distinct results in 20 calls, even with one OpenMP thread); the
registration's thresholds turned those bits into different pose sets from run to run. Here every
sum runs in one fixed order (one loop over the points, compiled by numba), so the same input gives
the same pose.
The iteration follows Open3D's: nearest target point within max_distance_m for each source point,
one linearised point-to-plane step, stop when both the share of source points paired and their
root mean square distance change by less than the tolerance since the last step, or (a cycle of
two states, which Open3D runs to its iteration limit) since the step before it.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numba import njit
from pykdtree.kdtree import KDTree

from binpick.geometry.transforms import axis_angle_to_R, make_T

# Fewer pairs than this leave the six unknowns of a step undetermined.
MIN_PAIRS = 6


def point_to_plane_icp(
    source_points: np.ndarray,
    target_points: np.ndarray,
    target_normals: np.ndarray,
    T_target_from_source: np.ndarray,
    max_distance_m: float,
    max_iterations: int,
    tolerance: float,
    free_turn: tuple[np.ndarray, np.ndarray] | None = None,
    ray_pairing_rad: float | None = None,
) -> np.ndarray:
    """(4, 4) T_target_from_source refined from the given start so that the source points lie on
    the planes of their nearest target points (or of the target points on their rays).

    source_points : (n, 3) source frame, metres.
    target_points, target_normals : (m, 3) target frame, metres and unit normals.
    max_distance_m : pairs farther apart than this (at the current pose) are not used.
    tolerance : stop when the paired share and the pairs' rms distance (metres) change by less.
    free_turn : (axis direction (3,), a point on it (3,)), target frame: the target is a surface
                of revolution about that axis. No pairing can fix the turn about it, and a step
                that includes it spins the source by noise (3-20 degrees a step on a gear shaft,
                pairs changing every time, so that ICP never stopped before max_iterations); the
                steps leave that turn out.
    ray_pairing_rad : pair each source point with the target point nearest its ray from the
                source frame's origin (a depth sensor's centre), within this angle, instead of
                the nearest target point. A depth sensor's noise lies along its rays; on a curved
                surface the nearest point to a measurement displaced along a grazing ray lies
                beside the true one, outward of a convex surface, so that the nearest-point fit
                comes toward the sensor by about sigma^2 / (2 r) (sigma the depth noise, r the
                radius of curvature). The point on the ray has no such bias.
    """
    source = np.ascontiguousarray(source_points, dtype=np.float64)
    target = np.ascontiguousarray(target_points, dtype=np.float64)
    normals = np.asarray(target_normals, dtype=np.float64)
    T = np.array(T_target_from_source, dtype=np.float64)
    if len(source) == 0 or len(target) == 0:
        return T
    tree = KDTree(target)
    basis = (
        None
        if free_turn is None
        else _without_turn(tuple(np.ravel(free_turn[0]).tolist()), tuple(np.ravel(free_turn[1]).tolist()))
    )

    def paired(moved: np.ndarray) -> tuple[np.ndarray, np.ndarray, int, float, float]:
        """The step's normal equations at these source positions, the paired share and the pairs'
        rms distance."""
        if ray_pairing_rad is None:
            d, j = tree.query(moved, distance_upper_bound=max_distance_m)
        else:
            d, j = _ray_pairs(moved, target, T[:3, 3], ray_pairing_rad, max_distance_m)
        JtJ, Jtr, n_pairs, sum_d2 = _normal_equations(moved, target, normals, d, j.astype(np.int64))
        return JtJ, Jtr, n_pairs, n_pairs / len(source), float(np.sqrt(sum_d2 / n_pairs)) if n_pairs else 0.0

    moved = source @ T[:3, :3].T + T[:3, 3]
    JtJ, Jtr, n_pairs, fitness, rmse = paired(moved)
    history: tuple[float, ...] = ()  # (fitness, rmse) one and two steps back
    for _ in range(max_iterations):
        if n_pairs < MIN_PAIRS:
            break
        try:
            x = (
                np.linalg.solve(JtJ, Jtr)
                if basis is None
                else basis @ np.linalg.solve(basis.T @ JtJ @ basis, basis.T @ Jtr)
            )
        except np.linalg.LinAlgError:  # the pairs do not fix the pose (one plane): keep it
            break
        angle = float(np.linalg.norm(x[:3]))
        R = axis_angle_to_R(x[:3] / angle, angle) if angle > 0.0 else np.eye(3)
        T = make_T(R, x[3:]) @ T
        moved = moved @ R.T + x[3:]
        history = (fitness, rmse, *history[:2])
        JtJ, Jtr, n_pairs, fitness, rmse = paired(moved)
        # Converged: nothing changed since the last step; or caught in a two-step cycle (the
        # pairs of one state pull to the other and back): nothing changed since the step before.
        if any(
            abs(fitness - f) < tolerance and abs(rmse - r) < tolerance
            for f, r in zip(history[::2], history[1::2], strict=True)
        ):
            break
    return T


def _ray_pairs(
    moved: np.ndarray, target: np.ndarray, origin: np.ndarray, max_angle_rad: float, max_distance_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """For each source point (n, 3), the target point (m, 3) whose direction from origin (3,) is
    nearest its own, within max_angle_rad: the distances (n,; inf where unpaired or farther apart
    than max_distance_m) and the target indices (n,). Target frame, metres."""
    to_target = target - origin
    to_target /= np.linalg.norm(to_target, axis=1, keepdims=True)
    to_moved = moved - origin
    to_moved /= np.linalg.norm(to_moved, axis=1, keepdims=True)
    # On the unit sphere a chord of 2 sin(a / 2) spans the angle a.
    chord, j = KDTree(to_target).query(to_moved, distance_upper_bound=2.0 * np.sin(max_angle_rad / 2.0))
    j = np.minimum(j, len(target) - 1).astype(np.int64)
    d = np.linalg.norm(moved - target[j], axis=1)
    d[~np.isfinite(chord) | (d > max_distance_m)] = np.inf
    return d, j


@lru_cache(maxsize=32)
def _without_turn(axis: tuple[float, ...], point: tuple[float, ...]) -> np.ndarray:
    """(6, 5) orthonormal basis of the steps (rotation vector, translation) that have no
    component along the turn about the axis through `point`: that turn, p -> p + w a x (p - o),
    is the step (a, o x a) per radian. Kept per axis (read only): a part's ICP runs, hundreds a
    capture, share it, and its SVD cost 0.3 ms a run."""
    a = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    turn = np.concatenate([a, np.cross(np.asarray(point, dtype=np.float64), a)])
    turn /= np.linalg.norm(turn)
    # The right singular vectors after the first span the complement of `turn`.
    basis = np.linalg.svd(turn[None, :])[2][1:].T
    basis.setflags(write=False)
    return basis


@njit(cache=True, nogil=True)
def _normal_equations(
    moved: np.ndarray, target: np.ndarray, normals: np.ndarray, d: np.ndarray, j: np.ndarray
) -> tuple[np.ndarray, np.ndarray, int, float]:
    """The point-to-plane step's normal equations J^T J (6, 6) and J^T r (6,) over the paired
    points (finite d), in the order of the points, with the pair count and the sum of squared
    pair distances. A row of J: (p x n, n), the residual's derivative by (rotation vector,
    translation); r = (q - p) . n."""
    JtJ = np.zeros((6, 6))
    Jtr = np.zeros(6)
    row = np.empty(6)
    n_pairs = 0
    sum_d2 = 0.0
    for i in range(len(moved)):
        if not np.isfinite(d[i]):
            continue
        p, q, n = moved[i], target[j[i]], normals[j[i]]
        row[0] = p[1] * n[2] - p[2] * n[1]
        row[1] = p[2] * n[0] - p[0] * n[2]
        row[2] = p[0] * n[1] - p[1] * n[0]
        row[3], row[4], row[5] = n[0], n[1], n[2]
        r = (q[0] - p[0]) * n[0] + (q[1] - p[1]) * n[1] + (q[2] - p[2]) * n[2]
        for a in range(6):
            Jtr[a] += row[a] * r
            for b in range(a, 6):
                JtJ[a, b] += row[a] * row[b]
        n_pairs += 1
        sum_d2 += d[i] * d[i]
    for a in range(6):
        for b in range(a):
            JtJ[a, b] = JtJ[b, a]
    return JtJ, Jtr, n_pairs, sum_d2
