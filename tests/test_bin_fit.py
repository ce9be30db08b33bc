"""Fitting a cell's bin as a box from one capture (binpick fit-bin)."""

import numpy as np
import trimesh

from binpick.cell.bin_box import WALL_SIDES, BinBox
from binpick.cell.bin_fit import fit_bin_box, implausible, min_area_rectangle, sides_out_of_view
from binpick.generation.bin import T_bin_from_cam, bin_meshes
from binpick.generation.camera import camera_of, render
from binpick.geometry.pointcloud import fit_plane_ransac
from binpick.geometry.transforms import axis_angle_to_R, invert_T, make_T, transform_points

from settings import PARAMS


def test_smallest_rectangle_of_a_turned_rectangle():
    rng = np.random.default_rng(0)
    uv = rng.uniform([-0.2, -0.05], [0.2, 0.05], (2000, 2))
    angle = np.radians(25.0)
    R = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    centre, found, half = min_area_rectangle(uv @ R.T + [0.3, -0.1])
    assert np.allclose(centre, [0.3, -0.1], atol=0.003) and np.allclose(half, [0.2, 0.05], atol=0.003)
    assert abs(np.mod(found - angle + np.pi / 2, np.pi) - np.pi / 2) < np.radians(1.0)


def test_the_bin_is_fitted_on_a_table_and_the_carton_beside_it_left_out():
    bin_params = PARAMS.generate.bin
    table = trimesh.creation.box(extents=[1.2, 1.0, 0.01])
    table.apply_translation([0.0, 0.0, -0.025])
    part = trimesh.creation.box(extents=[0.06, 0.04, 0.03])
    part.apply_translation([0.03, 0.02, 0.015])
    carton = trimesh.creation.box(extents=[0.08, 0.05, 0.12])
    carton.apply_translation([bin_params.inner_x_m / 2 + 0.12, 0.0, 0.04])
    # The bin turned by 20 degrees on the table and seen from a camera tilted by 10 degrees.
    T_table_bin = make_T(axis_angle_to_R(np.array([0.0, 0.0, 1.0]), np.radians(20.0)), np.zeros(3))
    T_cam_table = invert_T(T_bin_from_cam(0.8)) @ make_T(
        axis_angle_to_R(np.array([1.0, 0.0, 0.0]), np.radians(10.0)), np.zeros(3)
    )
    meshes = [
        (transform_points(T_cam_table @ T_table_bin, np.asarray(m.vertices)), np.asarray(m.faces))
        for m in [*bin_meshes(bin_params), part]
    ]
    meshes += [(transform_points(T_cam_table, np.asarray(m.vertices)), np.asarray(m.faces)) for m in (table, carton)]
    labels_of_meshes = [-1] * len(bin_meshes(bin_params)) + [1, -1, -1]  # the part is 1
    frame = render(meshes, labels_of_meshes, camera_of(PARAMS.camera.model_copy(update={"downscale": 4})))
    xyz = frame.xyz_m.reshape(-1, 3)
    ok = np.all(np.isfinite(xyz), axis=1)
    pts = xyz[ok]
    floor, _ = fit_plane_ransac(pts, 0.003, 1000, 0)
    floor = floor if floor[3] > 0 else -floor
    box = fit_bin_box(pts, floor, 0.004)
    outer = np.array([bin_params.inner_x_m, bin_params.inner_y_m]) + 2 * bin_params.wall_thickness_m
    size = box.inner_max_m[:2] - box.inner_min_m[:2]
    assert np.allclose(size, outer, atol=0.01), size  # the bin's footprint, walls included
    # Every wall's rim was seen: the walls stand as high as the bin's (above the ground plane found),
    # also through 3 mm of depth noise (a Kinect-class sensor at a metre).
    assert np.allclose(box.wall_heights_m, bin_params.wall_height_m, atol=0.01), box.wall_heights_m
    rng = np.random.default_rng(1)
    noisy = pts + pts / np.linalg.norm(pts, axis=1, keepdims=True) * rng.normal(0.0, 0.003, (len(pts), 1))
    floor, _ = fit_plane_ransac(noisy, 0.009, 1000, 0)
    noisy_box = fit_bin_box(noisy, floor if floor[3] > 0 else -floor, 0.009)
    assert np.allclose(noisy_box.wall_heights_m, bin_params.wall_height_m, atol=0.012), noisy_box.wall_heights_m
    centre_in_table = transform_points(invert_T(T_cam_table), box.T_cam_from_bin[:3, 3][None])[0]
    assert np.linalg.norm(centre_in_table[:2]) < 0.01
    in_box = transform_points(invert_T(box.T_cam_from_bin), pts)
    inside = np.all((in_box >= box.inner_min_m) & (in_box <= box.inner_max_m), axis=1)
    labels = frame.labels.reshape(-1)[ok]
    assert inside[labels == 1].all()  # the part in the bin
    carton_pts = transform_points(invert_T(T_cam_table), pts)
    near_carton = np.abs(carton_pts[:, 0] - (bin_params.inner_x_m / 2 + 0.12)) < 0.03
    assert near_carton.sum() > 20 and not inside[near_carton & (carton_pts[:, 2] > 0.01)].any()


