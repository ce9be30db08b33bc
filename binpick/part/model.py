"""Parts: the built-in default part and the kernel that turns a mesh into a part model."""

from __future__ import annotations

import numpy as np
import trimesh

from binpick.io.part_model import PartModel
from binpick.params import DEFAULT_DENSITY_KG_M3, Params, SymmetryParams

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


# Point sets up to this size get the exact diameter by all pairs of convex-hull vertices.
EXACT_DIAMETER_MAX_POINTS = 20_000
# Larger sets: widths along this many directions over a half sphere (a width is the same along
# u and -u). Their covering radius is below 0.04 rad, so the widest is within
# 1 - cos(0.04) = 0.08 % of the diameter (DIAMETER_MAX_REL_ERROR); the pairs found are then refined.
DIAMETER_DIRECTIONS = 3000
DIAMETER_MAX_REL_ERROR = 1.0 - np.cos(0.04)


def _half_sphere_directions(n: int) -> np.ndarray:
    """(n, 3) unit vectors with z >= 0 on a Fibonacci spiral (even coverage, deterministic)."""
    i = np.arange(n) + 0.5
    z = 1.0 - i / n  # uniform in z over (0, 1]: uniform in area on the half sphere
    phi = np.pi * (1.0 + 5.0**0.5) * i
    r = np.sqrt(1.0 - z * z)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def _max_pair_distance(a: np.ndarray, b: np.ndarray, chunk: int = 2048) -> tuple[float, int, int]:
    """Largest distance between a point of `a` (n, 3) and one of `b` (m, 3), in row chunks."""
    best, bi, bj = -1.0, 0, 0
    b2 = (b * b).sum(1)
    for start in range(0, len(a), chunk):
        block = a[start : start + chunk]
        d2 = (block * block).sum(1)[:, None] + b2[None, :] - 2.0 * block @ b.T
        k = int(np.argmax(d2))
        i, j = divmod(k, len(b))
        if d2[i, j] > best:
            best, bi, bj = float(d2[i, j]), start + i, j
    return float(np.sqrt(max(best, 0.0))), bi, bj


