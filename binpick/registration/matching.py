"""Matching a part onto a segment or a whole scene: voting, clustering, refinement and
verification in turn, then duplicate suppression. Scene points and normals in the camera frame,
metres, normals facing the camera; poses T_cam_from_model."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numba import njit
from pykdtree.kdtree import KDTree
from scipy.spatial import cKDTree

from binpick.geometry.pointcloud import voxel_downsample_indices
from binpick.io.poses import PartPose
from binpick.io.ppf_model import PPFModel
from binpick.params import RegisterParams
from binpick.registration.clustering import cluster_poses, repeats_any, same_pose
from binpick.registration.constants import (
    COARSE_STRIDE,
    FINE_CLUSTERS,
    FINE_STRIDE,
    MAX_CLUSTER_CANDIDATES,
    MIN_FREE_SHARE,
    MIN_SEGMENT_REFS,
    SCENE_CLUSTERS_PER_INSTANCE,
    SCENE_REFS_PER_CHUNK,
    SEGMENT_EXPLAINED_SHARE,
    TOP_CLUSTERS,
    Scales,
)
from binpick.registration.verification import (
    explained_points,
    refine_icp,
    score_pose,
    seen_through,
    suppress_by_support,
    visible_support,
)
from binpick.registration.visibility import DepthView
from binpick.registration.voting import prepare_scene, vote


def match_segment(
    model: PPFModel,
    scene_points: np.ndarray,
    scene_normals: np.ndarray,
    params: RegisterParams,
    rng: np.random.Generator,
    view: DepthView | None = None,
    cloud_tree: KDTree | None = None,
) -> PartPose | None:
    """The best pose of the part on one segment (camera frame points and normals), or None.

    With the capture's view and a pykdtree of its whole cleaned cloud (camera frame), the
    finalists are ranked by their score times what the camera saw of them: the share of their
    surface in view that is measured, and the share not lying where the camera saw through. A
    segment holding a part and part of its neighbour fits a wrong turn that takes in the
    neighbour's points better than the right one; the view tells them apart. The pose keeps its
    score_pose score (min_score keeps its meaning)."""
    if scene_points.ndim != 2 or scene_points.shape[1] != 3 or scene_normals.shape != scene_points.shape:
        raise ValueError("expected scene points and normals (n, 3)")
    scales = Scales.of(model, params)
    idx = voxel_downsample_indices(scene_points, scales.sample_step_m)
    if len(idx) < 3:
        return None
    pts, nrm = scene_points[idx].astype(np.float64), scene_normals[idx].astype(np.float64)
    n_refs = min(len(pts), max(MIN_SEGMENT_REFS, int(round(params.scene_ref_fraction * len(pts)))))
    refs = np.sort(rng.choice(len(pts), size=n_refs, replace=False))
    candidates = vote(model, pts, nrm, refs)
    if not candidates:
        return None
    # Refinement and scoring work on a grid finer than the voting one but bounded, so that their
    # cost does not grow with the density of the capture.
    scene_points = scene_points[voxel_downsample_indices(scene_points, scales.refine_step_m)]
    inlier = scales.inlier_m
    scene_tree = KDTree(np.ascontiguousarray(scene_points, dtype=np.float64))
    # Each strong cluster is refined by coarse ICP (on a subsample of the model) and scored;
    # comparing clusters only after ICP keeps a pose slid along a long part from winning. The
    # FINE_CLUSTERS best get the fine ICP and are scored again. (Two clusters that coarse ICP
    # brings within the clustering tolerance both get it: dropping the second cost accuracy,
    # median translation error 0.16 -> 0.19 mm in bench ppf.)
    coarse: list[tuple[float, np.ndarray]] = []
    for T, _ in cluster_poses(candidates, model, params, MAX_CLUSTER_CANDIDATES)[:TOP_CLUSTERS]:
        T = refine_icp(model, T, scene_points, scales.coarse_icp_m, params.icp_iterations, COARSE_STRIDE)
        coarse.append((score_pose(model, T, scene_points, inlier, scene_tree, stride=COARSE_STRIDE), T))
    best: PartPose | None = None
    best_rank = -1.0
    for _, T in sorted(coarse, key=lambda c: -c[0])[:FINE_CLUSTERS]:
        T = refine_icp(model, T, scene_points, scales.fine_icp_m, params.icp_iterations, FINE_STRIDE)
        score = score_pose(model, T, scene_points, inlier, scene_tree)
        rank = score
        if view is not None and cloud_tree is not None:
            # Finalists are ranked by the support of all their facing surface, grazing included:
            # the head-on share alone, the verification's, chose worse finalists (bench clutter,
            # ring screw, 8 scenes: pose recall 0.981 against 1.00).
            support = visible_support(model, T, view, cloud_tree, inlier, max_incidence_deg=90.0)
            rank = score * support * (1.0 - seen_through(model, T, view))
        if rank > best_rank:
            best, best_rank = PartPose(T_cam_from_model=T, score=score), rank
    return best


def explained_by(
    model: PPFModel, scene_points: np.ndarray, params: RegisterParams, known: Sequence[np.ndarray]
) -> bool:
    """Whether the known poses T_cam_from_model explain the scene points (n, 3, camera frame):
    on the voting grid, at least SEGMENT_EXPLAINED_SHARE of them lie within match_scene's take
    distance of a known pose's surface, and what is left could not hold a part (fewer than
    MIN_FREE_SHARE of the model's voting-grid points). A segment so explained is a fragment of a
    part found already."""
    if len(known) == 0:
        return False
    scales = Scales.of(model, params)
    pts = scene_points[voxel_downsample_indices(scene_points, scales.sample_step_m)]
    taken = np.zeros(len(pts), bool)
    tree = cKDTree(pts)
    for T in known:
        _take(taken, model, T, pts, tree, scales)
    return bool(taken.mean() >= SEGMENT_EXPLAINED_SHARE) and int((~taken).sum()) < MIN_FREE_SHARE * len(model.points_m)


def _take(
    taken: np.ndarray, model: PPFModel, T: np.ndarray, grid_points: np.ndarray, tree: cKDTree, scales: Scales
) -> None:
    """Mark in taken (n,) bool the voting-grid points (n, 3), in `tree`, that the pose T explains
    (within 1.5 inlier distances of its surface: the grid is coarser than the refine grid)."""
    taken[explained_points(model, np.asarray(T), grid_points, tree, 1.5 * scales.inlier_m, scales.reach_m)] = True


def match_scene(
    model: PPFModel,
    scene_points: np.ndarray,
    scene_normals: np.ndarray,
    params: RegisterParams,
    rng: np.random.Generator,
    max_instances: int = 30,
    known: Sequence[np.ndarray] = (),
    votes_from: np.ndarray | None = None,
    view: DepthView | None = None,
    max_seen_through: float | None = None,
) -> list[PartPose]:
    """Every instance of the part in a whole scene, without segments: votes from reference
    points all over the scene, the strongest pose clusters refined and scored, poses scoring
    below params.min_score dropped, then non-maximum suppression by explained points. Best first.

    scene_points, scene_normals : (n, 3) camera frame, metres; normals facing the camera.
    known : poses T_cam_from_model found already (e.g. on segments); the scene points they
            explain are taken, and only other instances are returned.
    votes_from : (n,) bool, the points a vote may start from (default all). Poses are still
            fitted and scored on every point.
    view : what the camera saw (its z-buffer): facing surface with no measurement on its ray
            does not count against a pose's score (verification.whole_scene_share).
    max_seen_through : with the view, a pose more of whose facing surface than this lies where
            the camera saw through it (verification.seen_through) is not there: it is passed over
            before it takes the points it fits, so the right pose of those points is still looked
            for (a T-joint standing on edge, whose flipped pose fits its top as well and puts its
            branch in the air). None: every pose that scores is kept here.
    """
    if scene_points.ndim != 2 or scene_points.shape[1] != 3 or scene_normals.shape != scene_points.shape:
        raise ValueError("expected scene points and normals (n, 3)")
    scales = Scales.of(model, params)
    idx = voxel_downsample_indices(scene_points, scales.sample_step_m)
    if len(idx) < 3:
        return []
    pts, nrm = scene_points[idx].astype(np.float64), scene_normals[idx].astype(np.float64)
    free = np.arange(len(pts))
    grid_tree = cKDTree(pts)
    taken = np.zeros(len(pts), bool)  # voting-grid points a known or found pose explains
    if votes_from is not None:
        # A point the network calls no part's (a carton, the desk) starts no vote: a part is
        # only looked for where the network saw one. Taken from the start, such points also
        # leave the stopping test below.
        taken |= ~np.asarray(votes_from, bool)[idx]
    min_free = MIN_FREE_SHARE * len(model.points_m)

    if len(known) or votes_from is not None:
        # Votes come only from what the known poses leave unexplained: the rest is found.
        for T in known:
            _take(taken, model, T, pts, grid_tree, scales)
        free = np.flatnonzero(~taken)
        if len(free) == 0 or len(free) < min_free:
            return []
    n_refs = max(1, int(round(params.scene_ref_fraction * len(free))))
    refs = np.sort(rng.choice(free, size=n_refs, replace=False))
    candidates: list[tuple[np.ndarray, float]] = []
    # In chunks: the accumulator holds (references x model points x angle bins) counts.
    # Every point's alignment and grid cell once, not once a chunk (over a gear shaft's 1 m bin
    # at a tee's grid, hundreds of chunks, it had cost a minute or more a capture).
    prepared = prepare_scene(pts, nrm, model.diameter_m)
    for chunk in np.array_split(refs, int(np.ceil(len(refs) / SCENE_REFS_PER_CHUNK))):
        candidates += vote(model, pts, nrm, chunk, prepared)
    fine = scene_points[voxel_downsample_indices(scene_points, scales.refine_step_m)]
    inlier = scales.inlier_m
    tree = cKDTree(fine)  # ball queries
    score_tree = KDTree(np.ascontiguousarray(fine, dtype=np.float64))  # nearest neighbours
    estimates: list[PartPose] = []
    support: list[np.ndarray] = []
    centre = model.dense_points_m.mean(axis=0)
    reach = scales.reach_m

    def explained(T: np.ndarray) -> np.ndarray:
        return explained_points(model, T, fine, tree, inlier, reach)

    settled = np.asarray(known, dtype=np.float64).reshape(-1, 4, 4)  # poses a coarse fit may repeat
    links: np.ndarray | None = None  # voting-grid point pairs within two steps, found once

    for T, _ in cluster_poses(candidates, model, params)[: SCENE_CLUSTERS_PER_INSTANCE * max_instances]:
        # ICP and support only see the scene around the pose: the rest cannot match this part.
        near = np.asarray(tree.query_ball_point(T[:3, :3] @ centre + T[:3, 3], reach), dtype=np.int64)
        if len(near) < 6:
            continue
        local = fine[near]
        T = refine_icp(model, T, local, scales.coarse_icp_m, params.icp_iterations, COARSE_STRIDE)
        # Most clusters of a cluttered scene slide, under coarse ICP, onto a part already known
        # or already estimated here: the fine fit would repeat that pose and suppression by
        # support would drop it. Only poses new after the coarse fit are refined and scored.
        if repeats_any(model, T, settled, params.cluster_rotation_deg, scales.cluster_translation_m):
            continue
        T = refine_icp(model, T, local, scales.fine_icp_m, params.icp_iterations, FINE_STRIDE)
        score = score_pose(model, T, fine, inlier, score_tree, whole_scene=True, view=view)
        if score >= params.min_score and not (
            view is not None and max_seen_through is not None and seen_through(model, T, view) > max_seen_through
        ):
            estimates.append(PartPose(T_cam_from_model=T, score=score))
            support.append(explained(T))
            settled = np.concatenate([settled, T[None]])
            # Done when what is left unexplained could no longer hold a part: no connected
            # patch of it holds min_free points (the pass's entry test, per patch: the edges
            # and slivers that poses leave unexplained hold no part).
            _take(taken, model, T, pts, grid_tree, scales)
            if links is None:
                links = grid_tree.query_pairs(2.0 * scales.sample_step_m, output_type="ndarray")
            if _largest_patch(links, ~taken) < min_free:
                break
    claimed = np.zeros(len(fine), bool)
    for T in known:
        claimed[explained(np.asarray(T))] = True
    return [estimates[k] for k in suppress_by_support([e.score for e in estimates], support, claimed)][:max_instances]


@njit(cache=True)
def _largest_patch(links: np.ndarray, kept: np.ndarray) -> int:  # pragma: no cover - compiled
    """Points in the largest connected patch of those kept ((n,) bool), linked by the pairs
    (m, 2) of point indices whose both ends are kept (union-find). The pairs of all points are
    found once and filtered here: finding them afresh among the kept points and building a
    graph after every pose had cost seven seconds a capture over a gear shaft's bin at a tee's
    grid."""
    root = np.arange(len(kept))
    for e in range(len(links)):
        a, b = links[e, 0], links[e, 1]
        if not (kept[a] and kept[b]):
            continue
        while root[a] != a:
            root[a] = root[root[a]]
            a = root[a]
        while root[b] != b:
            root[b] = root[root[b]]
            b = root[b]
        if a != b:
            root[max(a, b)] = min(a, b)
    size = np.zeros(len(kept), np.int64)
    for i in range(len(kept)):
        if kept[i]:
            r = i
            while root[r] != r:
                r = root[r]
            size[r] += 1
    return int(size.max()) if len(kept) else 0


def suppress_duplicates(
    model: PPFModel, estimates: Sequence[PartPose], params: RegisterParams, scene_points: np.ndarray | None = None
) -> list[int]:
    """Indices of the estimates kept by non-maximum suppression, best score first: an estimate
    that repeats the pose of a better one (one part split into two segments) is dropped; with
    the whole scene's points (n, 3), so is one whose supporting points a better one explains
    (a wrong fit on the fragment of a part that another segment gave whole)."""
    order = sorted(range(len(estimates)), key=lambda k: -estimates[k].score)
    kept: list[int] = []
    scales = Scales.of(model, params)
    trans_thr = scales.cluster_translation_m
    for k in order:
        T = estimates[k].T_cam_from_model
        if not any(
            same_pose(model, estimates[j].T_cam_from_model, T, params.cluster_rotation_deg, trans_thr) for j in kept
        ):
            kept.append(k)
    if scene_points is None or len(kept) < 2:
        return kept
    fine = scene_points[voxel_downsample_indices(scene_points, scales.refine_step_m)]
    tree = cKDTree(fine)
    inlier, reach = scales.inlier_m, scales.reach_m
    support = [explained_points(model, estimates[k].T_cam_from_model, fine, tree, inlier, reach) for k in kept]
    by_support = suppress_by_support([estimates[k].score for k in kept], support, np.zeros(len(fine), bool))
    return [kept[i] for i in by_support]
