"""The robot arm: its model from the shipped URDF, IK against FK, configuration choice, the arm
against what the camera measured, and the place; each test recovers a known answer."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import ROOT

from binpick.geometry.transforms import axis_angle_to_R, invert_T, make_T
from binpick.params import load_params
from binpick.picking.arm import HITS_WALL, ArmPlanner, turned
from binpick.picking.place import place_tool_poses
from binpick.registration.visibility import depth_view
from binpick.robot.arm import ARMS, load_arm
from binpick.robot.configuration import JOINT_LIMIT, choose_configuration, nearest_turns
from binpick.robot.trajectory import JointLimits, line_samples, motion, positions

PARAMS = load_params(ROOT / "params.yaml", "t_joint")
# Camera 0.5 m above the base's plane at x = 0.45 m, looking straight down (params.yaml's cell).
T_BASE_FROM_CAM = np.asarray(PARAMS.pick.T_base_from_cam, dtype=float)


@pytest.mark.parametrize("name", ARMS)
def test_ik_of_a_forward_kinematics_pose_returns_the_configuration(name):
    arm = load_arm(name)
    rng = np.random.default_rng(3)
    for _ in range(20):
        q = rng.uniform(-np.pi, np.pi, 6)
        q[4] = rng.choice([-1.0, 1.0]) * rng.uniform(0.3, 2.8)  # away from the wrist singularity
        T = arm.flange_pose(q)
        solutions = arm.ik(T)
        assert len(solutions) >= 1
        # Every solution reaches the pose, and one of them is q (up to turns of 2 pi).
        assert all(np.allclose(arm.flange_pose(s), T, atol=1e-6) for s in solutions)
        wrapped = np.angle(np.exp(1j * (solutions - q)))
        assert np.min(np.abs(wrapped).max(axis=1)) < 1e-6


@pytest.mark.parametrize("name", ARMS)
def test_link_chain_agrees_with_the_urdf_library_and_ends_at_the_flange(name):
    yourdfpy = pytest.importorskip("yourdfpy")
    arm = load_arm(name)
    urdf = yourdfpy.URDF.load(str(arm.urdf_path))
    Q = np.random.default_rng(0).uniform(-3.0, 3.0, (4, 6))
    Ts = arm.link_transforms(Q)
    for n, q in enumerate(Q):
        urdf.update_cfg(q)
        for k, link in enumerate(arm.link_names):
            assert np.allclose(Ts[n, k], urdf.get_transform(link, "base"), atol=1e-9)
        assert np.allclose(urdf.get_transform("tool0", "base"), arm.flange_pose(q), atol=1e-9)
    assert np.all(arm.max_velocity_rad_s > 0) and np.all(arm.max_acceleration_rad_s2 > 0)


def test_nearest_turn_of_a_joint_is_taken_within_its_limits():
    lower, upper = np.full(6, -2 * np.pi), np.full(6, 2 * np.pi)
    q = np.array([[3.0, 0.0, 0.0, 0.0, 0.0, -3.0]])
    near = nearest_turns(q, np.array([-3.0, 0, 0, 0, 0, 3.0]), lower, upper)
    assert np.allclose(near, [[3.0 - 2 * np.pi, 0, 0, 0, 0, -3.0 + 2 * np.pi]])
    # A joint of +-2.5 rad: 3.5 rad has no turn within it (3.5 - 2 pi = -2.78 has, within +-2 pi).
    assert np.isnan(
        nearest_turns(np.array([[0, 0, 3.5, 0, 0, 0]]), np.zeros(6), np.full(6, -2.5), np.full(6, 2.5))[0, 2]
    )
    assert nearest_turns(np.array([[0, 0, 3.5, 0, 0, 0]]), np.zeros(6), lower, upper)[0, 2] == pytest.approx(
        3.5 - 2 * np.pi
    )


def test_the_configuration_moving_least_is_chosen_and_a_limit_is_named():
    lower, upper, speed = np.full(6, -2 * np.pi), np.full(6, 2 * np.pi), np.full(6, np.pi)
    a, b = np.zeros(6), np.full(6, 1.0)
    assert np.allclose(choose_configuration(np.stack([b, a]), np.full(6, 0.1), lower, upper, speed, 0.0).q, a)
    assert np.allclose(choose_configuration(np.stack([b, a]), np.full(6, 0.9), lower, upper, speed, 0.0).q, b)
    narrow = np.full(6, 0.5)
    assert choose_configuration(np.stack([b]), a, -narrow, narrow, speed, 0.0).reason == JOINT_LIMIT


def test_motion_stays_on_the_joint_line_within_the_limits():
    limits = JointLimits(np.full(6, np.pi), np.full(6, 2.5))
    q0, q1 = np.zeros(6), np.array([1.0, -0.5, 0.2, 0.0, 0.0, 2.0])
    trajectory = motion(q0, q1, limits)
    t = np.linspace(0.0, trajectory.duration, 50)
    q = positions(trajectory, t)
    # Phase-synchronised: every configuration lies on the line from q0 to q1.
    share = q[:, 5] / 2.0
    assert np.allclose(q, share[:, None] * q1, atol=1e-9)
    speed = np.abs(np.diff(q, axis=0)) / np.diff(t)[:, None]
    assert np.all(speed <= np.pi + 1e-6)
    # The longest joint (2 rad) at 2.5 rad/s^2 never reaches pi rad/s: 2 sqrt(2 / 2.5) s.
    assert trajectory.duration == pytest.approx(2.0 * np.sqrt(2.0 / 2.5), rel=1e-6)
    assert len(line_samples(q0, q1, 0.05)) == 41


def _planner(view_points_cam: np.ndarray, walls_cam: np.ndarray, arm_name: str = "ur5e", **cell) -> ArmPlanner:
    arm = load_arm(arm_name)
    view = depth_view(view_points_cam, None, 0.003)
    return ArmPlanner(arm, PARAMS.cell.model_copy(update=cell), T_BASE_FROM_CAM, view, walls_cam, 0.05, 0.05)


def _wall_through(point_base: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A wall (points, camera frame) in the base's x = const plane through point_base, from the
    base's plane up to 2 cm above the point, and that plane in the camera frame."""
    y, z = np.meshgrid(np.linspace(-0.3, 0.3, 121), np.linspace(0.0, point_base[2] + 0.02, 60))
    wall = np.column_stack([np.full(y.size, point_base[0]), point_base[1] + y.ravel(), z.ravel()])
    floor_y, floor_x = np.meshgrid(np.linspace(-0.3, 0.3, 61), np.linspace(0.2, 0.7, 51))
    floor = np.column_stack([floor_x.ravel(), floor_y.ravel(), np.zeros(floor_x.size)])
    T = invert_T(T_BASE_FROM_CAM)
    points = np.concatenate([wall, floor]) @ T[:3, :3].T + T[:3, 3]
    normal_cam = T[:3, :3] @ np.array([1.0, 0.0, 0.0])
    plane = np.append(normal_cam, -normal_cam @ (T[:3, :3] @ point_base + T[:3, 3]))
    return points, plane[None]


