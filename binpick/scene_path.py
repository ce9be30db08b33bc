"""The scene path, in process: a capture's arrays in, the cleaned cloud, its segments and a pose
per part out. The part's models are loaded once (`PartModels.load`) and serve any number of
captures; the DVC stages, the benchmarks and a resident service all call these functions, so
they cannot drift apart.

Steps: `clean` (range, region, floor and walls, the network's voxel grid and normals),
`segment` (FPCC instance labels), `register` (PPF matching per segment and/or over the whole
scene, score filter, duplicate suppression), `pick` (a collision-free grasp per part, ranked);
`process` runs them (picks when the models carry grasps). Camera frame, metres; poses are
T_cam_from_model.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from pykdtree.kdtree import KDTree
from scipy.spatial import cKDTree

from binpick.cleaning import clean_capture
from binpick.geometry.pointcloud import voxel_downsample_indices
from binpick.io.cloud import CleanCloud
from binpick.io.grasps import GraspSet, load_grasps
from binpick.io.part_model import PartModel, load_part_model
from binpick.io.poses import PartPose
from binpick.io.ppf_model import PPFModel, load_ppf_model
from binpick.network.checkpoint import InferenceSettings
from binpick.network.infer import Segmenter, load_segmenter
from binpick.params import ImportCaptureParams, Params, PickParams, RegisterParams
from binpick.picking import BinBoxObstacle, PickPlan, plan_picks
from binpick.registration.constants import DEFAULT_MAX_SEEN_THROUGH, DEFAULT_MIN_VISIBLE_SUPPORT, Scales
from binpick.registration.matching import explained_by, match_scene, match_segment, suppress_duplicates
from binpick.registration.near_symmetry import resolve
from binpick.registration.verification import score_pose, seen_through, visible_support
from binpick.registration.visibility import DepthView
from binpick.seeding import derive_int, derive_seed

log = logging.getLogger(__name__)

# Segments matched at once, on threads: two, for the two cores the service is sized for. The
# matcher's kernels (voting, k-d tree queries) already use both cores; the second
# thread fills the gaps between them (the interpreter's share of a match): 0.72 -> 0.44-0.70 s of
# registration on 8-part T-joint bins. A constant, not the machine's core count: which segments
# are matched, and so the poses, must not depend on the machine.
SEGMENT_WAVE = 2


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

    @classmethod
    def load(
        cls, params: Params, part_model: str | Path, ppf_model: str | Path, checkpoint: str | Path | None, grasps: str | Path | None = None
    ) -> PartModels:
        """params: resolved for the part (load_params(path, part)); checkpoint None: no network;
        grasps: the part's grasp file (None: no picks)."""
        segmenter = load_segmenter(checkpoint, params.segment) if checkpoint is not None else None
        register_params = params.registration
        if segmenter is None and register_params.mode != "whole_scene":
            log.info("no network for the part: registration over the whole scene")
            register_params = register_params.model_copy(update={"mode": "whole_scene"})
        return cls(
            part=load_part_model(part_model),
            ppf=load_ppf_model(ppf_model),
            segmenter=segmenter,
            import_params=params.import_capture,
            register_params=with_verification(register_params, segmenter.settings if segmenter is not None else None),
            grasps=load_grasps(grasps)[params.pick.gripper] if grasps is not None else None,
            pick_params=params.pick,
        )


def with_verification(params: RegisterParams, settings: InferenceSettings | None) -> RegisterParams:
    """register params with max_seen_through and min_visible_support resolved: the value in
    params, else the one chosen at training (in the checkpoint's settings), else the default
    (DEFAULT_MAX_SEEN_THROUGH, DEFAULT_MIN_VISIBLE_SUPPORT)."""
    update: dict[str, float] = {}
    if params.max_seen_through is None:
        chosen = settings.max_seen_through if settings is not None else None
        update["max_seen_through"] = DEFAULT_MAX_SEEN_THROUGH if chosen is None else chosen
    if params.min_visible_support is None:
        chosen = settings.min_visible_support if settings is not None else None
        update["min_visible_support"] = DEFAULT_MIN_VISIBLE_SUPPORT if chosen is None else chosen
    return params.model_copy(update=update) if update else params


