"""The scene path for a bin of several kinds of part: the capture cleaned once per distinct import
setting of the parts (once when they agree), each part's segmentation and registration on its
cleaning, conflicts between parts resolved by the verification the poses carry, and one ordered
pick list across the parts.

A region of the capture gets at most one part: two poses of different parts that claim the same
measured points (more than CONFLICT_SHARE of the smaller claim) are a conflict, and the pose
that explains more of the capture keeps the points: the measured points it claims, weighted by
its verification (score x visible support x (1 - seen-through share)). Weighing by the
verification alone gave a long gear shaft's region to a three-way pipe posed on a stretch of its
round body (0.53 against 0.39: the pipe's small surface all lay on the shaft, and the shaft's
score counts its whole surface), and the other false tees on that shaft, which the shaft's pose
would have beaten, then had no rival. Each part's picks see the other parts' kept poses as
obstacles (their unseen sides too).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from binpick.cell.retries import FailedGrips
from binpick.geometry.transforms import transform_points
from binpick.io.cloud import CleanCloud
from binpick.io.picks import mixed_picks_document, pose_entries
from binpick.io.poses import PartPose
from binpick.params import ImportCaptureParams
from binpick.picking.measured import point_spacing_m
from binpick.picking.plan import Pick, body_sample_stride
from binpick.picking.ranking import rank_key
from binpick.scene.clean import clean
from binpick.scene.pick import pick
from binpick.scene.process import PartModels
from binpick.scene.register import register
from binpick.scene.segment import segment
from binpick.seeding import SceneSeeds

# Two poses of different parts conflict when they share more than this of the smaller one's
# measured points.
CONFLICT_SHARE = 0.3
# Every k-th model surface point stands for a part's surface when the measured points it claims
# are counted (the dense sample is 20,000).
CLAIM_STRIDE = 5


def pose_quality(pose: PartPose) -> float:
    """What a conflict is decided by: score x visible support x (1 - seen-through share); an
    unmeasured check counts as passed."""
    support = 1.0 if pose.visible_support is None else float(pose.visible_support)
    through = 0.0 if pose.seen_through is None else float(pose.seen_through)
    return float(pose.score) * support * (1.0 - through)


def claimed_points(
    points_m: np.ndarray, model_points_m: np.ndarray, T_cam_from_model: np.ndarray, inlier_m: float, tree=None
) -> np.ndarray:
    """Indices (k,) of the measured points (n, 3), camera frame, within inlier_m of the posed model
    surface (model_points_m (m, 3), model frame; T_cam_from_model (4, 4)), sorted."""
    tree = tree or cKDTree(np.asarray(points_m, dtype=np.float64))
    posed = transform_points(np.asarray(T_cam_from_model, dtype=np.float64), model_points_m)
    hits = tree.query_ball_point(posed, inlier_m)
    return np.unique(np.concatenate([np.asarray(h, dtype=np.int64) for h in hits])) if len(hits) else np.zeros(0, int)


def explained_weight(pose: PartPose, claim: np.ndarray) -> float:
    """How much of the capture a pose explains: the number of measured points it claims (claim:
    their indices) times its pose_quality."""
    return pose_quality(pose) * len(claim)


def resolve_conflicts(
    claims: list[np.ndarray], weight: list[float], kinds: list[str], share: float = CONFLICT_SHARE
) -> tuple[list[bool], list[tuple[int, int]]]:
    """Which poses of several parts keep their region: claims (per pose, the indices of the
    measured points it explains), weight (per pose, higher wins: explained_weight), kinds (per
    pose, its part's name). A pose is kept unless a weightier pose of another part, kept already,
    shares more than `share` of the smaller of their claims. Returns the keep flags and, for each
    pose dropped, (dropped, kept by) indices."""
    order = sorted(range(len(claims)), key=lambda i: -weight[i])
    keep = [False] * len(claims)
    lost: list[tuple[int, int]] = []
    kept: list[int] = []
    for i in order:
        rival = None
        for j in kept:
            if kinds[j] == kinds[i]:
                continue  # the same part's poses were told apart by its own registration
            shared = len(np.intersect1d(claims[i], claims[j], assume_unique=True))
            if shared > share * max(1, min(len(claims[i]), len(claims[j]))):
                rival = j
                break
        if rival is None:
            keep[i] = True
            kept.append(i)
        else:
            lost.append((i, rival))
    return keep, lost


@dataclass(frozen=True)
class MixedPick:
    """One pick of a mixed bin: the part's name and its pick (pose_index into that part's poses)."""

    part: str
    pick: Pick


@dataclass
class MixedResult:
    """A mixed capture's answer: the cleaned cloud, each part's kept poses, the poses dropped as
    another part's region (part, pose, the part that kept it), one ordered pick list, each part's
    unpicked (pose_index, reason), timings per step (summed over the parts)."""

    cloud: CleanCloud
    poses: dict[str, list[PartPose]]
    conflicts: list[tuple[str, PartPose, str]]
    picks: list[MixedPick]
    unpicked: dict[str, list[tuple[int, str]]]
    up_cam: np.ndarray  # (3,) the bin's up axis, camera frame (the picks' approach cone's)
    timings_s: dict[str, float] = field(default_factory=dict)

    def posed(self) -> list[tuple[str, PartPose]]:
        """Every kept pose with its part's name, in the order the answer's pose_index counts."""
        return [(name, p) for name, found in self.poses.items() for p in found]

    def document(
        self, capture: str, grippers: dict[str, str], T_base_from_cam: np.ndarray | None, pose_format: str
    ) -> dict:
        """The picks.json content (binpick.io.picks.mixed_picks_document) of this answer, with its
        `poses`; grippers: part -> its gripper, in the parts' order."""
        doc = mixed_picks_document(
            capture,
            grippers,
            {name: len(found) for name, found in self.poses.items()},
            [(mp.part, mp.pick) for mp in self.picks],
            self.unpicked,
            [(lost, kept) for lost, _, kept in self.conflicts],
            self.up_cam,
            T_base_from_cam,
            pose_format,
        )
        doc["poses"] = pose_entries(self.posed())
        return doc


