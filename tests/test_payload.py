"""The held part against the gripper's hold: the accelerations of a carried point, the carry's
speed share and the planner's use of it; each test recovers a known answer."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import ROOT

from binpick.geometry.transforms import make_T
from binpick.params import load_params
from binpick.picking.arm import TOO_HEAVY, ArmPlanner
from binpick.registration.visibility import depth_view
from binpick.robot.arm import load_arm
from binpick.robot.payload import (
    CARRY_FORCE_SHARE,
    GRAVITY_M_S2,
    MIN_CARRY_SHARE,
    Payload,
    carry_share,
    point_accelerations,
)
from binpick.robot.trajectory import JointLimits

PARAMS = load_params(ROOT / "params.yaml", "t_joint")
T_BASE_FROM_CAM = np.asarray(PARAMS.pick.T_base_from_cam, dtype=float)
ELBOW_UP = np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])


def test_a_point_carried_by_the_base_joint_has_the_circular_motions_peak_acceleration():
    arm = load_arm("ur5e")
    # The base joint turns 3 rad at 1 rad/s and 2 rad/s^2: the flange's origin, r from the base's
    # axis, peaks as the speed is reached, with r * 2 along its path and r * 1^2 toward the axis.
    turned = ELBOW_UP + np.array([3.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    limits = JointLimits(np.full(6, 1.0), np.full(6, 2.0))
    a = point_accelerations(arm, [ELBOW_UP, turned], limits, np.zeros(3))
    r = np.linalg.norm(arm.flange_pose(ELBOW_UP)[:2, 3])
    assert np.max(np.linalg.norm(a, axis=1)) == pytest.approx(r * np.sqrt(2.0**2 + 1.0**4), rel=0.02)
    # The base joint turns in the horizontal plane: nothing vertical.
    assert np.max(np.abs(a[:, 2])) < 1e-6
    # A point 0.1 m out along the flange's z moves with it: a different radius, a different peak.
    out = point_accelerations(arm, [ELBOW_UP, turned], limits, np.array([0.0, 0.0, 0.1]))
    T = arm.flange_pose(ELBOW_UP)
    r_out = np.linalg.norm((T[:3, :3] @ np.array([0.0, 0.0, 0.1]) + T[:3, 3])[:2])
    assert np.max(np.linalg.norm(out, axis=1)) == pytest.approx(r_out * np.sqrt(5.0), rel=0.02)


def test_the_carry_share_keeps_the_force_within_the_hold_and_a_too_heavy_part_gets_none():
    a = np.array([[12.0, 0.0, 0.0], [0.0, 0.0, -5.0]])  # m/s^2 at full speed: the peak is 12
    hold = 10.0
    # Light: 0.1 kg asks 0.1 * (12 + 9.81) = 2.2 N at full speed, within 0.8 * 10 N.
    assert carry_share(a, Payload(0.1, hold)) == 1.0
    # 0.5 kg: spare 8 / 0.5 - 9.81 = 6.19 m/s^2 of the peak's 12: share sqrt(6.19 / 12).
    share = carry_share(a, Payload(0.5, hold))
    assert share == pytest.approx(np.sqrt((CARRY_FORCE_SHARE * hold / 0.5 - GRAVITY_M_S2) / 12.0))
    assert share is not None
    worst = 0.5 * np.max(np.linalg.norm(share**2 * a - np.array([0.0, 0.0, -GRAVITY_M_S2]), axis=1))
    assert worst <= CARRY_FORCE_SHARE * hold + 1e-9
    # Its weight alone past the hold's share, or a share below the least allowed: none.
    assert carry_share(a, Payload(CARRY_FORCE_SHARE * hold / GRAVITY_M_S2 * 1.01, hold)) is None
    barely = CARRY_FORCE_SHARE * hold / (GRAVITY_M_S2 + 0.5 * MIN_CARRY_SHARE**2 * 12.0)
    assert carry_share(a, Payload(barely, hold)) is None
    assert carry_share(np.zeros((0, 3)), Payload(0.5, hold)) == 1.0


def _planner(payload: Payload | None) -> ArmPlanner:
    return ArmPlanner(
        load_arm("ur5e"),
        PARAMS.cell,
        T_BASE_FROM_CAM,
        depth_view(np.zeros((0, 3)), None, 0.003),
        np.zeros((0, 4)),
        0.05,
        0.05,
        payload=payload,
    )


def test_the_arm_carries_a_heavier_part_slower_and_refuses_one_the_gripper_cannot_lift():
    T_cam_from_tool = make_T(np.eye(3), np.array([0.0, 0.0, 0.45]))
    centre = np.array([0.0, 0.0, 0.02])  # the part's centre 2 cm behind the cup's lip
    home = np.asarray(PARAMS.cell.home_q_rad)
    free = _planner(None).plan(T_cam_from_tool, np.eye(4), "suction", centre, home)
    light = _planner(Payload(0.05, 4.5)).plan(T_cam_from_tool, np.eye(4), "suction", centre, home)
    heavy = _planner(Payload(0.33, 4.5)).plan(T_cam_from_tool, np.eye(4), "suction", centre, home)
    assert not isinstance(free, str) and not isinstance(light, str) and not isinstance(heavy, str)
    assert free.carry_share == light.carry_share == 1.0 and light.motion_s == pytest.approx(free.motion_s)
    # 0.33 kg on a 4.5 N cup (3.2 N of its 3.6 N share at rest): the same path, slowed from the
    # grasp on so that the hold holds (the carry peaks at about 2 m/s^2 at full speed).
    assert heavy.path == free.path and 0.1 < heavy.carry_share < 1.0 and heavy.motion_s > free.motion_s
    arm, planner = load_arm("ur5e"), _planner(None)
    carry = [heavy.q[name] for name in heavy.path[heavy.path.index("grasp") :]]
    a = point_accelerations(arm, carry, planner.limits.scaled(heavy.carry_share), centre + [0.0, 0.0, 0.17])
    force = 0.33 * np.max(np.linalg.norm(a - np.array([0.0, 0.0, -GRAVITY_M_S2]), axis=1))
    assert force <= CARRY_FORCE_SHARE * 4.5 + 1e-6
    # 0.5 kg weighs 4.9 N: more than the cup holds, whatever the speed.
    assert _planner(Payload(0.5, 4.5)).plan(T_cam_from_tool, np.eye(4), "suction", centre, home) == TOO_HEAVY
