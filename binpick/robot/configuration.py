"""Choosing one joint configuration among an arm's inverse kinematics solutions: the turn of each
joint nearest the previous configuration, within the joint limits with a margin, away from the
arm's singularities, with the least motion. Radians; configurations (6,) in the joint order of
robot.arm.ArmModel (a UR: base, shoulder, elbow, wrist 1, 2, 3).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

TWO_PI = 2.0 * np.pi
# Reasons a pose has no configuration.
UNREACHABLE, JOINT_LIMIT, SINGULAR = "unreachable", "joint limit", "singular"


def nearest_turns(q: np.ndarray, q_ref: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """(m, 6) each configuration of q (m, 6) with every joint turned by the multiple of 2 pi that
    brings it nearest q_ref (6,) within [lower, upper]; NaN where no turn of that joint lies
    within the limits. A joint of +-2 pi range has two turns of every angle: the wrist need not
    unwind half a revolution between two picks."""
    q = np.asarray(q, dtype=float).reshape(-1, 6)
    k = np.round((q_ref - q) / TWO_PI)
    near = q + k * TWO_PI
    # The nearest turn may lie beyond a limit while the next one in lies within.
    near = np.where(near > upper, near - TWO_PI, near)
    near = np.where(near < lower, near + TWO_PI, near)
    return np.where((near >= lower) & (near <= upper), near, np.nan)


def ur_singularity_margin(q: np.ndarray, a2_m: float, a3_m: float) -> np.ndarray:
    """(m,) how far configurations q (m, 6) of a UR arm are from its three singularities, each
    as the sine that vanishes there, the least of them: the wrist (wrist 2 at 0 or pi: wrist 1 and
    3 aligned), the elbow (elbow at 0: arm stretched; at pi it folds on itself) and the shoulder
    (the wrist centre on the base axis, as a share of the reach a2 + a3)."""
    q = np.asarray(q, dtype=float).reshape(-1, 6)
    wrist = np.abs(np.sin(q[:, 4]))
    elbow = np.abs(np.sin(q[:, 2]))
    # The wrist centre's distance from the base axis, in the arm's plane: |a2 cos q2 + a3 cos(q2 + q3)|.
    radius = np.abs(a2_m * np.cos(q[:, 1]) + a3_m * np.cos(q[:, 1] + q[:, 2]))
    shoulder = np.clip(radius / (abs(a2_m) + abs(a3_m)), 0.0, 1.0)
    return np.minimum(np.minimum(wrist, elbow), shoulder)


@dataclass(frozen=True)
class Choice:
    """q (6,) the chosen configuration, or NaN with `reason` (UNREACHABLE, JOINT_LIMIT, SINGULAR);
    motion_s the least time the move from the reference takes at the joints' speed limits."""

    q: np.ndarray
    reason: str | None
    motion_s: float


def choose_configuration(
    solutions: np.ndarray,
    q_ref: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    max_velocity: np.ndarray,
    limit_margin_rad: float,
    singularity: np.ndarray | None = None,
    min_singularity: float = 0.0,
) -> Choice:
    """The configuration among IK solutions (m, 6) (each joint at its turn nearest q_ref) that
    keeps limit_margin_rad from every joint limit and `min_singularity` from a singularity
    (singularity: (m,) a margin per solution, e.g. ur_singularity_margin) and moves least from
    q_ref: the least time at the joints' speed limits, the total joint travel breaking ties. When
    none qualifies, the reason of the nearest miss."""
    nan = Choice(np.full(6, np.nan), UNREACHABLE, float("inf"))
    solutions = np.asarray(solutions, dtype=float).reshape(-1, 6)
    if len(solutions) == 0:
        return nan
    turned = nearest_turns(solutions, q_ref, lower + limit_margin_rad, upper - limit_margin_rad)
    ok = np.all(np.isfinite(turned), axis=1)
    if not ok.any():
        return Choice(nan.q, JOINT_LIMIT, nan.motion_s)
    if singularity is not None:
        away = np.asarray(singularity, dtype=float).reshape(-1) >= min_singularity
        if not (ok & away).any():
            return Choice(nan.q, SINGULAR, nan.motion_s)
        ok &= away
    travel = np.abs(turned - q_ref)
    seconds = np.max(travel / max_velocity, axis=1)
    cost = np.where(ok, seconds + 1e-3 * travel.sum(axis=1), np.inf)
    best = int(np.argmin(cost))
    return Choice(turned[best], None, float(seconds[best]))


def follow(
    solutions_along: list[np.ndarray], q_start: np.ndarray, lower: np.ndarray, upper: np.ndarray, max_step_rad: float
) -> np.ndarray | str:
    """(k + 1, 6) configurations along a path of tool poses: q_start (6,), then for each pose's
    inverse kinematics solutions ((m, 6), k of them) the one nearest the configuration before,
    its joints turned within [lower, upper]; or why the arm cannot follow: UNREACHABLE where a
    pose has no solution or the nearest moves a joint more than max_step_rad (a jump to another
    branch, near a singularity), JOINT_LIMIT where only the limits stop it."""
    chain = [np.asarray(q_start, dtype=float)]
    for solutions in solutions_along:
        if len(solutions) == 0:
            return UNREACHABLE
        turns = nearest_turns(solutions, chain[-1], lower, upper)
        within = ~np.any(np.isnan(turns), axis=1)
        if not within.any():
            return JOINT_LIMIT
        step = np.max(np.abs(turns[within] - chain[-1]), axis=1)
        if step.min() > max_step_rad:
            return UNREACHABLE
        chain.append(turns[within][np.argmin(step)])
    return np.array(chain)