@dataclass(frozen=True)
class SceneSeeds:
    """The seed of each random step. `of(seed, name)` derives them from the project seed and a
    capture name; the DVC stages pass the seeds they always used."""

    clean: int
    segment: np.random.SeedSequence
    register: np.random.SeedSequence

    @classmethod
    def of(cls, seed: int, name: str) -> SceneSeeds:
        return cls(derive_int(seed, "import", name), derive_seed(seed, "segment", name), derive_seed(seed, "register", name))


@dataclass(frozen=True)
class Registration:
    """poses: best first within each source (segments, then whole scene); n_segments: segments;
    n_duplicates_suppressed: segment poses dropped as repeats, and segments not matched because
    a pose found already explains them; per_instance_ms: matching time per segment matched
    (whole-scene time shared among its poses)."""

    poses: list[PartPose]
    n_segments: int
    n_duplicates_suppressed: int
    per_instance_ms: list[float]
    n_seen_through: int = 0  # poses dropped: too much of their surface where the camera saw through
    n_unsupported: int = 0  # poses dropped: too little of their surface in view measured


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


def clean(xyz_m: np.ndarray, rgb: np.ndarray | None, frame_shape: tuple[int, int] | None, params: ImportCaptureParams, seed: int) -> CleanCloud:
    """The cleaned cloud of a capture: xyz_m (n, 3) camera frame, metres, NaN = no return
    (n = H * W, row-major, for an organized frame of shape frame_shape); rgb (n, 3) uint8 or None."""
    return clean_capture(xyz_m, rgb, frame_shape, params, seed)


def segment(cloud: CleanCloud, segmenter: Segmenter, seed: np.random.SeedSequence | int) -> np.ndarray:
    """Instance labels (n,) int32 of the cloud's points, -1 = not a part."""
    return segmenter.segment(cloud.points_m, cloud.normals, np.random.default_rng(seed))


