"""Picks: for every detected part, a grasp the gripper can reach without hitting anything, and the
order to take them in. Camera frame, metres; poses are T_cam_from_model, grasps T_model_from_tool
(binpick/picking/gripper.py has the tool frame).

A grasp on a detected part is kept when
- its approach lies within approach_cone_deg of straight down the bin's up axis (the support
  plane's normal toward the camera; the bin box's up axis when the bin is given; the camera's -z
  when there is neither), or, for a part none of
  whose grasps within that cone is kept, within fallback_cone_deg (tried after them), and
- the gripper, swept along its approach from the pre-grasp pose to the grasp and back out to the
  post-grasp pose (or up to it, see below), stays clearance_m away from: the captured points (everything the camera
  measured, floor and walls included, except the target's own points: those within own_points_m
  of its posed model's surface), the bin (the support plane, and the given box's walls and floor when
  the bin is given in params, else the walls found at import where the camera did not see them:
  obstacles.unseen_walls), and the other detected parts at their estimated poses (their
  whole model surface, the sides the camera did not see included).
and the part it holds comes out of the heap free (picking/lift.py): back along the approach, or
(leave_straight_up), that dragging it into a neighbour and the approach tilted, straight up the
bin's axis (the tool's way up checked too; the post-grasp pose then lies above the grasp),
and its contact is where the camera measured a surface: under a suction cup the captured points
lie on the contact plane (within the seal tolerance, widened by the noise the capture shows
about the pose) and the plane they span faces the cup,
between a jaw's fingers (tip to palm) there are captured points. A part's pick is its best-ranked grasp that is
kept (grasps are tried best first, up to max_candidates_per_part; when more lie in the cone,
each grasp's symmetry images take turns: images_in_turn). Parts with a pick are ordered
by the keys in `order`: `height` (of the part's centre above the support plane, in steps of
height_tolerance_m, highest first), `score` (the pose's, highest first), `clearance` (of the
swept gripper, largest first).
Picks from poses not trusted come after all others, whatever the keys say: a pose is trusted
when at most max_seen_through of its camera-facing surface lies where the camera saw through it.
Registration keeps poses up to its own, looser limit as detections (a pose within a tenth of the
part's size counts a part); a cup needs the pose right to millimetres. On rendered bins of the
T-joint and the gear shaft, poses within 5 degrees and 5 mm showed up to 0.09, wrong ones that
registration kept 0.13-0.34. A part lying alone against a wall may show more and still be right:
its pick is kept, last, rather than the bin left with a part in it.
A part without a pick says why: every grasp outside the approach cone, or what the grasps hit.
"""

from __future__ import annotations

import dataclasses
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from pykdtree.kdtree import KDTree
from scipy.spatial import cKDTree

from binpick.cell.bin_box import BinBox, support_frame
from binpick.cell.retries import near_contacts
from binpick.geometry.depth_noise import NOISE_NEIGHBOURS, image_coordinates, local_noise_m
from binpick.geometry.pointcloud import voxel_downsample_indices
from binpick.geometry.transforms import invert_T, transform_points
from binpick.io.grasps import GraspSet
from binpick.params import PickParams
from binpick.picking.arm import ARM_REASONS, ArmMotion, ArmPlanner, turned
from binpick.picking.gripper import contact_size_m, gripper_primitives, swept
from binpick.picking.lift import across_the_way_out, lift_blockers, walls_touched, way_outs
from binpick.picking.measured import (
    NOISE_BAND_FACTOR,
    OWN_NOISE_SIGMAS,
    OwnPoints,
    PosedSurface,
    captured_near,
    contact_seen,
    point_spacing_m,
    seen_offset_m,
)
from binpick.picking.obstacles import (
    moved_tool_hits,
    source_name,
    surface_normals,
    tool_collisions,
    unseen_walls,
)
from binpick.picking.ranking import known_keys, rank_key

# Obstacle points are thinned to a grid of this share of the clearance (at least 1 mm): closer
# points add nothing a gripper of millimetres could slip between.
OBSTACLE_GRID_M = 0.001
# Each detected part's obstacle is its surface sample at about this spacing: the gripper's
# smallest primitive (a 5 mm cup) cannot slip between its points, whatever the part's size (a
# fixed count of 1,500 left 7.7 mm between the points of the 0.44 m gear shaft).
PART_OBSTACLE_GRID_M = 0.003