def _block(lo, hi, step=0.002):
    """Points on the surface of an axis-aligned block (lo, hi), bin frame, about step apart."""
    axes = [np.arange(a, b + step / 2, step) for a, b in zip(lo, hi, strict=True)]
    faces = []
    for fixed in range(3):
        others = [k for k in range(3) if k != fixed]
        A, B = np.meshgrid(axes[others[0]], axes[others[1]], indexing="ij")
        for value in (lo[fixed], hi[fixed]):
            f = np.empty((A.size, 3))
            f[:, fixed], f[:, others[0]], f[:, others[1]] = value, A.ravel(), B.ravel()
            faces.append(f)
    return np.concatenate(faces)


def test_a_low_box_heaped_over_its_rim_keeps_its_walls_low_and_a_heap_on_a_table_has_none():
    # A heap of three blocks touching each other (each side of its rectangle touches one block over
    # less than the side's length); then the same heap in a box 30 x 20 cm with a 1 cm floor and
    # 3 cm walls, with one more part hanging 12 cm high over its +x rim (to x = 0.18).
    heap = [((-0.10, -0.05, 0.0), (0.0, 0.02, 0.06)), ((-0.02, 0.0, 0.0), (0.08, 0.08, 0.09))]
    heap += [((0.0, -0.08, 0.0), (0.04, 0.0, 0.05))]
    rim = [((-0.15, -0.10, 0.0), (-0.14, 0.10, 0.03)), ((0.14, -0.10, 0.0), (0.15, 0.10, 0.03))]
    rim += [((-0.15, -0.10, 0.0), (0.15, -0.09, 0.03)), ((-0.15, 0.09, 0.0), (0.15, 0.10, 0.03))]
    rim += [((-0.15, -0.10, 0.0), (0.15, 0.10, 0.01))]
    over = [((0.08, -0.04, 0.0), (0.18, 0.04, 0.12))]
    T_cam_from_bin = invert_T(T_bin_from_cam(0.8))
    floor = np.array([0.0, 0.0, -1.0, 0.8])  # z = 0.8 in the camera frame, the normal toward it

    def fitted(blocks):
        pts = np.concatenate([_block(lo, hi) for lo, hi in blocks])
        return fit_bin_box(transform_points(T_cam_from_bin, pts), floor, 0.004)

    on_table = fitted(heap)
    assert np.allclose(on_table.inner_max_m[:2] - on_table.inner_min_m[:2], [0.18, 0.16], atol=0.005)
    assert np.all(on_table.wall_heights_m == 0.0), on_table.wall_heights_m
    box = fitted(rim + heap + over)
    assert np.allclose(box.inner_max_m[:2] - box.inner_min_m[:2], [0.33, 0.20], atol=0.005)
    assert box.inner_max_m[2] > 0.12  # the box reaches over the heap ...
    # ... its walls where the rim was seen; the side the part hangs over (+x) is the part's own edge.
    R = (invert_T(T_cam_from_bin) @ box.T_cam_from_bin)[:3, :3]
    outward = np.array([-R[:, 0], R[:, 0], -R[:, 1], R[:, 1]])
    expected = np.where(outward @ [1.0, 0.0, 0.0] > 0.99, 0.0, 0.03)
    assert np.allclose(box.wall_heights_m, expected, atol=0.003), (box.wall_heights_m, outward)


