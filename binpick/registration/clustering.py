"""Clustering of pose candidates in SE(3), with rotation AND translation thresholds and the
part's symmetries; pose closeness tests."""

from __future__ import annotations

import numba
import numpy as np

from binpick.io.ppf_model import PPFModel
from binpick.params import RegisterParams


def cluster_poses(
    candidates: list[tuple[np.ndarray, float]],
    model: PPFModel,
    params: RegisterParams,
    max_candidates: int | None = None,
) -> list[tuple[np.ndarray, float]]:
    """Greedy SE(3) clustering: a pose joins the first (strongest) cluster whose best pose, or a
    twin of it by a symmetry or a near symmetry of the part, is within the rotation AND the
    translation threshold. Returns (best pose, summed votes), strongest first. max_candidates:
    only the strongest poses are clustered (weak peaks, from references on clutter or ambiguous
    patches, decide nothing).

    Near symmetries join too: the votes for a part whose turns about an axis look alike (a cup
    whose lid relief alone tells its turns apart) spread over every turn, and no one turn's cluster
    outvoted a wrong pose with its votes in one place (an upright IC-BIN cup seen lid-on: 0.28,
    lying on its side, against 0.64 for the right pose once its turns are one cluster). Which turn
    is right is decided afterwards from the capture (registration/near_symmetry.py)."""
    order = sorted(range(len(candidates)), key=lambda k: -candidates[k][1])[:max_candidates]
    if not order:
        return []
    poses = np.ascontiguousarray(np.stack([candidates[k][0] for k in order]), dtype=np.float64)
    weights = np.array([candidates[k][1] for k in order], dtype=np.float64)
    reps, votes = _greedy_clusters(
        poses,
        weights,
        np.ascontiguousarray(_twins(model), dtype=np.float64),
        np.cos(np.radians(params.cluster_rotation_deg)),
        params.cluster_translation_rel * model.diameter_m,
    )
    ranked = sorted(range(len(reps)), key=lambda c: -votes[c])
    return [(poses[reps[c]], float(votes[c])) for c in ranked]


# Two twin transforms this close (rotation, degrees; translation, share of the diameter) are one.
TWIN_SAME_DEG = 2.0
TWIN_SAME_REL = 0.01


def _twins(model: PPFModel) -> np.ndarray:
    """(m, 4, 4) the transforms of the model frame a cluster's pose is compared through: the
    symmetries, each composed with each near symmetry and each product of two (identity first),
    repeats dropped. The products are needed because a cluster's pose may itself be a turned
    one: a mug's poses turned by 30 degrees and flipped upside down are reached from a pose
    turned by 60 degrees only through a turn and the flip."""
    if not len(model.near_symmetries):
        return model.symmetries
    near = model.near_symmetries
    pairs = np.einsum("aij,bjk->abik", near, near).reshape(-1, 4, 4)
    products = np.concatenate([near, pairs])
    every = np.concatenate([model.symmetries, np.einsum("aij,bjk->abik", model.symmetries, products).reshape(-1, 4, 4)])
    kept: list[np.ndarray] = []
    for T in every:
        if not kept or not _close(T[None], np.stack(kept), TWIN_SAME_DEG, TWIN_SAME_REL * model.diameter_m).any():
            kept.append(T)
    return np.stack(kept)


# The greedy clustering's grid of cubes holds at most this many (32 MB of int64 heads).
MAX_GRID_CELLS = 1 << 22