def body_sample_stride(spacing_m: float) -> int:
    """k: every k-th point of a part's evenly spread surface sample (points spacing_m apart, as
    OwnPoints measures it) stands for its body as an obstacle, k the points per
    PART_OBSTACLE_GRID_M square: a grid's density at a stride's cost (a grid over 20,000 points
    took 30 ms)."""
    return max(1, int((PART_OBSTACLE_GRID_M / max(spacing_m, 1e-6)) ** 2))


# The held part's sample on the arm's way out spaced about this (the walls it must clear are
# centimetres thick).
CARRIED_GRID_M = 0.01
UNSEEN = "contact not where the camera measured the part"
# A grasp whose part, pulled out, pushes into something ahead of it (binpick/picking/lift.py).
LIFTS_INTO = "the part lifts into "
# A part left unplanned: picks ranked before it were all that were asked for (max_picks).
NOT_PLANNED = "not planned: enough picks rank before it"
# A part the cell's grip failed on a moment ago, left alone for now (binpick/cell/retries.py).
GRIP_FAILED = "the gripper failed to hold it in an earlier attempt"
# A grasp whose contact lies where a grip failed before (binpick/cell/retries.py).
FAILED_HERE = "where a grip failed before"


@dataclass(frozen=True)
class Pick:
    """pose_index: the part (its index in the poses); T_cam_from_tool at pre-grasp, grasp and
    post-grasp (turned about the tool axis as the arm takes it, when it was checked); clearance_m
    of the swept gripper (capped at CLEARANCE_CAP_M); height_m of the part's centre above the
    support plane."""

    pose_index: int
    grasp_id: str
    grasp_index: int
    width_m: float
    T_cam_from_pregrasp: np.ndarray
    T_cam_from_grasp: np.ndarray
    T_cam_from_postgrasp: np.ndarray
    score: float
    clearance_m: float
    height_m: float
    trusted: bool = True  # the pose's seen-through share within max_seen_through (or not measured)
    arm: ArmMotion | None = None  # the arm's motion when the arm was checked (picking/arm.py)
    # What the part pushes on its way out when no part of the capture came out free and the pick
    # was taken past its neighbours (pick.lift_past_parts): 'part 3', 'captured points'.
    lifts_past: tuple[str, ...] = ()

    @property
    def retreat_cam(self) -> np.ndarray:
        """(3,) unit: the way the tool leaves the grasp, to the post-grasp pose (back along the
        approach, or straight up the bin: picking/lift.py)."""
        out = self.T_cam_from_postgrasp[:3, 3] - self.T_cam_from_grasp[:3, 3]
        norm = float(np.linalg.norm(out))
        return out / norm if norm > 0 else -self.T_cam_from_grasp[:3, 2]


@dataclass(frozen=True)
class Rejected:
    """A grasp tried and refused: its tool pose at the grasp and what it hit (or 'approach')."""

    pose_index: int
    grasp_id: str
    T_cam_from_grasp: np.ndarray
    reason: str


@dataclass(frozen=True)
class PickPlan:
    """picks in the order to take them; unpicked: (pose_index, reason) of parts without a pick;
    rejected: the grasps tried and refused; up_cam (3,) the bin's up axis."""

    picks: list[Pick]
    unpicked: list[tuple[int, str]]
    rejected: list[Rejected]
    up_cam: np.ndarray
    n_candidates: int

    def counts(self) -> dict[str, float]:
        return {
            "n_parts": float(len(self.picks) + len(self.unpicked)),
            "n_picks": float(len(self.picks)),
            "n_unpicked": float(len(self.unpicked)),
            "n_grasps_tried": float(self.n_candidates),
            "n_grasps_rejected": float(len(self.rejected)),
        }


def thin(points: np.ndarray, grid_m: float) -> np.ndarray:
    """One point per occupied cell of a grid, (m, 3)."""
    if len(points) == 0:
        return points.reshape(0, 3)
    return points[voxel_downsample_indices(points, grid_m)]


