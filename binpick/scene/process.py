"""The scene path as one call: a part's models loaded once (`PartModels.load`), the seeds of
each step (`SceneSeeds`), and `process`, which runs clean, segment, register and pick on a capture."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from binpick.cell.retries import FailedGrips
from binpick.io.cloud import CleanCloud
from binpick.io.grasps import GraspSet, load_grasps
from binpick.io.part_model import PartModel, load_part_model
from binpick.io.poses import PartPose
from binpick.io.ppf_model import PPFModel, load_ppf_model
from binpick.io.verification import Verification, load_verification
from binpick.network.infer import Segmenter, load_segmenter
from binpick.params import DEFAULT_DENSITY_KG_M3, CellParams, ImportCaptureParams, Params, PickParams, RegisterParams
from binpick.part.model import density_kg_m3
from binpick.picking.plan import PickPlan
from binpick.scene.clean import clean
from binpick.scene.pick import pick
from binpick.scene.register import Registration, register, with_verification
from binpick.scene.segment import segment
from binpick.seeding import SceneSeeds

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PartModels:
    """Everything the scene path needs for one part, loaded once: the part model, its PPF model,
    its segmenter (None: registration over the whole scene only, no network) and the settings of
    the import and registration steps (the part's own overrides applied)."""

    part: PartModel
    ppf: PPFModel
    segmenter: Segmenter | None
    import_params: ImportCaptureParams
    register_params: RegisterParams
    grasps: GraspSet | None = None  # None: no picks
    pick_params: PickParams | None = None
    cell_params: CellParams | None = None  # None: picks checked for the gripper only
    density_kg_m3: float = DEFAULT_DENSITY_KG_M3  # the part's material: its weight on the gripper

    @classmethod
    def load(
        cls,
        params: Params,
        part_model: str | Path,
        ppf_model: str | Path,
        checkpoint: str | Path | None,
        grasps: str | Path | None = None,
        verification: str | Path | None = None,
    ) -> PartModels:
        """params: resolved for the part (load_params(path, part)); checkpoint None: no network;
        grasps: the part's grasp file (None: no picks); verification: the part's verification.json
        (absent: the thresholds an older checkpoint carries, else the defaults)."""
        segmenter = load_segmenter(checkpoint, params.segment) if checkpoint is not None else None
        register_params = params.registration
        if segmenter is None and register_params.mode != "whole_scene":
            log.info("no network for the part: registration over the whole scene")
            register_params = register_params.model_copy(update={"mode": "whole_scene"})
        part = load_part_model(part_model)
        return cls(
            part=part,
            ppf=load_ppf_model(ppf_model),
            segmenter=segmenter,
            import_params=params.import_capture,
            register_params=with_verification(register_params, chosen_verification(verification, segmenter)),
            grasps=load_grasps(grasps, params.pick.oval_cup)[params.pick.gripper] if grasps is not None else None,
            pick_params=params.pick,
            cell_params=params.cell,
            density_kg_m3=density_kg_m3(params, part.name),
        )


def chosen_verification(path: str | Path | None, segmenter: Segmenter | None) -> Verification | None:
    """The verification thresholds chosen for a part: its verification.json when there is one,
    else those an older checkpoint carries (chosen at training), else None (the defaults)."""
    if path is not None and Path(path).is_file():
        return load_verification(path)
    settings = segmenter.settings if segmenter is not None else None
    if settings is None or settings.max_seen_through is None:
        return None
    return Verification(settings.max_seen_through, settings.min_visible_support)


@dataclass(frozen=True)
class SceneResult:
    """The scene path's answer for one capture; timings_s per step (clean_s, segment_s, register_s)."""

    cloud: CleanCloud
    labels: np.ndarray
    registration: Registration
    timings_s: dict[str, float] = field(default_factory=dict)
    picks: PickPlan | None = None

    @property
    def poses(self) -> list[PartPose]:
        return self.registration.poses


def process(
    xyz_m: np.ndarray,
    rgb: np.ndarray | None,
    frame_shape: tuple[int, int] | None,
    models: PartModels,
    seeds: SceneSeeds,
    q_from: np.ndarray | None = None,
    max_picks: int | None = None,
    failed: FailedGrips | None = None,
) -> SceneResult:
    """clean, segment (unless the models have no segmenter), register and (when the models carry
    grasps) pick one capture; q_from: the arm's joint angles when the arm is checked (default:
    cell.home_q_rad); max_picks: only the first this many picks planned (a cell executes one);
    failed: the grips that failed in this bin, parts and places not picked now (cell/retries.py)."""
    t0 = time.perf_counter()
    cloud = clean(xyz_m, rgb, frame_shape, models.import_params, seeds.clean)
    t1 = time.perf_counter()
    segments = segment(cloud, models.segmenter, seeds.segment) if models.segmenter is not None else None
    t2 = time.perf_counter()
    registration = register(
        cloud,
        segments.labels if segments is not None else None,
        models.ppf,
        models.register_params,
        seeds.register,
        segments.is_part if segments is not None else None,
    )
    t3 = time.perf_counter()
    plan = None
    if models.grasps is not None and models.pick_params is not None:
        plan = pick(
            cloud,
            registration.poses,
            models.part,
            models.grasps,
            models.pick_params,
            models.import_params,
            models.cell_params,
            q_from,
            density_kg_m3=models.density_kg_m3,
            max_picks=max_picks,
            failed=failed,
        )
    t4 = time.perf_counter()
    labels = segments.labels if segments is not None else np.full(len(cloud.points_m), -1, np.int32)
    timings = {
        "clean_s": t1 - t0,
        "segment_s": t2 - t1,
        "register_s": t3 - t2,
        **({"pick_s": t4 - t3} if plan is not None else {}),
    }
    return SceneResult(cloud, labels, registration, timings, plan)