def test_a_row_of_cups_lying_along_a_side_is_no_wall():
    # Four cylinders (radius 4 cm, a cup's) lying side by side across the +y side of a heap, their
    # ends on it: the side is covered end to end and 4-8 cm high, but not level as a rim is.
    theta = np.linspace(0.0, np.pi, 60)
    y = np.arange(0.02, 0.1001, 0.002)
    cups = []
    for x_c in (-0.12, -0.04, 0.04, 0.12):
        T, Y = np.meshgrid(theta, y, indexing="ij")
        cups.append(np.column_stack([x_c + 0.04 * np.cos(T).ravel(), Y.ravel(), 0.04 + 0.04 * np.sin(T).ravel()]))
    heap = np.concatenate([*cups, _block((-0.16, -0.10, 0.0), (0.16, 0.02, 0.03))])
    T_cam_from_bin = invert_T(T_bin_from_cam(0.8))
    box = fit_bin_box(transform_points(T_cam_from_bin, heap), np.array([0.0, 0.0, -1.0, 0.8]), 0.004)
    R = (invert_T(T_cam_from_bin) @ box.T_cam_from_bin)[:3, :3]
    outward = np.array([-R[:, 0], R[:, 0], -R[:, 1], R[:, 1]])
    plus_y = int(np.argmax(outward @ [0.0, 1.0, 0.0]))
    assert np.allclose(box.inner_max_m[:2] - box.inner_min_m[:2], [0.32, 0.20], atol=0.005)
    assert box.wall_heights_m[plus_y] == 0.0, box.wall_heights_m


def test_a_bin_box_is_an_obstacle_only_as_high_as_its_walls():
    from binpick.cell.bin_box import BinBox

    box = BinBox(np.eye(4), np.array([-0.15, -0.1, 0.0]), np.array([0.15, 0.1, 0.2]), np.array([0.0, 0.05, 0.2, 0.2]))
    points, normals = box.surface(0.01)  # the faces' normals point into the bin

    def face(normals, inward):
        return np.all(np.isclose(normals, inward), axis=1)

    assert not face(normals, [1.0, 0.0, 0.0]).any()  # no -x wall
    plus_x = face(normals, [-1.0, 0.0, 0.0])
    assert np.allclose(points[plus_x, 0], 0.15) and np.isclose(points[plus_x, 2].max(), 0.05)
    assert np.isclose(points[face(normals, [0.0, -1.0, 0.0]), 2].max(), 0.2)
    assert np.allclose(points[face(normals, [0.0, 0.0, 1.0]), 2], 0.0)  # the floor
    full, full_normals = BinBox(np.eye(4), box.inner_min_m, box.inner_max_m).surface(0.01)
    assert np.isclose(full[face(full_normals, [1.0, 0.0, 0.0]), 2].max(), 0.2)
    # Its side walls as planes, normals into the bin: each of the wall's points lies on its
    # plane, in a box seen from a camera turned and moved (the -x wall it lacks not among them).
    T_cam_from_bin = make_T(axis_angle_to_R(np.array([0.3, -0.2, 0.9]), 0.7), np.array([0.05, -0.02, 0.9]))
    seen = BinBox(T_cam_from_bin, box.inner_min_m, box.inner_max_m, box.wall_heights_m)
    points_cam, normals_cam = seen.surface(0.01)
    planes = seen.side_planes()
    assert len(planes) == 3
    for plane in planes:
        on = np.all(np.isclose(normals_cam, plane[:3]), axis=1)
        assert on.any() and np.allclose(points_cam[on] @ plane[:3] + plane[3], 0.0, atol=1e-9)
    centre = T_cam_from_bin[:3, :3] @ np.array([0.0, 0.0, 0.1]) + T_cam_from_bin[:3, 3]
    assert np.all(planes[:, :3] @ centre + planes[:, 3] > 0.09)


