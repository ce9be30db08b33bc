import json

import numpy as np
import pytest

from binpick.errors import BinpickError, InputError
from binpick.io.capture import load_capture
from binpick.io.cloud import load_cloud, save_cloud
from binpick.io.ply import PointCloudData, load_ply, save_ply
from binpick.io.poses import PartPose, load_poses, save_poses
from binpick.scene.cleaning import _at_the_edge, _long_and_low, _square_to, clean_capture

from settings import PARAMS, changed


def _bin_frame(H=240, W=320, f=300.0, floor_m=0.5, rng=None):
    """An organized frame: a floor 0.5 m away, a 60 x 40 x 30 mm box on it, some NaN."""
    rng = rng or np.random.default_rng(0)
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    d = np.stack([(u - W / 2) / f, (v - H / 2) / f, np.ones_like(u, dtype=float)], -1)
    z = np.full((H, W), floor_m)
    x, y = d[..., 0] * (floor_m - 0.03), d[..., 1] * (floor_m - 0.03)
    on_box = (np.abs(x) < 0.03) & (np.abs(y) < 0.02)
    z[on_box] = floor_m - 0.03
    xyz = d * z[..., None] + rng.normal(0, 0.0002, (H, W, 1)) * d
    xyz[rng.random((H, W)) < 0.05] = np.nan
    return xyz.reshape(-1, 3).astype(np.float32), on_box.reshape(-1)


def test_cleaning_recovers_the_floor_and_keeps_the_object():
    xyz, on_box = _bin_frame()
    cloud = clean_capture(xyz, None, (240, 320), changed(PARAMS.import_capture, remove_walls=False), seed=0)
    a, b, c, d = cloud.floor_plane
    assert np.allclose([a, b, c], [0, 0, -1], atol=0.01) and abs(d - 0.5) < 0.002
    assert d > 0  # oriented toward the camera
    kept_on_box = on_box[cloud.pixel_index]
    assert kept_on_box.mean() > 0.99
    # The box top is 60 x 40 mm: about 600 cells of a 2 mm grid.
    assert 400 < len(cloud.points_m) < 800
    assert np.all(cloud.normals[:, 2] < 0)
    assert 0.5 < cloud.removed_fraction[0] < 1.0


def test_a_floor_seen_through_more_depth_noise_than_the_plane_threshold_is_still_the_floor():
    """A floor 1.9 m away measured with 5 mm of depth noise along the rays (a Kinect-class sensor
    that far; the plane threshold is 3 mm): a quarter or more of its points lie more than the
    threshold behind any plane RANSAC draws through it. It is found at its true place all the
    same, since behind is counted beyond the noise the capture shows on the plane, and the box
    on it (30 mm high) is kept whole."""
    rng = np.random.default_rng(4)
    xyz, on_box = _bin_frame(floor_m=1.9, rng=rng)
    rays = xyz / xyz[:, 2:3]
    xyz = (xyz + rng.normal(0.0, 0.005, (len(xyz), 1)) * rays).astype(np.float32)
    params = changed(PARAMS.import_capture, remove_walls=False, max_range_m=3.0)
    cloud = clean_capture(xyz, None, (240, 320), params, seed=0)
    a, b, c, d = cloud.floor_plane
    assert np.allclose([a, b, c], [0, 0, -1], atol=0.02) and abs(d - 1.9) < 0.004
    kept = cloud.pixel_index[cloud.pixel_index >= 0]
    assert on_box[kept].sum() >= 0.9 * (on_box & np.isfinite(xyz[:, 2])).sum()
    assert 0.7 < cloud.removed_fraction[0] < 1.0


def test_cleaning_errors_and_warnings():
    xyz, _ = _bin_frame()
    with pytest.raises(BinpickError, match="no valid point"):
        clean_capture(np.full((100, 3), np.nan, np.float32), None, None, PARAMS.import_capture, 0)
    with pytest.raises(BinpickError, match="unit"):
        clean_capture(xyz * 1000, None, None, PARAMS.import_capture, 0)  # millimetres read as metres
    # A scene with no plane: a random blob; nothing is removed, NaN floor reported.
    blob = np.random.default_rng(1).normal([0, 0, 0.5], 0.03, (5000, 3)).astype(np.float32)
    cloud = clean_capture(blob, None, None, PARAMS.import_capture, 0)
    assert np.isnan(cloud.floor_plane).all() and (cloud.pixel_index == -1).all()