def plan_picks(
    T_cam_from_model: np.ndarray,
    scores: np.ndarray,
    grasps: GraspSet,
    part_points_m: np.ndarray,
    part_normals: np.ndarray,
    centre_m: np.ndarray,
    captured_m: np.ndarray,
    floor_plane: np.ndarray,
    params: PickParams,
    bin_box: BinBox | None = None,
    seen_through: np.ndarray | None = None,
    arm: ArmPlanner | None = None,
    q_from: np.ndarray | None = None,
    max_picks: int | None = None,
    skip: np.ndarray | None = None,
    failed_contacts_m: np.ndarray | None = None,
    wall_planes: np.ndarray | None = None,
    wall_band_m: float = 0.0,
    past_parts: bool = False,
) -> PickPlan:
    """Picks for the detected parts.

    When no part comes out of the heap free and some were refused only for what their way out
    pushes (pick.lift_past_parts), the parts are planned again (past_parts) with only the bin
    and its walls stopping a lift: a part with its neighbour's end resting on it or two parts
    crossed, the last of a heap, is taken anyway (the neighbour slides off or is lifted a little
    and drops back), those pushing the fewest parts first. On rendered T-joint bins of the cell
    benchmark, five of 20 parts ended in such a chain, each under the next, and the bin was left
    with them.

    T_cam_from_model : (p, 4, 4) detected parts' poses; scores (p,)
    grasps           : the part's grasps of the configured gripper, model frame, best first
    part_points_m    : (m, 3) the part's surface sample, model frame; part_normals (m, 3) its
                       outward unit normals; centre_m (3,) model frame
    captured_m       : (n, 3) everything the camera measured, camera frame
    floor_plane      : (4,) the support plane (NaN: none)
    seen_through     : (p,) each pose's seen-through share (registration/visibility.py; NaN or
                       None: not measured, trusted)
    arm              : the whole arm's check of a grasp the gripper check kept (None: the gripper
                       only); q_from (6,) the configuration the arm starts each pick from
    max_picks        : only the first this many picks are wanted (a cell executes one): parts are
                       tried in the order of the ranking's keys known before their grasps (up to
                       clearance); those that can no longer rank first are NOT_PLANNED; None: all
    skip             : (p,) bool, parts not to pick now (GRIP_FAILED); they stay obstacles
    failed_contacts_m: (k, 3) camera frame, where the tool centre point was at grips that failed:
                       grasps within the gripper's contact size of one are not tried (FAILED_HERE)
    wall_planes      : (w, 4) the bin walls found at import, camera frame; the captured points
                       within wall_band_m of one, like the given bin's faces, are a surface a part
                       lifted parallel to it slides along (lift.py)
    past_parts       : a way out is stopped only by the bin (its given faces, the captured points
                       on a wall found at import, the unseen walls); what else it pushes is the
                       pick's lifts_past
    """
    T_cam_from_model = np.asarray(T_cam_from_model, dtype=np.float64).reshape(-1, 4, 4)
    n_parts = len(T_cam_from_model)
    up, plane = support_frame(floor_plane, bin_box)
    cos_cone = np.cos(np.radians(params.approach_cone_deg))
    widest_deg = params.approach_cone_deg if params.fallback_cone_deg is None else params.fallback_cone_deg
    cos_widest = np.cos(np.radians(widest_deg))
    sin_widest = np.sin(np.radians(min(widest_deg, 90.0)))
    back = max(params.pregrasp_distance_m, params.retreat_distance_m)
    grid = max(OBSTACLE_GRID_M, params.clearance_m / 2.0)

    part_points = np.asarray(part_points_m, dtype=np.float64).reshape(-1, 3)
    own_of = OwnPoints(
        part_points, np.asarray(part_normals, dtype=np.float64).reshape(-1, 3), NOISE_BAND_FACTOR * params.own_points_m
    )
    stride = body_sample_stride(own_of.spacing_m)
    model_sample = part_points[::stride]
    model_normals = np.asarray(part_normals, dtype=np.float64).reshape(-1, 3)[::stride]
    # The part's way out is checked across the sample's spacing (its silhouette has no gaps).
    lift_radius = max(PART_OBSTACLE_GRID_M, params.clearance_m)
    posed = [transform_points(T, model_sample) for T in T_cam_from_model]
    # The part as the arm carries it out of the bin, about a centimetre between points.
    carried_sample = part_points[:: max(1, int((CARRIED_GRID_M / max(own_of.spacing_m, 1e-6)) ** 2))]
    captured = thin(np.asarray(captured_m, dtype=np.float64).reshape(-1, 3), grid)
    walls = np.zeros((0, 4)) if wall_planes is None else wall_planes
    side_walls = bin_box.side_planes() if bin_box is not None else walls
    spacing_m = point_spacing_m(captured)
    # Obstacle points with their source: -1 captured, -2 the bin (the given box's faces, else the
    # stretches of the walls found at import that the camera did not see), k >= 0 detected part k.
    bin_surface = (
        bin_box.surface(grid * 2)
        if bin_box is not None
        else unseen_walls(captured, walls, up, plane, wall_band_m, PART_OBSTACLE_GRID_M, 2.0 * spacing_m)
    )
    chunks = [captured] + ([bin_surface[0]] if bin_surface is not None else []) + posed
    # The walls' normals (NaN elsewhere): a part lifted along a wall it rests against is not
    # dragged into it.
    obstacle_normals = np.concatenate(
        [surface_normals(captured, walls, wall_band_m)]
        + ([bin_surface[1]] if bin_surface is not None else [])
        + [np.full((len(p), 3), np.nan) for p in posed]
    )
    sources = (
        [np.full(len(captured), -1)]
        + ([np.full(len(bin_surface[0]), -2)] if bin_surface is not None else [])
        + [np.full(len(p), k) for k, p in enumerate(posed)]
    )
    obstacles = np.concatenate(chunks) if chunks else np.zeros((0, 3))
    source = np.concatenate(sources) if sources else np.zeros(0, int)
    # Midpoint splits, nodes not shrunk to their points: 14-16 ms to build over the 100,000
    # obstacle points of an 8-part T-joint bin instead of 37-39 ms, and ball queries no slower.
    tree = cKDTree(obstacles, balanced_tree=False, compact_nodes=False) if len(obstacles) else None
    captured_tree = KDTree(image_coordinates(captured)) if len(captured) >= NOISE_NEIGHBOURS else None
    reach = (
        float(np.max(np.linalg.norm(model_sample - centre_m, axis=1))) + own_of.reach_m if len(model_sample) else 0.0
    )

    centres = np.array([T[:3, :3] @ centre_m + T[:3, 3] for T in T_cam_from_model]).reshape(-1, 3)
    heights = centres @ up + (plane[3] if plane is not None else 0.0)

    grasp_of = image_groups(grasps.ids)
    picks: list[Pick] = []
    unpicked: list[tuple[int, str]] = []
    rejected: list[Rejected] = []
    n_tried = 0
    shares = (
        np.full(n_parts, np.nan)
        if seen_through is None
        else np.asarray(seen_through, dtype=np.float64).reshape(n_parts)
    )
    trusted = ~(shares > params.max_seen_through)
    known = [known_keys(bool(trusted[i]), float(heights[i]), float(scores[i]), params) for i in range(n_parts)]
    order = sorted(range(n_parts), key=lambda k: (known[k], k))
    for n_done, i in enumerate(order):
        if max_picks is not None and len(picks) >= max_picks:
            last = sorted(picks, key=lambda p: rank_key(p, params))[max_picks - 1]
            if known[i] > known[last.pose_index]:
                unpicked.extend((k, NOT_PLANNED) for k in order[n_done:])
                break
        if skip is not None and skip[i]:
            unpicked.append((i, GRIP_FAILED))
            continue
        T = T_cam_from_model[i]
        # The target's own captured points: near its posed model surface (obstacle rows
        # 0..len(captured) are the captured points).
        own = np.zeros(len(obstacles), bool)
        noise_m, limit, centre = 0.0, params.own_points_m, 0.0
        if len(captured):
            near = captured_near(tree, len(captured), centres[i], reach)
            if len(near):
                nearest, offset = own_of.distances(transform_points(invert_T(T), captured[near]))
                band = np.isfinite(offset)
                noise_m = local_noise_m(captured, captured_tree, captured[near[band]])
                limit = max(params.own_points_m, OWN_NOISE_SIGMAS * noise_m)
                # About where the points sit (the seen depth's nearest-of-a-cell lies toward the camera).
                centre = seen_offset_m(offset[band], limit)
                close = nearest <= limit + abs(centre) + own_of.spacing_m
                own[near[(np.abs(offset - centre) <= limit) & close]] = True
        surface = PosedSurface(own_of, T, centre)
        tools = T @ grasps.T_model_from_tool if len(grasps) else np.zeros((0, 4, 4))
        near_lift = None  # what may lie in the part's way out, gathered once a grasp gets that far
        # What stops the part along each way out, by direction: the same for every grasp that
        # leaves that way (straight up, away from a wall). A gear shaft bin's captures had spent
        # 38 % of their time asking it again for each grasp.
        way_out_blockers: dict[bytes, tuple[dict[int, int], tuple[str, ...]]] = {}
        cos_approach = tools[:, :3, 2] @ -up if len(tools) else np.zeros(0)
        in_cone = cos_approach >= cos_cone - 1e-12
        # Beyond the cone, only when nothing within it is free (a part leaning on a wall, whose
        # upward faces the straight-down tool cannot reach): tilted grasps are the second choice.
        fallback = (cos_approach >= cos_widest - 1e-12) & ~in_cone
        causes: Counter[str] = Counter()
        n_out = int((~(in_cone | fallback)).sum())
        found: Pick | None = None
        tiers = [
            images_in_turn(np.flatnonzero(in_cone), grasp_of, -cos_approach, params.max_candidates_per_part),
            images_in_turn(np.flatnonzero(fallback), grasp_of, -cos_approach, params.max_candidates_per_part),
        ]
        candidates = np.concatenate(tiers).astype(np.int64)
        failed_here = 0
        if failed_contacts_m is not None and len(candidates):
            again = near_contacts(tools[candidates, :3, 3], failed_contacts_m, contact_size_m(params, grasps.kind))
            failed_here = int(again.sum())
            candidates = candidates[~again]
        # Grasps with less than room_m about the gripper wait until the part's others are tried:
        # a neighbour leaning on the part drops into the room it leaves as it comes out, toward
        # the tool (bench cell: a T-joint tipped 2.9 mm into the tool 0.13 s into the lift of its
        # neighbour, the swept tool having passed 3.2 mm from it).
        tight: list[int] = []
        for g, deferred in _in_turn(candidates, in_cone, tight):
            n_tried += int(not deferred)
            T_tool = tools[g]
            if not contact_seen(
                T_tool, grasps.kind, float(grasps.width_m[g]), captured, tree, params, noise_m, spacing_m, surface
            ):
                causes[UNSEEN] += 1
                rejected.append(Rejected(i, grasps.ids[g], T_tool, UNSEEN))
                continue
            tool = gripper_primitives(params, grasps.kind, float(grasps.width_m[g]))
            body = swept(tool, back)
            hit, clearance = tool_collisions(body, T_tool, tree, obstacles, source, i, own, plane, params.clearance_m)
            if hit:
                causes.update(hit)
                rejected.append(Rejected(i, grasps.ids[g], T_tool, ", ".join(sorted(hit))))
                continue
            if clearance < params.room_m and not deferred:
                tight.append(g)
                continue
            # The part itself, out of the heap and up a diameter, must come free (lift.py).
            if near_lift is None:
                normals_cam = model_normals @ T[:3, :3].T
                near_lift = np.asarray(tree.query_ball_point(centres[i], 3 * reach + back) if tree else [], np.int64)
                # The same for every grasp of the part: gathered once (170,000 points about a gear
                # shaft took 14 ms a grasp).
                ahead = near_lift[(source[near_lift] != i) & ~own[near_lift]]
                ahead_points = obstacles[ahead]
                # Only what lies across the part's way out can stop it (lift.across_the_way_out:
                # the way tilted at most to the widest cone, moved retreat_distance_m along).
                sideways_m = (params.retreat_distance_m + lift_radius + 2 * limit) * sin_widest + lift_radius
                across = across_the_way_out(posed[i], up, ahead_points, sideways_m)
                ahead, ahead_points = ahead[across], ahead_points[across]
                ahead_sources, ahead_normals = source[ahead], obstacle_normals[ahead]
                # The bin: its faces and the captured points on a wall (those with a known normal).
                fixed = (ahead_sources == -2) | np.isfinite(ahead_normals[:, 0])
                resting_on = walls_touched(posed[i], centres[i], side_walls, lift_radius + 2 * limit)
            retreat: np.ndarray | None = None
            dragged: set[str] = set()
            pushed: tuple[str, ...] = ()
            for direction in way_outs(T_tool[:3, 2], up, params.leave_straight_up, resting_on):
                if float(direction @ -T_tool[:3, 2]) < 1.0 - 1e-9 and tree is not None:
                    # Off the tool's axis its own way out is not in the swept check above.
                    tool_hit = moved_tool_hits(
                        tool,
                        T_tool,
                        params.retreat_distance_m * direction,
                        tree,
                        obstacles,
                        source,
                        i,
                        own,
                        params.clearance_m,
                    )
                    if tool_hit:
                        dragged |= tool_hit
                        continue
                key = np.asarray(direction, dtype=np.float64).tobytes()
                if key not in way_out_blockers:
                    moves = [(direction, params.retreat_distance_m), (up, 2.0 * reach)]
                    blockers = lift_blockers(
                        posed[i],
                        normals_cam,
                        moves,
                        ahead_points,
                        ahead_sources,
                        lift_radius,
                        lift_radius + 2 * limit,
                        ahead_normals,
                    )
                    pushes: tuple[str, ...] = ()
                    if blockers and past_parts:
                        stopped = lift_blockers(
                            posed[i],
                            normals_cam,
                            moves,
                            ahead_points[fixed],
                            ahead_sources[fixed],
                            lift_radius,
                            lift_radius + 2 * limit,
                            ahead_normals[fixed],
                        )
                        if not stopped:
                            pushes = tuple(_name(source_name(b)) for b in sorted(blockers, key=lambda b: (b < 0, b)))
                            blockers = {}
                    way_out_blockers[key] = (blockers, pushes)
                blockers, pushes = way_out_blockers[key]
                if not blockers:
                    retreat, pushed = direction, pushes
                    break
                dragged |= {LIFTS_INTO + _name(source_name(b)) for b in blockers}
            if retreat is None:
                causes.update(sorted(dragged))  # a set's order changes from run to run
                rejected.append(Rejected(i, grasps.ids[g], T_tool, ", ".join(sorted(dragged))))
                continue
            motion = None
            if arm is not None and q_from is not None:
                planned = arm.plan(
                    T_tool, grasps.T_model_from_tool[g], grasps.kind, centre_m, q_from, carried_sample, retreat
                )
                if isinstance(planned, str):
                    causes[planned] += 1
                    rejected.append(Rejected(i, grasps.ids[g], T_tool, planned))
                    continue
                motion = planned
                T_tool = turned(T_tool, np.radians(motion.turn_deg))
            approach = T_tool[:3, 2]
            found = Pick(
                i,
                grasps.ids[g],
                int(g),
                float(grasps.width_m[g]),
                _moved(T_tool, -params.pregrasp_distance_m * approach),
                T_tool,
                _moved(T_tool, params.retreat_distance_m * retreat),
                float(scores[i]),
                clearance,
                float(heights[i]),
                bool(trusted[i]),
                motion,
                pushed,
            )
            break
        if found is not None:
            picks.append(found)
            continue
        where_failed = f"; {failed_here} lie {FAILED_HERE}" if failed_here else ""
        if len(grasps) == 0:
            unpicked.append((i, f"the part has no {grasps.kind} grasps"))
        elif not causes and failed_here:
            unpicked.append((i, f"every grasp in reach lies {FAILED_HERE} ({failed_here})"))
        elif not causes:
            unpicked.append(
                (i, f"no reachable grasp: all {n_out} grasps approach outside the {widest_deg:g} degree cone")
            )
        elif set(causes) & ARM_REASONS:
            refused = ", ".join(f"{_name(k)} ({v})" for k, v in _most_first(causes))
            unpicked.append((i, f"no grasp in reach the arm can execute: {refused}{where_failed}"))
        else:
            hits = ", ".join(f"{_name(k)} ({v})" for k, v in _most_first(causes))
            unpicked.append(
                (
                    i,
                    f"every grasp in reach collides: with {hits}"
                    + (f"; {n_out} outside the approach cone" if n_out else "")
                    + where_failed,
                )
            )
    # Parts were tried in rank order; their refusals are listed by pose.
    unpicked.sort(key=lambda u: u[0])
    rejected.sort(key=lambda r: r.pose_index)
    if past_parts:
        picks.sort(key=lambda p: (len(p.lifts_past), rank_key(p, params)))
        return PickPlan(picks, unpicked, rejected, up, n_tried)
    picks.sort(key=lambda p: rank_key(p, params))
    if picks or not params.lift_past_parts or not any(LIFTS_INTO in why for _, why in unpicked):
        return PickPlan(picks, unpicked, rejected, up, n_tried)
    # Every part planned (their ranking by pushes is known only after): such heaps are the few
    # parts left at the bottom of a bin.
    past = plan_picks(
        T_cam_from_model, scores, grasps, part_points_m, part_normals, centre_m, captured_m, floor_plane, params,
        bin_box, seen_through, arm, q_from, None, skip, failed_contacts_m, wall_planes, wall_band_m, past_parts=True,
    )  # fmt: skip
    if not past.picks:
        return PickPlan(picks, unpicked, rejected, up, n_tried)
    return dataclasses.replace(past, n_candidates=n_tried + past.n_candidates)


