"""The robot behind one interface (`Robot`): the simulated cell (binpick/cell/simulation.py) or a
Universal Robots arm through ur_rtde (`URRobot`), and one pick executed on either
(`execute_pick`). Joint angles in radians, in the arm's joint order.

The real arm: joint moves with `moveJ` (a path of configurations, each reached at rest: speed and
acceleration are the leading joint's, the slowest joint's limit times cell.speed_scaling), the
lift's straight line with `moveL_FK` to its last configuration (the controller's own straight
line, at LINE_SPEED_M_S and LINE_ACCELERATION_M_S2 times the carry's share), the suction cup's vacuum
on a standard digital output and its vacuum sensor on a standard digital input
(cell.robot.vacuum_out / vacuum_in; no sensor: the hold is assumed). Not tried on hardware.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from types import ModuleType
from typing import Protocol

import numpy as np

from binpick.errors import BinpickError
from binpick.picking.arm import ArmMotion
from binpick.robot.trajectory import JointLimits

# What a pick on the robot came to (besides "placed").
NO_GRIP, GRASP_LOST, ARM_STOPPED = "no grip", "grasp lost", "arm stopped"
# The real arm's straight lines: the tool's speed m/s and acceleration m/s^2 (UR's moveL defaults).
LINE_SPEED_M_S, LINE_ACCELERATION_M_S2 = 0.25, 1.2


class RobotStopped(BinpickError):
    """The arm stopped on its own (a protective or emergency stop, the program ended): the cell must
    not go on until someone has looked."""


class Robot(Protocol):
    def joints(self) -> np.ndarray:
        """(6,) the arm's joint angles now."""
        ...

    def move(self, path: list[np.ndarray], share: float = 1.0) -> None:
        """Through the configurations in order (straight joint lines, at rest at each) at `share`
        of the joint speed (share^2 of the acceleration: the same motion, slower); raises
        RobotStopped when the arm stops on its own."""
        ...

    def move_line(self, chain: np.ndarray, share: float = 1.0) -> None:
        """Along the tool's straight line that the chain of configurations (k, 6) follows (from
        where the arm is to the last), without stopping, at `share` of the speed; raises
        RobotStopped when the arm stops on its own."""
        ...

    def grip(self, width_m: float) -> bool:
        """Vacuum on (jaws closed on a part width_m wide); whether it holds a part."""
        ...

    def holding(self) -> bool:
        """Whether the gripper still holds a part."""
        ...

    def release(self) -> None:
        """Vacuum off (jaws open)."""
        ...

    def close(self) -> None: ...


# A cell (and the benchmarks' simulated one) gives a bin up after this many failed attempts in a row.
MAX_FAILURES_IN_A_ROW = 3
# A cell executes the first pick of a capture and captures again: only that many are planned (the
# arm's plan is most of the pick step's time in a full bin).
PICKS_PER_CAPTURE = 1


@dataclass
class Execution:
    """What one pick did in the simulated cell.

    outcome: "placed" (the part arrived within tolerance), "misplaced" (arrived outside it),
    "no seal" / "no hold" (the cup did not seal / the jaws did not close on a part), "dropped"
    (held, then lost on the way); target: the body index of the part grasped (None: none);
    touched: what the arm or tool touched on the way ("bin", "part"); double: other parts that
    left the bin with it; motion_s: the arm's motion time including the dwell at the grasp and
    the place; out_of_view_s: when the arm left the camera's view after the grasp (seconds from
    the motion's start; the next capture may be taken from then).
    """

    outcome: str
    target: int | None
    touched: set[str] = field(default_factory=set)
    double: int = 0
    motion_s: float = 0.0
    out_of_view_s: float = 0.0
    lost: str = ""  # a dropped part: what it touched as it tore off

    @property
    def state(self) -> str:
        """The outcome as a robot reports it (execute_pick's states): NO_GRIP when nothing was
        held at the grasp, GRASP_LOST when the part fell on the way, "placed" when it was
        released at the place (where it came to rest is the outcome's business)."""
        if self.outcome in ("no seal", "no hold"):
            return NO_GRIP
        return GRASP_LOST if self.outcome == "dropped" else "placed"