def test_organized_ply_roundtrip_keeps_nan_and_shape(tmp_path):
    xyz, _ = _bin_frame(H=20, W=30)
    rgb = np.random.default_rng(0).integers(0, 255, (600, 3)).astype(np.uint8)
    save_ply(tmp_path / "c.ply", PointCloudData(xyz * 1000, rgb, None, (20, 30)))
    back = load_ply(tmp_path / "c.ply")
    assert back.shape == (20, 30)
    assert np.array_equal(np.isnan(back.xyz), np.isnan(xyz * 1000))
    assert np.allclose(back.xyz, xyz * 1000, equal_nan=True) and np.array_equal(back.rgb, rgb)
    cap = load_capture(tmp_path / "c.ply", "mm")
    assert np.allclose(cap.xyz_m, xyz, equal_nan=True, atol=1e-6)


def test_bad_capture_files(tmp_path):
    xyz, _ = _bin_frame(H=20, W=30)
    save_ply(tmp_path / "c.ply", PointCloudData(xyz, None, None, (20, 30)))
    data = (tmp_path / "c.ply").read_bytes()
    (tmp_path / "cut.ply").write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="cut.ply"):
        load_capture(tmp_path / "cut.ply", "mm")
    (tmp_path / "x.step").write_text("ISO-10303-21;")
    with pytest.raises(InputError, match="unsupported capture format"):
        load_capture(tmp_path / "x.step", "mm")
    with pytest.raises(InputError, match="not found"):
        load_capture(tmp_path / "none.ply", "mm")


def test_cloud_and_pose_files_roundtrip(tmp_path):
    xyz, _ = _bin_frame()
    cloud = clean_capture(xyz, None, (240, 320), PARAMS.import_capture, 0)
    save_cloud(tmp_path / "cloud.npz", cloud)
    back = load_cloud(tmp_path / "cloud.npz")
    assert np.array_equal(back.points_m, cloud.points_m) and np.array_equal(back.pixel_index, cloud.pixel_index)
    T = np.eye(4)
    T[:3, 3] = [0.01, 0.02, 0.5]
    written = [
        PartPose(T, 0.9, 3, visible_fraction=0.5),
        PartPose(T, 0.7, seen_through=0.123456, visible_support=0.9, turned_by_near_symmetry=True),
    ]
    save_poses(tmp_path / "p.json", "t_joint", written)
    part, poses = load_poses(tmp_path / "p.json")
    assert part == "t_joint" and np.allclose(poses[0].T_cam_from_model, T) and poses[0].segment == 3
    assert (poses[0].visible_fraction, poses[0].seen_through, poses[0].turned_by_near_symmetry) == (0.5, None, False)
    # The typed fields are stored under "extra" as before, rounded only in the file.
    assert json.loads((tmp_path / "p.json").read_text())["poses"][1]["extra"] == {
        "turned_by_near_symmetry": 1.0,
        "seen_through": 0.1235,
        "visible_support": 0.9,
    }
    assert (poses[1].seen_through, poses[1].visible_support, poses[1].turned_by_near_symmetry, poses[1].extra) == (
        0.1235,
        0.9,
        True,
        None,
    )
    (tmp_path / "bad.json").write_text('{"part": "x"}')
    with pytest.raises(InputError, match="bad.json"):
        load_poses(tmp_path / "bad.json")


def test_region_of_interest_in_a_bin_frame():
    from binpick.generation.bin import T_bin_from_cam
    from binpick.geometry.transforms import invert_T

    xyz, on_box = _bin_frame()
    T_cam_bin = invert_T(T_bin_from_cam(0.5))  # bin floor 0.5 m below the camera, z up
    roi = changed(
        PARAMS.import_capture,
        roi_min_m=(-0.02, -0.05, -0.01),
        roi_max_m=(0.05, 0.05, 0.1),
        T_cam_from_roi=tuple(map(tuple, T_cam_bin)),
    )
    cloud = clean_capture(xyz, None, (240, 320), roi, 0)
    # Only the box top (30 mm above the floor) between x = -20 and +30 mm of the bin frame is left.
    x_bin = cloud.points_m[:, 0]  # the camera's x is the bin's x
    assert on_box[cloud.pixel_index].all() and x_bin.min() > -0.0205 and x_bin.max() < 0.0305
    with pytest.raises(ValueError, match="rigid"):
        changed(PARAMS.import_capture, T_cam_from_roi=((2, 0, 0, 0), (0, 1, 0, 0), (0, 0, 1, 0), (0, 0, 0, 1)))


