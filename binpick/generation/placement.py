"""Object placement in a bin by vertical drop on height maps.

Each new object gets a random orientation and x/y position, and is lowered until it rests on the
pile: in every grid column it occupies, its lowest point stays above the highest point already
there (dilated by one cell). Objects therefore never interpenetrate, up to the grid resolution and
the density of the surface sample. It is conservative: nothing slides under an overhang.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy.ndimage import maximum_filter

from binpick.geometry.transforms import axis_angle_to_R, make_T, random_rotation
from binpick.params import BinParams, PlacementParams

log = logging.getLogger(__name__)

MOSTLY_LYING_TILT_SIGMA_RAD = np.pi / 8


@dataclass(frozen=True)
class Placement:
    """T_bin_from_model : (k, 4, 4) float64, poses of the placed objects, bin frame, metres;
    kinds : (k,) int, which kind of part each is (index into the point sets; all 0 for one part)."""

    T_bin_from_model: np.ndarray
    n_requested: int
    kinds: np.ndarray | None = None


def sample_orientation(rng: np.random.Generator, mode: str) -> np.ndarray:
    """(3, 3) rotation: uniform on SO(3), or 'mostly lying' (tilt about x/y near pi/2, any yaw)."""
    if mode == "uniform":
        return random_rotation(rng)
    if mode == "mostly_lying":
        tilt = np.clip(rng.normal(np.pi / 2, MOSTLY_LYING_TILT_SIGMA_RAD), 0.25 * np.pi, 0.75 * np.pi)
        tilt_axis = "x" if rng.random() < 0.5 else "y"
        R_tilt = axis_angle_to_R(np.eye(3)[0 if tilt_axis == "x" else 1], tilt)
        R_yaw = axis_angle_to_R(np.array([0.0, 0.0, 1.0]), rng.uniform(0, 2 * np.pi))
        return R_yaw @ R_tilt
    raise ValueError(f"unknown orientation mode {mode!r}")


def start_height(rng: np.random.Generator, placement: PlacementParams, bin_params: BinParams) -> float:
    """Height of an object's lowest point above the floor, before the pile below is considered."""
    if placement.heights == "pile":
        return 0.0  # no draw: the default mode's random stream stays as it was
    if placement.heights == "u_shaped":
        return float(bin_params.wall_height_m * rng.beta(0.5, 0.5))
    return float(rng.choice(placement.height_levels_m))


# The kernels below visit each surface point once; points are (n, 3) in the bin frame of the
# candidate orientation, grid column (i, j) holds x in [i, i + 1) * cell from the bin's corner.


@njit(cache=True, nogil=True)
def _bounds(p):  # pragma: no cover - compiled
    """Lowest and highest x, y, z of the points, and their mean z."""
    lo = p[0].copy()
    hi = p[0].copy()
    z_sum = 0.0
    for k in range(len(p)):
        for a in range(3):
            lo[a] = min(lo[a], p[k, a])
            hi[a] = max(hi[a], p[k, a])
        z_sum += p[k, 2]
    return lo, hi, z_sum / len(p)


@njit(cache=True, nogil=True)
def _column(p, k, ox, oy, cell, nx, ny):  # pragma: no cover - compiled
    i = min(max(int((p[k, 0] + ox) / cell), 0), nx - 1)
    j = min(max(int((p[k, 1] + oy) / cell), 0), ny - 1)
    return i, j


@njit(cache=True, nogil=True)
def _contact(p, ox, oy, cell, support):  # pragma: no cover - compiled
    """The lift at which the points, shifted by (ox, oy) onto the grid, rest on `support`:
    max over points of (pile height in its column - its z)."""
    nx, ny = support.shape
    lift = -np.inf
    for k in range(len(p)):
        i, j = _column(p, k, ox, oy, cell, nx, ny)
        lift = max(lift, support[i, j] - p[k, 2])
    return lift


@njit(cache=True, nogil=True)
def _stamp(top, p, ox, oy, tz, cell):  # pragma: no cover - compiled
    """Raise the pile height map to the placed object's points (lifted by tz), in place."""
    nx, ny = top.shape
    for k in range(len(p)):
        i, j = _column(p, k, ox, oy, cell, nx, ny)
        top[i, j] = max(top[i, j], p[k, 2] + tz)


