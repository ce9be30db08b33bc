"""Gripper geometry: the tool as boxes and cylinders in its own frame, the volume it sweeps along
its approach, and signed distances of obstacle points to it.

The tool frame (every grasp and pick pose is a T_..._from_tool):
- origin: the tool centre point (TCP). Suction: the centre of the cup's lip, where it touches the
  part. Jaws: midway between the two finger pads' centres, where the part's contacts lie.
- z: the approach direction, from the gripper toward the part (a suction cup's axis, pointing
  into the surface).
- x: the jaws' closing axis; an oval suction cup's long axis (for a round cup any axis across z);
  y = z cross x.
Everything the gripper is made of lies at z <= its fingertips, behind the TCP or around it.
Lengths in metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from binpick.params import JawParams, PickParams, SuctionParams


@dataclass(frozen=True)
class Box:
    """Axis-aligned in the tool frame: lo (3,), hi (3,) corners."""

    lo: np.ndarray
    hi: np.ndarray

    def extended_back(self, back_m: float) -> Box:
        lo = self.lo.copy()
        lo[2] -= back_m
        return Box(lo, self.hi)


@dataclass(frozen=True)
class Cylinder:
    """Along the tool's z axis: radius, from z0 to z1 (z0 < z1)."""

    radius: float
    z0: float
    z1: float

    def extended_back(self, back_m: float) -> Cylinder:
        return Cylinder(self.radius, self.z0 - back_m, self.z1)


Primitive = Box | Cylinder


def suction_primitives(s: SuctionParams) -> list[Primitive]:
    """The cup (lip at z = 0; an oval cup as the box around it) and the tool behind it."""
    a, b = s.lip_half_axes_m
    cup: Primitive = (
        Box(np.array([-a, -b, -s.cup_length_m]), np.array([a, b, 0.0]))
        if s.oval
        else Cylinder(s.cup_radius_m, -s.cup_length_m, 0.0)
    )
    return [cup, Cylinder(s.tool_radius_m, -s.cup_length_m - s.tool_length_m, -s.cup_length_m)]


def jaw_opening_m(j: JawParams, width_m: float) -> float:
    """How far the fingers open to approach a grasp of this width."""
    return float(min(j.opening_max_m, width_m + 2.0 * j.open_margin_m))


def jaw_primitives(j: JawParams, opening_m: float) -> list[Primitive]:
    """Two fingers with their inner faces opening_m apart, from their tips (half a pad past the
    tool centre point) back to the palm, the palm behind them, the tool behind that."""
    half_w, tip, back = j.finger_width_m / 2.0, j.pad_m / 2.0, -j.palm_from_tcp_m
    inner = opening_m / 2.0
    outer = j.opening_max_m / 2.0 + j.finger_thickness_m
    palm_top = back - j.palm_depth_m
    return [
        Box(np.array([inner, -half_w, back]), np.array([inner + j.finger_thickness_m, half_w, tip])),
        Box(np.array([-inner - j.finger_thickness_m, -half_w, back]), np.array([-inner, half_w, tip])),
        Box(np.array([-outer, -j.palm_width_m / 2.0, palm_top]), np.array([outer, j.palm_width_m / 2.0, back])),
        Cylinder(j.tool_radius_m, palm_top - j.tool_length_m, palm_top),
    ]


def holding_force_n(params: PickParams, kind: str) -> float:
    """The most the gripper holds a part with, newtons: the suction cup's rated holding force, or
    the jaws' friction (two pads, tan(friction_deg) times the closing force each)."""
    if kind == "suction":
        return float(params.suction.holding_force_n)
    return float(2.0 * np.tan(np.radians(params.jaw.friction_deg)) * params.jaw.grip_force_n)


def contact_size_m(params: PickParams, kind: str) -> float:
    """How far across the gripper touches the part, metres: the suction cup's lip, or a jaw
    finger's width. Two grasps whose tool centre points lie closer touch much the same surface."""
    if kind == "suction":
        return float(2.0 * params.suction.cup_radius_m)
    return float(params.jaw.finger_width_m)


def gripper_primitives(params: PickParams, kind: str, width_m: float = 0.0) -> list[Primitive]:
    """The gripper of `kind` ('suction' or 'jaw', opened for a grasp of width_m) at its grasp pose."""
    if kind == "suction":
        return suction_primitives(params.suction)
    return jaw_primitives(params.jaw, jaw_opening_m(params.jaw, width_m))


def swept(primitives: list[Primitive], back_m: float) -> list[Primitive]:
    """The volume the primitives sweep moving straight along z from back_m behind to where they are."""
    return [p.extended_back(back_m) for p in primitives]


def translated_poses(T: np.ndarray, offset_m: np.ndarray, step_m: float) -> np.ndarray:
    """(k, 4, 4) the pose T (4, 4) moved along offset_m (3,, T's parent frame) in k even steps of
    at most step_m, the last at the full offset (T itself not among them): the tool's positions
    on a move out that is not along its own axis (where `swept` does not apply)."""
    offset_m = np.asarray(offset_m, dtype=np.float64)
    k = max(1, int(np.ceil(np.linalg.norm(offset_m) / step_m)))
    out = np.repeat(np.asarray(T, dtype=np.float64)[None], k, axis=0)
    out[:, :3, 3] += np.outer(np.arange(1, k + 1) / k, offset_m)
    return out


