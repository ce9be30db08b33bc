"""Point-to-plane ICP (geometry/icp.py): a pose applied to a view of the T-joint is recovered from
a start a few degrees and millimetres off, pairs beyond the distance limit do not pull it, the
same input gives the same bits every time, and on a surface of revolution the turn about its
axis is left as it starts while the rest of the pose is recovered."""

from __future__ import annotations

import numpy as np

from binpick.geometry.icp import point_to_plane_icp
from binpick.geometry.symmetry import revolution_axis, symmetry_transforms
from binpick.geometry.transforms import axis_angle_to_R, invert_T, make_T, rotation_angle_deg, transform_points
from binpick.params import SymmetryParams


def _view(t_joint, rng):
    """Surface points of the T-joint facing +z (a camera's view from above), moved by a known pose,
    with 0.3 mm noise: (points (n, 3) scene frame, T_scene_from_model)."""
    facing = t_joint.normals[:, 2] > 0.2
    T_scene_from_model = make_T(
        axis_angle_to_R(np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8]), 0.7),
        np.array([0.02, -0.01, 0.45]),
    )
    points = transform_points(T_scene_from_model, t_joint.points_m[facing][::3])
    return points + rng.normal(0.0, 0.0003, points.shape), T_scene_from_model


def _start(T_model_from_scene, angle_deg, offset_m):
    nudge = make_T(
        axis_angle_to_R(np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0), np.radians(angle_deg)),
        np.array([offset_m, -offset_m, offset_m]),
    )
    return nudge @ T_model_from_scene


def test_a_pose_off_by_degrees_and_millimetres_is_recovered(t_joint):
    scene, T_scene_from_model = _view(t_joint, np.random.default_rng(0))
    truth = invert_T(T_scene_from_model)
    T = point_to_plane_icp(scene, t_joint.points_m, t_joint.normals, _start(truth, 4.0, 0.002), 0.008, 30, 1e-6)
    # The model points where the pose found puts them, against where they are: 4 degrees and
    # 3.5 mm off at the start.
    moved = np.linalg.norm(
        transform_points(invert_T(T), t_joint.points_m) - transform_points(T_scene_from_model, t_joint.points_m), axis=1
    )
    assert moved.mean() < 0.0002, moved.mean()
    assert rotation_angle_deg(T[:3, :3], truth[:3, :3]) < 0.2


def test_points_beyond_the_distance_limit_do_not_pull():
    """A plane z = 0 and a scene on it shifted 1 mm up, with a cluster 5 cm above: ICP with a 5 mm
    limit brings the plane points down and ignores the cluster."""
    rng = np.random.default_rng(1)
    target = np.c_[rng.uniform(-0.05, 0.05, (4000, 2)), np.zeros(4000)]
    normals = np.tile([0.0, 0.0, 1.0], (4000, 1))
    # A ridge along x and y keeps the in-plane motion determined (the plane alone fixes 3 of 6).
    ridge = np.c_[rng.uniform(-0.05, 0.05, 400), np.zeros(400), rng.uniform(0, 0.01, 400)]
    target = np.vstack([target, ridge, ridge[:, [1, 0, 2]]])
    normals = np.vstack([normals, np.tile([0.0, 1.0, 0.0], (400, 1)), np.tile([1.0, 0.0, 0.0], (400, 1))])
    on_plane = target[::5] + [0.0, 0.0, 0.001]
    cluster = rng.uniform(-0.01, 0.01, (300, 3)) + [0.0, 0.0, 0.05]
    T = point_to_plane_icp(np.vstack([on_plane, cluster]), target, normals, np.eye(4), 0.005, 30, 1e-7)
    assert abs(T[2, 3] + 0.001) < 1e-5
    assert rotation_angle_deg(T[:3, :3], np.eye(3)) < 0.01


def test_the_same_input_gives_the_same_bits(t_joint):
    scene, T_scene_from_model = _view(t_joint, np.random.default_rng(2))
    start = _start(invert_T(T_scene_from_model), 3.0, 0.001)
    results = {
        point_to_plane_icp(scene, t_joint.points_m, t_joint.normals, start, 0.006, 30, 1e-6).tobytes()
        for _ in range(20)
    }
    assert len(results) == 1


def _vase(n: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """A surface of revolution about the axis z through (0.01, -0.02, 0): radius 30 mm + 8 mm
    sin(40 z), 0 <= z <= 0.1 m (its waist fixes it along the axis). (points, unit normals)."""
    z, phi = rng.uniform(0.0, 0.1, n), rng.uniform(0.0, 2.0 * np.pi, n)
    r, dr = 0.03 + 0.008 * np.sin(40.0 * z), 0.32 * np.cos(40.0 * z)
    points = np.c_[0.01 + r * np.cos(phi), -0.02 + r * np.sin(phi), z]
    normals = np.c_[np.cos(phi), np.sin(phi), -dr]
    return points, normals / np.linalg.norm(normals, axis=1, keepdims=True)


def test_the_turn_about_an_axis_of_revolution_is_left_free():
    """A view of the vase's side (points facing +y), 3 degrees tilted, 2 mm off and turned 20
    degrees about its axis at the start: the tilt and offset are recovered, the turn stays."""
    rng = np.random.default_rng(3)
    target, normals = _vase(20000, rng)
    axis, point = np.array([0.0, 0.0, 1.0]), np.array([0.01, -0.02, 0.0])
    seen = target[normals[:, 1] > 0.3][::4]
    seen = seen + rng.normal(0.0, 0.0002, seen.shape)
    turn = make_T(axis_angle_to_R(axis, np.radians(20.0)), point - axis_angle_to_R(axis, np.radians(20.0)) @ point)
    start = make_T(axis_angle_to_R(np.array([1.0, 0.0, 0.0]), np.radians(3.0)), np.array([0.002, 0.0, -0.002])) @ turn
    T = point_to_plane_icp(seen, target, normals, start, 0.01, 30, 1e-7, free_turn=(axis, point))
    # T takes the seen points (on the vase at the identity) to the turned vase: T = turn.
    assert rotation_angle_deg(T[:3, :3], turn[:3, :3]) < 0.1
    assert np.abs(transform_points(T, seen) - transform_points(turn, seen)).max() < 0.0003


def test_the_axis_of_a_declared_revolution_is_found():
    S = symmetry_transforms(SymmetryParams(kind="revolution", axis=(0.0, 0.6, 0.8), origin_m=(0.01, 0.02, 0.03)))
    axis, point = revolution_axis(S)
    assert abs(abs(axis @ np.array([0.0, 0.6, 0.8])) - 1.0) < 1e-9
    # The point lies on the declared axis through origin_m.
    offset = point - np.array([0.01, 0.02, 0.03])
    assert np.linalg.norm(offset - (offset @ axis) * axis) < 1e-9
    assert revolution_axis(symmetry_transforms(SymmetryParams(kind="n_fold", axis=(0.0, 0.0, 1.0), order=6))) is None
    assert revolution_axis(symmetry_transforms(SymmetryParams())) is None
