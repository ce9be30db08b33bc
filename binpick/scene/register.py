"""Scene step `register`: PPF matching per segment and/or over the whole scene, score filter,
duplicate suppression, near symmetries resolved, and verification against what the camera saw.
Camera frame, metres; poses are T_cam_from_model."""

from __future__ import annotations

import logging
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import numpy as np
from pykdtree.kdtree import KDTree
from scipy.spatial import cKDTree

from binpick.geometry.depth_noise import NOISE_NEIGHBOURS, image_coordinates, local_noise_m
from binpick.geometry.pointcloud import voxel_downsample_indices
from binpick.io.cloud import CleanCloud
from binpick.io.poses import PartPose
from binpick.io.ppf_model import PPFModel
from binpick.io.verification import Verification
from binpick.params import RegisterParams
from binpick.registration.constants import (
    DEFAULT_MAX_SEEN_THROUGH,
    DEFAULT_MIN_VISIBLE_SUPPORT,
    NOISE_INLIER_SIGMAS,
    SUPPORT_MAX_INCIDENCE_DEG,
    Scales,
)
from binpick.registration.matching import explained_by, match_scene, match_segment, suppress_duplicates
from binpick.registration.near_symmetry import resolve
from binpick.registration.verification import (
    in_the_floor,
    part_share,
    refine_along_rays,
    score_pose,
    seen_through,
    support_cut,
    visible_support,
)
from binpick.registration.visibility import DepthView

log = logging.getLogger(__name__)

# Segments matched at once, on threads: two, for the two cores the service is sized for. The
# matcher's kernels (voting, k-d tree queries) already use both cores; the second
# thread fills the gaps between them (the interpreter's share of a match): 0.72 -> 0.44-0.70 s of
# registration on 8-part T-joint bins. A constant, not the machine's core count: which segments
# are matched, and so the poses, must not depend on the machine.
SEGMENT_WAVE = 2
# The noise about a pose is measured on this many captured points nearest its centre.
NOISE_PROBE_POINTS = 400


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
    n_not_part: int = 0  # poses dropped: the network calls most of the points on them no part's
    n_in_the_floor: int = 0  # poses dropped: reaching far below the support plane
    capture_noise_m: float = 0.0  # the depth noise the capture shows (it widens the inlier distance)


def with_capture_noise(params: RegisterParams, noise_m: float, diameter_m: float) -> RegisterParams:
    """register params whose inlier distance (score_inlier_rel, and with it the fine ICP's
    correspondence distance) is at least NOISE_INLIER_SIGMAS times the capture's depth noise.

    A score counts the part's surface with a measured point within the inlier distance: on a
    capture whose noise is above that distance (a Kinect-class frame at 0.6 m: 2 mm, the 68 mm
    T-joint's inlier distance 1.4 mm), a right pose found a neighbour for a third of its
    surface and scored under min_score, so min_score meant something else on every sensor.
    Bench sensors, T-joint, 6 Kinect-class bins, the randomised network: pose recall 0.70 ->
    0.95 at one sigma; 1.5 sigmas let false poses through. A clean capture keeps its distance."""
    rel = NOISE_INLIER_SIGMAS * noise_m / diameter_m
    if rel <= params.score_inlier_rel:
        return params
    log.info(
        "the capture's depth noise (%.2f mm) widens the inlier distance from %.2f to %.2f mm",
        1000 * noise_m,
        1000 * params.score_inlier_rel * diameter_m,
        1000 * rel * diameter_m,
    )
    return params.model_copy(update={"score_inlier_rel": rel})


def with_verification(params: RegisterParams, chosen: Verification | None) -> RegisterParams:
    """register params with max_seen_through and min_visible_support resolved: the value in
    params, else the one the verify stage chose (verification.json, or an older checkpoint's),
    else the default (DEFAULT_MAX_SEEN_THROUGH, DEFAULT_MIN_VISIBLE_SUPPORT). A support cut chosen
    with another incidence limit than today's measures another share: the default applies."""
    update: dict[str, float] = {}
    if params.max_seen_through is None:
        update["max_seen_through"] = DEFAULT_MAX_SEEN_THROUGH if chosen is None else chosen.max_seen_through
    if params.min_visible_support is None:
        least = (
            chosen.min_visible_support
            if chosen is not None and chosen.support_incidence_deg == SUPPORT_MAX_INCIDENCE_DEG
            else None
        )
        update["min_visible_support"] = DEFAULT_MIN_VISIBLE_SUPPORT if least is None else least
    return params.model_copy(update=update) if update else params


