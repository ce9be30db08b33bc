"""Scene step `pick`: picks for the posed parts (binpick/picking/plan.py) among what the capture measured."""

from __future__ import annotations

import numpy as np

from binpick.cell.bin_box import BinBox
from binpick.cell.retries import FailedGrips, near_failed
from binpick.io.cloud import CleanCloud
from binpick.io.grasps import GraspSet
from binpick.io.part_model import PartModel
from binpick.io.poses import PartPose
from binpick.params import DEFAULT_DENSITY_KG_M3, CellParams, ImportCaptureParams, PickParams
from binpick.part.model import part_mass_kg
from binpick.picking.arm import ArmPlanner
from binpick.picking.gripper import gripper_primitives, holding_force_n, surface_points
from binpick.picking.plan import PickPlan, plan_picks
from binpick.registration.visibility import DepthView
from binpick.robot.arm import load_arm
from binpick.robot.payload import Payload

# The gripper's surface is sampled this finely for the arm's check of its moves outside the approach.
TOOL_SAMPLE_SPACING_M = 0.005


def pick(
    cloud: CleanCloud,
    poses: list[PartPose],
    part: PartModel,
    grasps: GraspSet,
    params: PickParams,
    import_params: ImportCaptureParams,
    cell: CellParams | None = None,
    q_from: np.ndarray | None = None,
    extra_obstacles_m: np.ndarray | None = None,
    density_kg_m3: float = DEFAULT_DENSITY_KG_M3,
    max_picks: int | None = None,
    failed: FailedGrips | None = None,
) -> PickPlan:
    """Picks for the posed parts (binpick/picking/plan.py): obstacles are everything the capture
    measured (its z-buffer; the cleaned points when it has none), the support plane, the bin
    when params give it, and the other parts at their poses. With a cell whose arm is set and
    the camera's place in the base frame (pick.T_base_from_cam), each pick is checked for the
    whole arm (binpick/picking/arm.py), starting from q_from (default: the cell's home).
    extra_obstacles_m (k, 3), camera frame: more obstacles (another kind of part's posed body in
    a mixed bin, binpick/scene/mixed.py). density_kg_m3: the part's material; with the gripper's
    hold it sets how fast the arm may carry the part, or that it cannot (binpick/robot/payload.py).
    max_picks: only the first this many picks are planned (plan_picks; None: every part's).
    failed: the grips that failed in this bin (binpick/cell/retries.py): the parts left alone are
    not picked now, and no grasp goes where a grip failed."""
    seen = DepthView(cloud.seen_depth_m, cloud.seen_K)
    planner = None
    if cell is not None and cell.arm is not None and params.T_base_from_cam is not None:
        planner = ArmPlanner(
            load_arm(cell.arm),
            cell,
            np.asarray(params.T_base_from_cam, dtype=float),
            seen,
            cloud.wall_planes,
            params.pregrasp_distance_m,
            params.retreat_distance_m,
            surface_points(gripper_primitives(params, grasps.kind, params.jaw.opening_max_m), TOOL_SAMPLE_SPACING_M),
            params.clearance_m,
            payload=Payload(part_mass_kg(part, density_kg_m3), holding_force_n(params, grasps.kind)),
            oval_cup=grasps.kind == "suction" and params.suction.oval,
        )
        q_from = np.asarray(cell.home_q_rad if q_from is None else q_from, dtype=float)
    captured = seen.points_m()
    if len(captured) == 0:
        captured = cloud.points_m
    if extra_obstacles_m is not None and len(extra_obstacles_m):
        captured = np.concatenate([np.asarray(captured, dtype=np.float64), np.asarray(extra_obstacles_m, float)])
    T = np.array([p.T_cam_from_model for p in poses]).reshape(-1, 4, 4)
    scores = np.array([p.score for p in poses], dtype=np.float64)
    skip = None
    if failed is not None:
        skip = near_failed(T[:, :3, :3] @ part.centre_m + T[:, :3, 3], failed.centres_m(), part.diameter_m)
    shares = np.array([np.nan if p.seen_through is None else p.seen_through for p in poses], dtype=np.float64)
    return plan_picks(
        T,
        scores,
        grasps,
        part.points_m,
        part.normals,
        part.centre_m,
        captured,
        cloud.floor_plane,
        params,
        BinBox.of_import(import_params),
        shares,
        planner,
        q_from,
        max_picks,
        skip,
        failed.contacts_m() if failed is not None else None,
        cloud.wall_planes,
        import_params.plane_threshold_m,
    )