def process_mixed(
    xyz_m: np.ndarray,
    rgb: np.ndarray | None,
    frame_shape: tuple[int, int] | None,
    models: dict[str, PartModels],
    seeds: SceneSeeds,
    priority: list[str] | None = None,
    q_from: np.ndarray | None = None,
    quota: dict[str, int] | None = None,
    failed: FailedGrips | None = None,
) -> MixedResult:
    """The scene path on a capture of several kinds of part (the module's docstring). models:
    each part's models (each part's import settings clean the capture for it; the cloud cleaned
    with the finest grid decides which measured points a pose claims);
    priority: parts picked before the others, in that order (the rest by pick.order whatever the
    part; None or []: all by pick.order); quota: at most this many picks of a part in the list
    (within_quota; parts not named: no limit); failed: where grips failed (cell/retries.py)."""
    names = list(models)
    if not names:
        raise ValueError("a mixed capture needs at least one part")
    t0 = time.perf_counter()
    # Each part sees the capture cleaned with its own import settings, as its network and matcher
    # were built for (a cloud thinned from the finest cleaning keeps more points there, which cost
    # a long part 6 times the registration time); equal settings share one cleaning.
    cleanings: list[tuple[ImportCaptureParams, CleanCloud]] = []
    clean_s = 0.0

    def cleaned(settings: ImportCaptureParams) -> CleanCloud:
        nonlocal clean_s
        for known, cloud in cleanings:
            if known == settings:
                return cloud
        c0 = time.perf_counter()
        cloud = clean(xyz_m, rgb, frame_shape, settings, seeds.clean)
        clean_s += time.perf_counter() - c0
        cleanings.append((settings, cloud))
        return cloud

    finest = min(names, key=lambda n: models[n].import_params.voxel_size_m)
    cloud = cleaned(models[finest].import_params)
    found: dict[str, list[PartPose]] = {}
    clouds: dict[str, CleanCloud] = {}
    segment_s = 0.0
    # Largest part first: its poses explain a share of the capture that a smaller part's
    # whole-scene pass then does not vote over (a tee's fine grid over a bin of gear shafts, every
    # point of which the tee's network calls a part, voted for 3-4 minutes a capture). Conflicts
    # are still resolved over every part's poses below.
    for name in sorted(names, key=lambda n: -models[n].part.diameter_m):
        m = models[name]
        clouds[name] = cleaned(m.import_params)
        s0 = time.perf_counter()
        segments = segment(clouds[name], m.segmenter, seeds.segment) if m.segmenter is not None else None
        segment_s += time.perf_counter() - s0
        found[name] = register(
            clouds[name],
            segments.labels if segments is not None else None,
            m.ppf,
            # Another part's points neither vote for this part nor let its geometry overrule the
            # network: two tees alike fit each other's points, and only the network tells them apart.
            m.register_params.model_copy(update={"scene_votes_from": "parts", "part_share_waived_at_support": None}),
            seeds.register,
            segments.is_part if segments is not None else None,
            _explained(clouds[name].points_m, [(models[n], p) for n in found for p in found[n]]),
        ).poses
    t2 = time.perf_counter()
    flat = [(name, p) for name in names for p in found[name]]
    tree = cKDTree(np.asarray(cloud.points_m, dtype=np.float64)) if len(cloud.points_m) else None
    claims = [
        claimed_points(
            cloud.points_m, models[n].part.points_m[::CLAIM_STRIDE], p.T_cam_from_model, _inlier_m(models[n]), tree
        )
        if tree is not None
        else np.zeros(0, int)
        for n, p in flat
    ]
    weights = [explained_weight(p, c) for (_, p), c in zip(flat, claims, strict=True)]
    keep, lost = resolve_conflicts(claims, weights, [n for n, _ in flat])
    poses: dict[str, list[PartPose]] = {n: [] for n in names}
    for (name, pose), kept in zip(flat, keep, strict=True):
        if kept:
            poses[name].append(pose)
    conflicts = [(flat[i][0], flat[i][1], flat[j][0]) for i, j in lost]
    t3 = time.perf_counter()
    picks, unpicked, up_cam = _picks(clouds, poses, models, priority or [], q_from, failed)
    picks, over = within_quota(picks, quota or {})
    for mp in over:
        unpicked[mp.part].append(
            (mp.pick.pose_index, f"over the quota of {(quota or {})[mp.part]} {mp.part} an answer holds")
        )
    t4 = time.perf_counter()
    register_s = t2 - t0 - clean_s - segment_s
    timings = {"clean_s": clean_s, "segment_s": segment_s, "register_s": register_s, "resolve_s": t3 - t2}
    if picks or unpicked:
        timings["pick_s"] = t4 - t3
    return MixedResult(cloud, poses, conflicts, picks, unpicked, up_cam, timings)