def test_plane_quad_lies_on_the_plane_under_the_points():
    from review.recording import plane_quad

    plane = np.array([0.1, -0.05, -1.0, 0.5])
    plane /= np.linalg.norm(plane[:3])
    pts = np.random.default_rng(0).uniform([-0.1, -0.08, 0.4], [0.12, 0.09, 0.45], (200, 3))
    quad = plane_quad(plane, pts, margin_m=0.01)
    assert np.allclose(quad @ plane[:3] + plane[3], 0.0, atol=1e-6)
    assert np.allclose(quad[:, :2].min(axis=0), pts[:, :2].min(axis=0) - 0.01, atol=1e-6)
    assert np.allclose(quad[:, :2].max(axis=0), pts[:, :2].max(axis=0) + 0.01, atol=1e-6)
    assert plane_quad(np.array([1.0, 0.0, 0.0, 0.1]), pts) is None  # edge-on to the camera


def test_points_outside_the_bin_walls_are_dropped():
    """A rendered bin with a part inside and a carton standing on the table outside it: the walls
    are found and only what lies inside them is kept."""
    import trimesh

    from binpick.generation.bin import T_bin_from_cam, bin_meshes
    from binpick.generation.camera import camera_of, render
    from binpick.geometry.transforms import invert_T, transform_points

    bin_params = PARAMS.generate.bin
    table = trimesh.creation.box(extents=[1.2, 1.0, 0.01])
    table.apply_translation([0.0, 0.0, -0.025])  # a table reaching far beyond the bin
    inside = trimesh.creation.box(extents=[0.06, 0.04, 0.03])
    inside.apply_translation([0.03, 0.02, 0.015])
    outside = trimesh.creation.box(extents=[0.08, 0.05, 0.12])  # a carton beside the bin
    outside.apply_translation([bin_params.inner_x_m / 2 + 0.09, 0.0, 0.04])
    T_cam_bin = invert_T(T_bin_from_cam(0.8))  # far enough to see past the bin
    meshes = [
        (transform_points(T_cam_bin, np.asarray(m.vertices)), np.asarray(m.faces))
        for m in [*bin_meshes(bin_params), table, inside, outside]
    ]
    labels = [-1] * (len(meshes) - 3) + [-1, 0, 1]
    camera = PARAMS.camera.model_copy(update={"downscale": 4})
    frame = render(meshes, labels, camera_of(camera))
    H, W = frame.labels.shape
    params = changed(PARAMS.import_capture, crop_to_walls=True)
    cloud = clean_capture(frame.xyz_m.reshape(-1, 3), None, (H, W), params, 0)
    kept = frame.labels.reshape(-1)[cloud.pixel_index]
    assert len(cloud.wall_planes) >= 2
    assert (kept == 0).sum() > 50 and (kept == 1).sum() == 0  # the part stays, the carton goes
    uncropped = clean_capture(frame.xyz_m.reshape(-1, 3), None, (H, W), changed(params, crop_to_walls=False), 0)
    assert (frame.labels.reshape(-1)[uncropped.pixel_index] == 1).sum() > 50  # it was there to drop


def test_walls_are_found_under_a_heap_of_flat_layers():
    """A bin holding flat plates at nine heights (each a floor-parallel plane, like a heap of flat
    parts seen from above) and a carton outside: the layers do not take the wall search's tries,
    the walls found stand upright at the bin's inner faces, and the carton goes."""
    import trimesh

    from binpick.generation.bin import T_bin_from_cam, bin_meshes
    from binpick.generation.camera import camera_of, render
    from binpick.geometry.transforms import invert_T, transform_points

    bin_params = PARAMS.generate.bin
    table = trimesh.creation.box(extents=[1.2, 1.0, 0.01])
    table.apply_translation([0.0, 0.0, -0.025])
    plates = []
    for k, (x, y) in enumerate((x, y) for x in (-0.07, 0.0, 0.07) for y in (-0.05, 0.0, 0.05)):
        plate = trimesh.creation.box(extents=[0.05, 0.035, 0.004])
        plate.apply_translation([x, y, 0.004 + 0.005 * k])  # nine heights, 5 mm apart
        plates.append(plate)
    outside = trimesh.creation.box(extents=[0.08, 0.05, 0.12])
    outside.apply_translation([bin_params.inner_x_m / 2 + 0.09, 0.0, 0.04])
    T_cam_bin = invert_T(T_bin_from_cam(0.8))
    scene = [*bin_meshes(bin_params), table, *plates, outside]
    meshes = [(transform_points(T_cam_bin, np.asarray(m.vertices)), np.asarray(m.faces)) for m in scene]
    labels = [-1] * (len(scene) - len(plates) - 1) + [0] * len(plates) + [1]
    frame = render(meshes, labels, camera_of(PARAMS.camera.model_copy(update={"downscale": 4})))
    H, W = frame.labels.shape
    cloud = clean_capture(
        frame.xyz_m.reshape(-1, 3), None, (H, W), changed(PARAMS.import_capture, crop_to_walls=True), 0
    )
    kept = frame.labels.reshape(-1)[cloud.pixel_index]
    assert len(cloud.wall_planes) >= 2
    # Upright (the bin's walls are), and at the inner faces: 0.15 m and 0.10 m from the bin's axis.
    up = T_cam_bin[:3, 2]
    centre = T_cam_bin[:3, 3]
    for plane in cloud.wall_planes:
        assert abs(plane[:3] @ up) < 0.02, plane
        assert min(abs(abs(plane[:3] @ centre + plane[3]) - a) for a in (0.15, 0.10)) < 0.004, plane
    assert (kept == 0).sum() > 500 and (kept == 1).sum() == 0


