"""Is this mesh, in this unit, a part the configured camera and bin can image? And is it one body?

Mesh files carry no unit, and a wrong one is silent: the shared inch part read as millimetres is
a 5.7 mm part whose rendered instances hold a handful of points, and training on them ends
"successfully" with precision 0. These kernels check a part against the imaging settings it will
be trained and used with, and name the unit that would fit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from binpick.io.mesh import METRES_PER_UNIT

# Units tried for `auto`, in this order (CAD exports are most often millimetres, then inches).
UNIT_CANDIDATES = ("mm", "in", "m")
# A part this many times wider than the bin (or the camera's view of the bin floor) is not one
# the cell was set up for; wider than the bin alone is only warned about (a long part lies diagonally).
MAX_PART_OVER_BIN = 2.0
# Bodies farther apart than this share of the diameter are separate parts, not one assembly.
BODY_GAP_REL = 0.02


@dataclass(frozen=True)
class Imaging:
    """How a part is imaged: the bin, the camera above it, and the import and segmentation grid.

    bin_x_m, bin_y_m : inner size of the bin; view_m : the camera's view across at the bin floor
    (the smaller of its width and height); pixel_m : a training pixel's footprint at the floor;
    voxel_m : the import voxel grid; min_points : the fewest points of an instance the network
    learns from (segment.min_points).
    """

    bin_x_m: float
    bin_y_m: float
    view_m: float
    pixel_m: float
    voxel_m: float
    min_points: int

    @property
    def bin_diagonal_m(self) -> float:
        return float(np.hypot(self.bin_x_m, self.bin_y_m))


def expected_instance_points(area_m2: float, imaging: Imaging) -> float:
    """About how many points one instance of a part with surface `area_m2` gets in a scene.

    A convex body's silhouette is on average a quarter of its surface (Cauchy); each point covers
    a cell of the coarser of the voxel grid and the pixel footprint.
    """
    cell = max(imaging.voxel_m, imaging.pixel_m)
    return area_m2 / 4.0 / (cell * cell)


def scale_problem(diameter_m: float, area_m2: float, imaging: Imaging) -> str | None:
    """Why a part of this size cannot be trained with these settings, or None when it can."""
    points = expected_instance_points(area_m2, imaging)
    if points < imaging.min_points:
        return (
            f"about {points:.0f} points per instance at this size (segment.min_points is {imaging.min_points}): "
            f"too small for the camera and bin it is imaged with"
        )
    limit = MAX_PART_OVER_BIN * min(imaging.bin_diagonal_m, imaging.view_m)
    if diameter_m > limit:
        return (
            f"larger than the bin ({imaging.bin_diagonal_m * 1000:.0f} mm across) and the camera's view "
            f"({imaging.view_m * 1000:.0f} mm) it is imaged with"
        )
    return None


def size_warning(diameter_m: float, imaging: Imaging) -> str | None:
    if diameter_m > imaging.bin_diagonal_m:
        return (
            f"the part ({diameter_m * 1000:.0f} mm) is longer than the bin's diagonal "
            f"({imaging.bin_diagonal_m * 1000:.0f} mm): "
            "give it a larger bin (generate.bin) in its params entry"
        )
    return None


def fitting_units(diameter_file: float, area_file2: float, imaging: Imaging) -> list[str]:
    """The units, of UNIT_CANDIDATES, in which a mesh of this size (file units) passes scale_problem."""
    return [
        u
        for u in UNIT_CANDIDATES
        if scale_problem(diameter_file * METRES_PER_UNIT[u], area_file2 * METRES_PER_UNIT[u] ** 2, imaging) is None
    ]


def describe_size(diameter_file: float, unit: str) -> str:
    d_m = diameter_file * METRES_PER_UNIT[unit]
    return f"{d_m * 1000:.4g} mm" if d_m < 1.0 else f"{d_m:.4g} m"


@dataclass(frozen=True)
class Bodies:
    """The connected pieces of a mesh and how they group: pieces whose boxes overlap (within a
    small gap) are one body (nested shells, touching solids); groups are separate bodies."""

    n_pieces: int
    n_groups: int
    largest_gap_m: float


def bodies(mesh: trimesh.Trimesh, diameter: float) -> Bodies:
    """Group the connected components of `mesh` (any unit; gap in the same unit)."""
    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(mesh.faces))
    n = int(labels.max()) + 1 if len(labels) else 0
    if n <= 1:
        return Bodies(n, n, 0.0)
    tri = mesh.vertices[mesh.faces]
    lo = np.full((n, 3), np.inf)
    hi = np.full((n, 3), -np.inf)
    np.minimum.at(lo, labels, tri.min(1))
    np.maximum.at(hi, labels, tri.max(1))
    pad = BODY_GAP_REL * diameter
    # Union of pieces whose padded boxes overlap.
    parent = list(range(n))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    order = np.argsort(lo[:, 0])
    for a_pos, a in enumerate(order):
        for b in order[a_pos + 1 :]:
            if lo[b, 0] > hi[a, 0] + pad:
                break
            if np.all(lo[a] <= hi[b] + pad) and np.all(lo[b] <= hi[a] + pad):
                parent[find(int(a))] = find(int(b))
    roots = {find(i) for i in range(n)}
    if len(roots) == 1:
        return Bodies(n, 1, 0.0)
    groups = {r: [i for i in range(n) if find(i) == r] for r in roots}
    g_lo = np.array([lo[idx].min(0) for idx in groups.values()])
    g_hi = np.array([hi[idx].max(0) for idx in groups.values()])
    # Gap between each group's box and the nearest other group's box.
    gaps = []
    for i in range(len(g_lo)):
        others = [
            float(np.linalg.norm(np.maximum(0.0, np.maximum(g_lo[j] - g_hi[i], g_lo[i] - g_hi[j]))))
            for j in range(len(g_lo))
            if j != i
        ]
        gaps.append(min(others))
    return Bodies(n, len(roots), float(max(gaps)))
