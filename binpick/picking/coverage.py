"""Which ways a part comes to rest leave it without a grasp: for each stable pose of the part on a
flat floor (trimesh's quasi-static estimate, with the probability that a dropped part ends in it),
the grasps whose approach lies within a cone about straight down. A part lying with no grasp in
reach stays in the bin, whatever the vision does: the IC-BIN coffee cup's scanned lid offers a
10 mm suction cup no seal, so a cup standing lid-up has none (docs/guide/picks.md).

Frames: the model's (metres); the floor frame of a stable pose has its z up, out of the floor.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from binpick.geometry.symmetry import symmetry_transforms
from binpick.io.grasps import GraspSet
from binpick.io.part_model import PartModel
from binpick.params import PickParams
from binpick.picking.grasps import REVOLUTION_GRASP_STEPS, centre_of_mass, expand_by_symmetry, suction_grasps

# Stable poses whose up axes (in the model frame) lie within this of each other are one side when
# reported: a solid of revolution lying on its flank has dozens, a few degrees apart.
SAME_SIDE_DEG = 20.0
# Smaller suction cups tried when a side has no grasp: this much less radius each time, down to
# this radius (a 4 mm lip), at most this many tries (each generates the grasps again: seconds).
SMALLER_CUP_STEP_M = 0.001
SMALLEST_CUP_M = 0.002
SMALLER_CUP_TRIES = 3


@dataclass(frozen=True)
class RestingSide:
    """A way the part comes to rest: up_model (3,), the unit direction of the model frame that
    faces up, away from the floor; probability: the share of drops that end so (summed over the
    stable poses grouped into it); n_grasps: the fewest grasps within the cone of any of them."""

    up_model: np.ndarray
    probability: float
    n_grasps: int


def stable_poses(part: PartModel) -> tuple[np.ndarray, np.ndarray]:
    """(n, 4, 4) T_floor_from_model of the part resting on a floor (z = 0, z up) and (n,) their
    probabilities (summing to 1), most likely first: trimesh's stable poses of the mesh's convex
    hull about the part's centre of mass."""
    mesh = trimesh.Trimesh(part.mesh_vertices_m, part.mesh_faces, process=False)
    T, probability = trimesh.poses.compute_stable_poses(
        mesh, center_mass=centre_of_mass(part), sigma=0.0, n_samples=1, threshold=0.0
    )
    probability = np.asarray(probability, dtype=np.float64)
    total = float(probability.sum())
    return np.asarray(T, dtype=np.float64).reshape(-1, 4, 4), probability / total if total > 0 else probability


def grasps_in_cone(T_floor_from_model: np.ndarray, approach_model: np.ndarray, cone_deg: float) -> np.ndarray:
    """(n,) for each resting pose (n, 4, 4), how many grasps (approach directions (k, 3), unit,
    model frame: the tool's z, pointing into the part) come within cone_deg of straight down."""
    approach_floor = np.einsum("nij,kj->nki", T_floor_from_model[:, :3, :3], approach_model)
    return np.sum(-approach_floor[..., 2] >= np.cos(np.radians(cone_deg)) - 1e-12, axis=1)


def resting_sides(T_floor_from_model: np.ndarray, probability: np.ndarray, n_grasps: np.ndarray) -> list[RestingSide]:
    """The resting poses grouped into sides (up axes within SAME_SIDE_DEG of the group's most
    likely pose), most likely first; each side's grasp count is its poorest pose's."""
    up_model = T_floor_from_model[:, 2, :3]  # the model-frame direction the floor's z is: row 2 of R
    order = np.argsort(-probability, kind="stable")
    sides: list[tuple[np.ndarray, float, int]] = []
    cos_same = np.cos(np.radians(SAME_SIDE_DEG))
    for i in order:
        for k, (axis, p, n) in enumerate(sides):
            if float(axis @ up_model[i]) >= cos_same:
                sides[k] = (axis, p + float(probability[i]), min(n, int(n_grasps[i])))
                break
        else:
            sides.append((up_model[i] / np.linalg.norm(up_model[i]), float(probability[i]), int(n_grasps[i])))
    return [RestingSide(axis, p, n) for axis, p, n in sides]


def grasp_sides(
    T_floor_from_model: np.ndarray, probability: np.ndarray, grasps: GraspSet, cone_deg: float
) -> list[RestingSide]:
    """The resting sides (resting_sides) with the grasps' counts within cone_deg of straight down."""
    approach = grasps.T_model_from_tool[:, :3, 2]
    return resting_sides(T_floor_from_model, probability, grasps_in_cone(T_floor_from_model, approach, cone_deg))


def covered_share(sides: list[RestingSide]) -> float:
    """The share of drops that end with at least one grasp in the cone."""
    # Rounded: the probabilities' float sum misses 1 by rounding steps (0.9999999999999997).
    return round(float(min(1.0, sum(s.probability for s in sides if s.n_grasps > 0))), 6)


def describe_side(up_model: np.ndarray) -> str:
    """'its model +z up' (the nearest model axis) or the direction's components."""
    k = int(np.argmax(np.abs(up_model)))
    if abs(up_model[k]) >= np.cos(np.radians(SAME_SIDE_DEG)):
        return f"its model {'+' if up_model[k] > 0 else '-'}{'xyz'[k]} up"
    return "its model direction ({:.2f}, {:.2f}, {:.2f}) up".format(*up_model)


def widest_cone_deg(params: PickParams) -> float:
    """The widest approach the picker tries: the fallback cone when set, else the approach cone."""
    return max(params.approach_cone_deg, params.fallback_cone_deg or 0.0)


def suction_sides(
    part: PartModel, params: PickParams, T_floor_from_model: np.ndarray, probability: np.ndarray
) -> list[RestingSide]:
    """The resting sides with the suction grasps params give (generated from the model and
    expanded by its symmetry) counted within the widest cone."""
    grasps = expand_by_symmetry(
        suction_grasps(part, params), symmetry_transforms(part.symmetry, REVOLUTION_GRASP_STEPS)
    )
    return grasp_sides(T_floor_from_model, probability, grasps, widest_cone_deg(params))


def smaller_cup_radii(cup_radius_m: float) -> list[float]:
    """The suction cup radii (metres) tried below cup_radius_m, largest first: SMALLER_CUP_STEP_M
    apart, down to SMALLEST_CUP_M, SMALLER_CUP_TRIES at most (empty for a cup already that small)."""
    steps = (cup_radius_m - k * SMALLER_CUP_STEP_M for k in range(1, SMALLER_CUP_TRIES + 1))
    return [r for r in steps if r >= SMALLEST_CUP_M - 1e-9]


def smaller_cup_covering(
    part: PartModel,
    params: PickParams,
    T_floor_from_model: np.ndarray,
    probability: np.ndarray,
    min_probability: float,
) -> float | None:
    """The largest suction cup radius (metres) of smaller_cup_radii whose grasps reach every side
    at least min_probability likely; None when none of those does. A smaller lip seals on narrower flats
    (a lid's rim between its recess and its edge) but holds less (force goes with its area)."""
    for r in smaller_cup_radii(params.suction.cup_radius_m):
        smaller = params.model_copy(update={"suction": params.suction.model_copy(update={"cup_radius_m": r})})
        sides = suction_sides(part, smaller, T_floor_from_model, probability)
        if all(s.n_grasps > 0 for s in sides if s.probability >= min_probability):
            return r
    return None
