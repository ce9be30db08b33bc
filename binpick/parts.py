"""Parts: the built-in default part and the kernel that turns a mesh into a part model."""

from __future__ import annotations

import numpy as np
import trimesh

from binpick.io.part_model import PartModel
from binpick.params import SymmetryParams

# The built-in part: a T-joint pipe fitting, in millimetres like most CAD exports.
DEFAULT_PART_NAME = "t_joint"
T_JOINT_OUTER_RADIUS_MM = 12.0
T_JOINT_INNER_RADIUS_MM = 9.0
T_JOINT_RUN_LENGTH_MM = 64.0  # main pipe along x, centred on the origin
T_JOINT_BRANCH_LENGTH_MM = 38.0  # branch along +y, from the main pipe's axis
T_JOINT_SECTIONS = 48
# Rotating by 180 degrees about the branch axis (y) maps the T onto itself.
T_JOINT_SYMMETRY = SymmetryParams(kind="n_fold", axis=(0.0, 1.0, 0.0), order=2)


def _cylinder_along(axis: str, radius: float, start: float, stop: float) -> trimesh.Trimesh:
    """A closed cylinder along `axis` ('x' or 'y') from `start` to `stop` (mm)."""
    cyl = trimesh.creation.cylinder(radius=radius, height=stop - start, sections=T_JOINT_SECTIONS)
    cyl.apply_translation([0.0, 0.0, (start + stop) / 2.0])  # along z first
    if axis == "x":
        cyl.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    elif axis == "y":
        cyl.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0]))
    return cyl


def build_t_joint_mesh() -> trimesh.Trimesh:
    """The default part: a hollow T-joint pipe, millimetres, watertight.

    Main run along x centred on the origin, branch along +y; wall 3 mm thick.
    """
    half = T_JOINT_RUN_LENGTH_MM / 2.0
    outer = trimesh.boolean.union(
        [
            _cylinder_along("x", T_JOINT_OUTER_RADIUS_MM, -half, half),
            _cylinder_along("y", T_JOINT_OUTER_RADIUS_MM, 0.0, T_JOINT_BRANCH_LENGTH_MM),
        ],
        engine="manifold",
    )
    # The bores reach past the open ends so that the ends are open, not capped.
    bore = trimesh.boolean.union(
        [
            _cylinder_along("x", T_JOINT_INNER_RADIUS_MM, -half - 1.0, half + 1.0),
            _cylinder_along("y", T_JOINT_INNER_RADIUS_MM, 0.0, T_JOINT_BRANCH_LENGTH_MM + 1.0),
        ],
        engine="manifold",
    )
    part = trimesh.boolean.difference([outer, bore], engine="manifold")
    part.merge_vertices()
    return part


def sample_surface(
    vertices: np.ndarray, faces: np.ndarray, n_points: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Area-weighted uniform sample of a triangle mesh surface.

    vertices : (v, 3) float, any unit; faces : (f, 3) int.
    Returns points (n, 3) float32 in the unit of `vertices` and unit face normals (n, 3) float32
    (outward where the winding is outward).
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"expected vertices (v, 3) and faces (f, 3), got {vertices.shape}, {faces.shape}")
    tri = vertices[faces]  # (f, 3 corners, 3)
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area2 = np.linalg.norm(cross, axis=1)
    if area2.sum() <= 0:
        raise ValueError("mesh has zero surface area")
    face_idx = rng.choice(len(faces), size=n_points, p=area2 / area2.sum())
    u, v = rng.random((2, n_points))
    flip = u + v > 1.0  # fold the unit square onto the triangle
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    t = tri[face_idx]
    points = t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])
    normals = cross[face_idx] / np.maximum(area2[face_idx], 1e-300)[:, None]
    return points.astype(np.float32), normals.astype(np.float32)


def diameter(points: np.ndarray) -> float:
    """Largest distance between two of the (n, 3) points, exact (via the convex hull)."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) < 2:
        raise ValueError(f"expected at least two points (n, 3), got {points.shape}")
    try:
        hull = trimesh.convex.convex_hull(points).vertices
    except Exception:  # flat or degenerate sets have no 3-D hull; all points then
        hull = points
    d2 = np.max(((hull[:, None, :] - hull[None, :, :]) ** 2).sum(-1))
    return float(np.sqrt(d2))


def make_part_model(
    name: str,
    mesh_m: trimesh.Trimesh,
    symmetry: SymmetryParams,
    n_points: int,
    rng: np.random.Generator,
    source_unit: str,
) -> PartModel:
    """Build a part model from a mesh already in metres (model frame kept as in the CAD file)."""
    points, normals = sample_surface(mesh_m.vertices, mesh_m.faces, n_points, rng)
    lo, hi = mesh_m.bounds
    return PartModel(
        name=name,
        mesh_vertices_m=np.asarray(mesh_m.vertices, dtype=np.float64),
        mesh_faces=np.asarray(mesh_m.faces, dtype=np.int64),
        points_m=points,
        normals=normals,
        diameter_m=diameter(mesh_m.vertices),
        centre_m=(lo + hi) / 2.0,
        symmetry=symmetry,
        source_unit=source_unit,
        watertight=bool(mesh_m.is_watertight),
    )
