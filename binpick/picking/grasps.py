"""Grasps generated from a part's CAD model, in its model frame (metres), for a suction cup and a
parallel-jaw gripper, and their expansion by the part's symmetry.

Suction: a surface point is a grasp when the cup's lip finds a seal there: the dense surface
sample within the cup's radius lies within max_deviation_m of the tangent plane, its normals
within max_normal_deg of the point's normal and their mean within AXIS_MAX_DEG of it, and it
covers the lip all around (no edge or hole under the cup); the approach is the inward normal (of
a part declared a solid of revolution, the smooth surface's: see _revolution_normals), and the
cup and tool, coming along it, meet no other part of the part. Jaws: antipodal pairs: a ray into
the part from a surface point along its inward normal leaves it at the opposite contact, whose
normal must lie within friction_deg of
the line between them; the width must fit the opening; approach directions around the closing
axis are kept where fingers, palm and tool clear the part. Both rank grasps by the distance of the
TCP from the centre of mass (nearest first: the least torque on a held part), keeping grasps at
least a spacing apart so the few kept cover the part.
"""

from __future__ import annotations

import logging

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from binpick.geometry.symmetry import symmetry_transforms
from binpick.io.grasps import GraspSet, tool_frame
from binpick.io.part_model import PartModel
from binpick.params import PickParams, SuctionParams
from binpick.part.model import sample_surface
from binpick.picking.gripper import gripper_primitives, signed_distance, swept
from binpick.picking.seal import cup_seal

log = logging.getLogger(__name__)

# Sectors around the cup's lip that must each hold surface points beyond LIP_RING of its radius
# (no edge under the cup: the contact lies at least LIP_RING cos(180 / LIP_SECTORS degrees),
# 0.69 radii, from any edge, whichever way the edge runs).
LIP_SECTORS = 12
LIP_RING = 0.8
# The mean normal of the patch under the cup lies within this of the contact's normal.
AXIS_MAX_DEG = 5.0
# A solid of revolution's suction grasps are checked at this many turns about its axis.
REVOLUTION_CHECK_TURNS = 12
# Candidate surface points tried: about this many, spread over the part.
N_CANDIDATES = 1500
# The patch under the cup is read from a surface sample with about this many points per cup disc:
# a large part's sample at the ingest's fixed count (20,000 points on the 0.44 m gear shaft: about
# 11 per disc of a 5 mm cup) is too sparse to show the lip, and the patch search resamples the
# mesh, up to MAX_PATCH_POINTS points.
POINTS_PER_CUP = 6 * LIP_SECTORS
MAX_PATCH_POINTS = 1_000_000
# The part's own surface points checked against the gripper (every k-th of the dense sample).
SELF_CHECK_POINTS = 6000
# Approach directions tried around a jaw grasp's closing axis.
JAW_APPROACHES = 8
# The cup and tool keep this from the part's own surface behind the contact plane: a pose about a
# millimetre off must not set the lip on a step beside it. In bench cell two of the pipe's cups
# did not seal on poses right to 0.8 mm and 0.5 degrees: two of the lip's 16 rays met the part
# 6-8 mm up, a wall rising just beyond the cup's rim.
SELF_MARGIN_M = 0.0015
# A suction contact is kept only where the cup's lip seals on the part's mesh (seal.cup_seal)
# there and this far off it each way across the approach: the point sample's patch test passes
# contacts whose lip, at the cup's full radius, hangs into a hole or meets a rise the sample
# missed. In bench cell a ring screw's cup did not seal with its pose right to 0.2 mm: 3 of the
# lip's 16 rays fell 20 mm through the ring's eye. Of the generated grasps, 6 of the ring screw's
# 20 (18 mm cup), 24 of the pipe's 204 and 10 of the T-joint's 198 failed this.
SEAL_OFFSET_M = 0.001
# Symmetric duplicates: grasps this close (TCP, metres; axes, degrees) are one.
SAME_POSITION_M = 0.001
SAME_AXIS_DEG = 5.0
# A revolution symmetry expands grasps by this many rotations.
REVOLUTION_GRASP_STEPS = 24


def centre_of_mass(part: PartModel) -> np.ndarray:
    """(3,) model frame: the solid's centre of mass when the mesh is closed, else the surface's."""
    mesh = trimesh.Trimesh(part.mesh_vertices_m, part.mesh_faces, process=False)
    if part.watertight and mesh.volume > 0:
        return np.asarray(mesh.center_mass, dtype=np.float64)
    return np.asarray(part.points_m, dtype=np.float64).mean(axis=0)