def image_groups(ids: list[str]) -> np.ndarray:
    """(k,) for each grasp id, the rank of the grasp it is a symmetry image of (ids '<id>@<k>',
    grasps.expand_by_symmetry; an original is its own): the originals' order."""
    first: dict[str, int] = {}
    return np.array([first.setdefault(i.split("@")[0], len(first)) for i in ids], dtype=np.int64)


def images_in_turn(candidates: np.ndarray, grasp_of: np.ndarray, tilt: np.ndarray, cap: int) -> np.ndarray:
    """At most cap of the candidate grasps (indices, best first), all of them when they fit; else
    each grasp's symmetry images (grasp_of: image_groups) take turns: the image least tilted
    (tilt, per grasp) of every grasp in their order, then the second of each, and so on. A solid
    of revolution has 24 images of each grasp, about five of them within the approach cone: the
    first cap in list order were a few grasps' images about its centre, and a neighbour lying
    across those few left the part no pick however many grasps it had elsewhere."""
    if len(candidates) <= cap:
        return candidates
    grouped = candidates[np.lexsort((tilt[candidates], grasp_of[candidates]))]
    group = grasp_of[grouped]
    starts = np.flatnonzero(np.r_[True, group[1:] != group[:-1]])
    turn = np.arange(len(grouped)) - np.repeat(starts, np.diff(np.r_[starts, len(grouped)]))
    return grouped[np.lexsort((group, turn))][:cap]


def _in_turn(candidates: np.ndarray, in_cone: np.ndarray, tight: list[int]) -> Iterator[tuple[int, bool]]:
    """The grasps to try, (index, deferred): the tier within the cone, then the grasps of it that
    the loop put in tight, then the same for the fallback tier."""
    for tier in (candidates[in_cone[candidates]], candidates[~in_cone[candidates]]):
        tight.clear()
        yield from ((int(g), False) for g in tier)
        yield from ((g, True) for g in list(tight))


def _most_first(causes: Counter[str]) -> list[tuple[str, int]]:
    """The causes, most frequent first, equals by name: the same answer in every run."""
    return sorted(causes.items(), key=lambda kv: (-kv[1], kv[0]))


def _name(cause: str) -> str:
    return f"part {cause}" if cause.isdigit() else cause


def _moved(T: np.ndarray, offset: np.ndarray) -> np.ndarray:
    out = T.copy()
    out[:3, 3] += offset
    return out