def test_a_wall_runs_along_the_floor_and_a_part_side_does_not():
    """Points on the plane x = 0.2 (floor z = 0, normal +z): a bin wall 0.4 m long and 0.15 m
    high is one; the side of a part standing on the floor, 0.08 m wide and 0.12 m high, is not,
    nor is it with things far along the same plane (past a gap)."""
    rng = np.random.default_rng(0)
    floor, plane = np.array([0.0, 0.0, 1.0, 0.0]), np.array([-1.0, 0.0, 0.0, 0.2])

    def patch(y0, y1, height, n):
        return np.c_[np.full(n, 0.2), rng.uniform(y0, y1, n), rng.uniform(0.0, height, n)]

    assert _long_and_low(patch(-0.2, 0.2, 0.15, 3000), floor, plane, 0.02)
    side = patch(0.0, 0.08, 0.12, 600)
    assert not _long_and_low(side, floor, plane, 0.02)
    assert not _long_and_low(
        np.vstack([side, patch(0.2, 0.26, 0.12, 400), patch(0.4, 0.45, 0.1, 300)]), floor, plane, 0.02
    )


def test_a_walls_own_rim_counts_on_neither_side_of_it():
    """The last wall x = 0.2 of a nearly empty bin (floor z = 0, the bin at x < 0.2, walls 0.08 m
    high): what is left is the rims of the walls (the 10 mm top faces: this wall's beyond its face,
    two others' inside) and one part leaning on it. Counting this wall's rim, a quarter of the
    points lie beyond it and it is no wall; without it, it is one. A plane through a heap, parts
    on both sides at every height, is still none."""
    rng = np.random.default_rng(0)
    floor, plane = np.array([0.0, 0.0, 1.0, 0.0]), np.array([1.0, 0.0, 0.0, -0.2])

    def box(lo, hi, n):
        return rng.uniform(lo, hi, (n, 3))

    own_rim = box([0.2, -0.1, 0.079], [0.21, 0.1, 0.081], 800)
    other_rims = box([-0.2, -0.11, 0.079], [0.2, -0.1, 0.081], 900)
    part = box([0.15, -0.02, 0.01], [0.195, 0.02, 0.07], 1100)
    left = np.vstack([own_rim, other_rims, part])
    assert not _at_the_edge(left, floor, plane, 0.002)
    assert _at_the_edge(left, floor, plane, 0.002, top_m=0.08)
    heap = np.vstack([box([0.1, -0.1, 0.0], [0.2, 0.1, 0.1], 1500), box([0.2, -0.1, 0.0], [0.3, 0.1, 0.1], 1500)])
    assert not _at_the_edge(heap, floor, plane, 0.002, top_m=0.08)


def test_walls_stand_square_to_each_other():
    """After a wall with normal +x: walls with normals along y or -x (5 degrees off) are square
    to it; a plane along a diagonal row of parts (30 degrees) is not."""
    first = np.array([1.0, 0.0, 0.0, -0.2])

    def plane(deg):
        a = np.radians(deg)
        return np.array([np.cos(a), np.sin(a), 0.0, 0.1])

    assert _square_to(plane(0.0), []) and _square_to(plane(95.0), [first]) and _square_to(plane(175.0), [first])
    assert not _square_to(plane(30.0), [first]) and not _square_to(plane(135.0), [first])


