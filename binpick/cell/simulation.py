"""The cell in physics (pybullet): the bin, the parts in it, the arm from its URDF and the tool on
its flange. A pick's joint waypoints are executed along ruckig's time-optimal motions at the
simulator's step; the suction cup holds a part only where its lip seals on the part's true mesh,
the jaws only where both pads touch it, and the hold is a constraint whose force is limited to the
cup's rated holding force (the jaws' friction), so that a part too heavy for the lift's
acceleration, or hooked under a neighbour, is lost as it would be in the cell.

World frame: the bin frame (the floor's centre, z up), metres at the interface; the simulator runs
with lengths scaled by generation.physics.SCALE (its contact tolerances suit metre-sized bodies).
The arm and the tool are moved kinematically (their joint states set each step); they collide
with nothing by themselves, so every step asks the simulator for their closest points to the bin
and the parts: any within CONTACT_M is a touch.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from binpick.cell.robot import NO_GRIP, Execution, execute_pick
from binpick.cell.sim_contact import arrived, jaws_touch
from binpick.cell.sim_world import add_arm, add_boxes, add_part, add_tool
from binpick.generation.physics import SCALE, TIME_STEP_S, convex_parts_obj, quaternion_xyzw
from binpick.geometry.transforms import invert_T, make_T, transform_points
from binpick.io.part_model import PartModel
from binpick.params import CellParams, PickParams
from binpick.part.model import part_mass_kg
from binpick.picking.arm import ArmMotion
from binpick.picking.gripper import holding_force_n
from binpick.picking.seal import CONTACT_TOLERANCE_M, contact_tolerance_m, cup_seal
from binpick.robot.arm import LINK_SAMPLE_SPACING_M, ArmModel
from binpick.robot.trajectory import JointLimits, chain_motion, motion

# A body this close to the arm or the tool touches it (metres).
CONTACT_M = 0.0005
# Steps between two contact queries while the arm moves (at 240 Hz: every 17 ms; a link at the
# arm's 1.5 m/s moves 2.5 cm in that time, a touch that short would pass unseen).
CONTACT_EVERY = 4
# A held part this far from where the hold put it has torn off the cup (slipped out of the jaws):
# about what a bellows cup gives.
SLIP_M = 0.01
# Parts still faster than this after the pick are left to settle (at most SETTLE_S).
REST_SPEED_M_S, SETTLE_S = 0.002, 1.5
# The bin as generated is settled again in this world for at least this long before the first
# capture: its poses come from the generator's physics, and a part resting there on an edge may
# tip here. Three ring screws of three bins did, 1-2 s into the first pick, under no arm or
# tool: the pose was right to 0.1 mm at the capture, the part 27-35 mm away at the grip.
FIRST_SETTLE_S = 0.5


class SimulatedCell:
    """One bin of parts and the arm, in a pybullet world of its own (DIRECT, no window)."""

    def __init__(
        self,
        arm: ArmModel,
        cell: CellParams,
        pick: PickParams,
        kind: str,
        part: PartModel,
        density_kg_m3: float,
        bin_boxes: list[tuple[np.ndarray, np.ndarray]],
        inner_half_xy_m: tuple[float, float],
        T_bin_from_base: np.ndarray,
        T_bin_from_parts: np.ndarray,
        in_view: Callable[[np.ndarray], bool],
    ) -> None:
        import pybullet as pb

        self.pb, self.arm, self.cell, self.pick, self.kind, self.part = pb, arm, cell, pick, kind, part
        self.inner_half_xy_m = inner_half_xy_m
        self.T_bin_from_base = np.asarray(T_bin_from_base, dtype=float)
        self.T_flange_from_tcp = np.asarray(cell.T_flange_from_tcp, dtype=float)
        self.limits = JointLimits(arm.max_velocity_rad_s, arm.max_acceleration_rad_s2).scaled(cell.speed_scaling)
        self.in_view = in_view  # (n, 3) bin-frame points -> whether any lies in the camera's image
        self.client = pb.connect(pb.DIRECT)
        c = self.client
        pb.setGravity(0, 0, -9.81 * SCALE, physicsClientId=c)
        pb.setTimeStep(TIME_STEP_S, physicsClientId=c)
        pb.setPhysicsEngineParameter(numSolverIterations=50, deterministicOverlappingPairs=1, physicsClientId=c)
        # A table under the bin and the arm (the bin's ground reaches only just beyond its walls).
        self.bin_bodies, self.body_names = add_boxes(pb, c, bin_boxes)
        # Part bodies live in a frame at the centre of the part's box (as generation.physics).
        vertices = part.mesh_vertices_m
        self.centre_m = (vertices.min(axis=0) + vertices.max(axis=0)) / 2.0
        self.T_model_from_body = make_T(np.eye(3), self.centre_m)
        self.part_shape = pb.createCollisionShape(
            pb.GEOM_MESH, fileName=convex_parts_obj(vertices - self.centre_m, part.mesh_faces), physicsClientId=c
        )
        mesh = trimesh.Trimesh(part.mesh_vertices_m, part.mesh_faces, process=False)
        self.mass_kg = part_mass_kg(part, density_kg_m3)
        self.rays = trimesh.ray.ray_triangle.RayMeshIntersector(mesh)
        self.parts: list[int | None] = []
        for T in np.asarray(T_bin_from_parts, dtype=float):
            self.parts.append(self._add_part(T))
        self.robot, self.joint_index, self.link_of_sample = add_arm(pb, c, arm, self.T_bin_from_base)
        self.tool, self.tool_points = add_tool(pb, c, pick, kind)
        self.hold: int | None = None
        self.aimed: int | None = None
        self.hold_force = 0.0  # the hold's force limit, simulator units
        # One pick's record: the simulated clock, what was touched, when the grip came and the arm
        # left the camera's view after it, the part held, whether it arrived, parts out with it.
        self.clock_s, self.touched = 0.0, set[str]()
        self.gripped_at_s: float | None = None
        self.out_of_view_s: float | None = None
        self.target: int | None = None
        self.arrived, self.double, self.lost = False, 0, ""
        self.q = np.asarray(cell.home_q_rad, dtype=float)
        self._pose_arm(self.q, np.zeros(6))
        self._settle(FIRST_SETTLE_S)

    def _add_part(self, T_bin_from_model: np.ndarray) -> int:
        return add_part(self.pb, self.client, self.part_shape, self.mass_kg, T_bin_from_model @ self.T_model_from_body)

    # -- state

    def part_poses(self) -> tuple[np.ndarray, list[int]]:
        """(k, 4, 4) T_bin_from_model of the parts still in the world, and their indices."""
        poses, index = [], []
        for i, body in enumerate(self.parts):
            if body is None:
                continue
            poses.append(self._body_pose(body) @ invert_T(self.T_model_from_body))
            index.append(i)
        return np.array(poses).reshape(-1, 4, 4), index

    def in_bin(self) -> np.ndarray:
        """(k,) bool per part index: its centre within the bin's walls, above its floor (however
        high: a full bin's heap rises above the rim; what leaves the bin leaves its footprint)."""
        out = np.zeros(len(self.parts), bool)
        for i, body in enumerate(self.parts):
            if body is None:
                continue
            p = self._body_pose(body)[:3, 3]
            out[i] = bool(np.all(np.abs(p[:2]) < self.inner_half_xy_m) and p[2] > -0.01)
        return out

    def remove_outside(self) -> int:
        """Take the parts that left the bin out of the world (they fell out, or came out with a
        pick); how many."""
        gone = 0
        inside = self.in_bin()
        for i, body in enumerate(self.parts):
            if body is not None and not inside[i] and i != self.hold:
                self.pb.removeBody(body, physicsClientId=self.client)
                self.parts[i] = None
                gone += 1
        return gone

    def close(self) -> None:
        self.pb.disconnect(self.client)

    def _body_pose(self, body: int) -> np.ndarray:
        position, q = self.pb.getBasePositionAndOrientation(body, physicsClientId=self.client)
        R = np.asarray(self.pb.getMatrixFromQuaternion(q, physicsClientId=self.client)).reshape(3, 3)
        return make_T(R, np.asarray(position) / SCALE)

    def tcp_pose(self, q: np.ndarray) -> np.ndarray:
        """T_bin_from_tcp at joint angles q."""
        return self.T_bin_from_base @ self.arm.flange_pose(q) @ self.T_flange_from_tcp

    def _pose_arm(self, q: np.ndarray, qd: np.ndarray) -> None:
        pb, c = self.pb, self.client
        self.q_now = np.asarray(q, dtype=float)
        for j, angle, speed in zip(self.joint_index, q, qd, strict=True):
            pb.resetJointState(self.robot, j, float(angle), float(speed), physicsClientId=c)
        T = self.tcp_pose(q)
        pb.resetBasePositionAndOrientation(
            self.tool, (T[:3, 3] * SCALE).tolist(), quaternion_xyzw(T[:3, :3]).tolist(), physicsClientId=c
        )
        # The tool's velocity too: the hold's constraint then carries the part along with it instead
        # of pulling it after a tool that seems to stand still and jump (the part would lag).
        self.q_ahead = q + qd * TIME_STEP_S  # where the simulator's step carries what the tool holds
        ahead = self.tcp_pose(self.q_ahead)
        linear = (ahead[:3, 3] - T[:3, 3]) / TIME_STEP_S * SCALE
        turn = ahead[:3, :3] @ T[:3, :3].T
        angular = Rotation.from_matrix(turn).as_rotvec() / TIME_STEP_S
        pb.resetBaseVelocity(self.tool, linear.tolist(), angular.tolist(), physicsClientId=c)

    # -- execution

    # -- the robot's interface (binpick/cell/robot.py)

    def joints(self) -> np.ndarray:
        return self.q.copy()

    def move(self, path: list[np.ndarray], share: float = 1.0) -> None:
        """Through the configurations along ruckig's motions (at `share` of the joint speed),
        stepping the world; what the arm or the tool touches collects in `touched`, a held part
        that tears off is let go."""
        limits = self.limits.scaled(share)
        for q_next in path:
            trajectory = motion(self.q, q_next, limits)
            self._follow(np.asarray(q_next, dtype=float), trajectory.duration, trajectory.at_time)

    def move_line(self, chain: np.ndarray, share: float = 1.0) -> None:
        """Along the chain of configurations (k, 6) without stopping, as move does."""
        line = chain_motion(chain, self.limits.scaled(share))
        self._follow(np.asarray(chain[-1], dtype=float), line.duration, line.at_time)

    def _follow(self, q_next: np.ndarray, duration_s: float, at_time: Callable[[float], tuple]) -> None:
        """Step the world along a motion of duration_s to q_next: at_time(t) gives the
        configuration and joint velocities (6,) each, t seconds in."""
        self._aim(q_next)
        steps = max(1, int(np.ceil(duration_s / TIME_STEP_S)))
        for s in range(1, steps + 1):
            state = at_time(min(s * TIME_STEP_S, duration_s))
            q = np.asarray(state[0])
            self._pose_arm(q, np.asarray(state[1]))
            self.pb.stepSimulation(physicsClientId=self.client)
            self.clock_s += TIME_STEP_S
            if s % CONTACT_EVERY == 0 or s == steps:
                self.touched |= self._touches()
                if self.hold is not None and self._slipped():
                    self._let_go()
            if self.gripped_at_s is not None and self.out_of_view_s is None and not self._arm_in_view(q):
                self.out_of_view_s = self.clock_s
        self.q = q_next

    def grip(self, width_m: float) -> bool:
        self.clock_s += self._dwell(self.cell.robot.grip_s)
        self.gripped_at_s = self.clock_s
        self.target = self._grasp(width_m)
        return self.target is not None

    def holding(self) -> bool:
        return self.hold is not None

    def release(self) -> None:
        if self.hold is not None:
            self.arrived = self._arrived()
            others = np.array([b is not None for b in self.parts]) & (np.arange(len(self.parts)) != self.hold)
            self.double = int(np.sum(~self.in_bin() & others))
            self._release()
        self.clock_s += self._dwell(self.cell.robot.release_s)

    def _aim(self, q_next: np.ndarray) -> None:
        """The part the tool comes down on, when this move ends at a part's surface, or leaves,
        when it starts at one (backing out of a grip that did not take): the tool may touch it (a
        bellows cup gives), and no other."""
        aimed = None
        if self.hold is None:
            aimed = self._part_at(self.tcp_pose(q_next))
            if aimed is None:
                # The cup starts on the part it failed to seal on: leaving it is not touching it.
                aimed = self._part_at(self.tcp_pose(self.q))
        if aimed == self.aimed:
            return
        if self.aimed is not None and self.aimed != self.hold and self.parts[self.aimed] is not None:
            self._collide(self.tool, self.aimed, True)
        if aimed is not None:
            self._collide(self.tool, aimed, False)
        self.aimed = aimed

    # -- one pick, judged (bench cell)

    def execute(self, plan: ArmMotion, q_from: np.ndarray, width_m: float = 0.0) -> Execution:
        """The pick executed (robot.execute_pick) from q_from (where the arm is), then the rest
        left to settle: what it did, for the benchmark's judge."""
        assert np.allclose(q_from, self.q, atol=1e-6), "the arm is not where the plan starts"
        self.clock_s, self.touched, self.gripped_at_s, self.out_of_view_s = 0.0, set(), None, None
        self.target, self.arrived, self.double, self.lost = None, False, 0, ""
        state = execute_pick(self, plan, width_m)
        if state == "placed":
            outcome = "placed" if self.arrived else "misplaced"
        elif state == NO_GRIP:
            outcome = "no seal" if self.kind == "suction" else "no hold"
        else:
            outcome = "dropped"
        self._settle()
        return Execution(
            outcome,
            self.target,
            set(self.touched),
            self.double,
            self.clock_s,
            self.out_of_view_s if self.out_of_view_s is not None else self.clock_s,
            self.lost,
        )

    def _dwell(self, seconds: float) -> float:
        for _ in range(int(round(seconds / TIME_STEP_S))):
            self.pb.stepSimulation(physicsClientId=self.client)
        return seconds

    def _settle(self, at_least_s: float = 0.0) -> None:
        """Step the world until every part is slower than REST_SPEED_M_S (checked every 24 steps
        after at_least_s), at most at_least_s + SETTLE_S."""
        first = int(round(at_least_s / TIME_STEP_S))
        for step in range(first + int(SETTLE_S / TIME_STEP_S)):
            self.pb.stepSimulation(physicsClientId=self.client)
            if step >= first and step % 24 == 23:
                speeds = [
                    np.linalg.norm(self.pb.getBaseVelocity(b, physicsClientId=self.client)[0]) / SCALE
                    for b in self.parts
                    if b is not None
                ]
                if not speeds or max(speeds) < REST_SPEED_M_S:
                    break

    def _part_at(self, T_bin_from_tcp: np.ndarray) -> int | None:
        """The part whose true surface lies nearest the tool centre point, within 5 CONTACT_TOLERANCE_M
        (and half a bellows cup's travel)."""
        reach_m = 4 * CONTACT_TOLERANCE_M + (
            contact_tolerance_m(self.pick.suction) if self.kind == "suction" else CONTACT_TOLERANCE_M
        )
        best: tuple[float, int] | None = None
        for i, body in enumerate(self.parts):
            if body is None:
                continue
            local = transform_points(
                invert_T(self._body_pose(body) @ invert_T(self.T_model_from_body)), T_bin_from_tcp[:3, 3][None]
            )
            _, distance, _ = trimesh.proximity.closest_point(self.rays.mesh, local)
            if distance[0] <= reach_m and (best is None or distance[0] < best[0]):
                best = (float(distance[0]), i)
        return None if best is None else best[1]

    def _collide(self, body: int, part: int, enable: bool) -> None:
        """Switch collisions between every link of body (the tool, the arm) and a part on or off."""
        other = self.parts[part]
        assert other is not None
        for link in range(-1, self.pb.getNumJoints(body, physicsClientId=self.client)):
            self.pb.setCollisionFilterPair(body, other, link, -1, int(enable), physicsClientId=self.client)

    def _touches(self) -> set[str]:
        """What the arm's moving links, or the tool, are within CONTACT_M of: the table, the bin, or a
        part other than the one the tool comes down on or holds."""
        pb, c, d = self.pb, self.client, CONTACT_M * SCALE
        part_index = {body: i for i, body in enumerate(self.parts) if body is not None}
        out: set[str] = set()
        # Each moving link's box from the arm's own sampled surface (the simulator keeps no fresh
        # boxes for bodies it does not move itself), the tool's from its shapes, widened by the
        # sample's spacing; the simulator's candidates overlapping it, then their exact distance.
        points, index = self.arm.surface_points(self.q_now)
        T = self.T_bin_from_base
        points = points[0] @ T[:3, :3].T + T[:3, 3]
        tool = transform_points(self.tcp_pose(self.q_now), self.tool_points)
        movers = [(self.robot, j, points[index == k]) for k, j in self.link_of_sample.items()]
        movers.append((self.tool, -1, tool))
        for body, link, pts in movers:
            if len(pts) == 0:
                continue
            pad = LINK_SAMPLE_SPACING_M + CONTACT_M
            lo, hi = (pts.min(axis=0) - pad) * SCALE, (pts.max(axis=0) + pad) * SCALE
            near = pb.getOverlappingObjects(lo.tolist(), hi.tolist(), physicsClientId=c) or []
            for other, _ in {(o, None) for o, _ in near}:
                if other in (self.robot, self.tool):
                    continue
                i = part_index.get(other)
                if i is not None and (i == self.hold or (body == self.tool and i == self.aimed)):
                    continue
                if body == self.tool and pb.getClosestPoints(body, other, d, physicsClientId=c):
                    out.add("part" if i is not None else self.body_names.get(other, "bin"))
                elif body == self.robot and pb.getClosestPoints(body, other, d, linkIndexA=link, physicsClientId=c):
                    out.add("part" if i is not None else self.body_names.get(other, "bin"))
        return out

    def _arm_in_view(self, q: np.ndarray) -> bool:
        points, link = self.arm.surface_points(q)
        points = points[0] @ self.T_bin_from_base[:3, :3].T + self.T_bin_from_base[:3, 3]
        return bool(self.in_view(points))

    def _slipped(self) -> bool:
        """Whether the hold tears: the part has moved SLIP_M from where the hold keeps it in the tool
        frame (the hold's force, limited to the cup's or the jaws', could not keep it there; the
        force the simulator reports spikes with every step of the kinematic tool, so it is not the
        test)."""
        assert self.hold is not None
        body = self.parts[self.hold]
        assert body is not None
        T_tcp = self.tcp_pose(self.q_ahead)
        off = np.linalg.norm((invert_T(T_tcp) @ self._body_pose(body))[:3, 3] - self.T_tcp_from_body[:3, 3])
        return bool(off > SLIP_M)

    def _let_go(self) -> None:
        """The hold is lost: the part falls where it is, and collides again; `lost` says what the
        part touched as it tore off."""
        assert self.hold is not None
        body = self.parts[self.hold]
        part_index = {b: i for i, b in enumerate(self.parts) if b is not None}
        touching = {
            "another part" if c[2] in part_index else self.body_names.get(c[2], "the arm")
            for c in self.pb.getContactPoints(bodyA=body, physicsClientId=self.client)
        }
        where = self.tcp_pose(self.q_now)[:3, 3]
        self.lost = (f"touching {' and '.join(sorted(touching))}" if touching else "touching nothing") + (
            f", {1000 * (self.clock_s - (self.gripped_at_s or 0.0)):.0f} ms after the grip, the tool at"
            f" ({where[0]:.2f}, {where[1]:.2f}, {where[2]:.2f}) m in the bin frame"
        )
        self.pb.removeConstraint(self.constraint, physicsClientId=self.client)
        self._collide(self.tool, self.hold, True)
        self._collide(self.robot, self.hold, True)
        self.hold = None

    def _grasp(self, width_m: float) -> int | None:
        """The part the tool holds now (its index), or None: the cup's lip seals on one part's true
        mesh at the tool (the jaws' pads both touch one part); the hold is a constraint limited
        to the rated force."""
        T_tcp = self.tcp_pose(self.q)
        held = self._sealed_part(T_tcp) if self.kind == "suction" else self._jawed_part(T_tcp, width_m)
        if held is None:
            return None
        pb, c = self.pb, self.client
        body = self.parts[held]
        assert body is not None
        T_tcp_from_body = invert_T(T_tcp) @ self._body_pose(body)
        self.T_tcp_from_body = T_tcp_from_body
        # Held: the tool and the arm carry it, their shapes no longer push it.
        self._collide(self.tool, held, False)
        self._collide(self.robot, held, False)
        self.constraint = pb.createConstraint(
            self.tool,
            -1,
            body,
            -1,
            pb.JOINT_FIXED,
            [0, 0, 0],
            parentFramePosition=(T_tcp_from_body[:3, 3] * SCALE).tolist(),
            childFramePosition=[0, 0, 0],
            parentFrameOrientation=quaternion_xyzw(T_tcp_from_body[:3, :3]).tolist(),
            physicsClientId=c,
        )
        # Forces in the scaled world: kg * (m * SCALE) / s^2.
        self.hold_force = holding_force_n(self.pick, self.kind) * SCALE
        pb.changeConstraint(self.constraint, maxForce=self.hold_force, physicsClientId=c)
        self.hold = held
        return held

    def _model_pose(self, body: int) -> np.ndarray:
        """T_bin_from_model of a part's body."""
        return self._body_pose(body) @ invert_T(self.T_model_from_body)

    def _sealed_part(self, T_bin_from_tcp: np.ndarray) -> int | None:
        """The part whose true mesh the cup's lip seals on at this tool pose (picking/seal.py)."""
        for i, body in enumerate(self.parts):
            if body is not None:
                sealed = cup_seal(self.rays, invert_T(self._model_pose(body)) @ T_bin_from_tcp, self.pick.suction)
                if sealed is not None:
                    return i if sealed else None
        return None

    def _jawed_part(self, T_bin_from_tcp: np.ndarray, width_m: float) -> int | None:
        """The part both jaw pads touch (their centres, width_m apart along the closing axis) when
        the jaws close at this tool pose."""
        half = T_bin_from_tcp[:3, 0] * width_m / 2.0
        pads = np.stack([T_bin_from_tcp[:3, 3] - half, T_bin_from_tcp[:3, 3] + half])
        for i, body in enumerate(self.parts):
            if body is not None and jaws_touch(
                self.rays.mesh, transform_points(invert_T(self._model_pose(body)), pads)
            ):
                return i
        return None

    def _arrived(self) -> bool:
        """Whether the held part is where the place wants it (cell.place's kind and tolerances)."""
        assert self.hold is not None
        body = self.parts[self.hold]
        assert body is not None
        return arrived(invert_T(self.T_bin_from_base) @ self._model_pose(body), self.centre_m, self.cell.place)

    def _release(self) -> None:
        """Let go at the place and take the part out of the world (the next machine has it)."""
        assert self.hold is not None
        self.pb.removeConstraint(self.constraint, physicsClientId=self.client)
        body = self.parts[self.hold]
        if body is not None:
            self.pb.removeBody(body, physicsClientId=self.client)
        self.parts[self.hold] = None
        self.hold = None
