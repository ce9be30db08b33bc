import numpy as np
import pytest

from binpick.geometry.pointcloud import estimate_normals, fit_plane_ransac, sample_normals, voxel_downsample_indices
from binpick.geometry.symmetry import symmetry_transforms
from binpick.geometry.transforms import (
    axis_angle_to_R,
    invert_T,
    make_T,
    random_rotation,
    rotation_angle_deg,
    transform_points,
)
from binpick.params import SymmetryParams


def test_invert_and_compose():
    rng = np.random.default_rng(1)
    T = make_T(random_rotation(rng), rng.normal(size=3))
    assert np.allclose(invert_T(T) @ T, np.eye(4))
    p = rng.normal(size=(10, 3))
    assert np.allclose(transform_points(invert_T(T), transform_points(T, p)), p)


def test_random_rotation_is_proper_and_angle_known():
    R = random_rotation(np.random.default_rng(2))
    assert np.allclose(R @ R.T, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)
    R30 = axis_angle_to_R(np.array([1.0, 2.0, 3.0]), np.radians(30))
    assert np.isclose(rotation_angle_deg(R, R @ R30), 30.0)


def test_symmetry_transforms_map_axis_points_to_themselves():
    S = symmetry_transforms(SymmetryParams(kind="n_fold", axis=(0, 1, 0), order=2, origin_m=(0.01, 0, 0)))
    assert S.shape == (2, 4, 4) and np.allclose(S[0], np.eye(4))
    # A point on the axis stays; a point off the axis goes to its mirror about the axis.
    assert np.allclose(transform_points(S[1], np.array([[0.01, 0.5, 0.0]])), [[0.01, 0.5, 0.0]])
    assert np.allclose(transform_points(S[1], np.array([[0.02, 0.0, 0.0]])), [[0.0, 0.0, 0.0]])
    assert len(symmetry_transforms(SymmetryParams(kind="revolution"))) == 360
    assert len(symmetry_transforms(SymmetryParams())) == 1