def test_one_pass_screen_keeps_the_view_grid_of_the_points_in_range_and_region():
    """The fused pass of clean_capture against its definition in plain numpy: valid points,
    range within [min, max], inside the ROI box of the bin frame, then view_grid's first point
    per voxel. The same pixels, in the same order."""
    from binpick.geometry.pointcloud import first_in_each_voxel
    from binpick.geometry.transforms import invert_T, transform_points
    from binpick.scene.cleaning import _kept_voxel_keys, _screen
    from binpick.view import ViewParams, view_grid

    xyz, _ = _bin_frame()
    xyz[::7] *= 5.0  # some pixels out of range (2.5 m)
    T_roi_from_cam = invert_T(np.array([[0.8, -0.6, 0, 0.01], [0.6, 0.8, 0, -0.02], [0, 0, 1, 0.45], [0, 0, 0, 1.0]]))
    lo, hi = np.array([-0.04, -0.03, -0.01]), np.array([0.05, 0.02, 0.2])
    params = PARAMS.import_capture
    voxel = ViewParams.of_import(params).voxel_size_m

    valid = np.isfinite(xyz).all(axis=1)
    r = np.linalg.norm(xyz.astype(np.float64), axis=1)
    in_box = np.all(
        (transform_points(T_roi_from_cam, xyz.astype(np.float64)) >= lo)
        & (transform_points(T_roi_from_cam, xyz.astype(np.float64)) <= hi),
        axis=1,
    )
    keep = valid & (r >= params.min_range_m) & (r <= params.max_range_m) & in_box
    expected = np.flatnonzero(keep)[view_grid(xyz[keep], ViewParams.of_import(params))]

    got_valid, got_keep, lo_xyz, hi_xyz, key_lo, key_hi, n_valid, n_keep = _screen(
        xyz,
        params.min_range_m**2,
        params.max_range_m**2,
        True,
        np.ascontiguousarray(T_roi_from_cam[:3, :3]),
        T_roi_from_cam[:3, 3].copy(),
        lo,
        hi,
        1.0 / voxel,
    )
    assert (
        np.array_equal(got_valid, valid)
        and np.array_equal(got_keep, keep)
        and n_valid == valid.sum()
        and n_keep == keep.sum()
    )
    assert np.allclose(lo_xyz, np.nanmin(xyz, axis=0)) and np.allclose(hi_xyz, np.nanmax(xyz, axis=0))
    span = key_hi - key_lo + 1
    kept, flat = _kept_voxel_keys(xyz, got_keep, n_keep, key_lo, span, 1.0 / voxel)
    assert 100 < len(expected) < keep.sum()
    assert np.array_equal(kept[first_in_each_voxel(flat, int(np.prod(span)))], expected)


def test_a_given_box_removes_a_wall_only_where_it_has_one_and_only_up_to_its_rim():
    """A box as `binpick fit-bin` gives a heap over a low rim: a 5 cm wall at -x, none at the
    other sides. A bar resting on the -x rim, its face in the wall's plane above the rim, keeps
    that face; a bar standing along the +y side, its face where a wall would be, is no wall; the
    -x wall itself is removed (an oblique camera sees both faces)."""
    import trimesh

    from binpick.cell.bin_box import BinBox
    from binpick.generation.camera import camera_of, render
    from binpick.geometry.transforms import invert_T, make_T, transform_points

    def block(lo, hi):
        mesh = trimesh.creation.box(extents=np.subtract(hi, lo))
        mesh.apply_translation((np.add(lo, hi)) / 2)
        return mesh

    floor = block([-0.25, -0.2, -0.01], [0.25, 0.2, 0.0])
    wall = block([-0.165, -0.1, 0.0], [-0.155, 0.1, 0.05])
    on_rim = block([-0.205, -0.09, 0.05], [-0.155, 0.09, 0.10])
    along_side = block([-0.14, 0.095, 0.0], [0.14, 0.135, 0.08])
    # A camera 0.7 m from the floor's centre, off toward +x and -y, looking at it.
    eye = np.array([0.2, -0.2, 0.65])
    z = -eye / np.linalg.norm(eye)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    T_cam_bin = invert_T(make_T(np.column_stack([x, np.cross(z, x), z]), eye))
    scene = [floor, wall, on_rim, along_side]
    meshes = [(transform_points(T_cam_bin, np.asarray(m.vertices)), np.asarray(m.faces)) for m in scene]
    frame = render(meshes, [-1, 0, 1, 2], camera_of(PARAMS.camera.model_copy(update={"downscale": 4})))
    H, W = frame.labels.shape
    box = BinBox(T_cam_bin, np.array([-0.16, -0.125, 0.004]), np.array([0.16, 0.125, 0.15]), np.array([0.05, 0, 0, 0]))
    given = changed(PARAMS.import_capture, crop_to_walls=True, **box.as_import_settings())
    cloud = clean_capture(frame.xyz_m.reshape(-1, 3), None, (H, W), given, 0)
    # The same crop with no wall removed: what each bar has to keep. The rim's bar is judged on
    # its face from 1 cm over the rim (the wall's plane is removed to a plane threshold above it).
    unwalled = clean_capture(frame.xyz_m.reshape(-1, 3), None, (H, W), changed(given, remove_walls=False), 0)
    labels = frame.labels.reshape(-1)
    xyz_bin = transform_points(invert_T(T_cam_bin), np.nan_to_num(frame.xyz_m.reshape(-1, 3)))
    face = (labels == 1) & (np.abs(xyz_bin[:, 0] + 0.155) < 0.002) & (xyz_bin[:, 2] > 0.06)
    kept, reference = np.zeros(len(labels), bool), np.zeros(len(labels), bool)
    kept[cloud.pixel_index], reference[unwalled.pixel_index] = True, True
    assert (reference & (labels == 0)).sum() > 200, "the camera sees the wall"
    assert (kept & (labels == 0)).sum() < 0.2 * (reference & (labels == 0)).sum(), "the wall is removed"
    for part, name in ((face, "the face over the rim"), (labels == 2, "the bar along the side with no wall")):
        assert (reference & part).sum() > 200 and (kept & part).sum() > 0.95 * (reference & part).sum(), name


