"""Joint-space motions timed within the arm's speed and acceleration limits (ruckig), phase
synchronised: every joint starts and stops together and the path is the straight line in joint
space between the two configurations, the line the collision check samples. Radians, seconds."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from ruckig import InputParameter, Result, Ruckig, Synchronization, Trajectory


@dataclass(frozen=True)
class JointLimits:
    """(6,) per joint: speed rad/s and acceleration rad/s^2 (the rated ones times a scaling)."""

    max_velocity: np.ndarray
    max_acceleration: np.ndarray

    def scaled(self, share: float) -> JointLimits:
        # Accelerations scale with the square: the same path at `share` of the speed.
        return JointLimits(self.max_velocity * share, self.max_acceleration * share**2)


def motion(q_from: np.ndarray, q_to: np.ndarray, limits: JointLimits) -> Trajectory:
    """The time-optimal rest-to-rest motion between two configurations (6,)."""
    inp = InputParameter(6)
    inp.current_position = [float(x) for x in q_from]
    inp.target_position = [float(x) for x in q_to]
    inp.max_velocity = [float(x) for x in limits.max_velocity]
    inp.max_acceleration = [float(x) for x in limits.max_acceleration]
    # Jerk unlimited: the controller's own profile smooths it (a UR's movej is trapezoidal).
    inp.max_jerk = [float("inf")] * 6
    inp.synchronization = Synchronization.Phase
    trajectory = Trajectory(6)
    result = Ruckig(6).calculate(inp, trajectory)
    if result not in (Result.Working, Result.Finished):
        raise ValueError(f"no motion from {np.round(q_from, 3)} to {np.round(q_to, 3)}: ruckig says {result}")
    return trajectory


def duration_s(q_from: np.ndarray, q_to: np.ndarray, limits: JointLimits) -> float:
    """Seconds the motion between two configurations takes."""
    return float(motion(q_from, q_to, limits).duration)


def path_duration_s(waypoints: list[np.ndarray], limits: JointLimits) -> float:
    """Seconds through the configurations in order, stopping at each."""
    return sum(duration_s(a, b, limits) for a, b in zip(waypoints[:-1], waypoints[1:], strict=True))


def positions(trajectory: Trajectory, times_s: np.ndarray) -> np.ndarray:
    """(t, 6) the configurations at the given times of a motion."""
    return np.array([trajectory.at_time(float(t))[0] for t in times_s])


def line_samples(q_from: np.ndarray, q_to: np.ndarray, max_step_rad: float) -> np.ndarray:
    """(k, 6) configurations along the straight joint-space line, no joint moving more than
    max_step_rad between two, both ends included."""
    q_from, q_to = np.asarray(q_from, dtype=float), np.asarray(q_to, dtype=float)
    n = max(1, int(np.ceil(np.max(np.abs(q_to - q_from)) / max_step_rad)))
    return q_from + np.linspace(0.0, 1.0, n + 1)[:, None] * (q_to - q_from)