def test_the_shared_icbin_frame_gives_no_pose_outside_its_box(shared_data, tmp_path):
    """The real RGB-D bin frame (cardboard box on a desk): the box is fitted from the frame, the
    capture is cropped to it, whole-scene registration of the cup (no network needed) runs, and
    no pose lies outside the box; no kept pose lies where the camera saw through it."""
    import json

    from binpick.geometry.symmetry import symmetry_transforms
    from binpick.io.capture import ImportOptions, load_capture
    from binpick.params import PartParams
    from binpick.part.ingest import ingest_part
    from binpick.registration.constants import DEFAULT_MAX_SEEN_THROUGH
    from binpick.registration.model import train_ppf
    from binpick.scene.cleaning import clean_capture
    from binpick.scene.register import register
    from binpick.view import ViewParams, view_grid

    from settings import changed

    scan = shared_data / "scans" / "icbin_scene1"
    camera = json.loads((scan / "camera.json").read_text())
    (tmp_path / "k.json").write_text(json.dumps({k: camera[k] for k in ("fx", "fy", "cx", "cy")}))
    cap = load_capture(scan / "depth" / "0000.png", ImportOptions(unit="mm", intrinsics=tmp_path / "k.json"))
    settings = changed(PARAMS.import_capture, plane_threshold_m=0.008)
    xyz = cap.xyz_m[np.all(np.isfinite(cap.xyz_m), axis=1)]
    grid = xyz[view_grid(xyz, ViewParams(0.004, 0.01))]
    floor, _ = fit_plane_ransac(grid, settings.plane_threshold_m, 1000, 0)
    floor = floor if floor[3] > 0 else -floor
    box = fit_bin_box(grid, floor, settings.keep_above_plane_m)
    size = box.inner_max_m[:2] - box.inner_min_m[:2]
    assert 0.2 < size[1] <= size[0] < 0.6  # a desk-top box, not the desk
    cropped = changed(settings, **box.as_import_settings())
    cloud = clean_capture(cap.xyz_m, cap.rgb, cap.shape, cropped, 0)
    params = PARAMS.model_copy(update={"parts": {"cup": PartParams(mesh="cup.ply", unit="mm")}})
    cup, _ = ingest_part(params, "cup", scan / "coffee_cup_model.ply")
    ppf = train_ppf(cup.points_m, cup.normals, cup.diameter_m, symmetry_transforms(cup.symmetry), PARAMS.registration)
    result = register(cloud, None, ppf, changed(PARAMS.registration, mode="whole_scene", max_instances=10), seed=0)
    centres = transform_points(
        invert_T(box.T_cam_from_bin),
        np.array([p.T_cam_from_model[:3, :3] @ cup.centre_m + p.T_cam_from_model[:3, 3] for p in result.poses]).reshape(
            -1, 3
        ),
    )
    assert np.all((centres >= box.inner_min_m - 1e-9) & (centres <= box.inner_max_m + 1e-9))
    assert all(p.seen_through <= DEFAULT_MAX_SEEN_THROUGH for p in result.poses)  # no network: the prior


def test_a_box_that_is_no_bin_for_the_part_and_the_camera_is_flagged():

    def box(size_m, height_m, tilt_deg=0.0):
        R = axis_angle_to_R(np.array([1.0, 0.0, 0.0]), np.pi + np.radians(tilt_deg))  # z toward the camera
        half = np.asarray(size_m) / 2
        return BinBox(
            make_T(R, np.array([0.0, 0.0, 0.8])),
            np.array([-half[0], -half[1], 0.004]),
            np.array([half[0], half[1], height_m]),
        )

    assert implausible(box([0.4, 0.3], 0.15), 0.12) == []
    assert implausible(box([0.4, 0.3], 0.15, tilt_deg=45.0), 0.12) == []  # an oblique camera
    # The fit of one oblique IC-BIN frame: 2.2 x 0.9 x 1.1 m, for a 0.12 m cup.
    problems = implausible(box([2.2, 0.9], 1.1), 0.12)
    assert len(problems) == 2 and "2.20 m long" in problems[0] and "1.10 m high" in problems[1]
    assert "28 part diameters long" in implausible(box([1.4, 0.9], 0.3), 0.05)[0]
    assert "narrower than the part" in implausible(box([0.3, 0.08], 0.1), 0.12)[0]
    assert "tilted 70 degrees" in implausible(box([0.4, 0.3], 0.15, tilt_deg=70.0), 0.12)[0]
    assert implausible(box([1.0, 0.8], 0.5), None) == []  # no part model: only the bin's own limits