def signed_distance(points_tool: np.ndarray, primitives: list[Primitive]) -> np.ndarray:
    """(n,) signed distance of points (n, 3), tool frame, to the union of the primitives:
    negative inside, metres."""
    p = np.asarray(points_tool, dtype=np.float64)
    best = np.full(len(p), np.inf)
    for prim in primitives:
        if isinstance(prim, Box):
            centre, half = (prim.lo + prim.hi) / 2.0, (prim.hi - prim.lo) / 2.0
            q = np.abs(p - centre) - half
        else:
            zc, hz = (prim.z0 + prim.z1) / 2.0, (prim.z1 - prim.z0) / 2.0
            q = np.column_stack([np.hypot(p[:, 0], p[:, 1]) - prim.radius, np.abs(p[:, 2] - zc) - hz])
        outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
        inside = np.minimum(q.max(axis=1), 0.0)
        best = np.minimum(best, outside + inside)
    return best


def covering_spheres(primitives: list[Primitive], margin_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Spheres (centres (k, 3), tool frame; radii (k,)) whose union holds every point within
    margin_m of the primitives: a row of spheres along each primitive's z axis. For a long, thin
    tool they hold a fraction of what one bounding sphere would, so fewer obstacle points need
    an exact distance."""
    centres, radii = [], []
    for prim in primitives:
        if isinstance(prim, Box):
            xy = (prim.lo[:2] + prim.hi[:2]) / 2.0
            r = float(np.linalg.norm(prim.hi[:2] - prim.lo[:2]) / 2.0)
            z0, z1 = float(prim.lo[2]), float(prim.hi[2])
        else:
            xy, r, z0, z1 = np.zeros(2), prim.radius, prim.z0, prim.z1
        across = r + margin_m
        length = z1 - z0 + 2.0 * margin_m
        n = max(1, int(np.ceil(length / across)))
        step = length / n
        # A point within `across` of the axis and step / 2 of a centre along it is inside.
        for k in range(n):
            centres.append([xy[0], xy[1], z0 - margin_m + (k + 0.5) * step])
            radii.append(float(np.hypot(across, step / 2.0)))
    return np.array(centres, dtype=np.float64).reshape(-1, 3), np.array(radii, dtype=np.float64)


def lowest_height(primitives: list[Primitive], T_frame_from_tool: np.ndarray, plane: np.ndarray) -> float:
    """The least signed height n . x + d of the primitives (placed by T_frame_from_tool) above a
    plane (a, b, c, d) with unit normal n: negative where they reach below it."""
    n, d = np.asarray(plane[:3], dtype=np.float64), float(plane[3])
    R, t = T_frame_from_tool[:3, :3], T_frame_from_tool[:3, 3]
    n_tool = R.T @ n  # the plane normal in the tool frame
    base = float(n @ t + d)
    low = np.inf
    for prim in primitives:
        if isinstance(prim, Box):
            # The lowest corner: per axis, the end the normal points away from.
            corner = np.where(n_tool > 0, prim.lo, prim.hi)
            low = min(low, base + float(n_tool @ corner))
        else:
            across = float(np.hypot(n_tool[0], n_tool[1]))
            low = min(low, base + min(n_tool[2] * prim.z0, n_tool[2] * prim.z1) - prim.radius * across)
    return low


def surface_samples(primitives: list[Primitive], spacing_m: float) -> np.ndarray:
    """(m, 3) points on the primitives' surfaces about spacing_m apart, tool frame (for drawing)."""
    out = []
    for prim in primitives:
        if isinstance(prim, Box):
            axes = [
                np.linspace(lo, hi, max(2, int(np.ceil((hi - lo) / spacing_m)) + 1))
                for lo, hi in zip(prim.lo, prim.hi, strict=True)
            ]
            g = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
            on_face = np.any(np.isclose(g, prim.lo) | np.isclose(g, prim.hi), axis=1)
            out.append(g[on_face])
        else:
            n_around = max(8, int(np.ceil(2 * np.pi * prim.radius / spacing_m)))
            n_along = max(2, int(np.ceil((prim.z1 - prim.z0) / spacing_m)) + 1)
            a = np.linspace(0, 2 * np.pi, n_around, endpoint=False)
            z = np.linspace(prim.z0, prim.z1, n_along)
            A, Z = np.meshgrid(a, z, indexing="ij")
            out.append(np.column_stack([prim.radius * np.cos(A).ravel(), prim.radius * np.sin(A).ravel(), Z.ravel()]))
    return np.concatenate(out) if out else np.zeros((0, 3))


def surface_points(primitives: list[Primitive], spacing_m: float) -> np.ndarray:
    """(n, 3) points on the primitives' surfaces about spacing_m apart, tool frame: rings around
    each cylinder (and its end discs' rims), a grid on each box's faces."""
    out = []
    for prim in primitives:
        if isinstance(prim, Cylinder):
            z = np.linspace(prim.z0, prim.z1, max(2, int(np.ceil((prim.z1 - prim.z0) / spacing_m)) + 1))
            n = max(6, int(np.ceil(2.0 * np.pi * prim.radius / spacing_m)))
            a = 2.0 * np.pi * np.arange(n) / n
            ring = np.column_stack([prim.radius * np.cos(a), prim.radius * np.sin(a)])
            out.append(np.column_stack([np.tile(ring, (len(z), 1)), np.repeat(z, n)]))
        else:
            axes = [
                np.linspace(lo, hi, max(2, int(np.ceil((hi - lo) / spacing_m)) + 1))
                for lo, hi in zip(prim.lo, prim.hi, strict=True)
            ]
            grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
            on_face = np.any(np.isclose(grid, prim.lo) | np.isclose(grid, prim.hi), axis=1)
            out.append(grid[on_face])
    return np.concatenate(out) if out else np.zeros((0, 3))
