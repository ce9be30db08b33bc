"""Joint-space motions timed within the arm's speed and acceleration limits (ruckig), phase
synchronised: every joint starts and stops together and the path is the straight line in joint
space between the two configurations, the line the collision check samples. A tool's straight
line (the lift out of the bin) is a dense chain of configurations instead, followed without
stopping, timed by TOPP-RA (toppra; `LineMotion`). Radians, seconds."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

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


def stops_duration_s(start: np.ndarray, stops: list[np.ndarray], limits: JointLimits) -> float:
    """Seconds from the configuration start (6,) through the stops in order, at rest at each: a
    configuration (6,) along the straight joint line, a chain (k, 6) from the stop before along
    the chain (chain_motion)."""
    seconds, before = 0.0, np.asarray(start, dtype=float)
    for stop in stops:
        stop = np.asarray(stop, dtype=float)
        seconds += chain_motion(stop, limits).duration if stop.ndim == 2 else duration_s(before, stop, limits)
        before = stop[-1] if stop.ndim == 2 else stop
    return seconds


def positions(trajectory: Trajectory, times_s: np.ndarray) -> np.ndarray:
    """(t, 6) the configurations at the given times of a motion."""
    return np.array([trajectory.at_time(float(t))[0] for t in times_s])


@dataclass(frozen=True)
class LineMotion:
    """Rest-to-rest along a chain of configurations (chain_motion) without stopping on the way: the
    chain's spline (through every configuration) timed by TOPP-RA (toppra), the fastest within
    every joint's speed and acceleration limits all along it."""

    trajectory: Any = field(repr=False)  # toppra's interpolated trajectory

    @property
    def duration(self) -> float:
        return float(self.trajectory.duration)

    def at_time(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(6,) configuration and (6,) joint velocities at t_s seconds from the start."""
        t = min(max(t_s, 0.0), self.duration)
        return np.asarray(self.trajectory(t), dtype=float), np.asarray(self.trajectory(t, 1), dtype=float)


def chain_motion(chain: np.ndarray, limits: JointLimits) -> LineMotion:
    """The motion along a chain of configurations (k >= 2, 6), at rest at both ends."""
    import toppra
    from toppra import algorithm, constraint

    chain = np.asarray(chain, dtype=float)
    # The spline's parameter runs with the joint-space distance: evenly spaced configurations
    # (the tool's steps along its line) get an even parameter.
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(chain, axis=0), axis=1))])
    if s[-1] <= 0.0:
        raise ValueError("a chain of configurations that does not move")
    logging.getLogger("toppra").setLevel(logging.WARNING)  # it logs every solve at INFO
    path = toppra.SplineInterpolator(s, chain)
    velocity = constraint.JointVelocityConstraint(np.column_stack([-limits.max_velocity, limits.max_velocity]))
    acceleration = constraint.JointAccelerationConstraint(
        np.column_stack([-limits.max_acceleration, limits.max_acceleration])
    )
    trajectory = algorithm.TOPPRA(
        [velocity, acceleration], path, parametrizer="ParametrizeConstAccel"
    ).compute_trajectory()
    if trajectory is None:
        raise ValueError(f"no motion along a chain of {len(chain)} configurations: TOPP-RA found none")
    return LineMotion(trajectory)


def line_samples(q_from: np.ndarray, q_to: np.ndarray, max_step_rad: float) -> np.ndarray:
    """(k, 6) configurations along the straight joint-space line, no joint moving more than
    max_step_rad between two, both ends included."""
    q_from, q_to = np.asarray(q_from, dtype=float), np.asarray(q_to, dtype=float)
    n = max(1, int(np.ceil(np.max(np.abs(q_to - q_from)) / max_step_rad)))
    return q_from + np.linspace(0.0, 1.0, n + 1)[:, None] * (q_to - q_from)