@numba.njit(cache=True)
def _greedy_clusters(poses, weights, symmetries, min_cos, max_dist):  # pragma: no cover - compiled
    """Indices of the cluster representatives (in order of creation) and each cluster's votes.

    The twins (pose @ symmetry) of each representative are made once and filed in a grid of
    cubes (of side max_dist or more) by their translation: a pose is compared only with the twins in its
    own cube and the 26 around it (the others lie farther than max_dist on some axis), first
    their translation (three numbers), then their rotation: cos of the relative angle =
    (trace(R_twin^T R) - 1) / 2. It joins the earliest cluster one of whose twins passes both,
    as a scan of every cluster in order would find: a whole scene's tens of thousands of
    candidates form thousands of clusters, and that scan had cost 25 s a capture."""
    n, m = len(poses), len(symmetries)
    twins = np.empty((n * m, 3, 4))
    reps = np.empty(n, np.int64)
    votes = np.zeros(n)
    n_reps = 0
    d2 = max_dist * max_dist
    if n == 0:
        return reps, votes
    # The grid spans every translation a twin can have: a pose's own, moved by a symmetry's
    # translation turned (its length kept), one cube of margin on every side.
    reach = 0.0
    for s in range(m):
        reach = max(reach, np.sqrt(symmetries[s, 0, 3] ** 2 + symmetries[s, 1, 3] ** 2 + symmetries[s, 2, 3] ** 2))
    # Cubes no smaller than max_dist, and at most MAX_GRID_CELLS of them (memory, whatever the
    # spread: 256 along each axis would have been 134 MB).
    cell = max_dist
    lo = np.empty(3)
    dims = np.empty(3, np.int64)
    while True:
        for a in range(3):
            lo[a] = poses[:, a, 3].min() - reach - cell
            dims[a] = np.int64((poses[:, a, 3].max() + reach + cell - lo[a]) / cell) + 2
        if dims[0] * dims[1] * dims[2] <= MAX_GRID_CELLS:
            break
        cell *= 1.5
    head = np.full(dims[0] * dims[1] * dims[2], -1, np.int64)  # a cube's last twin filed
    below = np.empty(n * m, np.int64)  # the twin filed in the same cube before each
    for k in range(n):
        T = poses[k]
        cx = np.int64((T[0, 3] - lo[0]) / cell)
        cy = np.int64((T[1, 3] - lo[1]) / cell)
        cz = np.int64((T[2, 3] - lo[2]) / cell)
        found = n
        for x in range(cx - 1, cx + 2):
            for y in range(cy - 1, cy + 2):
                for z in range(cz - 1, cz + 2):
                    t = head[(x * dims[1] + y) * dims[2] + z]
                    while t >= 0:
                        c = t // m
                        if c < found:
                            W = twins[t]
                            dx, dy, dz = W[0, 3] - T[0, 3], W[1, 3] - T[1, 3], W[2, 3] - T[2, 3]
                            if dx * dx + dy * dy + dz * dz < d2:
                                tr = 0.0
                                for a in range(3):
                                    for b in range(3):
                                        tr += W[a, b] * T[a, b]
                                if (tr - 1.0) / 2.0 > min_cos:
                                    found = c
                        t = below[t]
        if found < n:
            votes[found] += weights[k]
            continue
        for s in range(m):
            S = symmetries[s]
            t = n_reps * m + s
            for a in range(3):
                for b in range(4):
                    v = 0.0
                    for e in range(4):
                        v += T[a, e] * S[e, b]
                    twins[t, a, b] = v
            filed = (
                np.int64((twins[t, 0, 3] - lo[0]) / cell) * dims[1] + np.int64((twins[t, 1, 3] - lo[1]) / cell)
            ) * dims[2] + np.int64((twins[t, 2, 3] - lo[2]) / cell)
            below[t] = head[filed]
            head[filed] = t
        reps[n_reps] = k
        votes[n_reps] = weights[k]
        n_reps += 1
    return reps[:n_reps], votes[:n_reps]


def _close(A: np.ndarray, B: np.ndarray, rotation_deg: float, translation_m: float) -> np.ndarray:
    """(a, b) mask: pose A[i] within translation_m AND rotation_deg of pose B[j]; A (a, 4, 4), B (b, 4, 4)."""
    close_t = np.linalg.norm(A[:, None, :3, 3] - B[None, :, :3, 3], axis=2) < translation_m
    # cos of the relative angle: (trace(R_a^T R_b) - 1) / 2
    cos = (np.einsum("aij,bij->ab", A[:, :3, :3], B[:, :3, :3]) - 1.0) / 2.0
    return close_t & (cos > np.cos(np.radians(rotation_deg)))


def same_pose(model: PPFModel, T_a: np.ndarray, T_b: np.ndarray, rotation_deg: float, translation_m: float) -> bool:
    """Whether two poses of the part agree within the thresholds, up to the part's symmetries."""
    return repeats_any(model, T_a, T_b[None], rotation_deg, translation_m)


def repeats_any(model: PPFModel, T: np.ndarray, poses: np.ndarray, rotation_deg: float, translation_m: float) -> bool:
    """Whether pose T (4, 4) agrees with any of the poses (n, 4, 4) within the thresholds, up to
    the part's symmetries."""
    if len(poses) == 0:
        return False
    return bool(_close(T[None] @ model.symmetries, poses, rotation_deg, translation_m).any())