def _candidates(points: np.ndarray, n: int) -> np.ndarray:
    """Indices of about n points spread evenly over the sample (every k-th of a voxel-sorted order)."""
    step = max(1, len(points) // n)
    return np.arange(0, len(points), step)


def _spread(order: np.ndarray, positions: np.ndarray, spacing_m: float, limit: int) -> list[int]:
    """Greedy: walk `order` best first, keep a position at least spacing_m from every kept one."""
    kept: list[int] = []
    for i in order:
        if len(kept) >= limit:
            break
        if not kept or np.min(np.linalg.norm(positions[kept] - positions[i], axis=1)) >= spacing_m:
            kept.append(int(i))
    return kept


def suction_grasps(part: PartModel, params: PickParams) -> GraspSet:
    """Suction grasps on patches flat enough for the cup, best first (params.max_grasps at most);
    an oval cup's long axis (the tool's x) along the patch's least curved direction."""
    s = params.suction
    half_length, half_width = s.lip_half_axes_m
    pts = np.asarray(part.points_m, dtype=np.float64)
    nrm = np.asarray(part.normals, dtype=np.float64)
    patch_pts, patch_nrm = patch_surface(part, s.cup_radius_m)
    tree = cKDTree(patch_pts)
    cos_max = np.cos(np.radians(s.max_normal_deg))
    cos_axis = np.cos(np.radians(AXIS_MAX_DEG))
    body = swept(gripper_primitives(params, "suction"), params.pregrasp_distance_m)
    com = centre_of_mass(part)
    rays = trimesh.ray.ray_triangle.RayMeshIntersector(
        trimesh.Trimesh(part.mesh_vertices_m, part.mesh_faces, process=False)
    )
    revolution = part.symmetry.kind == "revolution"
    smooth = _revolution_normals(part, nrm) if revolution else nrm
    # The turns about the axis, identity left out (the rotations come before any flips).
    turns = (
        symmetry_transforms(part.symmetry, REVOLUTION_CHECK_TURNS)[1:REVOLUTION_CHECK_TURNS]
        if revolution
        else np.zeros((0, 4, 4))
    )

    def patch(c: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The patch under a cup at c (3,) with outward axis n (3,): its points relative to c, their
        normals and the lip's long axis (3,; across n), or None when it is too small, faces away
        or is not flat enough."""
        near = np.asarray(tree.query_ball_point(c, half_length))
        # The patch under the cup is the surface facing it: a thin wall's far side is not.
        near = near[patch_nrm[near] @ n > 0.0] if len(near) else near
        if len(near) < 3 * LIP_SECTORS:
            return None
        q, qn = patch_pts[near] - c, patch_nrm[near]
        x = lip_axis(qn, n) if s.oval else _across(n)
        if s.oval:
            inside = ((q @ x) / half_length) ** 2 + ((q @ np.cross(n, x)) / half_width) ** 2 <= 1.0
            if inside.sum() < 3 * LIP_SECTORS:
                return None
            q, qn = q[inside], qn[inside]
        # The surface under the cup faces where its centre does: the patch's mean normal (the
        # samples are spread evenly by area) within AXIS_MAX_DEG of the point's. On a coarsely
        # tessellated curve (the gear shaft's facets turn by 14 degrees) this keeps contacts near
        # the middle of a facet, where a pose a millimetre off still lands on it; a contact near
        # a fold, or on a patch partly over another face, would meet the surface turned away.
        mean = qn.mean(axis=0)
        if mean @ n < cos_axis * np.linalg.norm(mean):
            return None
        if np.max(np.abs(q @ n)) > s.max_deviation_m or np.min(qn @ n) < cos_max:
            return None
        return q, qn, x

    good: list[int] = []
    long_axes: dict[int, np.ndarray] = {}
    for i in _candidates(pts, N_CANDIDATES):
        c, n = pts[i], smooth[i]
        found = patch(c, n)
        if found is None:
            continue
        # A solid of revolution's pose leaves its turn about the axis open: the grasp must hold
        # wherever around the axis it lands (not on a gear tooth that only the CAD's turn has there).
        if any(patch(S[:3, :3] @ c + S[:3, 3], S[:3, :3] @ n) is None for S in turns):
            continue
        q, qn, x = found
        # The lip all around: points in every sector of the outer ring of the lip (an oval's
        # ring and sectors measured in the lip's own scale along and across it).
        y = np.cross(n, x)
        u, v = (q @ x) / half_length, (q @ y) / half_width
        ring = np.hypot(u, v) > LIP_RING
        if ring.sum() < LIP_SECTORS:
            continue
        sector = ((np.arctan2(v[ring], u[ring]) + np.pi) / (2 * np.pi) * LIP_SECTORS).astype(int) % LIP_SECTORS
        if len(np.unique(sector)) < LIP_SECTORS:
            continue
        # Cup and tool coming along the inward normal meet no other part of the part: points
        # behind the contact plane (toward the gripper) within SELF_MARGIN_M of the swept volume.
        T = tool_frame(c, -n, x if s.oval else None)
        local = (pts - c) @ T[:3, :3]
        behind = local[:, 2] < -s.max_deviation_m
        if behind.any() and np.min(signed_distance(local[behind], body)) < SELF_MARGIN_M:
            continue
        if not _seals(rays, T, s):
            continue
        good.append(int(i))
        long_axes[int(i)] = x
    if not good:
        return GraspSet.empty("suction")
    good_arr = np.array(good)
    order = good_arr[np.argsort(np.linalg.norm(pts[good_arr] - com, axis=1), kind="stable")]
    kept = _spread(order, pts, s.cup_radius_m, params.max_grasps)
    Ts = np.array([tool_frame(pts[i], -smooth[i], long_axes[i] if s.oval else None) for i in kept])
    return GraspSet("suction", [f"s{k}" for k in range(len(kept))], Ts, np.zeros(len(kept)))


def _across(n: np.ndarray) -> np.ndarray:
    """A unit direction (3,) across the unit axis n (3,), as tool_frame picks a round cup's x."""
    e = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    return e / np.linalg.norm(e)


def lip_axis(normals: np.ndarray, n: np.ndarray) -> np.ndarray:
    """The direction (3,; unit, across the unit axis n (3,)) along which the surface with these
    unit normals (m, 3) curves least: the tangent direction the normals vary least along (a
    cylinder's axis, whatever its radius). An oval cup laid along it seals where one laid across
    would not."""
    e1 = _across(n)
    e2 = np.cross(n, e1)
    t = normals @ np.column_stack([e1, e2])  # (m, 2): the normals' tilt in the tangent plane
    _, vectors = np.linalg.eigh(t.T @ t)
    along = vectors[0, 0] * e1 + vectors[1, 0] * e2  # the smallest eigenvalue's vector
    return along / np.linalg.norm(along)


def _seals(rays, T_model_from_tool: np.ndarray, suction: SuctionParams) -> bool:
    """Whether the cup's lip seals on the mesh (rays: its intersector) at the tool pose (4, 4, model
    frame) and SEAL_OFFSET_M off it along the tool's x and y, both ways."""
    for dx, dy in ((0.0, 0.0), (1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0)):
        T = T_model_from_tool.copy()
        T[:3, 3] += SEAL_OFFSET_M * (dx * T[:3, 0] + dy * T[:3, 1])
        if cup_seal(rays, T, suction) is not True:
            return False
    return True


def _revolution_normals(part: PartModel, normals: np.ndarray) -> np.ndarray:
    """Unit normals (n, 3) of a part declared a solid of revolution: the facet normals (n, 3) at
    its sample points with their component around the axis removed, the normals of the smooth
    surface the facets approximate. A pose of such a part says nothing about its turn about the
    axis, so a grasp lands anywhere around it on the real part: on the gear shaft's 14 degree
    facets, an approach along its own facet's normal met the facet there up to 14 degrees off,
    one along the smooth normal at most half that."""
    axis = np.asarray(part.symmetry.axis, dtype=np.float64)
    axis /= np.linalg.norm(axis)
    radial = np.asarray(part.points_m, dtype=np.float64) - np.asarray(part.symmetry.origin_m, dtype=np.float64)
    radial -= np.outer(radial @ axis, axis)
    r = np.linalg.norm(radial, axis=1)
    around = np.cross(axis, radial / np.maximum(r, 1e-12)[:, None])
    out = normals - np.einsum("ij,ij->i", normals, around)[:, None] * around
    length = np.linalg.norm(out, axis=1)
    # On the axis (an end face's centre) the direction around is undefined: the facet's normal.
    ok = (r > 1e-9) & (length > 1e-9)
    out[ok] /= length[ok, None]
    out[~ok] = normals[~ok]
    return out


def patch_surface(part: PartModel, cup_radius_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Surface points (n, 3) and unit normals (n, 3), model frame, dense enough to read the patch
    under a cup of this radius: the part's own sample, or a sample of its mesh with about
    POINTS_PER_CUP points per cup disc (a fixed seed: the grasps are a function of the part)."""
    pts = np.asarray(part.points_m, dtype=np.float64)
    nrm = np.asarray(part.normals, dtype=np.float64)
    mesh = trimesh.Trimesh(part.mesh_vertices_m, part.mesh_faces, process=False)
    needed = int(np.ceil(mesh.area * POINTS_PER_CUP / (np.pi * cup_radius_m**2)))
    if needed <= len(pts):
        return pts, nrm
    n = min(needed, MAX_PATCH_POINTS)
    log.info("%s: %d surface points for the suction patches (the part's sample holds %d)", part.name, n, len(pts))
    dense, dense_nrm = sample_surface(part.mesh_vertices_m, part.mesh_faces, n, np.random.default_rng(0))
    return dense.astype(np.float64), dense_nrm.astype(np.float64)


def jaw_grasps(part: PartModel, params: PickParams) -> GraspSet:
    """Antipodal parallel-jaw grasps within the opening range, best first (params.max_grasps at most)."""
    j = params.jaw
    mesh = trimesh.Trimesh(part.mesh_vertices_m, part.mesh_faces, process=False)
    pts = np.asarray(part.points_m, dtype=np.float64)
    nrm = np.asarray(part.normals, dtype=np.float64)
    solid = pts[_candidates(pts, SELF_CHECK_POINTS)]
    idx = _candidates(pts, N_CANDIDATES)
    origins = pts[idx] - 1e-6 * nrm[idx]
    # Every surface the ray crosses: across a hollow part (a pipe) the far contact is on the
    # outside again, past the bore.
    hits, rays, tris = mesh.ray.intersects_location(origins, -nrm[idx], multiple_hits=True)
    cos_f = np.cos(np.radians(j.friction_deg))
    face_normals = mesh.face_normals
    pairs: list[tuple[np.ndarray, np.ndarray]] = []
    for hit, ray, tri in zip(hits, rays, tris, strict=True):
        p, n = pts[idx[ray]], nrm[idx[ray]]
        width = float(np.linalg.norm(hit - p))
        # The opening must close on it (at least opening_min_m) and open past it; the far
        # contact faces away from the near one, within the friction cone.
        if not max(j.opening_min_m, 1e-4) <= width < j.opening_max_m or float(face_normals[tri] @ n) > -cos_f:
            continue
        pairs.append((p, hit))
    if not pairs:
        return GraspSet.empty("jaw")
    centres = np.array([(a + b) / 2.0 for a, b in pairs])
    com = centre_of_mass(part)
    order = np.argsort(np.linalg.norm(centres - com, axis=1), kind="stable")
    spacing = max(0.05 * part.diameter_m, 0.002)
    Ts: list[np.ndarray] = []
    widths: list[float] = []
    for i in _spread(order, centres, spacing, 4 * params.max_grasps):
        a, b = pairs[i]
        closing = (b - a) / np.linalg.norm(b - a)
        width = float(np.linalg.norm(b - a))
        body = swept(gripper_primitives(params, "jaw", width), params.pregrasp_distance_m)
        helper = np.array([1.0, 0.0, 0.0]) if abs(closing[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        u = np.cross(closing, helper)
        u /= np.linalg.norm(u)
        v = np.cross(closing, u)
        for k in range(JAW_APPROACHES):
            angle = 2 * np.pi * k / JAW_APPROACHES
            T = tool_frame(centres[i], np.cos(angle) * u + np.sin(angle) * v, closing)
            local = (solid - centres[i]) @ T[:3, :3]
            if np.min(signed_distance(local, body)) < 0.0:
                continue
            Ts.append(T)
            widths.append(width)
        if len(Ts) >= params.max_grasps:
            break
    Ts, widths = Ts[: params.max_grasps], widths[: params.max_grasps]
    if not Ts:
        return GraspSet.empty("jaw")
    return GraspSet("jaw", [f"j{k}" for k in range(len(Ts))], np.array(Ts), np.array(widths))


def generate_grasps(part: PartModel, params: PickParams) -> dict[str, GraspSet]:
    """Both kinds, generated from the part model."""
    return {"suction": suction_grasps(part, params), "jaw": jaw_grasps(part, params)}


def expand_by_symmetry(grasps: GraspSet, symmetries: np.ndarray) -> GraspSet:
    """Each grasp under every symmetry transform S (m, 4, 4), model frame (S @ T_model_from_tool),
    near-duplicates dropped; the original order first, then the images of each grasp in turn.
    Ids of images are '<id>@<k>' for the k-th transform."""
    if len(grasps) == 0 or len(symmetries) <= 1:
        return grasps
    ids, Ts, widths = list(grasps.ids), list(grasps.T_model_from_tool), list(grasps.width_m)
    cos_same = np.cos(np.radians(SAME_AXIS_DEG))
    for gid, T, w in zip(grasps.ids, grasps.T_model_from_tool, grasps.width_m, strict=True):
        for k, S in enumerate(symmetries[1:], start=1):
            image = S @ T
            stack = np.array(Ts)
            same = (np.linalg.norm(stack[:, :3, 3] - image[:3, 3], axis=1) < SAME_POSITION_M) & (
                stack[:, :3, 2] @ image[:3, 2] > cos_same
            )
            if grasps.kind == "jaw":  # a jaw grasp and its image with the fingers swapped are one grasp
                same &= np.abs(stack[:, :3, 0] @ image[:3, 0]) > cos_same
            if same.any():
                continue
            ids.append(f"{gid}@{k}")
            Ts.append(image)
            widths.append(w)
    return GraspSet(grasps.kind, ids, np.array(Ts), np.array(widths))