def test_ransac_recovers_a_tilted_plane_among_outliers():
    rng = np.random.default_rng(3)
    normal = np.array([0.1, -0.2, 1.0])
    normal /= np.linalg.norm(normal)
    d = -0.5
    u = np.cross(normal, [1, 0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    pts = rng.uniform(-0.2, 0.2, (3000, 1)) * u + rng.uniform(-0.2, 0.2, (3000, 1)) * v - d * normal
    pts += rng.normal(0, 0.0005, (3000, 1)) * normal
    outliers = rng.uniform(-0.3, 0.3, (1000, 3)) + [0, 0, 0.3]
    plane, inliers = fit_plane_ransac(np.vstack([pts, outliers]), 0.003, 500, seed=0)
    sign = np.sign(plane[:3] @ normal)
    assert np.allclose(sign * plane[:3], normal, atol=0.01)
    assert abs(sign * plane[3] - d) < 0.002
    assert inliers[:3000].mean() > 0.99 and inliers[3000:].mean() < 0.1


def test_ransac_finds_the_largest_plane_the_same_way_every_time():
    """A floor (60 % of the points) and a wall (40 %): the floor, and the very same plane for the
    same seed (the hypotheses and the stopping point follow the seed, not the threads); the
    wall's points are not its inliers."""
    rng = np.random.default_rng(3)
    floor = np.column_stack(
        [rng.uniform(-0.3, 0.3, 6000), rng.uniform(-0.3, 0.3, 6000), 0.8 + rng.normal(0, 0.0005, 6000)]
    )
    wall = np.column_stack(
        [0.3 + rng.normal(0, 0.0005, 4000), rng.uniform(-0.3, 0.3, 4000), rng.uniform(0.5, 0.8, 4000)]
    )
    pts = np.vstack([floor, wall])
    first, inliers = fit_plane_ransac(pts, 0.003, 1000, seed=7)
    assert abs(abs(first[2]) - 1.0) < 1e-3 and abs(abs(first[3]) - 0.8) < 1e-3
    assert inliers[:6000].mean() > 0.99 and inliers[6000:].mean() < 0.02
    for _ in range(3):
        again, again_inliers = fit_plane_ransac(pts, 0.003, 1000, seed=7)
        assert np.array_equal(again, first) and np.array_equal(again_inliers, inliers)


def test_a_fan_of_rows_through_the_camera_is_not_taken_for_the_floor():
    """A floor 0.8 m away (40 % of the points) and a plane through the camera holding more (the
    points of a few image rows): the largest plane is the fan; planes at least the camera's
    least range away leave the floor, the plane that was built."""
    rng = np.random.default_rng(5)
    floor = np.column_stack(
        [rng.uniform(-0.3, 0.3, 4000), rng.uniform(-0.3, 0.3, 4000), 0.8 + rng.normal(0, 0.0005, 4000)]
    )
    # The fan: rays from the camera (the origin) within the plane y = 0.2 z, ending on parts at
    # 0.4-0.75 m.
    z = rng.uniform(0.4, 0.75, 6000)
    fan = np.column_stack([rng.uniform(-0.3, 0.3, 6000) * z, 0.2 * z, z])
    pts = np.vstack([floor, fan])
    largest, _ = fit_plane_ransac(pts, 0.003, 1000, seed=1)
    assert abs(largest[3]) < 1e-3
    plane, inliers = fit_plane_ransac(pts, 0.003, 1000, seed=1, min_distance_m=0.2)
    assert abs(abs(plane[2]) - 1.0) < 1e-3 and abs(abs(plane[3]) - 0.8) < 1e-3
    assert inliers[:4000].mean() > 0.99


def test_voxel_downsample_keeps_one_point_per_voxel():
    pts = np.array([[0.001, 0.001, 0.001], [0.002, 0.002, 0.002], [0.011, 0.0, 0.0], [0.0, 0.0, 0.025]])
    idx = voxel_downsample_indices(pts, 0.01)
    assert idx.tolist() == [0, 2, 3]


def test_voxel_downsample_dense_and_sorted_paths_agree(monkeypatch):
    import binpick.geometry.pointcloud as pc

    rng = np.random.default_rng(5)
    pts = rng.uniform(-0.05, 0.05, (20000, 3)).astype(np.float32)
    # The first point of each voxel, by a plain dictionary.
    first: dict[tuple[int, int, int], int] = {}
    for i, k in enumerate(map(tuple, np.floor(pts.astype(np.float64) / 0.004).astype(int))):
        first.setdefault(k, i)
    expected = sorted(first.values())
    dense = voxel_downsample_indices(pts, 0.004)
    monkeypatch.setattr(pc, "DENSE_VOXEL_CELLS", 0)  # forces the sorting path
    assert dense.tolist() == expected == voxel_downsample_indices(pts, 0.004).tolist()


def test_normals_face_the_camera():
    rng = np.random.default_rng(4)
    xy = rng.uniform(-0.1, 0.1, (2000, 2))
    pts = np.column_stack([xy, np.full(2000, 0.5)])  # a plane 0.5 m in front of the camera
    n = estimate_normals(pts, 0.01)
    assert np.allclose(n, [0, 0, -1], atol=1e-3)


def test_kernels_reject_bad_shapes():
    with pytest.raises(ValueError):
        transform_points(np.eye(4), np.zeros((3, 2)))
    with pytest.raises(ValueError):
        voxel_downsample_indices(np.zeros(3), 0.1)


def test_dihedral_symmetry_group():
    S = symmetry_transforms(SymmetryParams(kind="n_fold", axis=(0, 1, 0), order=6, flip_axis=(1, 0, 0)))
    assert S.shape == (12, 4, 4)
    # A group: closed under composition.
    for a in S:
        for b in S:
            assert min(np.abs(a @ b - c).max() for c in S) < 1e-9
    with pytest.raises(ValueError, match="perpendicular"):
        SymmetryParams(kind="n_fold", axis=(0, 1, 0), order=6, flip_axis=(0, 1, 1))


def test_sample_normals_recover_a_plane_and_a_wall():
    """A floor z = 0 and a wall x = 0.3 tilted 5 degrees, 1 mm noise: the normals of a sample of
    the points are the planes' own, up to sign (but where a point's neighbours take in both)."""
    rng = np.random.default_rng(4)
    floor = np.c_[rng.uniform(-0.2, 0.2, (3000, 2)), rng.normal(0.0, 0.001, 3000)]
    tilt = np.radians(5.0)
    wall_normal = np.array([np.cos(tilt), 0.0, np.sin(tilt)])
    u, v = rng.uniform(-0.2, 0.2, 2000), rng.uniform(0.0, 0.15, 2000)
    wall = np.array([0.3, 0.0, 0.0]) + np.outer(u, [0.0, 1.0, 0.0]) + np.outer(v, [-np.sin(tilt), 0.0, np.cos(tilt)])
    wall += rng.normal(0.0, 0.001, wall.shape) * wall_normal
    points = np.vstack([floor, wall])
    index = np.r_[rng.choice(3000, 200, replace=False), 3000 + rng.choice(2000, 200, replace=False)]
    n = sample_normals(points, index)
    assert np.percentile(np.abs(n[:200, 2]), 5) > 0.97
    assert np.percentile(np.abs(n[200:] @ wall_normal), 5) > 0.97
