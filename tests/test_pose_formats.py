"""Robot-native poses: one rotation given in all four controllers' conventions, worked out here by
hand (elementary rotations and the Hamilton product, not the library under test), and round trips
through each format."""

from __future__ import annotations

import math

import numpy as np
import pytest

from binpick.robot.pose_formats import FIELDS, POSE_FORMATS, from_robot, rounded, to_robot


def _Rx(deg):
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _Ry(deg):
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _Rz(deg):
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _q_axis(axis, deg):
    """Unit quaternion (w, x, y, z) of a turn about a coordinate axis."""
    h = math.radians(deg) / 2
    return np.array([math.cos(h), *(math.sin(h) * np.eye(3)[axis])])


def _hamilton(p, q):
    w1, x1, y1, z1 = p
    w2, x2, y2, z2 = q
    return np.array(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ]
    )


# A tool 0.1 m along x, -0.2 m along y and 0.3 m up, turned 30 deg about z, then 20 deg about the
# new y, then 10 deg about the newest x.
A, B, C = 30.0, 20.0, 10.0
T = np.eye(4)
T[:3, :3] = _Rz(A) @ _Ry(B) @ _Rx(C)
T[:3, 3] = [0.1, -0.2, 0.3]
Q = _hamilton(_hamilton(_q_axis(2, A), _q_axis(1, B)), _q_axis(0, C))
ANGLE = 2 * math.acos(Q[0])
ROTVEC = ANGLE * Q[1:] / np.linalg.norm(Q[1:])


def test_one_pose_in_each_robots_convention():
    assert np.allclose(to_robot(T, "kuka"), [100.0, -200.0, 300.0, A, B, C])
    assert np.allclose(to_robot(T, "fanuc"), [100.0, -200.0, 300.0, C, B, A])  # W about x, P about y, R about z
    assert np.allclose(to_robot(T, "abb"), [100.0, -200.0, 300.0, *Q])
    assert np.allclose(to_robot(T, "ur"), [0.1, -0.2, 0.3, *ROTVEC])
    assert np.allclose(to_robot(T, "matrix"), T)
    # The quaternion is a unit one with its scalar first and not negative.
    q = np.asarray(to_robot(T, "abb"))[3:]
    assert q[0] > 0 and math.isclose(float(np.linalg.norm(q)), 1.0)


def test_a_tool_pointing_down_as_a_ur_programmer_writes_it():
    # z down, x along the base's x: half a turn about y, URScript's p[x, y, z, 0, 3.1416, 0].
    down = np.diag([-1.0, 1.0, -1.0, 1.0])
    down[:3, 3] = [0.4, 0.0, 0.2]
    ur = np.asarray(to_robot(down, "ur"))
    assert np.allclose(ur[:3], [0.4, 0.0, 0.2])
    assert np.allclose(np.abs(ur[3:]), [0.0, math.pi, 0.0])
    assert np.allclose(from_robot([0.4, 0.0, 0.2, 0.0, math.pi, 0.0], "ur"), down)


@pytest.mark.parametrize("fmt", POSE_FORMATS)
def test_round_trips(fmt):
    rng = np.random.default_rng(7)
    for _ in range(50):
        q = rng.normal(size=4)
        w, x, y, z = q / np.linalg.norm(q)
        R = np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
            ]
        )
        pose = np.eye(4)
        pose[:3, :3] = R
        pose[:3, 3] = rng.uniform(-1.5, 1.5, 3)
        values = to_robot(pose, fmt)
        assert np.allclose(from_robot(values, fmt), pose, atol=1e-9)
        # The rounded numbers an answer carries still give the pose to a micrometre / microradian.
        assert np.allclose(from_robot(rounded(values, fmt), fmt), pose, atol=2e-6)


@pytest.mark.parametrize("fmt", ["kuka", "fanuc"])
def test_gimbal_lock_still_gives_the_same_matrix(fmt):
    locked = np.eye(4)
    locked[:3, :3] = _Rz(40) @ _Ry(90) @ _Rx(-15)
    values = to_robot(locked, fmt)
    assert math.isclose(values[4], 90.0, abs_tol=1e-6)
    assert np.allclose(from_robot(values, fmt), locked, atol=1e-9)


def test_wrong_input_is_refused():
    with pytest.raises(ValueError, match="not one of"):
        to_robot(T, "staubli")
    with pytest.raises(ValueError, match="6 numbers"):
        from_robot([1.0, 2.0, 3.0], "kuka")
    with pytest.raises(ValueError, match="4 x 4"):
        to_robot(np.eye(3), "ur")
    assert set(FIELDS) == set(POSE_FORMATS) - {"matrix"}


def test_the_params_offer_the_formats_there_are():
    from typing import get_args

    from binpick.params import PickParams

    assert get_args(PickParams.model_fields["pose_format"].annotation) == POSE_FORMATS