def test_a_given_bin_box_sets_the_floor_and_the_walls():
    """A bin whose floor is covered by a layer of six flat parts lying side by side, cropped to its
    box just above its floor (as `binpick fit-bin` gives it): the parts' tops, the largest plane
    left, are not taken for the floor (every part keeps its top), and no plane through the parts
    is taken for a wall: the walls found stand at the box's sides."""
    import trimesh

    from binpick.cell.bin_box import BinBox
    from binpick.generation.bin import T_bin_from_cam, bin_meshes
    from binpick.generation.camera import camera_of, render
    from binpick.geometry.transforms import invert_T, transform_points

    bin_params = PARAMS.generate.bin  # 0.30 x 0.20 m inside, 8 cm walls
    plates = []
    for x in (-0.1, 0.0, 0.1):
        for y in (-0.05, 0.05):
            plate = trimesh.creation.box(extents=[0.09, 0.09, 0.02])
            plate.apply_translation([x, y, 0.01])
            plates.append(plate)
    T_cam_bin = invert_T(T_bin_from_cam(0.8))
    scene = [*bin_meshes(bin_params), *plates]
    meshes = [(transform_points(T_cam_bin, np.asarray(m.vertices)), np.asarray(m.faces)) for m in scene]
    labels = [-1] * (len(scene) - len(plates)) + list(range(len(plates)))
    frame = render(meshes, labels, camera_of(PARAMS.camera.model_copy(update={"downscale": 4})))
    H, W = frame.labels.shape
    half = np.array([bin_params.inner_x_m, bin_params.inner_y_m]) / 2 + bin_params.wall_thickness_m
    box = BinBox(T_cam_bin, np.append(-half, 0.004), np.append(half, 0.1))
    params = changed(PARAMS.import_capture, crop_to_walls=True, **box.as_import_settings())
    cloud = clean_capture(frame.xyz_m.reshape(-1, 3), None, (H, W), params, 0)
    kept = frame.labels.reshape(-1)[cloud.pixel_index]
    # The same frame without the box: the floor is in view and found, every part kept whole.
    whole = clean_capture(frame.xyz_m.reshape(-1, 3), None, (H, W), changed(PARAMS.import_capture), 0)
    reference = frame.labels.reshape(-1)[whole.pixel_index]
    for k in range(len(plates)):
        assert (reference == k).sum() > 100 and (kept == k).sum() > 0.9 * (reference == k).sum(), k
    assert np.allclose(cloud.floor_plane, np.append(T_cam_bin[:3, 2], -T_cam_bin[:3, 2] @ T_cam_bin[:3, 3]))
    centre = T_cam_bin[:3, 3]
    for plane in cloud.wall_planes:  # at the inner faces, 0.15 m and 0.10 m from the bin's axis
        assert min(abs(abs(plane[:3] @ centre + plane[3]) - a) for a in (0.15, 0.10)) < 0.004, plane