def register(
    cloud: CleanCloud,
    labels: np.ndarray | None,
    ppf: PPFModel,
    params: RegisterParams,
    seed: np.random.SeedSequence | int,
    is_part: np.ndarray | None = None,
    explained_elsewhere: np.ndarray | None = None,
) -> Registration:
    """Poses of the part in the cloud, as params.mode says: `segments` fits the part onto every
    segment, keeps poses scoring at least min_score and drops repeats (the same pose, or support
    a better pose explains); `whole_scene` matches the whole cloud; `segments_then_scene` does
    both, the whole scene only for points no segment pose explains. labels (n,) int: needed
    unless the mode is whole_scene. is_part (n,) bool: the points the network calls a part's
    (Segments.is_part; default all): with params.scene_votes_from `parts`, the whole-scene pass
    votes only from them. explained_elsewhere (n,) bool: the points other parts' poses explain
    (a mixed bin, binpick/scene/mixed.py): the whole-scene pass votes from none of them."""
    rng = np.random.default_rng(seed)
    points = np.asarray(cloud.points_m, dtype=np.float64)
    image_tree = KDTree(image_coordinates(points)) if len(points) >= NOISE_NEIGHBOURS else None
    capture_noise_m = local_noise_m(points, image_tree, points)
    params = with_capture_noise(params, capture_noise_m, ppf.diameter_m)
    mode = params.mode
    poses: list[PartPose] = []
    per_instance_ms: list[float] = []
    n_segments = int(labels.max()) + 1 if labels is not None and len(labels) else 0
    n_duplicates = 0
    # What the camera saw (its z-buffer) and the whole cleaned cloud: segment matching ranks its
    # finalists by them, and every pose is verified against them below.
    view = DepthView(cloud.seen_depth_m, cloud.seen_K)
    cloud_tree = KDTree(np.ascontiguousarray(cloud.points_m, dtype=np.float64)) if len(cloud.points_m) else None
    # The verification's limits, which the whole-scene pass also applies as it goes.
    resolved = with_verification(params, None)
    limit, least = resolved.max_seen_through, resolved.min_visible_support
    assert limit is not None and least is not None  # with_verification resolves both
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
                ppf,
                cloud.points_m[mask],
                cloud.normals[mask],
                params,
                np.random.default_rng(segment_seeds[seg]),
                view,
                cloud_tree,
            )
            return est, 1000.0 * (time.perf_counter() - t)

        with ThreadPoolExecutor(max_workers=SEGMENT_WAVE, thread_name_prefix="binpick-match") as pool:
            for start in range(0, len(order), SEGMENT_WAVE):
                wave = []
                for seg in order[start : start + SEGMENT_WAVE]:
                    if found and explained_by(
                        ppf, cloud.points_m[labels == seg], params, [f.T_cam_from_model for f in found]
                    ):
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
    # Verification against what the camera saw: a pose whose surface lies where the sensor saw
    # through it (a cup fitted into a box wall, a part floating before the wall behind a desk),
    # or much of whose surface in view has nothing measured on it (a shaft fitted onto a plain
    # cylinder, its gear in the air), is not there, whatever its fit to the points near it. Nor
    # is one on points the network calls no part's (a cup fitted onto a carton face): the
    # geometry and the network must both say so, unless the capture measures nearly all of the
    # pose's surface in view (a foreground head on a sensor it never saw). Nor is one reaching
    # deep into the floor the cleaning found: nothing measured can contradict it there (the
    # floor hides it), but no part lies inside the floor.
    dropped = {"seen_through": 0, "unsupported": 0, "not_part": 0, "in_the_floor": 0}
    scales = Scales.of(ppf, params)
    inlier_m = scales.inlier_m
    model_centre = ppf.dense_points_m.mean(axis=0)

    def noise_about(T_cam_from_model: np.ndarray) -> float:
        """The sensor's noise about a pose, from the captured points nearest its centre."""
        assert cloud_tree is not None  # verified() asks only when the cloud has points
        centre = T_cam_from_model[:3, :3] @ model_centre + T_cam_from_model[:3, 3]
        _, near = cloud_tree.query(centre[None], k=min(NOISE_PROBE_POINTS, len(points)))
        return local_noise_m(points, image_tree, points[np.ravel(near)])

    def _along_rays(T: np.ndarray) -> np.ndarray:
        """The pose refined along the camera rays on the captured points within reach of it."""
        centre = T[:3, :3] @ model_centre + T[:3, 3]
        near = points[np.linalg.norm(points - centre, axis=1) <= scales.reach_m]
        return refine_along_rays(ppf, T, near, scales.fine_icp_m, params.icp_iterations)

    fine: _FineScene | None = None  # the near symmetries' grid of the cloud, built once

    def verified(candidates: list[PartPose]) -> list[PartPose]:
        nonlocal fine
        if not candidates or cloud_tree is None:
            return []
        if len(ppf.near_symmetries):
            fine = fine or _FineScene.of(cloud, Scales.of(ppf, params).refine_step_m)
            candidates = _resolve_near_symmetries(cloud, labels, candidates, ppf, params, view, fine)
        kept = []
        for pose in candidates:
            if in_the_floor(ppf, pose.T_cam_from_model, cloud.floor_plane):
                dropped["in_the_floor"] += 1
                continue
            share = seen_through(ppf, pose.T_cam_from_model, view)
            if share > limit:
                dropped["seen_through"] += 1
                continue
            support = visible_support(ppf, pose.T_cam_from_model, view, cloud_tree, inlier_m)
            # The cut only eases (support_cut <= least): the noise is measured only when it can matter.
            if support < least and support < support_cut(least, noise_about(pose.T_cam_from_model), inlier_m):
                dropped["unsupported"] += 1
                continue
            waived = params.part_share_waived_at_support is not None and support >= params.part_share_waived_at_support
            if (
                is_part is not None
                and not waived
                and part_share(ppf, pose.T_cam_from_model, cloud_tree, is_part, inlier_m) < params.min_part_share
            ):
                dropped["not_part"] += 1
                continue
            kept.append(replace(pose, seen_through=share, visible_support=support))
        return kept

    n_candidates = len(poses)
    # The segments' poses are verified before the whole-scene pass: the points a pose explains
    # are left out of that pass's votes, and a false pose on a part's points (a gear shaft posed
    # across two shafts lying side by side, half of it where the camera saw through it) had hidden
    # the part it lay on from the pass, then fallen to the verification, leaving that part unposed.
    kept_poses = verified(poses)
    if mode in ("whole_scene", "segments_then_scene"):
        t = time.perf_counter()
        more = match_scene(
            ppf,
            cloud.points_m,
            cloud.normals,
            params,
            rng,
            params.max_instances,
            known=[p.T_cam_from_model for p in kept_poses],
            votes_from=_votes_from(is_part if params.scene_votes_from == "parts" else None, explained_elsewhere),
            view=view,
            max_seen_through=limit,
        )
        per_instance_ms += [1000.0 * (time.perf_counter() - t) / max(1, len(more))] * len(more)
        log.info("whole-scene matching added %d poses", len(more))
        n_candidates += len(more)
        kept_poses += verified(more)
    if params.refine_along_rays:
        # Last, once every pass is done: the passes' choices (which points a pose explains, what
        # the whole-scene pass looks for) stay as they were; only the poses come off the bias.
        kept_poses = [replace(pose, T_cam_from_model=_along_rays(pose.T_cam_from_model)) for pose in kept_poses]
    n_seen_through, n_unsupported = dropped["seen_through"], dropped["unsupported"]
    n_not_part, n_in_the_floor = dropped["not_part"], dropped["in_the_floor"]
    if len(kept_poses) < n_candidates:
        log.info(
            "dropped %d of %d poses: %d lying where the camera saw through them, %d with too little of their surface "
            "in view measured, %d on points the network calls no part's, %d reaching into the floor",
            n_candidates - len(kept_poses),
            n_candidates,
            n_seen_through,
            n_unsupported,
            n_not_part,
            n_in_the_floor,
        )
    return Registration(
        kept_poses,
        n_segments,
        n_duplicates,
        per_instance_ms,
        n_seen_through,
        n_unsupported,
        n_not_part,
        n_in_the_floor,
        capture_noise_m,
    )


