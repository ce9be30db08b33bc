"""What a held part asks of the gripper while the arm carries it: its weight plus the force of the
motion's accelerations, against the gripper's rated hold (a suction cup's holding force, the jaws'
friction). A carry that would ask for more is slowed down until it does not: the same path at a
share s of the joint speed (and s^2 of the acceleration, binpick/robot/trajectory.py) is the same
motion in time scaled by s, so every point's acceleration scales by s^2 exactly.

Frames: the arm's base (z up, against gravity) and its flange; metres, seconds, kilograms, newtons.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from binpick.robot.arm import ArmModel
from binpick.robot.trajectory import JointLimits, motion, positions

GRAVITY_M_S2 = 9.81
# A carry asks at most this share of the gripper's rated hold; the rest is for what the plan does not
# see: a neighbour's friction as the part comes up, the cup's give, the part's centre of mass off
# the mesh's centre.
CARRY_FORCE_SHARE = 0.8
# Motions are sampled this often for their peak acceleration (central differences of positions;
# a ruckig motion's phases last far longer).
SAMPLE_DT_S = 0.01
# Carries are never slowed below this share of the joint speed: a part that needs it is too heavy.
MIN_CARRY_SHARE = 0.1


@dataclass(frozen=True)
class Payload:
    """The part the gripper holds: its mass and the gripper's rated hold on it."""

    mass_kg: float
    hold_n: float

    def lifts(self) -> bool:
        """Whether the gripper holds the part's weight at all (within CARRY_FORCE_SHARE)."""
        return self.mass_kg * GRAVITY_M_S2 <= CARRY_FORCE_SHARE * self.hold_n


def point_accelerations(
    arm: ArmModel, waypoints: list[np.ndarray], limits: JointLimits, point_flange: np.ndarray
) -> np.ndarray:
    """(k, 3) accelerations m/s^2, base frame, of a point fixed to the flange (point_flange (3,),
    flange frame) along the rest-to-rest motions through the waypoints ((6,) each; ruckig at the
    limits, the arm at rest at each waypoint), sampled every SAMPLE_DT_S."""
    out = [np.zeros((0, 3))]
    p = np.asarray(point_flange, dtype=float)
    for a, b in zip(waypoints[:-1], waypoints[1:], strict=True):
        trajectory = motion(a, b, limits)
        if trajectory.duration <= 0.0:
            continue
        # At rest before and after: positions past either end are the end's.
        times = np.arange(-SAMPLE_DT_S, trajectory.duration + 2.0 * SAMPLE_DT_S, SAMPLE_DT_S)
        q = positions(trajectory, np.clip(times, 0.0, trajectory.duration))
        flange = arm.flange_poses(q)
        x = flange[:, :3, :3] @ p + flange[:, :3, 3]
        out.append((x[2:] - 2.0 * x[1:-1] + x[:-2]) / SAMPLE_DT_S**2)
    return np.concatenate(out)


def carry_share(accelerations_m_s2: np.ndarray, payload: Payload) -> float | None:
    """The share s (0, 1] of the joint speed at which carrying the part along a motion with these
    accelerations ((k, 3), base frame, at full speed) asks at most CARRY_FORCE_SHARE of the hold;
    None when even MIN_CARRY_SHARE asks more (or the weight alone does).

    The hold must give m (a - g) with g = (0, 0, -9.81); at share s the motion's accelerations are
    s^2 a, and |s^2 a - g| <= s^2 |a| + |g|, so s^2 = (CARRY_FORCE_SHARE hold / m - |g|) / max |a|
    keeps the force within the hold whatever the direction."""
    if not payload.lifts():
        return None
    a = np.asarray(accelerations_m_s2, dtype=float).reshape(-1, 3)
    peak = float(np.max(np.linalg.norm(a, axis=1))) if len(a) else 0.0
    spare = CARRY_FORCE_SHARE * payload.hold_n / payload.mass_kg - GRAVITY_M_S2
    if peak <= spare:
        return 1.0
    share = float(np.sqrt(spare / peak))
    return share if share >= MIN_CARRY_SHARE else None
