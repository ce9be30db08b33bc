"""Picks the arm can execute: a grasp the gripper check kept (picking/plan.py) is given to the arm,
turned about the suction cup's axis (or the jaws flipped) to the turn the arm reaches with the
least motion, away from its joint limits and singularities, and kept only when the arm's links
stay clear of the table and of what the camera measured all the way from where the arm is, down
along the approach, up out of the bin and over to the place (the gripper too, outside the
approach), and the place is reachable holding the part by this grasp.

Frames: base (the robot's), camera, tool (the tool centre point, z the approach), flange; a pose
T_a_from_b maps b coordinates to a. Motion is in joint space along straight lines (robot/trajectory.py),
but for the lift: from the post-grasp up to the lift the tool runs the straight line up that the
gripper check swept the part along (picking/lift.py), a chain of configurations LIFT_STEP_M
apart followed without stopping (a straight joint line strays 1-2 cm sideways over 20 cm and
drags the part into its neighbours).

The motion of one pick, through the named configurations (ArmMotion.path, the first of these
whose path is clear):
from (home or the last place) -> pregrasp -> grasp -> postgrasp -> lift -> [place_above ->] place
from -> pregrasp_above -> pregrasp -> grasp -> postgrasp -> lift -> [place_above ->] place
where postgrasp is the grasp moved back along the approach (or straight up the bin, where the
gripper check chose that way out: picking/lift.py), lift the post-grasp pose and pregrasp_above
the pre-grasp pose raised by cell.lift_m along the base's vertical (the same pose when the part
leaves back along the approach: the tool comes down and goes up one line); place_above is
left out at a drop zone (the part is let go from above). The target part itself is not an obstacle
of the links (the tool meets it; the gripper check has the tool), and the arm's base link is left
out (it stands beside the bin and does not move). The held part is checked (a sample about a
centimetre apart) from the lift on; on its straight way up out of the pile the gripper check's
lift check has it (a neighbour lying on it, which the camera may not show, is the physics
cell's to find).
"""

from __future__ import annotations

import itertools
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from binpick.geometry.transforms import invert_T
from binpick.params import CellParams
from binpick.picking.place import place_tool_poses
from binpick.registration.visibility import DepthView
from binpick.robot.arm import LINK_SAMPLE_SPACING_M, ArmModel
from binpick.robot.clearance import collides, near_planes, obstacle_view
from binpick.robot.configuration import (
    JOINT_LIMIT,
    SINGULAR,
    UNREACHABLE,
    choose_configuration,
    follow,
    ur_singularity_margin,
)
from binpick.robot.payload import Payload, carry_share, point_accelerations
from binpick.robot.trajectory import JointLimits, duration_s, line_samples, stops_duration_s

WAYPOINTS = ("pregrasp_above", "lift", "pregrasp", "grasp", "postgrasp", "place_above", "place")
# Reasons the arm refuses a grasp (beside robot.configuration's unreachable, joint limit, singular).
HITS_WALL, HITS_SCENE, HITS_TABLE, PLACE_UNREACHABLE, TOO_HEAVY = (
    "arm hits the bin wall",
    "arm hits the scene",
    "arm hits the table",
    "place unreachable with this grasp",
    "too heavy for the gripper",
)
ARM_REASONS = frozenset(
    {UNREACHABLE, JOINT_LIMIT, SINGULAR, HITS_WALL, HITS_SCENE, HITS_TABLE, PLACE_UNREACHABLE, TOO_HEAVY}
)
# A colliding link point this near a wall plane of the capture hit the bin wall.
WALL_BAND_M = 0.03
# Consecutive configurations of the short moves in the bin (5-20 cm) turn no joint further than this:
# more means the solver jumped to another branch (near a singularity), not a move to make.
MAX_SHORT_MOVE_RAD = 1.0
# Of a grasp's turns the least-motion ones whose paths are checked, and of the place's poses for each.
MAX_TURNS_CHECKED, MAX_PLACES_CHECKED = 6, 4
# Configurations whose links are checked in one pass.
PATH_CHUNK = 64
# The lift's straight line is followed through configurations this far apart (the joint line
# between two strays well under a millimetre); a joint turning more between two is a branch jump.
LIFT_STEP_M = 0.01
MAX_CHAIN_STEP_RAD = MAX_SHORT_MOVE_RAD / 4