def within_quota(picks: list[MixedPick], quota: dict[str, int]) -> tuple[list[MixedPick], list[MixedPick]]:
    """The picks in their order, at most quota[part] of each part named (a kit's count of it; 0:
    none, its poses stay obstacles), and those left over."""
    taken: dict[str, int] = {}
    kept, over = [], []
    for mp in picks:
        if mp.part in quota and taken.get(mp.part, 0) >= quota[mp.part]:
            over.append(mp)
        else:
            taken[mp.part] = taken.get(mp.part, 0) + 1
            kept.append(mp)
    return kept, over


def _explained(points_m: np.ndarray, posed: list[tuple[PartModels, PartPose]]) -> np.ndarray | None:
    """(n,) bool, the points (n, 3) that the poses of other parts claim (claimed_points); None
    when there are none."""
    points_m = np.asarray(points_m, dtype=np.float64)
    if not posed or len(points_m) == 0:
        return None
    tree = cKDTree(points_m)
    out = np.zeros(len(points_m), bool)
    for m, pose in posed:
        out[claimed_points(points_m, m.part.points_m[::CLAIM_STRIDE], pose.T_cam_from_model, _inlier_m(m), tree)] = True
    return out


def _inlier_m(m: PartModels) -> float:
    return m.register_params.score_inlier_rel * m.part.diameter_m


def _picks(
    clouds: dict[str, CleanCloud],
    poses: dict[str, list[PartPose]],
    models: dict[str, PartModels],
    priority: list[str],
    q_from: np.ndarray | None,
    failed: FailedGrips | None = None,
) -> tuple[list[MixedPick], dict[str, list[tuple[int, str]]], np.ndarray]:
    """Each part's picks with the other parts' posed bodies as obstacles, merged into one list:
    picks whose part comes out free before those taken past their neighbours (a part with no free
    pick of its own kind gets those: pick.lift_past_parts), then the priority's parts in its
    order, then by each part's own ranking (trusted first, then pick.order), ties by part name."""
    merged: list[tuple[tuple, MixedPick]] = []
    unpicked: dict[str, list[tuple[int, str]]] = {}
    # Each part's body as the others' obstacle: its surface sample on the grid a plan gives the
    # parts it poses itself. Every 4th of its 20,000 points (4-5 times as many) had made the pick
    # step of a T-joint + pipe capture 0.7 s slower than the two one-part runs' (now 0.3 s).
    bodies = {
        n: m.part.points_m[:: body_sample_stride(2.0 * point_spacing_m(m.part.points_m))] for n, m in models.items()
    }
    up_cam = np.array([0.0, 0.0, -1.0])  # the camera looking down, until a plan says where up is
    for name, m in models.items():
        if m.grasps is None or m.pick_params is None or not poses[name]:
            continue
        others = [
            transform_points(p.T_cam_from_model, bodies[other])
            for other in models
            if other != name
            for p in poses[other]
        ]
        obstacles = np.concatenate(others) if others else None
        plan = pick(
            clouds[name],
            poses[name],
            m.part,
            m.grasps,
            m.pick_params,
            m.import_params,
            m.cell_params,
            q_from,
            extra_obstacles_m=obstacles,
            density_kg_m3=m.density_kg_m3,
            failed=failed,
        )
        unpicked[name] = list(plan.unpicked)
        up_cam = plan.up_cam
        rank = priority.index(name) if name in priority else len(priority)
        for p in plan.picks:
            merged.append(((bool(p.lifts_past), rank, *rank_key(p, m.pick_params), name), MixedPick(name, p)))
    merged.sort(key=lambda kp: kp[0])
    return [mp for _, mp in merged], unpicked, up_cam
