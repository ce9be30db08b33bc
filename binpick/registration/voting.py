"""PPF voting: each scene reference point is paired with its neighbours within the model
diameter; matching model pairs vote for (model point, alpha); the accumulator peaks become pose
candidates. Scene points in the camera frame, metres; poses T_cam_from_model."""

from __future__ import annotations

import threading
from typing import NamedTuple

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


class PreparedScene(NamedTuple):
    """What the voting kernel reads of a scene's n points, computed once per capture.

    unit_normals (n, 3); R_align (n, 3, 3), t_align (n, 3): each point's alignment (_align_to_x);
    the points bucketed in a grid of cubes of side cell_m (metres, at least the pairing radius),
    so that a reference's partners are looked for in its 27 cells rather than among all n:
    order (n,) the point indices sorted by cell, cell_keys (m,) the occupied cells' keys
    ascending, cell_starts (m + 1,) where each cell's run begins in order, origin_m (3,) the
    grid's corner (camera frame), dims (3,) cells along x, y, z."""

    unit_normals: np.ndarray
    R_align: np.ndarray
    t_align: np.ndarray
    order: np.ndarray
    cell_keys: np.ndarray
    cell_starts: np.ndarray
    origin_m: np.ndarray
    dims: np.ndarray
    cell_m: float


def prepare_scene(pts: np.ndarray, nrm: np.ndarray, radius_m: float) -> PreparedScene:
    """PreparedScene of points and normals (n, 3 each, camera frame, metres) for pairing within
    radius_m (the model's diameter)."""
    T_s = _align_to_x(pts, nrm)
    # A cell a hair wider than the radius: a partner at exactly the radius stays within one cell
    # of its reference whatever the rounding of the division.
    cell_m = float(radius_m) * (1.0 + 1e-6)
    origin = pts.min(axis=0) if len(pts) else np.zeros(3)
    ijk = np.floor((pts - origin) / cell_m).astype(np.int64)
    dims = ijk.max(axis=0) + 1 if len(pts) else np.ones(3, np.int64)
    keys = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    order = np.argsort(keys, kind="stable")
    cell_keys, cell_first = np.unique(keys[order], return_index=True)
    return PreparedScene(
        nrm / np.linalg.norm(nrm, axis=1, keepdims=True),
        np.ascontiguousarray(T_s[:, :3, :3]),
        np.ascontiguousarray(T_s[:, :3, 3]),
        order.astype(np.int64),
        cell_keys.astype(np.int64),
        np.append(cell_first, len(pts)).astype(np.int64),
        np.asarray(origin, np.float64),
        np.asarray(dims, np.int64),
        cell_m,
    )