@dataclass(frozen=True)
class ArmMotion:
    """The arm's plan of one pick: q (waypoint -> (6,) joint angles, WAYPOINTS), the turn about
    the tool's axis it chose (degrees, from the grasp's own), the tool's pose at the place
    (T_base_from_place_tcp), the motion's seconds at the scaled joint limits and the path: the
    waypoints in the order the arm moves through them from where it starts (straight joint
    lines, stopping at each, or along a chain in `lines`); carry_share: the share of the joint
    speed from the grasp on, where the gripper holds the part (binpick/robot/payload.py; 1: the
    part's weight unknown or light enough for the full speed); lines: waypoint -> (k, 6) the
    chain of configurations from the waypoint before it to it, the tool on a straight line (the
    lift), followed without stopping."""

    q: dict[str, np.ndarray]
    turn_deg: float
    T_base_from_place_tcp: np.ndarray
    motion_s: float
    path: tuple[str, ...]
    carry_share: float = 1.0
    lines: dict[str, np.ndarray] = field(default_factory=dict)


def turned(T: np.ndarray, angle_rad: float) -> np.ndarray:
    """The pose T (4, 4) turned about its own z axis by angle_rad."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    R = np.array([[c, -s, 0.0, 0.0], [s, c, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
    return T @ R


def raised(T: np.ndarray, height_m: float) -> np.ndarray:
    """The pose T (4, 4) moved up the base's z by height_m."""
    out = np.array(T, dtype=float)
    out[2, 3] += height_m
    return out