def test_a_planted_arm_wall_contact_is_found_and_a_free_path_is_not_flagged():
    arm = load_arm("ur5e")
    q = np.array([np.pi, -1.2, 1.9, -2.3, -1.57, 0.0])
    points, link = arm.surface_points(q)
    forearm = points[0, link == arm.link_names.index("forearm_link")]
    # A wall through the lowest forearm point that lies in the camera's view.
    T = invert_T(T_BASE_FROM_CAM)
    cam = forearm @ T[:3, :3].T + T[:3, 3]
    in_view = np.abs(cam[:, 0] / cam[:, 2]) < 0.3
    assert in_view.any()
    target = forearm[in_view][np.argmin(forearm[in_view][:, 2])]
    wall, plane = _wall_through(target)
    assert _planner(wall, plane).configurations_hit(q[None]) == HITS_WALL
    # The same wall 0.25 m further out along x, and the floor: clear.
    away, plane_away = _wall_through(target + np.array([0.25, 0.0, -target[2] + 0.05]))
    assert _planner(away, plane_away).configurations_hit(q[None]) is None
    # A path sweeping the forearm down through the wall is caught between its ends.
    lifted = q + np.array([0.0, -0.5, 0.0, 0.0, 0.0, 0.0])
    assert _planner(wall, plane).path_hit([lifted, q, lifted]) == HITS_WALL
    assert _planner(wall, plane).configurations_hit(lifted[None]) is None


