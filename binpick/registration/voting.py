"""PPF voting: each scene reference point is paired with its neighbours within the model
diameter; matching model pairs vote for (model point, alpha); the accumulator peaks become pose
candidates. Scene points in the camera frame, metres; poses T_cam_from_model."""

from __future__ import annotations

import threading

import numba
import numpy as np
from numba import njit

from binpick.geometry.transforms import invert_T
from binpick.io.ppf_model import PPFModel
from binpick.registration.constants import PEAKS_PER_REFERENCE
from binpick.registration.model import _align_to_x

# One voting at a time in the process: both kernels already spread over every core, and numba's
# fallback thread pool (workqueue, where OpenMP is missing) aborts on launches from two threads.
# Segments matched on threads (binpick/scene/register.py) overlap the rest of their matching instead.
_KERNELS = threading.Lock()


def aligned_scene(pts: np.ndarray, nrm: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What the voting kernel reads of every scene point (n, 3 each): the unit normals and each
    point's alignment (_align_to_x) as rotations (n, 3, 3) and translations (n, 3)."""
    T_s = _align_to_x(pts, nrm)
    return (
        nrm / np.linalg.norm(nrm, axis=1, keepdims=True),
        np.ascontiguousarray(T_s[:, :3, :3]),
        np.ascontiguousarray(T_s[:, :3, 3]),
    )


def vote(
    model: PPFModel,
    pts: np.ndarray,
    nrm: np.ndarray,
    refs: np.ndarray,
    aligned: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> list[tuple[np.ndarray, float]]:
    """Pose candidates (T_cam_from_model, votes) from the accumulator peaks of each reference.
    aligned: aligned_scene(pts, nrm), given when the caller votes in chunks of references over
    the same points (once for all of them); computed here otherwise."""
    unit_normals, R_s, t_s = aligned_scene(pts, nrm) if aligned is None else aligned
    with _KERNELS:
        group_start, keys, alpha_s = _scene_pairs(
            pts,
            unit_normals,
            R_s,
            t_s,
            refs.astype(np.int64),
            model.diameter_m,
            model.distance_step_m,
            model.angle_bins,
        )
        if len(keys) == 0:
            return []
        A = model.angle_bins
        peak_flat, peak_votes = _accumulate_peaks(
            # The table as stored (int64 / int32 / float32): a converted copy would cost more than the voting.
            group_start,
            keys,
            alpha_s,
            np.asarray(model.key_starts, np.int64),
            np.asarray(model.ref_index, np.int32),
            np.asarray(model.alpha, np.float32),
            len(refs),
            len(model.points_m),
            A,
            PEAKS_PER_REFERENCE,
            4 * numba.get_num_threads(),
        )
    valid = peak_votes > 0
    ref_rows, _ = np.nonzero(valid)
    m_r, a_bin = np.divmod(peak_flat[valid], A)
    a = -np.pi + (a_bin + 0.5) * 2 * np.pi / A
    Rx = np.zeros((len(a), 4, 4))
    Rx[:, 0, 0] = Rx[:, 3, 3] = 1.0
    Rx[:, 1, 1], Rx[:, 1, 2], Rx[:, 2, 1], Rx[:, 2, 2] = np.cos(a), -np.sin(a), np.sin(a), np.cos(a)
    T_m = _align_to_x(model.points_m, model.normals)
    rows = refs[ref_rows]
    T_s = np.zeros((len(rows), 4, 4))
    T_s[:, :3, :3], T_s[:, :3, 3], T_s[:, 3, 3] = R_s[rows], t_s[rows], 1.0
    poses = invert_T(T_s) @ Rx @ T_m[m_r]
    return list(zip(poses, peak_votes[valid].astype(np.float64), strict=False))


@njit(cache=True, nogil=True, parallel=True)
def _scene_pairs(
    pts, unit_normals, R_align, t_align, refs, radius, distance_step, n_angles
):  # pragma: no cover - compiled
    """Every pair (reference refs[a], other point within radius), grouped by reference: the group
    bounds (n_refs + 1,), the quantised feature key of each pair and the angle alpha that turns
    the aligned partner into the half-plane y > 0, z = 0 (the same quantities as _features,
    _keys and _alpha, in one pass without temporaries; references spread over the cores)."""
    n_refs, n = len(refs), len(pts)
    r2 = radius * radius
    counts = np.zeros(n_refs + 1, np.int64)
    for a in numba.prange(n_refs):
        i = refs[a]
        c = 0
        for j in range(n):
            dx, dy, dz = pts[j, 0] - pts[i, 0], pts[j, 1] - pts[i, 1], pts[j, 2] - pts[i, 2]
            if j != i and dx * dx + dy * dy + dz * dz <= r2:
                c += 1
        counts[a + 1] = c
    starts = np.cumsum(counts)
    keys = np.empty(starts[-1], np.int64)
    alpha = np.empty(starts[-1])
    for a in numba.prange(n_refs):
        i = refs[a]
        k = starts[a]
        for j in range(n):
            dx, dy, dz = pts[j, 0] - pts[i, 0], pts[j, 1] - pts[i, 1], pts[j, 2] - pts[i, 2]
            d2 = dx * dx + dy * dy + dz * dz
            if j == i or d2 > r2:
                continue
            dist = np.sqrt(d2)
            inv = 1.0 / max(dist, 1e-12)
            ux, uy, uz = dx * inv, dy * inv, dz * inv
            c1 = unit_normals[i, 0] * ux + unit_normals[i, 1] * uy + unit_normals[i, 2] * uz
            c2 = unit_normals[j, 0] * ux + unit_normals[j, 1] * uy + unit_normals[j, 2] * uz
            c3 = (
                unit_normals[i, 0] * unit_normals[j, 0]
                + unit_normals[i, 1] * unit_normals[j, 1]
                + unit_normals[i, 2] * unit_normals[j, 2]
            )
            key = np.int64(np.floor(dist / distance_step))
            for cosine in (c1, c2, c3):
                q = np.int64(np.arccos(min(max(cosine, -1.0), 1.0)) / np.pi * n_angles)
                key = key * n_angles + min(q, n_angles - 1)
            keys[k] = key
            py = (
                R_align[i, 1, 0] * pts[j, 0]
                + R_align[i, 1, 1] * pts[j, 1]
                + R_align[i, 1, 2] * pts[j, 2]
                + t_align[i, 1]
            )
            pz = (
                R_align[i, 2, 0] * pts[j, 0]
                + R_align[i, 2, 1] * pts[j, 1]
                + R_align[i, 2, 2] * pts[j, 2]
                + t_align[i, 2]
            )
            alpha[k] = np.arctan2(-pz, py)
            k += 1
    return starts, keys, alpha


@njit(cache=True, nogil=True, parallel=True)
def _accumulate_peaks(
    group_start, keys, alpha_s, key_starts, ref_index, alpha_m, n_refs, n_model, n_angles, n_peaks, n_chunks
):  # pragma: no cover - compiled
    """The voting loop: every scene pair votes for (model reference point, alpha bin) of each
    model pair with its key; per scene reference, the n_peaks strongest accumulator cells.

    The pairs of reference r are group_start[r]:group_start[r + 1], as _scene_pairs makes them.
    References are spread over the cores in chunks, each with its own accumulator row, reset
    between references (only the touched cells), so the result does not depend on the cores.
    Returns (n_refs, n_peaks) flat cell indices (model point * n_angles + alpha bin) and votes.
    """
    peak_flat = np.zeros((n_refs, n_peaks), np.int64)
    peak_votes = np.zeros((n_refs, n_peaks), np.int32)
    n_keys = len(key_starts) - 1
    scale = n_angles / (2.0 * np.pi)
    n_chunks = min(n_chunks, n_refs)
    for c in numba.prange(n_chunks):
        acc = np.zeros(n_model * n_angles, np.int32)
        # One slot spare: every vote writes its cell, and only a first vote keeps it.
        touched = np.empty(n_model * n_angles + 1, np.int64)
        for r in range(c * n_refs // n_chunks, (c + 1) * n_refs // n_chunks):
            n_touched = 0
            for p in range(group_start[r], group_start[r + 1]):
                k = keys[p]
                if k < n_keys:
                    # bin of (alpha_m - alpha_s + pi) * scale, shifted by n_angles to be positive
                    # (truncation is then floor) and wrapped by at most two subtractions. The loop
                    # is branch-free: a data-dependent branch per vote (half of them mispredicted)
                    # cost more than the votes themselves.
                    offset = (np.pi - alpha_s[p]) * scale + n_angles
                    for q in range(key_starts[k], key_starts[k + 1]):
                        b = int(alpha_m[q] * scale + offset)
                        b -= n_angles * (b >= n_angles)
                        b -= n_angles * (b >= n_angles)
                        cell = np.int64(ref_index[q]) * n_angles + b
                        v = acc[cell]
                        touched[n_touched] = cell
                        n_touched += v == 0
                        acc[cell] = v + 1
            for t in range(n_touched):
                cell = touched[t]
                v = acc[cell]
                # insert into this reference's top list (sorted, strongest first; ties: first seen)
                if v > peak_votes[r, n_peaks - 1]:
                    for slot in range(n_peaks):
                        if v > peak_votes[r, slot]:
                            for j in range(n_peaks - 1, slot, -1):
                                peak_votes[r, j] = peak_votes[r, j - 1]
                                peak_flat[r, j] = peak_flat[r, j - 1]
                            peak_votes[r, slot] = v
                            peak_flat[r, slot] = cell
                            break
                acc[cell] = 0
    return peak_flat, peak_votes
