"""Whether a suction cup's lip seals on a part's mesh: rays around the lip cast onto the true
surface. The grasp generator keeps only contacts where it does (picking/grasps.py); the simulated
cell judges each grip by it (cell/sim_contact.py). Model frame of the part, metres.
"""

from __future__ import annotations

import numpy as np

from binpick.geometry.transforms import invert_T, transform_points
from binpick.params import SuctionParams

# Rays around the cup's lip that test its seal on the true mesh (an oval lip: this many per
# multiple of its width in its length, so they lie as close along its long sides).
LIP_RAYS = 16
# The planned contact lies within this of the part's true surface along the approach, or the
# cup meets air (or presses in).
CONTACT_TOLERANCE_M = 0.002
# The rays start this far behind the lip (a cup pressed slightly in still finds the surface).
RAY_BACK_M = 0.02


def contact_tolerance_m(suction: SuctionParams) -> float:
    """How far along the approach the part's true surface may lie from the planned contact,
    nearer or farther, for the cup's lip to meet it: CONTACT_TOLERANCE_M, plus half a bellows
    cup's travel (the tool centre point is its lip half pressed)."""
    return CONTACT_TOLERANCE_M + suction.stroke_m / 2.0


def cup_seal(rays, T_model_from_tool: np.ndarray, suction: SuctionParams) -> bool | None:
    """Whether the cup's lip seals on a part's true mesh at this tool pose (4, 4; the tool frame in
    the part's model frame; z the approach; an oval lip's length along x): None when the cup's
    centre does not meet the part within contact_tolerance_m (not this part), False when it meets
    it but the lip hangs over an edge or the lip's surface is not flat within max_deviation_m and
    facing within max_normal_deg, True when it seals. rays: a trimesh ray intersector of the part's mesh."""
    a, b = suction.lip_half_axes_m
    n_rays = LIP_RAYS * int(np.ceil(a / b - 1e-9))
    angles = 2.0 * np.pi * np.arange(n_rays) / n_rays
    lip = np.column_stack([a * np.cos(angles), b * np.sin(angles), np.zeros(n_rays)])
    origins = transform_points(T_model_from_tool, np.vstack([[0.0, 0.0, 0.0], lip]) - np.array([0.0, 0.0, RAY_BACK_M]))
    direction = np.broadcast_to(T_model_from_tool[:3, 2], origins.shape)
    hits, hit_rays, _ = rays.intersects_location(origins, direction, multiple_hits=False)
    if len(hit_rays) == 0 or 0 not in hit_rays:
        return None
    depth = np.full(n_rays + 1, np.nan)
    depth[hit_rays] = (hits - origins[hit_rays]) @ T_model_from_tool[:3, 2] - RAY_BACK_M
    if abs(depth[0]) > contact_tolerance_m(suction):
        return None
    if len(hit_rays) < n_rays + 1:
        return False  # the lip hangs over an edge
    lip_hits = transform_points(invert_T(T_model_from_tool), hits[np.argsort(hit_rays)][1:])
    centre = lip_hits.mean(axis=0)
    _, _, vt = np.linalg.svd(lip_hits - centre)
    normal = vt[2] * np.sign(vt[2, 2] or 1.0)
    flat = np.max(np.abs((lip_hits - centre) @ vt[2])) <= suction.max_deviation_m
    facing = np.degrees(np.arccos(min(1.0, abs(normal[2])))) <= suction.max_normal_deg
    return bool(flat and facing)