def test_a_suction_grasp_is_turned_about_the_cup_axis_to_keep_a_joint_limit():
    arm = load_arm("ur5e")
    # A grasp straight down at the bin's centre (camera frame: the tool's z along the camera's z).
    T_cam_from_tool = make_T(np.eye(3), np.array([0.0, 0.0, 0.45]))
    T_model_from_tool = np.eye(4)
    free = _planner(np.zeros((0, 3)), np.zeros((0, 4))).plan(
        T_cam_from_tool, T_model_from_tool, "suction", np.zeros(3), np.asarray(PARAMS.cell.home_q_rad)
    )
    assert not isinstance(free, str)
    # Wrist 3 limited to within 0.3 rad of where the turn the free arm chose leaves it, shifted
    # by 90 degrees: only the cup turned by another 90 degrees (or 270) keeps it.
    wrist = free.q["grasp"][5] + np.pi / 2
    limited = dataclasses.replace(
        arm,
        lower_rad=np.where(np.arange(6) == 5, wrist - 0.3, arm.lower_rad),
        upper_rad=np.where(np.arange(6) == 5, wrist + 0.3, arm.upper_rad),
    )
    planner = _planner(np.zeros((0, 3)), np.zeros((0, 4)), joint_limit_margin_deg=0.0)
    planner.arm = limited
    chosen = planner.plan(
        T_cam_from_tool, T_model_from_tool, "suction", np.zeros(3), np.asarray(PARAMS.cell.home_q_rad)
    )
    assert not isinstance(chosen, str), chosen
    assert abs(chosen.q["grasp"][5] - wrist) <= 0.3
    assert (chosen.turn_deg - free.turn_deg) % 180 == pytest.approx(90.0)
    # The configuration puts the tool at the grasp turned by the chosen angle.
    tcp = arm.flange_pose(chosen.q["grasp"]) @ np.asarray(PARAMS.cell.T_flange_from_tcp)
    assert np.allclose(tcp, T_BASE_FROM_CAM @ turned(T_cam_from_tool, np.radians(chosen.turn_deg)), atol=1e-6)


def test_the_place_pose_is_the_target_composed_with_the_grasp():
    target = make_T(axis_angle_to_R(np.array([0.0, 0.0, 1.0]), 0.4), np.array([0.1, 0.45, 0.1]))
    grasp = make_T(axis_angle_to_R(np.array([1.0, 0.0, 0.0]), np.pi), np.array([0.01, 0.0, 0.02]))
    fixture = PARAMS.cell.place.model_copy(update={"kind": "fixture", "T_base_from_part": target.tolist()})
    (pose,) = place_tool_poses(fixture, grasp, np.zeros(3))
    assert np.allclose(pose, target @ grasp)
    # A conveyor: the same turned about the vertical through the part's place.
    conveyor = fixture.model_copy(update={"kind": "conveyor"})
    for T in place_tool_poses(conveyor, grasp, np.zeros(3)):
        part = T @ invert_T(grasp)
        assert np.allclose(part[:3, 3], target[:3, 3]) and np.allclose(part[:3, 2], target[:3, 2])
    # A drop zone: the part's centre at the place, the tool straight down.
    centre = np.array([0.0, 0.01, 0.005])
    for T in place_tool_poses(fixture.model_copy(update={"kind": "drop"}), grasp, centre):
        part = T @ invert_T(grasp)
        assert np.allclose(part[:3, :3] @ centre + part[:3, 3], target[:3, 3])
        assert np.allclose(T[:3, 2], [0.0, 0.0, -1.0])