def register(
    cloud: CleanCloud, labels: np.ndarray | None, ppf: PPFModel, params: RegisterParams, seed: np.random.SeedSequence | int
) -> Registration:
    """Poses of the part in the cloud, as params.mode says: `segments` fits the part onto every
    segment, keeps poses scoring at least min_score and drops repeats (the same pose, or support
    a better pose explains); `whole_scene` matches the whole cloud; `segments_then_scene` does
    both, the whole scene only for points no segment pose explains. labels (n,) int: needed
    unless the mode is whole_scene."""
    rng = np.random.default_rng(seed)
    mode = params.mode
    poses: list[PartPose] = []
    per_instance_ms: list[float] = []
    n_segments = int(labels.max()) + 1 if labels is not None and len(labels) else 0
    n_duplicates = 0
    # What the camera saw (its z-buffer) and the whole cleaned cloud: segment matching ranks its
    # finalists by them, and every pose is verified against them below.
    view = DepthView(cloud.seen_depth_m, cloud.seen_K)
    cloud_tree = KDTree(np.ascontiguousarray(cloud.points_m, dtype=np.float64)) if len(cloud.points_m) else None
    if mode in ("segments", "segments_then_scene"):
        if labels is None:
            raise ValueError(f"registration mode {mode!r} needs segment labels")
        found: list[PartPose] = []
        # Largest segments first: a part split in two is then found on its larger piece, and the
        # smaller one, which the pose explains, is not matched again (it would repeat the pose,
        # and suppression would drop it). Segments are matched SEGMENT_WAVE at a time, one per
        # core: a segment is checked against the poses of the waves before its own. Each segment
        # draws from its own generator, so the poses do not depend on the number of cores.
        sizes = np.bincount(labels[labels >= 0], minlength=n_segments)
        segment_seeds = rng.integers(0, 2**63 - 1, size=n_segments)
        n_explained = 0
        order = np.argsort(-sizes, kind="stable").tolist()

        def match(seg: int) -> tuple[PartPose | None, float]:
            t = time.perf_counter()
            mask = labels == seg
            est = match_segment(
                ppf, cloud.points_m[mask], cloud.normals[mask], params, np.random.default_rng(segment_seeds[seg]), view, cloud_tree,
            )
            return est, 1000.0 * (time.perf_counter() - t)

        with ThreadPoolExecutor(max_workers=SEGMENT_WAVE, thread_name_prefix="binpick-match") as pool:
            for start in range(0, len(order), SEGMENT_WAVE):
                wave = []
                for seg in order[start:start + SEGMENT_WAVE]:
                    if found and explained_by(ppf, cloud.points_m[labels == seg], params, [f.T_cam_from_model for f in found]):
                        n_explained += 1
                    else:
                        wave.append(seg)
                for seg, (est, ms) in zip(wave, pool.map(match, wave), strict=True):
                    per_instance_ms.append(ms)
                    if est is not None and est.score >= params.min_score:
                        found.append(replace(est, segment=seg))
        kept = suppress_duplicates(ppf, found, params, cloud.points_m)
        poses = [found[k] for k in kept]
        n_duplicates = len(found) - len(kept) + n_explained
    if mode in ("whole_scene", "segments_then_scene"):
        t = time.perf_counter()
        more = match_scene(ppf, cloud.points_m, cloud.normals, params, rng, params.max_instances, known=[p.T_cam_from_model for p in poses])
        per_instance_ms += [1000.0 * (time.perf_counter() - t) / max(1, len(more))] * len(more)
        poses += more
        log.info("whole-scene matching added %d poses", len(more))
    if not poses or cloud_tree is None:
        return Registration([], n_segments, n_duplicates, per_instance_ms)
    if len(ppf.near_symmetries):
        poses = _resolve_near_symmetries(cloud, labels, poses, ppf, params, view)
    # Verification against what the camera saw: a pose whose surface lies where the sensor saw
    # through it (a cup fitted into a box wall, a part floating before the wall behind a desk),
    # or much of whose surface in view has nothing measured on it (a shaft fitted onto a plain
    # cylinder, its gear in the air), is not there, whatever its fit to the points near it.
    resolved = with_verification(params, None)
    limit, least = resolved.max_seen_through, resolved.min_visible_support
    assert limit is not None and least is not None  # with_verification resolves both
    kept_poses = []
    n_unsupported = 0
    inlier_m = Scales.of(ppf, params).inlier_m
    for pose in poses:
        share = seen_through(ppf, pose.T_cam_from_model, view)
        if share > limit:
            continue
        support = visible_support(ppf, pose.T_cam_from_model, view, cloud_tree, inlier_m)
        if support < least:
            n_unsupported += 1
            continue
        kept_poses.append(replace(pose, extra={**(pose.extra or {}), "seen_through": round(share, 4), "visible_support": round(support, 4)}))
    if len(kept_poses) < len(poses):
        log.info("dropped %d of %d poses: %d lying where the camera saw through them, %d with too little of their surface in view measured",
                 len(poses) - len(kept_poses), len(poses), len(poses) - len(kept_poses) - n_unsupported, n_unsupported)
    return Registration(kept_poses, n_segments, n_duplicates, per_instance_ms, len(poses) - len(kept_poses) - n_unsupported, n_unsupported)