def test_the_box_of_a_generated_bin_lies_on_its_inner_faces():
    """Every point of the box of a generated bin, seen from a turned camera, lies on the bin's
    meshes (the floor's top, the walls' inner faces), and its floor is the plane the parts rest on."""
    bin_params = PARAMS.generate.bin
    T_cam_from_bin = invert_T(make_T(axis_angle_to_R(np.array([0.8, -0.5, 0.3]), 0.4), np.array([0.05, -0.1, 0.9])))
    box = BinBox.of_generated(bin_params, T_cam_from_bin)
    surface = transform_points(invert_T(T_cam_from_bin), box.surface_points(0.02))
    meshes = trimesh.util.concatenate(bin_meshes(bin_params))
    _, distance, _ = trimesh.proximity.closest_point(meshes, surface)
    assert np.max(distance) < 1e-6
    np.testing.assert_allclose(
        box.inner_max_m - box.inner_min_m, [bin_params.inner_x_m, bin_params.inner_y_m, bin_params.wall_height_m]
    )


def test_a_large_bin_seen_by_a_coarse_noisy_sensor_from_two_metres():
    # A 0.9 x 0.75 x 0.2 m bin whose floor lies on the ground (generation/bin.py), one long part
    # clear of its walls and a carton on the ground beside it, seen from 1.9 m with 20 degrees of
    # tilt by a Kinect-class sensor: depth in 10 mm steps plus 4 mm of noise, on a 12 mm voxel
    # grid. The floor's scatter pokes above the 18 mm kept over it, and the points lie 8-12 mm
    # apart: the rim must still be one ring around the part, not specks.
    from binpick.geometry.pointcloud import voxel_downsample_indices

    bin_params = PARAMS.generate.bin.model_copy(
        update={"inner_x_m": 0.9, "inner_y_m": 0.75, "wall_height_m": 0.2, "wall_thickness_m": 0.01}
    )
    part = trimesh.creation.box(extents=[0.30, 0.06, 0.06])
    part.apply_translation([0.05, 0.08, 0.03])
    carton = trimesh.creation.box(extents=[0.2, 0.2, 0.25])
    carton.apply_translation([0.9 / 2 + 0.01 + 0.06 + 0.1, 0.0, 0.125])  # 6 cm beyond the +x wall
    # The camera orbits the bin's centre: it still looks at it.
    T_bin_from_camera = make_T(
        axis_angle_to_R(np.array([1.0, 0.0, 0.0]), np.radians(20.0)), np.zeros(3)
    ) @ T_bin_from_cam(1.9)
    T_cam_from_bin = invert_T(T_bin_from_camera)
    meshes = [
        (transform_points(T_cam_from_bin, np.asarray(m.vertices)), np.asarray(m.faces))
        for m in [*bin_meshes(bin_params), part, carton]
    ]
    labels_of_meshes = [-1] * len(bin_meshes(bin_params)) + [1, -1]
    frame = render(meshes, labels_of_meshes, camera_of(PARAMS.camera.model_copy(update={"downscale": 4})))
    xyz = frame.xyz_m.reshape(-1, 3)
    ok = np.all(np.isfinite(xyz), axis=1)
    pts, labels = xyz[ok], frame.labels.reshape(-1)[ok]
    rng = np.random.default_rng(0)
    rays = pts / pts[:, 2:3]
    z = np.round(pts[:, 2] / 0.01) * 0.01 + rng.normal(0.0, 0.004, len(pts))
    noisy = rays * z[:, None]
    keep = voxel_downsample_indices(noisy, 0.012)
    grid, grid_labels = noisy[keep], labels[keep]
    floor, _ = fit_plane_ransac(grid, 0.015, 1000, 0)
    box = fit_bin_box(grid, floor if floor[3] > 0 else -floor, 0.018)
    outer = np.array([bin_params.inner_x_m, bin_params.inner_y_m]) + 2 * bin_params.wall_thickness_m
    size = box.inner_max_m[:2] - box.inner_min_m[:2]
    assert np.all(np.abs(size - outer) < 0.05), size
    in_box = transform_points(invert_T(box.T_cam_from_bin), grid)
    inside = np.all((in_box[:, :2] >= box.inner_min_m[:2]) & (in_box[:, :2] <= box.inner_max_m[:2]), axis=1)
    assert inside[grid_labels == 1].all()  # the part in the bin ...
    carton_in_bin = transform_points(invert_T(T_cam_from_bin), grid)
    on_carton = (carton_in_bin[:, 0] > 0.52) & (carton_in_bin[:, 2] > 0.05)
    assert on_carton.sum() > 20 and not inside[on_carton].any()  # ... the carton beside it not
    assert sides_out_of_view(box, noisy) == []
    # A narrower view, ending a quarter of the way across the bin: the box ends where the view
    # does, and that is noticed.
    seen = grid[grid[:, 0] / grid[:, 2] < 0.1]
    floor, _ = fit_plane_ransac(seen, 0.015, 1000, 0)
    cut = fit_bin_box(seen, floor if floor[3] > 0 else -floor, 0.018)
    assert sides_out_of_view(cut, seen)
    assert any("the camera's view ends" in why for why in implausible(cut, None, seen))
    assert implausible(box, None, noisy) == []


