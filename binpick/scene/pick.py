"""Scene step `pick`: picks for the posed parts (binpick/picking/plan.py) among what the capture measured."""

from __future__ import annotations

import numpy as np

from binpick.cell.bin_box import BinBox
from binpick.io.cloud import CleanCloud
from binpick.io.grasps import GraspSet
from binpick.io.part_model import PartModel
from binpick.io.poses import PartPose
from binpick.params import ImportCaptureParams, PickParams
from binpick.picking.plan import PickPlan, plan_picks
from binpick.registration.visibility import DepthView


def pick(
    cloud: CleanCloud,
    poses: list[PartPose],
    part: PartModel,
    grasps: GraspSet,
    params: PickParams,
    import_params: ImportCaptureParams,
) -> PickPlan:
    """Picks for the posed parts (binpick/picking/plan.py): obstacles are everything the capture
    measured (its z-buffer; the cleaned points when it has none), the support plane, the bin
    when params give it, and the other parts at their poses."""
    captured = DepthView(cloud.seen_depth_m, cloud.seen_K).points_m()
    if len(captured) == 0:
        captured = cloud.points_m
    T = np.array([p.T_cam_from_model for p in poses]).reshape(-1, 4, 4)
    scores = np.array([p.score for p in poses], dtype=np.float64)
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
    )