@dataclass(frozen=True)
class _FineScene:
    """The cloud on the refinement grid (points_m (k, 3) float64, camera frame) and its two trees:
    ball_tree for the near-symmetry turns' ICP, score_tree for the whole-scene score."""

    points_m: np.ndarray
    ball_tree: cKDTree
    score_tree: KDTree

    @classmethod
    def of(cls, cloud: CleanCloud, refine_step_m: float) -> _FineScene:
        fine = cloud.points_m[voxel_downsample_indices(cloud.points_m, refine_step_m)].astype(np.float64)
        return cls(fine, cKDTree(fine), KDTree(np.ascontiguousarray(fine)))


def _resolve_near_symmetries(
    cloud: CleanCloud,
    labels: np.ndarray | None,
    poses: list[PartPose],
    ppf: PPFModel,
    params: RegisterParams,
    view: DepthView,
    fine_scene: _FineScene,
) -> list[PartPose]:
    """Each pose, or its turn by one of the part's near symmetries that what the camera saw
    supports better (registration/near_symmetry.py). A turned pose is scored again as its source
    scores (on its segment's points, or on the whole scene's). fine_scene: the cloud on the
    params' refinement grid (_FineScene.of)."""
    scales = Scales.of(ppf, params)
    fine, ball_tree, score_tree = fine_scene.points_m, fine_scene.ball_tree, fine_scene.score_tree
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
                score = score_pose(ppf, T, fine, scales.inlier_m, score_tree, whole_scene=True, view=view)
            pose = replace(pose, T_cam_from_model=T, score=score, turned_by_near_symmetry=True)
        out.append(pose)
    if n_turned:
        log.info("turned %d of %d poses by a near symmetry of the part, as the capture showed it", n_turned, len(out))
    return out


def _votes_from(is_part: np.ndarray | None, explained_elsewhere: np.ndarray | None) -> np.ndarray | None:
    """(n,) bool, the points the whole-scene pass may vote from (None: all)."""
    if explained_elsewhere is None:
        return is_part
    free = ~np.asarray(explained_elsewhere, bool)
    return free if is_part is None else free & np.asarray(is_part, bool)