def _resolve_near_symmetries(
    cloud: CleanCloud, labels: np.ndarray | None, poses: list[PartPose], ppf: PPFModel, params: RegisterParams, view: DepthView
) -> list[PartPose]:
    """Each pose, or its turn by one of the part's near symmetries that what the camera saw
    supports better (registration/near_symmetry.py). A turned pose is scored again as its source
    scores (on its segment's points, or on the whole scene's)."""
    scales = Scales.of(ppf, params)
    fine = cloud.points_m[voxel_downsample_indices(cloud.points_m, scales.refine_step_m)].astype(np.float64)
    ball_tree, score_tree = cKDTree(fine), KDTree(np.ascontiguousarray(fine))
    out = []
    n_turned = 0
    for pose in poses:
        T, turned = resolve(ppf, pose.T_cam_from_model, fine, ball_tree, view, scales, params.icp_iterations)
        if turned:
            n_turned += 1
            if pose.segment >= 0 and labels is not None:
                own = cloud.points_m[labels == pose.segment].astype(np.float64)
                own = own[voxel_downsample_indices(own, scales.refine_step_m)]
                score = score_pose(ppf, T, own, scales.inlier_m)
            else:
                score = score_pose(ppf, T, fine, scales.inlier_m, score_tree, whole_scene=True)
            pose = replace(pose, T_cam_from_model=T, score=score, extra={**(pose.extra or {}), "turned_by_near_symmetry": 1.0})
        out.append(pose)
    if n_turned:
        log.info("turned %d of %d poses by a near symmetry of the part, as the capture showed it", n_turned, len(out))
    return out


def bin_box_of(params: ImportCaptureParams) -> BinBoxObstacle | None:
    """The bin given in params (import_capture's region of interest with its frame), else None."""
    if params.T_cam_from_roi is None or params.roi_min_m is None or params.roi_max_m is None:
        return None
    return BinBoxObstacle(np.asarray(params.T_cam_from_roi, dtype=np.float64), np.asarray(params.roi_min_m, float), np.asarray(params.roi_max_m, float))


def pick(cloud: CleanCloud, poses: list[PartPose], part: PartModel, grasps: GraspSet, params: PickParams, import_params: ImportCaptureParams) -> PickPlan:
    """Picks for the posed parts (binpick/picking.py): obstacles are everything the capture
    measured (its z-buffer; the cleaned points when it has none), the support plane, the bin
    when params give it, and the other parts at their poses."""
    captured = DepthView(cloud.seen_depth_m, cloud.seen_K).points_m()
    if len(captured) == 0:
        captured = cloud.points_m
    T = np.array([p.T_cam_from_model for p in poses]).reshape(-1, 4, 4)
    scores = np.array([p.score for p in poses], dtype=np.float64)
    shares = np.array([(p.extra or {}).get("seen_through", np.nan) for p in poses], dtype=np.float64)
    return plan_picks(T, scores, grasps, part.points_m, part.normals, part.centre_m, captured, cloud.floor_plane, params, bin_box_of(import_params), shares)


def process(
    xyz_m: np.ndarray, rgb: np.ndarray | None, frame_shape: tuple[int, int] | None, models: PartModels, seeds: SceneSeeds
) -> SceneResult:
    """clean, segment (unless the models have no segmenter), register and (when the models carry
    grasps) pick one capture."""
    t0 = time.perf_counter()
    cloud = clean(xyz_m, rgb, frame_shape, models.import_params, seeds.clean)
    t1 = time.perf_counter()
    labels = segment(cloud, models.segmenter, seeds.segment) if models.segmenter is not None else None
    t2 = time.perf_counter()
    registration = register(cloud, labels, models.ppf, models.register_params, seeds.register)
    t3 = time.perf_counter()
    plan = None
    if models.grasps is not None and models.pick_params is not None:
        plan = pick(cloud, registration.poses, models.part, models.grasps, models.pick_params, models.import_params)
    t4 = time.perf_counter()
    if labels is None:
        labels = np.full(len(cloud.points_m), -1, np.int32)
    timings = {"clean_s": t1 - t0, "segment_s": t2 - t1, "register_s": t3 - t2, **({"pick_s": t4 - t3} if plan is not None else {})}
    return SceneResult(cloud, labels, registration, timings, plan)