def test_a_drop_zones_turn_lets_the_wrist_swing_with_the_base():
    # A grasp straight down over the camera's centre (base x = 0.45 m); the drop zone (params:
    # base (0.1, 0.45)) lies about 78 degrees around the base from it. Any turn of the tool there
    # will do: the quickest leaves wrist 3 where the lift had it (within half a turn step of the
    # place's candidates, 15 degrees), where the tool's heading kept in the world would turn it
    # back by the base's swing.
    T_cam_from_tool = make_T(np.eye(3), np.array([0.0, 0.0, 0.45]))
    plan = _planner(np.zeros((0, 3)), np.zeros((0, 4))).plan(
        T_cam_from_tool, np.eye(4), "suction", np.zeros(3), np.asarray(PARAMS.cell.home_q_rad)
    )
    assert not isinstance(plan, str), plan
    swing = np.angle(np.exp(1j * (plan.q["place"] - plan.q["lift"])))
    assert abs(swing[0]) > np.radians(60.0)
    assert abs(swing[5]) <= np.radians(15.0) + 1e-6


def test_a_grasp_left_straight_up_puts_the_arms_post_grasp_above_it():
    # A grasp tilted 40 degrees from straight down; the gripper check chose to leave it straight up
    # the camera's -z (the bin's up axis here), not back along the tilted approach.
    arm = load_arm("ur5e")
    T_cam_from_tool = make_T(axis_angle_to_R(np.array([1.0, 0.0, 0.0]), np.radians(40.0)), np.array([0.0, 0.0, 0.45]))
    planner = _planner(np.zeros((0, 3)), np.zeros((0, 4)))
    home = np.asarray(PARAMS.cell.home_q_rad)
    up = planner.plan(T_cam_from_tool, np.eye(4), "suction", np.zeros(3), home, retreat_cam=np.array([0.0, 0.0, -1.0]))
    back = planner.plan(T_cam_from_tool, np.eye(4), "suction", np.zeros(3), home)
    assert not isinstance(up, str) and not isinstance(back, str)
    T_flange_from_tcp = np.asarray(PARAMS.cell.T_flange_from_tcp)
    for planned, offset_cam in ((up, [0.0, 0.0, -0.05]), (back, -0.05 * T_cam_from_tool[:3, 2])):
        grasp = arm.flange_pose(planned.q["grasp"]) @ T_flange_from_tcp
        post = arm.flange_pose(planned.q["postgrasp"]) @ T_flange_from_tcp
        assert np.allclose(post[:3, 3] - grasp[:3, 3], T_BASE_FROM_CAM[:3, :3] @ offset_cam, atol=1e-6)
        assert np.allclose(post[:3, :3], grasp[:3, :3], atol=1e-6)  # moved, not turned


def test_a_chain_of_configurations_is_followed_without_stopping_within_the_limits():
    from binpick.robot.trajectory import chain_motion, stops_duration_s

    # A chain along a straight joint line: the fastest motion along it is ruckig's rest-to-rest
    # motion between its ends (both time-optimal within the same limits).
    q0, q1 = np.zeros(6), np.array([1.0, -0.5, 0.2, 0.0, 0.0, 2.0])
    chain = np.linspace(q0, q1, 11)
    limits = JointLimits(np.full(6, np.pi), np.full(6, 2.5))
    line = chain_motion(chain, limits)
    assert line.duration == pytest.approx(motion(q0, q1, limits).duration, rel=0.02)
    t = np.linspace(0.0, line.duration, 201)
    states = [line.at_time(x) for x in t]
    q = np.array([s[0] for s in states])
    qd = np.array([s[1] for s in states])
    assert np.allclose(q[0], q0, atol=1e-9) and np.allclose(q[-1], q1, atol=1e-6)
    assert np.allclose(q, q[:, 5:6] / 2.0 * q1, atol=1e-3)  # on the line
    assert np.all(np.abs(qd) <= np.pi * 1.001) and np.all(qd[1:-1, 5] > 0.0)  # never stops on the way
    qdd = np.diff(qd, axis=0) / np.diff(t)[:, None]
    assert np.all(np.abs(qdd) <= 2.5 * 1.05)
    # As a stop of a path: the same seconds after a joint move to its start.
    assert stops_duration_s(np.zeros(6), [chain], limits) == pytest.approx(line.duration)