def _update_support(support: np.ndarray, top: np.ndarray, p: np.ndarray, ox: float, oy: float, cell: float) -> None:
    """Recompute, in place, the one-cell dilation `support` of the height map `top` where stamping
    the points p (shifted by ox, oy onto the grid) can have changed it; elsewhere it still holds."""
    nx, ny = top.shape
    lo, hi, _ = _bounds(p)
    i0, i1 = (min(max(int((v + ox) / cell), 0), nx - 1) for v in (lo[0], hi[0]))
    j0, j1 = (min(max(int((v + oy) / cell), 0), ny - 1) for v in (lo[1], hi[1]))
    # Cells one beyond the stamped box can change; their neighbours, one further, are read.
    a0, a1, b0, b1 = max(i0 - 2, 0), min(i1 + 3, nx), max(j0 - 2, 0), min(j1 + 3, ny)
    r0, r1, c0, c1 = max(i0 - 1, 0), min(i1 + 2, nx), max(j0 - 1, 0), min(j1 + 2, ny)
    near = maximum_filter(top[a0:a1, b0:b1], size=3, mode="nearest")
    support[r0:r1, c0:c1] = near[r0 - a0 : r1 - a0, c0 - b0 : c1 - b0]


def place_objects(
    model_points_m: np.ndarray | list[np.ndarray],
    n_objects: int,
    bin_params: BinParams,
    placement: PlacementParams,
    rng: np.random.Generator,
    kinds: list[int] | None = None,
) -> Placement:
    """Drop `n_objects` copies of a part into the bin, one after the other.

    model_points_m : (n, 3) float, dense surface sample of the part, model frame, metres; or a
                     list of such, one per kind of part in a mixed bin. Their spacing should be
                     below `placement.heightmap_cell_m`.
    kinds          : the kind of each object dropped, in order (a mixed bin); default all 0.
    Returns the poses of the objects that fit; fewer than requested when the bin is full (logged).
    """
    sets = [
        np.asarray(m, dtype=np.float64)
        for m in (model_points_m if isinstance(model_points_m, list) else [model_points_m])
    ]
    for pts in sets:
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"expected model points (n, 3), got {pts.shape}")
    kinds = [0] * n_objects if kinds is None else list(kinds)
    if len(kinds) != n_objects or not all(0 <= k < len(sets) for k in kinds):
        raise ValueError(f"expected {n_objects} kinds, each below {len(sets)}, got {kinds}")
    cell = placement.heightmap_cell_m
    X, Y = bin_params.inner_x_m, bin_params.inner_y_m
    shape = (int(np.ceil(X / cell)), int(np.ceil(Y / cell)))
    top = np.zeros(shape)  # pile height per column; the floor is z = 0
    # The pile's height map dilated by one cell (see above); kept up to date around each new
    # object, so that a large bin costs no more per object than a small one.
    support = top.copy()
    poses: list[np.ndarray] = []
    for kind in kinds:
        pts = sets[kind]
        floor_gap = start_height(rng, placement, bin_params)
        # Of several random candidates, the one that comes to rest lowest: piles stay flat and
        # dense like a settled bin instead of growing towers on single contact points.
        best: tuple[float, np.ndarray, np.ndarray] | None = None
        for _candidate in range(placement.candidates_per_object):
            R = sample_orientation(rng, placement.orientation)
            p = pts @ R.T
            lo, hi, z_mean = _bounds(p)
            if hi[0] - lo[0] >= X or hi[1] - lo[1] >= Y:
                continue  # this orientation does not fit between the walls
            tx = rng.uniform(-X / 2 - lo[0], X / 2 - hi[0])
            ty = rng.uniform(-Y / 2 - lo[1], Y / 2 - hi[1])
            # Lowered until its lowest point in some column touches the pile there.
            tz = max(_contact(p, tx + X / 2, ty + Y / 2, cell, support), floor_gap - float(lo[2]))
            centre_z = tz + z_mean
            if best is None or centre_z < best[0]:
                best = (centre_z, make_T(R, np.array([tx, ty, tz])), p)
        if best is None or best[0] > placement.max_pile_height_m:
            log.warning("bin full: placed %d of %d objects", len(poses), n_objects)
            break
        _, pose, p = best
        _stamp(top, p, pose[0, 3] + X / 2, pose[1, 3] + Y / 2, pose[2, 3], cell)
        _update_support(support, top, p, pose[0, 3] + X / 2, pose[1, 3] + Y / 2, cell)
        poses.append(pose)
    T = np.stack(poses) if poses else np.zeros((0, 4, 4))
    return Placement(T_bin_from_model=T, n_requested=n_objects, kinds=np.asarray(kinds[: len(poses)], dtype=np.int64))
