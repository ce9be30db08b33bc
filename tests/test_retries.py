"""A part the gripper failed to hold is left alone until nothing else can be picked: the same part
posed again is recognised, a neighbour is not."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from binpick.cell.retries import SAME_PART_SHARE, FailedGrips, near_contacts, near_failed
from binpick.geometry.transforms import make_T

DIAMETER_M = 0.075
CENTRE_M = np.array([0.0, 0.005, 0.0])  # the part's centre in its model frame


def centre_cam(T: np.ndarray) -> np.ndarray:
    return T[:3, :3] @ CENTRE_M + T[:3, 3]


def test_the_same_part_posed_again_is_left_alone_and_its_neighbour_is_not():
    T_failed = make_T(Rotation.from_euler("xyz", [10, -20, 35], degrees=True).as_matrix(), np.array([0.1, -0.05, 0.8]))
    grips = FailedGrips()
    grips.failed(T_failed, CENTRE_M, T_failed)
    # Posed again 3 mm and 20 degrees (about the model's x axis) off; a neighbour beside it.
    again = T_failed @ make_T(Rotation.from_euler("x", 20, degrees=True).as_matrix(), np.array([0.003, 0.0, 0.0]))
    beside = make_T(T_failed[:3, :3], T_failed[:3, 3] + np.array([1.5 * SAME_PART_SHARE * DIAMETER_M, 0.0, 0.0]))
    centres = np.array([centre_cam(again), centre_cam(beside)])
    assert near_failed(centres, grips.centres_m(), DIAMETER_M).tolist() == [True, False]
    # No other pick: the parts left alone are tried again, once.
    assert grips.retry() and len(grips.centres_m()) == 0
    assert not grips.retry()
    assert near_failed(centres, grips.centres_m(), DIAMETER_M).tolist() == [False, False]


def test_where_a_grip_failed_is_remembered_across_retries():
    T_part = make_T(np.eye(3), np.array([0.02, 0.01, 0.6]))
    T_grasp = make_T(np.eye(3), np.array([0.03, 0.01, 0.58]))
    grips = FailedGrips()
    grips.failed(T_part, CENTRE_M, T_grasp)
    assert grips.retry()
    # The part may be tried again, but not at the same place.
    assert len(grips.centres_m()) == 0
    np.testing.assert_allclose(grips.contacts_m(), [[0.03, 0.01, 0.58]])
    tcp = np.array([[0.03, 0.01, 0.58], [0.03, 0.018, 0.58], [0.03, 0.022, 0.58]])
    assert near_contacts(tcp, grips.contacts_m(), 0.01).tolist() == [True, True, False]
    assert near_contacts(tcp, np.zeros((0, 3)), 0.01).tolist() == [False, False, False]


def test_a_part_lost_on_the_way_up_is_left_alone_but_where_it_held_is_not_ruled_out():
    T_part = make_T(np.eye(3), np.array([0.02, 0.01, 0.6]))
    T_grasp = make_T(np.eye(3), np.array([0.03, 0.01, 0.58]))
    grips = FailedGrips()
    grips.failed(T_part, CENTRE_M, T_grasp, held=True)
    assert near_failed(centre_cam(T_part)[None], grips.centres_m(), DIAMETER_M).tolist() == [True]
    assert len(grips.contacts_m()) == 0


def test_a_simulated_pick_reports_its_failure_as_a_robot_does():
    """The cell benchmark reads the simulator's outcome in the robot's words, as `binpick cell
    run` reads a robot: the same failures leave a part alone."""
    from binpick.cell.robot import GRASP_LOST, NO_GRIP, Execution

    states = {o: Execution(o, None).state for o in ("placed", "misplaced", "no seal", "no hold", "dropped")}
    assert states == {
        "placed": "placed",
        "misplaced": "placed",
        "no seal": NO_GRIP,
        "no hold": NO_GRIP,
        "dropped": GRASP_LOST,
    }