def test_the_lift_follows_the_tools_straight_line_up():
    # A grasp tilted 26 degrees, left back along its approach: from the post-grasp the tool goes
    # cell.lift_m straight up. A straight joint line between the two strays from that line by a
    # centimetre; the plan's chain (forward kinematics of each configuration) and the joint lines
    # between its configurations stay within a millimetre of it.
    arm = load_arm("ur5e")
    T_cam_from_tool = make_T(
        axis_angle_to_R(np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0), np.radians(26.0)), [0.05, 0.03, 0.45]
    )
    planner = _planner(np.zeros((0, 3)), np.zeros((0, 4)))
    planned = planner.plan(T_cam_from_tool, np.eye(4), "suction", np.zeros(3), np.asarray(PARAMS.cell.home_q_rad))
    assert not isinstance(planned, str)
    chain = planned.lines["lift"]
    assert np.allclose(chain[0], planned.q["postgrasp"]) and np.allclose(chain[-1], planned.q["lift"])
    T_flange_from_tcp = np.asarray(PARAMS.cell.T_flange_from_tcp)

    def tcp(q: np.ndarray) -> np.ndarray:
        return np.array([(arm.flange_pose(c) @ T_flange_from_tcp)[:3, 3] for c in q])

    start, end = tcp(chain[[0, -1]])
    assert np.allclose(end - start, [0.0, 0.0, PARAMS.cell.lift_m], atol=1e-6)

    def off_line(points: np.ndarray) -> np.ndarray:
        return np.linalg.norm((points - start)[:, :2], axis=1)  # the line runs up the base's z

    dense = np.concatenate([line_samples(a, b, 0.002) for a, b in zip(chain[:-1], chain[1:], strict=True)])
    assert off_line(tcp(dense)).max() < 0.001
    assert off_line(tcp(line_samples(chain[0], chain[-1], 0.002))).max() > 0.005  # what it replaces


def test_following_a_path_takes_the_nearest_solution_and_names_a_jump_or_a_limit():
    from binpick.robot.configuration import UNREACHABLE, follow

    lower, upper = np.full(6, -2.0 * np.pi), np.full(6, 2.0 * np.pi)
    # Two solutions per pose: the one near the configuration before is taken, its wrist turned a
    # whole turn back toward it (6.3 rad is 6.3 - 2 pi = 0.017 rad from the start).
    along = [np.array([[3.0] * 6, [0.1] * 6]), np.array([[0.2, 0.2, 0.2, 0.2, 0.2, 6.3], [-3.0] * 6])]
    chain = follow(along, np.zeros(6), lower, upper, 0.25)
    assert isinstance(chain, np.ndarray)
    assert np.allclose(chain, [[0.0] * 6, [0.1] * 6, [0.2, 0.2, 0.2, 0.2, 0.2, 6.3 - 2.0 * np.pi]])
    assert follow([np.array([[1.0] * 6])], np.zeros(6), lower, upper, 0.25) == UNREACHABLE  # a jump
    assert follow([np.zeros((0, 6))], np.zeros(6), lower, upper, 0.25) == UNREACHABLE  # no solution
    assert follow([np.array([[0.2] * 6])], np.zeros(6), np.full(6, -0.15), np.full(6, 0.15), 0.25) == JOINT_LIMIT