class ArmPlanner:
    """The arm's checks for one capture: built once (the obstacle z-buffer), asked per grasp."""

    def __init__(
        self,
        arm: ArmModel,
        cell: CellParams,
        T_base_from_cam: np.ndarray,
        seen: DepthView,
        wall_planes_cam: np.ndarray,
        pregrasp_m: float,
        retreat_m: float,
        tool_points_tcp: np.ndarray | None = None,
        tool_clearance_m: float = 0.0,
        check_path: bool = True,
        payload: Payload | None = None,
        oval_cup: bool = False,
    ) -> None:
        """tool_points_tcp: (n, 3) the gripper's surface, tool frame, checked on the moves to the
        pre-grasp and from the lift on (tool_clearance_m: pick.clearance_m; along the approach the
        gripper check has it); check_path False: the grasp's own turn only, its path not checked
        (today's hand-over of a gripper-only pick to the arm, the cell benchmark's baseline);
        payload: the part's mass and the gripper's hold (None: unknown, the carry at full speed);
        oval_cup: the suction cup's lip is oval (it turns about its axis by half a turn only)."""
        self.arm, self.cell = arm, cell
        self.T_base_from_cam = np.asarray(T_base_from_cam, dtype=float)
        self.T_cam_from_base = invert_T(self.T_base_from_cam)
        self.T_tcp_from_flange = invert_T(np.asarray(cell.T_flange_from_tcp, dtype=float))
        self.view = obstacle_view(seen, cell.arm_clearance_m + LINK_SAMPLE_SPACING_M / 2.0)
        self.walls = np.asarray(wall_planes_cam, dtype=float).reshape(-1, 4)
        self.pregrasp_m, self.retreat_m = pregrasp_m, retreat_m
        self.limits = JointLimits(arm.max_velocity_rad_s, arm.max_acceleration_rad_s2).scaled(cell.speed_scaling)
        self.margin = np.radians(cell.joint_limit_margin_deg)
        self.check_path = check_path
        tool = np.zeros((0, 3)) if tool_points_tcp is None else np.asarray(tool_points_tcp, dtype=float)
        # The tool's points in the flange frame, carried by the last link (wrist 3).
        T = np.asarray(cell.T_flange_from_tcp, dtype=float)
        self.tool_points_flange = tool @ T[:3, :3].T + T[:3, 3]
        self.tool_clearance_m = tool_clearance_m
        self.payload = payload
        self.oval_cup = oval_cup

    def configuration(self, T_base_from_tcp: np.ndarray, q_ref: np.ndarray) -> tuple[np.ndarray, str | None]:
        """The arm's configuration (6,) with the tool at T_base_from_tcp nearest q_ref, or NaN and why
        not; solutions that put a link below the table are not candidates (an elbow-down branch
        where the elbow-up one reaches)."""
        solutions = self.arm.ik(T_base_from_tcp @ self.T_tcp_from_flange)
        if len(solutions) and self.check_path:
            points, link = self.arm.surface_points(solutions)
            above = np.all(points[:, link > 0, 2] >= self.cell.table_z_m + self.cell.arm_clearance_m, axis=1)
            if not above.any():
                return np.full(6, np.nan), HITS_TABLE
            solutions = solutions[above]
        choice = choose_configuration(
            solutions,
            q_ref,
            self.arm.lower_rad,
            self.arm.upper_rad,
            self.limits.max_velocity,
            self.margin,
            ur_singularity_margin(solutions, self.arm.upper_arm_m, self.arm.forearm_m) if len(solutions) else None,
            self.cell.min_singularity,
        )
        return choice.q, choice.reason

    def plan(
        self,
        T_cam_from_tool: np.ndarray,
        T_model_from_tool: np.ndarray,
        kind: str,
        centre_m: np.ndarray,
        q_from: np.ndarray,
        part_points_m: np.ndarray | None = None,
        retreat_cam: np.ndarray | None = None,
    ) -> ArmMotion | str:
        """The motion for the grasp of gripper `kind` at T_cam_from_tool (T_model_from_tool on the
        part, whose centre is centre_m, model frame), the tool turned about its axis (turns_for)
        to the turn the arm reaches with the least motion from q_from whose place is reachable
        and whose path is clear; else why none is (the commonest reason). retreat_cam (3,): the
        way the tool leaves the grasp, camera frame, unit (None: back along the approach)."""
        if retreat_cam is None:
            retreat_cam = -np.asarray(T_cam_from_tool, dtype=float)[:3, 2]
        retreat_base = self.T_base_from_cam[:3, :3] @ np.asarray(retreat_cam, dtype=float)
        if self.payload is not None and not self.payload.lifts():
            return TOO_HEAVY
        reasons: Counter[str] = Counter()
        # The turns ranked by the move to their grasp configuration; the rest of a turn's motion is
        # worked out only when it comes up (most picks take the first).
        reachable: list[tuple[float, float, np.ndarray]] = []
        for angle in turns_for(kind, self.cell.turn_step_deg, self.oval_cup) if self.check_path else np.zeros(1):
            q_grasp, why = self.configuration(self.T_base_from_cam @ turned(T_cam_from_tool, float(angle)), q_from)
            if why:
                reasons[why] += 1
                continue
            reachable.append((duration_s(q_from, q_grasp, self.limits), float(angle), q_grasp))
        # The pick side (to the grasp and up to the lift) and the place side (from the lift on) are
        # checked apart: a turn whose pick side is blocked is not tried again for every place.
        for _, angle, q_grasp in sorted(reachable, key=lambda c: c[0])[:MAX_TURNS_CHECKED]:
            in_bin = self._in_bin(T_cam_from_tool, angle, q_grasp, retreat_base)
            if isinstance(in_bin, str):
                reasons[in_bin] += 1
                continue
            q, lines = in_bin
            pick_side = self._clear_pick_side(q, lines, q_from)
            if isinstance(pick_side, str):
                reasons[pick_side] += 1
                continue
            placed, hit = False, None
            places = self._places(turned(T_model_from_tool, angle), centre_m, q["lift"])
            for q_above, q_place, T_place in itertools.islice(places, MAX_PLACES_CHECKED):
                placed = True
                q.update(place_above=q_above, place=q_place)
                if self.check_path:
                    # A drop zone takes the part from above: no coming down onto it.
                    place_side = ("place",) if self.cell.place.kind == "drop" else ("place_above", "place")
                    # The part hangs from the tool from the lift on: it must clear the bin's walls too.
                    carried = None
                    if part_points_m is not None:
                        T = np.asarray(self.cell.T_flange_from_tcp, dtype=float) @ invert_T(
                            turned(T_model_from_tool, angle)
                        )
                        carried = part_points_m @ T[:3, :3].T + T[:3, 3]
                    hit = self.path_hit(
                        [q[pick_side[-1]]] + [q[n] for n in place_side], [True] * len(place_side), carried
                    )
                else:
                    place_side, hit = ("place_above", "place"), None
                if hit is None:
                    names = pick_side + place_side
                    at = names.index("grasp") + 1
                    # The lift's chain is timed as the line it is, the carry's accelerations from
                    # the joint line between its ends (alike but for the 1-2 cm stray).
                    share = self._carry_share(
                        [q[name] for name in names[at - 1 :]], turned(T_model_from_tool, angle), centre_m
                    )
                    if share is None:
                        reasons[TOO_HEAVY] += 1
                        break
                    stops = [lines.get(name, q[name]) for name in names]
                    seconds = stops_duration_s(q_from, stops[:at], self.limits) + stops_duration_s(
                        q["grasp"], stops[at:], self.limits.scaled(share)
                    )
                    return ArmMotion(dict(q), float(np.degrees(angle)), T_place, seconds, names, share, lines)
            if not placed:
                reasons[PLACE_UNREACHABLE] += 1
            elif hit is not None:
                reasons[hit] += 1
        return reasons.most_common(1)[0][0] if reasons else UNREACHABLE

    def _carry_share(
        self, carry: list[np.ndarray], T_model_from_tool: np.ndarray, centre_m: np.ndarray
    ) -> float | None:
        """The share of the joint speed at which the gripper holds the part (its centre, model
        frame, held by the grasp T_model_from_tool) along the carry's waypoints; 1 without a
        payload, None when no share down to payload.MIN_CARRY_SHARE does."""
        if self.payload is None:
            return 1.0
        T_flange_from_model = np.asarray(self.cell.T_flange_from_tcp, dtype=float) @ invert_T(T_model_from_tool)
        centre_flange = T_flange_from_model[:3, :3] @ np.asarray(centre_m, dtype=float) + T_flange_from_model[:3, 3]
        return carry_share(point_accelerations(self.arm, carry, self.limits, centre_flange), self.payload)

    def _clear_pick_side(
        self, q: dict[str, np.ndarray], lines: dict[str, np.ndarray], q_from: np.ndarray
    ) -> tuple[str, ...] | str:
        """The waypoints from q_from down to the grasp and up out of the bin, the first order whose
        path is clear (straight to the pre-grasp, else down from above it; out to the post-grasp,
        then up to the lift); or why neither is.
        Unchecked (check_path False): the pick as today's pick list hands it over."""
        if not self.check_path:
            return ("pregrasp", "grasp", "postgrasp")
        # Out to the post-grasp first, whatever its direction: a joint-space line straight from the
        # grasp to the lift strays sideways by centimetres and drags the part along its neighbours.
        out = ("postgrasp", "lift")
        hit = None
        # Down from straight above the pre-grasp, not from the lift: after a grasp left straight
        # up, the lift lies over the grasp, and a line from it to the pre-grasp swings the tool
        # sideways into the target (the arm's check leaves the target to the gripper check).
        for names in (("pregrasp", "grasp", *out), ("pregrasp_above", "pregrasp", "grasp", *out)):
            waypoints, flags = [q_from], []
            for name, flag in zip(names, _tool_checked(names), strict=True):
                inner = list(lines[name][1:-1]) if name in lines else []  # a chain's own configurations
                waypoints += [*inner, q[name]]
                flags += [flag] * (len(inner) + 1)
            hit = self.path_hit(waypoints, flags)
            if hit is None:
                return names
        assert hit is not None
        return hit

    def _in_bin(
        self, T_cam_from_tool: np.ndarray, angle: float, q_grasp: np.ndarray, retreat_base: np.ndarray
    ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]] | str:
        """The configurations at the pre-grasp, post-grasp (retreat_base (3,) the way there from the
        grasp, base frame, unit), lift and above the pre-grasp with the tool turned by angle, on the
        branch of the grasp's (q_grasp), with it, and the lift's chain ({"lift": (k, 6)}: the tool's
        straight line up from the post-grasp); or why there are none."""
        grasp = self.T_base_from_cam @ turned(T_cam_from_tool, angle)
        poses = {"grasp": grasp, "pregrasp": _back(grasp, grasp[:3, 2] * self.pregrasp_m)}
        poses["postgrasp"] = _back(grasp, -retreat_base * self.retreat_m)
        poses["lift"] = raised(poses["postgrasp"], self.cell.lift_m)
        poses["pregrasp_above"] = raised(poses["pregrasp"], self.cell.lift_m)
        q: dict[str, np.ndarray] = {"grasp": q_grasp}
        steps = (("pregrasp", "grasp"), ("postgrasp", "grasp"), ("lift", "postgrasp"), ("pregrasp_above", "pregrasp"))
        for name, ref in steps:
            q[name], why = self.configuration(poses[name], q[ref])
            if why:
                return why
            if np.max(np.abs(q[name] - q[ref])) > MAX_SHORT_MOVE_RAD:
                return UNREACHABLE
        if not self.check_path:
            return q, {}  # the baseline's hand-over goes no further than the post-grasp
        chain = self._chain(poses["postgrasp"], q["postgrasp"], q["lift"])
        return (q, {"lift": chain}) if isinstance(chain, np.ndarray) else chain

    def _chain(self, T_base_from_start: np.ndarray, q_start: np.ndarray, q_end: np.ndarray) -> np.ndarray | str:
        """(k, 6) configurations from q_start to q_end (the lift, cell.lift_m straight up from the
        tool pose T_base_from_start), the tool LIFT_STEP_M apart on the line; or why the arm
        cannot follow the line (robot.configuration.follow)."""
        n = max(1, int(np.ceil(self.cell.lift_m / LIFT_STEP_M)))
        poses = [raised(T_base_from_start, self.cell.lift_m * k / n) @ self.T_tcp_from_flange for k in range(1, n)]
        lower, upper = self.arm.lower_rad + self.margin, self.arm.upper_rad - self.margin
        chain = follow([self.arm.ik(T) for T in poses], q_start, lower, upper, MAX_CHAIN_STEP_RAD)
        if isinstance(chain, str):
            return chain
        if np.max(np.abs(q_end - chain[-1])) > MAX_CHAIN_STEP_RAD:
            return UNREACHABLE  # the lift's configuration lies on another branch
        return np.vstack([chain, q_end])

    def _places(
        self, T_model_from_tool: np.ndarray, centre_m: np.ndarray, q_lift: np.ndarray
    ) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """(q_place_above, q_place, T_base_from_place_tcp) for the part held by T_model_from_tool:
        the place's reachable tool poses, the quickest move from the lift first, then the least
        joint travel. (Ordered by the tool's turn about the vertical instead, the wrist turned
        back against the base's swing to the place, up to 2.6 rad there and back again on the
        way to the next pick.)"""
        reachable: list[tuple[float, float, int, np.ndarray]] = []
        candidates = place_tool_poses(self.cell.place, T_model_from_tool, centre_m)
        for k, T_place in enumerate(candidates):
            q_place, why = self.configuration(T_place, q_lift)
            if not why:
                seconds = round(duration_s(q_lift, q_place, self.limits), 3)  # ties: the slowest joint's move
                reachable.append((seconds, float(np.sum(np.abs(q_place - q_lift))), k, q_place))
        for _, _, k, q_place in sorted(reachable, key=lambda r: r[:3]):
            q_above, why = self.configuration(raised(candidates[k], self.cell.place.above_m), q_place)
            if why or np.max(np.abs(q_above - q_place)) > MAX_SHORT_MOVE_RAD:
                continue
            yield q_above, q_place, candidates[k]

    def path_hit(
        self, waypoints: list[np.ndarray], with_tool: list[bool] | None = None, carried: np.ndarray | None = None
    ) -> str | None:
        """Why the straight joint-space path through the configurations is not clear (the links,
        and the tool on the segments with_tool says, with the part it carries there: carried (k, 3)
        flange frame, against the table and what the camera measured), None when it is."""
        flags = with_tool or [False] * (len(waypoints) - 1)
        for tool in (False, True):
            segments = [
                line_samples(a, b, self.cell.max_step_rad)[1:]
                for a, b, f in zip(waypoints[:-1], waypoints[1:], flags, strict=True)
                if f == tool or not tool
            ]
            samples = np.concatenate(segments) if segments else np.zeros((0, 6))
            for start in range(0, len(samples), PATH_CHUNK):
                hit = self.configurations_hit(samples[start : start + PATH_CHUNK], tool, carried if tool else None)
                if hit:
                    return hit
            if not any(flags):
                break
        return None

    def configurations_hit(
        self, q: np.ndarray, with_tool: bool = False, carried: np.ndarray | None = None
    ) -> str | None:
        """Why the arm at any of the configurations q (N, 6) touches the table it stands on
        (HITS_TABLE: below cell.table_z_m, the camera need not see it) or what the camera measured
        (HITS_WALL near a wall plane of the capture, HITS_SCENE elsewhere), None when none does."""
        points, link = self.arm.surface_points(q)
        moving = points[:, link > 0].reshape(-1, 3)  # the base link stands still beside the bin
        clearance = np.full(len(moving), self.cell.arm_clearance_m)
        on_flange = self.tool_points_flange if with_tool else np.zeros((0, 3))
        if carried is not None:
            on_flange = np.concatenate([on_flange, carried])
        if len(on_flange):
            flange = self.arm.flange_poses(q)
            tool = np.matmul(on_flange[None], flange[:, :3, :3].transpose(0, 2, 1)) + flange[:, None, :3, 3]
            moving = np.concatenate([moving, tool.reshape(-1, 3)])
            clearance = np.concatenate([clearance, np.full(tool.shape[0] * tool.shape[1], self.tool_clearance_m)])
        if np.any(moving[:, 2] < self.cell.table_z_m + clearance):
            return HITS_TABLE
        cam = moving @ self.T_cam_from_base[:3, :3].T + self.T_cam_from_base[:3, 3]
        hit = collides(cam, self.view, clearance)
        if not hit.any():
            return None
        return HITS_WALL if near_planes(cam[hit], self.walls, WALL_BAND_M).any() else HITS_SCENE


def _tool_checked(names: tuple[str, ...]) -> list[bool]:
    """Per segment of a path (from its start through names): whether the tool is checked on it;
    not from the pre-grasp down to the grasp and out to the lift (the gripper check's)."""
    starts = ("from", *names[:-1])
    along_approach = {("pregrasp", "grasp"), ("grasp", "postgrasp"), ("grasp", "lift"), ("postgrasp", "lift")}
    return [(a, b) not in along_approach for a, b in zip(starts, names, strict=True)]


def _back(T: np.ndarray, offset: np.ndarray) -> np.ndarray:
    out = np.array(T, dtype=float)
    out[:3, 3] -= offset
    return out


def turns_for(kind: str, step_deg: float, oval_cup: bool = False) -> np.ndarray:
    """The turns about the tool axis a grasp of this kind may take: a round suction cup's any (in
    steps), the jaws' and an oval cup's half a turn (both are symmetric)."""
    if kind == "suction" and not oval_cup:
        return np.radians(np.arange(0.0, 360.0, step_deg))
    return np.array([0.0, np.pi])