def execute_pick(robot: Robot, motion: ArmMotion, width_m: float = 0.0) -> str:
    """Run one pick's motion on the robot: to the grasp, grip, out and over to the place, release.
    "placed", or NO_GRIP (nothing held at the grasp: the arm goes on without a part only back up
    to where it came down from), GRASP_LOST (the part fell on the way: the gripper is opened),
    ARM_STOPPED (RobotStopped: the arm stopped itself, nothing more is sent)."""
    at = motion.path.index("grasp")
    try:
        _move(robot, motion, motion.path[: at + 1])
        if not robot.grip(width_m):
            robot.release()
            robot.move([motion.q[motion.path[at - 1]]])  # back out along the approach
            return NO_GRIP
        # Carrying the part: no faster than the gripper's hold allows (binpick/robot/payload.py).
        _move(robot, motion, motion.path[at + 1 :], motion.carry_share)
        if not robot.holding():
            robot.release()
            return GRASP_LOST
        robot.release()
        return "placed"
    except RobotStopped:
        return ARM_STOPPED


def _move(robot: Robot, motion: ArmMotion, names: tuple[str, ...], share: float = 1.0) -> None:
    """Through the motion's waypoints `names`: joint lines, a waypoint with a chain along it."""
    run: list[np.ndarray] = []
    for name in names:
        if name in motion.lines:
            if run:
                robot.move(run, share)
                run = []
            robot.move_line(motion.lines[name], share)
        else:
            run.append(motion.q[name])
    if run:
        robot.move(run, share)


class URRobot:
    """A Universal Robots arm through ur_rtde's control, receive and IO interfaces."""

    def __init__(
        self,
        host: str,
        limits: JointLimits,
        vacuum_out: int,
        vacuum_in: int | None,
        grip_s: float,
        release_s: float,
        modules: tuple[ModuleType, ModuleType, ModuleType] | None = None,
    ) -> None:
        """modules: (rtde_control, rtde_receive, rtde_io) (default: imported; tests pass fakes)."""
        if modules is None:
            try:
                import rtde_control
                import rtde_io
                import rtde_receive
            except ImportError:
                raise BinpickError(
                    "the real robot needs ur_rtde: pip install -e .[robot] (or set cell.robot.driver: sim)"
                ) from None
            modules = (rtde_control, rtde_receive, rtde_io)
        control, receive, io = modules
        try:
            self.control = control.RTDEControlInterface(host)
            self.receive = receive.RTDEReceiveInterface(host)
            self.io = io.RTDEIOInterface(host)
        except RuntimeError as exc:
            raise BinpickError(f"cannot reach the robot at {host}: {exc}") from None
        # moveJ takes one speed and acceleration, the leading joint's: the slowest joint's limit.
        self.speed = float(np.min(limits.max_velocity))
        self.acceleration = float(np.min(limits.max_acceleration))
        self.vacuum_out, self.vacuum_in = vacuum_out, vacuum_in
        self.grip_s, self.release_s = grip_s, release_s

    def joints(self) -> np.ndarray:
        return np.asarray(self.receive.getActualQ(), dtype=float)

    def move(self, path: list[np.ndarray], share: float = 1.0) -> None:
        if not path:
            return
        # Blend 0: the arm stops at each configuration, the path the plan checked.
        speed, acceleration = self.speed * share, self.acceleration * share**2
        moves = [[*map(float, q), speed, acceleration, 0.0] for q in path]
        if not self.control.moveJ(moves):
            raise RobotStopped(self._why_stopped())

    def move_line(self, chain: np.ndarray, share: float = 1.0) -> None:
        end = [float(x) for x in np.asarray(chain)[-1]]
        if not self.control.moveL_FK(end, LINE_SPEED_M_S * share, LINE_ACCELERATION_M_S2 * share**2):
            raise RobotStopped(self._why_stopped())

    def _why_stopped(self) -> str:
        if self.receive.isEmergencyStopped():
            return "the arm is emergency-stopped"
        if self.receive.isProtectiveStopped():
            return "the arm made a protective stop"
        return "the arm did not complete the move (its program is not running)"

    def grip(self, width_m: float) -> bool:
        self.io.setStandardDigitalOut(self.vacuum_out, True)
        time.sleep(self.grip_s)
        return self.holding()

    def holding(self) -> bool:
        return True if self.vacuum_in is None else bool(self.receive.getDigitalInState(self.vacuum_in))

    def release(self) -> None:
        self.io.setStandardDigitalOut(self.vacuum_out, False)
        time.sleep(self.release_s)

    def close(self) -> None:
        self.control.stopScript()
        self.control.disconnect()