def vote(
    model: PPFModel,
    pts: np.ndarray,
    nrm: np.ndarray,
    refs: np.ndarray,
    prepared: PreparedScene | None = None,
) -> list[tuple[np.ndarray, float]]:
    """Pose candidates (T_cam_from_model, votes) from the accumulator peaks of each reference.
    prepared: prepare_scene(pts, nrm, model.diameter_m), given when the caller votes in chunks
    of references over the same points (once for all of them); computed here otherwise."""
    scene = prepare_scene(pts, nrm, model.diameter_m) if prepared is None else prepared
    R_s, t_s = scene.R_align, scene.t_align
    with _KERNELS:
        group_start, keys, alpha_s = _scene_pairs(
            pts, scene, refs.astype(np.int64), model.diameter_m, model.distance_step_m, model.angle_bins
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
    # Only the model points that won a peak: the whole model's alignment, made again for every
    # chunk of references, had cost a second a capture over a large bin.
    T_m = _align_to_x(model.points_m[m_r], model.normals[m_r])
    rows = refs[ref_rows]
    T_s = np.zeros((len(rows), 4, 4))
    T_s[:, :3, :3], T_s[:, :3, 3], T_s[:, 3, 3] = R_s[rows], t_s[rows], 1.0
    poses = invert_T(T_s) @ Rx @ T_m
    return list(zip(poses, peak_votes[valid].astype(np.float64), strict=False))


def _scene_pairs(
    pts: np.ndarray, scene: PreparedScene, refs: np.ndarray, radius: float, distance_step: float, n_angles: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every pair (reference refs[a], other point within radius), grouped by reference and, within
    a reference, by the partner's index: the group bounds (n_refs + 1,), the quantised feature
    key of each pair and the angle alpha that turns the aligned partner into the half-plane
    y > 0, z = 0 (the same quantities as _features, _keys and _alpha)."""
    if scene.cell_m < radius:
        raise ValueError(f"the scene was bucketed for pairs within {scene.cell_m} m, not {radius} m")
    return _pairs_kernel(
        pts,
        scene.unit_normals,
        scene.R_align,
        scene.t_align,
        refs,
        radius,
        distance_step,
        n_angles,
        scene.order,
        scene.cell_keys,
        scene.cell_starts,
        scene.origin_m,
        scene.dims,
        scene.cell_m,
    )


@njit(cache=True, nogil=True)
def _cell_runs(pts, i, order_starts, cell_keys, origin, dims, cell_m):  # pragma: no cover - compiled
    """The runs (n_runs of the (27, 2) rows: start, stop in the cell-sorted order) of point i's
    cell and the 26 around it."""
    c = np.empty(3, np.int64)
    for axis in range(3):
        c[axis] = np.int64(np.floor((pts[i, axis] - origin[axis]) / cell_m))
    runs = np.empty((27, 2), np.int64)
    n_runs = 0
    for dx in range(-1, 2):
        x = c[0] + dx
        if x < 0 or x >= dims[0]:
            continue
        for dy in range(-1, 2):
            y = c[1] + dy
            if y < 0 or y >= dims[1]:
                continue
            for dz in range(-1, 2):
                z = c[2] + dz
                if z < 0 or z >= dims[2]:
                    continue
                key = (x * dims[1] + y) * dims[2] + z
                k = np.searchsorted(cell_keys, key)
                if k < len(cell_keys) and cell_keys[k] == key:
                    runs[n_runs, 0], runs[n_runs, 1] = order_starts[k], order_starts[k + 1]
                    n_runs += 1
    return runs, n_runs


@njit(cache=True, nogil=True)
def _n_partners(pts, i, r2, order, cell_keys, cell_starts, origin, dims, cell_m):  # pragma: no cover - compiled
    """How many points lie within sqrt(r2) of point i, i itself left out."""
    runs, n_runs = _cell_runs(pts, i, cell_starts, cell_keys, origin, dims, cell_m)
    n = 0
    for run in range(n_runs):
        for s in range(runs[run, 0], runs[run, 1]):
            j = order[s]
            dx, dy, dz = pts[j, 0] - pts[i, 0], pts[j, 1] - pts[i, 1], pts[j, 2] - pts[i, 2]
            n += j != i and dx * dx + dy * dy + dz * dz <= r2
    return n


@njit(cache=True, nogil=True)
def _partners(pts, i, r2, n, order, cell_keys, cell_starts, origin, dims, cell_m):  # pragma: no cover - compiled
    """The n points within sqrt(r2) of point i (i itself left out), ascending."""
    runs, n_runs = _cell_runs(pts, i, cell_starts, cell_keys, origin, dims, cell_m)
    out = np.empty(n, np.int64)
    k = 0
    for run in range(n_runs):
        for s in range(runs[run, 0], runs[run, 1]):
            j = order[s]
            dx, dy, dz = pts[j, 0] - pts[i, 0], pts[j, 1] - pts[i, 1], pts[j, 2] - pts[i, 2]
            if j != i and dx * dx + dy * dy + dz * dz <= r2:
                out[k] = j
                k += 1
    # Ascending, as a scan of all points gives them: the accumulator's ties go to the first seen.
    return np.sort(out)


@njit(cache=True, nogil=True, parallel=True)
def _pairs_kernel(
    pts,
    unit_normals,
    R_align,
    t_align,
    refs,
    radius,
    distance_step,
    n_angles,
    order,
    cell_keys,
    cell_starts,
    origin,
    dims,
    cell_m,
):  # pragma: no cover - compiled
    """_scene_pairs in one compiled pass without temporaries, references spread over the cores."""
    n_refs = len(refs)
    r2 = radius * radius
    counts = np.zeros(n_refs + 1, np.int64)
    for a in numba.prange(n_refs):
        counts[a + 1] = _n_partners(pts, refs[a], r2, order, cell_keys, cell_starts, origin, dims, cell_m)
    starts = np.cumsum(counts)
    keys = np.empty(starts[-1], np.int64)
    alpha = np.empty(starts[-1])
    for a in numba.prange(n_refs):
        i = refs[a]
        k = starts[a]
        for j in _partners(pts, i, r2, counts[a + 1], order, cell_keys, cell_starts, origin, dims, cell_m):
            dx, dy, dz = pts[j, 0] - pts[i, 0], pts[j, 1] - pts[i, 1], pts[j, 2] - pts[i, 2]
            d2 = dx * dx + dy * dy + dz * dz
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