def test_a_wall_of_a_given_box_stands_at_one_of_its_sides():
    # A 1.0 x 0.8 m box turned 30 degrees about its up axis, 1.5 m below a camera.
    T_cam_from_bin = invert_T(T_bin_from_cam(1.5)) @ make_T(
        axis_angle_to_R(np.array([0.0, 0.0, 1.0]), np.radians(30.0)), np.zeros(3)
    )
    box = BinBox(T_cam_from_bin, np.array([-0.5, -0.4, 0.01]), np.array([0.5, 0.4, 0.3]))

    def plane(normal_bin, point_bin):
        n = T_cam_from_bin[:3, :3] @ (np.asarray(normal_bin) / np.linalg.norm(normal_bin))
        return np.append(n, -n @ transform_points(T_cam_from_bin, np.asarray(point_bin, float)[None])[0])

    assert box.is_wall(plane([1.0, 0.0, 0.0], [0.48, 0.0, 0.0]))  # the +x wall's inner face
    assert box.is_wall(plane([0.0, -1.0, 0.0], [0.1, -0.38, 0.1]))  # the -y wall, normal either way
    assert not box.is_wall(plane([1.0, 0.0, 0.0], [0.1, 0.0, 0.0]))  # parallel, through the parts
    assert not box.is_wall(plane([1.0, 0.0, 0.0], [0.0, 0.38, 0.0]))  # at the +y side, across it
    tilted = [np.cos(np.radians(20.0)), np.sin(np.radians(20.0)), 0.0]
    assert not box.is_wall(plane(tilted, [0.48, 0.0, 0.0]))  # 20 degrees off the side
    # Each side by name (WALL_SIDES), whichever way the normal faces.
    at_sides = [([1, 0, 0], [-0.47, 0.1, 0]), ([-1, 0, 0], [0.48, 0, 0]), ([0, -1, 0], [0, -0.38, 0])]
    at_sides.append(([0, 1, 0], [0, 0.39, 0]))
    for side, (normal, point) in enumerate(at_sides):
        assert box.wall_side(plane(normal, point)) == side, WALL_SIDES[side]
    # A box heaped over its rim on a table-like side: no wall where it has none.
    low = BinBox(box.T_cam_from_bin, box.inner_min_m, box.inner_max_m, np.array([0.05, 0.0, 0.05, 0.05]))
    assert low.is_wall(plane([1.0, 0.0, 0.0], [-0.48, 0.0, 0.0])) and low.wall_top_m(0) == 0.05
    assert not low.is_wall(plane([1.0, 0.0, 0.0], [0.48, 0.0, 0.0])) and low.wall_top_m(1) == 0.01