def diameter(points: np.ndarray) -> float:
    """Largest distance between two of the (n, 3) points (any unit; the same unit back).

    Up to EXACT_DIAMETER_MAX_POINTS points: exact, over all pairs of convex-hull vertices. More
    (CAD meshes of 10^5-10^6 faces): the widest of DIAMETER_DIRECTIONS projections, improved by
    exact pairs among the extreme points of the widest directions; never above the true diameter
    and at most DIAMETER_MAX_REL_ERROR (0.08 %) below it. Memory stays linear in n.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) < 2:
        raise ValueError(f"expected at least two points (n, 3), got {points.shape}")
    if len(points) <= EXACT_DIAMETER_MAX_POINTS:
        try:
            hull = trimesh.convex.convex_hull(points).vertices
        except Exception:  # flat or degenerate sets have no 3-D hull; all points then
            hull = points
        return _max_pair_distance(hull, hull)[0]
    # Projections in float32 (fast, 1e-7 relative): they only choose candidates; every distance
    # returned is computed in float64 from the points themselves.
    centred = (points - points.mean(0)).astype(np.float32)
    dirs = _half_sphere_directions(DIAMETER_DIRECTIONS).astype(np.float32)
    chunk = 8192
    lo = np.full(len(dirs), np.inf, dtype=np.float32)
    hi = np.full(len(dirs), -np.inf, dtype=np.float32)
    lo_chunk = np.zeros(len(dirs), dtype=np.int64)
    hi_chunk = np.zeros(len(dirs), dtype=np.int64)
    for c, start in enumerate(range(0, len(centred), chunk)):
        proj = centred[start : start + chunk] @ dirs.T  # (chunk, directions), 100 MB
        v_min, v_max = proj.min(0), proj.max(0)
        better_lo, better_hi = v_min < lo, v_max > hi
        lo[better_lo], lo_chunk[better_lo] = v_min[better_lo], c
        hi[better_hi], hi_chunk[better_hi] = v_max[better_hi], c
    width = (hi - lo).astype(np.float64)
    # The extreme points of the widest directions are the candidates for the farthest pair; the
    # distance among them is a true distance, so at least the widest width.
    top = np.argsort(width)[::-1][:64]
    ends = []
    for d in top:
        for c, pick in ((lo_chunk[d], np.argmin), (hi_chunk[d], np.argmax)):
            block = centred[c * chunk : (c + 1) * chunk] @ dirs[d]
            ends.append(c * chunk + int(pick(block)))
    candidates = np.unique(np.array(ends))
    best, i, _ = _max_pair_distance(points[candidates], points[candidates])
    # Walk: the farthest point from an end of the best pair, until it stops improving.
    a = points[candidates[i]]
    for _ in range(4):
        far = int(np.argmax(((points - a) ** 2).sum(1)))
        d = float(np.linalg.norm(points[far] - a))
        if d <= best * (1 + 1e-12):
            break
        best, a = d, points[far]
    return float(max(best, float(width.max()) * (1.0 - 1e-6)))  # float32 widths may round up


def simplify_mesh(mesh: trimesh.Trimesh, max_faces: int) -> trimesh.Trimesh:
    """The mesh decimated towards `max_faces` faces (quadric error metric), or the mesh itself when
    it has no more. Any unit; the surface moves by far less than a camera pixel for CAD parts.
    Meshes of long thin facets may stay above the target (all collapses left would fold faces)."""
    if len(mesh.faces) <= max_faces:
        return mesh
    import fast_simplification

    vertices, faces = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int32)
    # A pass can stop short of the target (on long thin facets it refuses collapses that would
    # fold faces over); another pass helps only while it still makes progress.
    for _ in range(3):
        before = len(faces)
        vertices, faces = fast_simplification.simplify(
            vertices, np.asarray(faces, dtype=np.int32), target_count=max_faces
        )
        if len(faces) <= max_faces or len(faces) > 0.8 * before:
            break
    simplified = trimesh.Trimesh(vertices=vertices, faces=faces, process=True)
    simplified.update_faces(simplified.nondegenerate_faces())
    simplified.remove_unreferenced_vertices()
    return simplified


def make_part_model(
    name: str,
    mesh_m: trimesh.Trimesh,
    symmetry: SymmetryParams,
    n_points: int,
    rng: np.random.Generator,
    source_unit: str,
    diameter_m: float | None = None,
) -> PartModel:
    """Build a part model from a mesh already in metres (model frame kept as in the CAD file).

    `diameter_m`: the diameter when already known (from the mesh before simplification).
    """
    points, normals = sample_surface(mesh_m.vertices, mesh_m.faces, n_points, rng)
    lo, hi = mesh_m.bounds
    return PartModel(
        name=name,
        mesh_vertices_m=np.asarray(mesh_m.vertices, dtype=np.float64),
        mesh_faces=np.asarray(mesh_m.faces, dtype=np.int64),
        points_m=points,
        normals=normals,
        diameter_m=diameter(mesh_m.vertices) if diameter_m is None else float(diameter_m),
        centre_m=(lo + hi) / 2.0,
        symmetry=symmetry,
        source_unit=source_unit,
        watertight=bool(mesh_m.is_watertight),
    )


def density_kg_m3(params: Params, name: str) -> float:
    """The part's material density (parts.<name>.density_kg_m3; DEFAULT_DENSITY_KG_M3 for a part
    the params do not list)."""
    return params.parts[name].density_kg_m3 if name in params.parts else DEFAULT_DENSITY_KG_M3


def part_mass_kg(part: PartModel, density: float) -> float:
    """The part's mass: its CAD mesh's enclosed volume (m^3) times the density (kg/m^3)."""
    return abs(float(trimesh.Trimesh(part.mesh_vertices_m, part.mesh_faces, process=False).volume)) * density
