import hashlib

import numpy as np
import pytest
import trimesh

from binpick.generation.bin import T_bin_from_cam, bin_meshes
from binpick.generation.camera import apply_sensor_noise, camera_of, render
from binpick.generation.placement import place_objects
from binpick.generation.scene import generate_scene
from binpick.geometry.camera import PinholeCamera
from binpick.geometry.transforms import invert_T, transform_points
from binpick.io.scene import load_scene, save_scene
from binpick.view import ViewParams
from flows.bench.generation import max_penetration_mm

from settings import PARAMS, changed

VIEW = ViewParams(voxel_size_m=0.002, normal_radius_m=0.006)


def test_drop_placement_has_no_interpenetration_and_stays_in_the_bin(t_joint):
    bin_params = PARAMS.generate.bin
    placed = place_objects(t_joint.points_m, 15, bin_params, PARAMS.generate.placement, np.random.default_rng(5))
    poses = placed.T_bin_from_model
    assert len(poses) == 15
    assert max_penetration_mm(t_joint, poses, np.random.default_rng(0)) <= 1.0
    for T in poses:
        p = transform_points(T, t_joint.points_m)
        assert p[:, 2].min() >= -1e-9
        assert np.all(np.abs(p[:, 0]) <= bin_params.inner_x_m / 2 + 1e-9)
        assert np.all(np.abs(p[:, 1]) <= bin_params.inner_y_m / 2 + 1e-9)


def test_a_mixed_bin_drops_each_kind_where_it_fits_without_touching_the_others(t_joint):
    from conftest import box_part_model

    box = box_part_model(np.array([0.05, 0.03, 0.02]))
    kinds = [0, 1] * 5
    placed = place_objects(
        [t_joint.points_m, box.points_m],
        10,
        PARAMS.generate.bin,
        PARAMS.generate.placement,
        np.random.default_rng(4),
        kinds,
    )
    assert placed.kinds.tolist() == kinds[: len(placed.T_bin_from_model)] and len(placed.T_bin_from_model) == 10
    # No object more than a millimetre inside another (as the one-part placement promises).
    import trimesh

    parts = [t_joint, box]
    meshes = []
    for T, k in zip(placed.T_bin_from_model, kinds, strict=True):
        mesh = trimesh.Trimesh(parts[k].mesh_vertices_m, parts[k].mesh_faces, process=False)
        meshes.append(mesh.apply_transform(T))
    for i in range(10):
        points = transform_points(placed.T_bin_from_model[i], parts[kinds[i]].points_m[::10])
        for j in range(10):
            if j != i:
                assert trimesh.proximity.signed_distance(meshes[j], points).max() <= 0.001, (i, j)
    # One part given as a list is the one-part placement, draw for draw.
    one = place_objects(t_joint.points_m, 6, PARAMS.generate.bin, PARAMS.generate.placement, np.random.default_rng(5))
    listed = place_objects(
        [t_joint.points_m], 6, PARAMS.generate.bin, PARAMS.generate.placement, np.random.default_rng(5)
    )
    assert np.array_equal(one.T_bin_from_model, listed.T_bin_from_model)


def test_a_full_bin_keeps_the_objects_that_fit(t_joint):
    small = changed(PARAMS.generate.bin, inner_x_m=0.1, inner_y_m=0.1)
    placed = place_objects(
        t_joint.points_m,
        200,
        small,
        changed(PARAMS.generate.placement, max_pile_height_m=0.06),
        np.random.default_rng(0),
    )
    assert 0 < len(placed.T_bin_from_model) < 200
    assert placed.n_requested == 200


def test_camera_sees_the_floor_at_its_distance():
    cam = changed(PARAMS.camera, downscale=8)
    intr = camera_of(cam)
    T_cam_bin = invert_T(T_bin_from_cam(cam.distance_m))
    meshes = [
        (transform_points(T_cam_bin, m.vertices), m.faces)
        for m in bin_meshes(changed(PARAMS.generate.bin, wall_height_m=0.0))
    ]
    r = render(meshes, [-1] * len(meshes), intr)
    assert (intr.height, intr.width) == r.labels.shape
    z = r.xyz_m[..., 2]
    assert np.isfinite(z).all() and np.allclose(z[intr.height // 2, intr.width // 2], cam.distance_m, atol=1e-6)
    assert np.allclose(r.normals[np.isfinite(z)], [0, 0, -1], atol=1e-6)
    assert (r.labels == -1).all()


def test_objects_over_a_cached_background_equal_one_cast_of_everything(t_joint):
    from binpick.generation.camera import render_background

    cam = changed(PARAMS.camera, downscale=4)
    intr = camera_of(cam)
    T_cam_bin = invert_T(T_bin_from_cam(cam.distance_m))
    gen = PARAMS.generate
    placed = place_objects(t_joint.points_m, 8, gen.bin, gen.placement, np.random.default_rng(2))
    objects = [
        (transform_points(T_cam_bin @ T, t_joint.mesh_vertices_m), t_joint.mesh_faces) for T in placed.T_bin_from_model
    ]
    clutter = [(transform_points(T_cam_bin, np.asarray(m.vertices)), np.asarray(m.faces)) for m in bin_meshes(gen.bin)]
    together = render(objects + clutter, list(range(len(objects))) + [-1] * len(clutter), intr)
    over = render(objects, list(range(len(objects))), intr, render_background(clutter, intr))
    assert set(np.unique(together.labels)) == {-1, *range(len(objects))}
    assert np.array_equal(together.labels, over.labels)
    assert np.allclose(together.xyz_m, over.xyz_m, equal_nan=True, atol=1e-7)
    assert np.allclose(together.normals, over.normals, equal_nan=True, atol=1e-6)
    assert render_background(clutter, intr) is render_background(clutter, intr)  # cached


def test_noise_grows_with_range_and_grazing_returns_drop():
    rng = np.random.default_rng(0)
    H, W = 200, 200
    dirs = PinholeCamera(W, H, 200.0, 200.0, 99.5, 99.5).ray_directions()
    out = []
    for depth in (0.5, 1.5):
        xyz = (dirs * depth).astype(np.float32)
        normals = np.broadcast_to(np.array([0, 0, -1], np.float32), xyz.shape).copy()
        from binpick.generation.camera import Render

        noisy = apply_sensor_noise(
            Render(xyz, normals, np.zeros((H, W), np.int32)),
            changed(PARAMS.generate.noise, max_incidence_deg=89.0),
            rng,
        )
        out.append(np.nanstd((noisy.xyz_m - xyz)[..., 2]))
    expected = [0.0002 + 0.0004 * d**2 for d in (0.5, 1.5)]
    assert np.allclose(out, expected, rtol=0.1)
    xyz = (dirs * 0.5).astype(np.float32)
    side = np.broadcast_to(np.array([1, 0, 0], np.float32), xyz.shape).copy()  # seen edge-on
    from binpick.generation.camera import Render

    noisy = apply_sensor_noise(Render(xyz, side, np.zeros((H, W), np.int32)), PARAMS.generate.noise, rng)
    assert np.isnan(noisy.xyz_m[H // 2, W // 2]).all()


def test_labelled_points_lie_on_their_object_at_the_true_pose(t_joint):
    gen = PARAMS.generate
    scene = generate_scene(t_joint, gen, changed(PARAMS.camera, downscale=4), VIEW, seed=11, n_objects=10)
    mesh = trimesh.Trimesh(t_joint.mesh_vertices_m, t_joint.mesh_faces)
    xyz, labels = scene.xyz_m.reshape(-1, 3), scene.labels.reshape(-1)
    # Noise std at this range; 5 sigma along the ray is the bound.
    depth = np.nanmax(xyz[:, 2])
    bound = 5 * (gen.noise.depth_sigma_m + gen.noise.depth_sigma_per_m2 * depth**2) * 1.1
    checked = 0
    for i, T in enumerate(scene.T_cam_from_model):
        pts = xyz[(labels == i) & np.isfinite(xyz[:, 2])]
        if len(pts) == 0:
            continue
        sample = pts[:: max(1, len(pts) // 300)]
        _, d, _ = trimesh.proximity.closest_point(mesh, transform_points(invert_T(T), sample.astype(np.float64)))
        assert d.max() < bound, (i, d.max(), bound)
        checked += 1
    assert checked >= 5
    assert (scene.visible_fraction >= 0).all() and (scene.visible_fraction <= 1.0 + 1e-9).all()
    assert set(np.unique(scene.view_labels)) <= set(range(len(scene.T_cam_from_model)))


def test_same_seed_gives_byte_identical_scene_files(tmp_path, t_joint):
    digests = []
    for k in range(2):
        scene = generate_scene(t_joint, PARAMS.generate, changed(PARAMS.camera, downscale=8), VIEW, seed=3)
        save_scene(tmp_path / f"s{k}.npz", scene)
        digests.append(hashlib.sha256((tmp_path / f"s{k}.npz").read_bytes()).hexdigest())
    assert digests[0] == digests[1]
    other = generate_scene(t_joint, PARAMS.generate, changed(PARAMS.camera, downscale=8), VIEW, seed=4)
    assert not np.array_equal(other.labels, load_scene(tmp_path / "s0.npz").labels)
    assert (tmp_path / "s0.png").is_file()


@pytest.mark.parametrize("origin_offset_m", [(0.0, 0.0, 0.0), (0.1, -0.1, 0.08)])
def test_physics_mode_settles_a_pile_without_interpenetration_reproducibly(t_joint, origin_offset_m):
    """Objects dropped from U-shaped start heights fall and settle: the pile ends lower than it
    started, inside the bin, no object more than 1 mm inside another, the same on a second run;
    also for a CAD model whose origin lies far outside the part."""
    import trimesh

    from binpick.part.model import T_JOINT_SYMMETRY, make_part_model
    from flows.bench.generation import max_penetration_mm

    if any(origin_offset_m):
        mesh = trimesh.Trimesh(t_joint.mesh_vertices_m + np.asarray(origin_offset_m), t_joint.mesh_faces)
        t_joint = make_part_model("offset", mesh, T_JOINT_SYMMETRY, 20000, np.random.default_rng(0), "m")
    from binpick.generation.placement import place_objects
    from binpick.generation.scene import settle_in_bin

    gen = changed(
        PARAMS.generate,
        placement=changed(
            PARAMS.generate.placement, mode="physics", heights="u_shaped", n_objects_min=10, n_objects_max=10
        ),
    )
    start = place_objects(t_joint.points_m, 10, gen.bin, gen.placement, np.random.default_rng(3)).T_bin_from_model
    runs = [settle_in_bin(t_joint, start, gen, np.random.default_rng(4)) for _ in range(2)]
    np.testing.assert_array_equal(runs[0], runs[1])
    settled = runs[0]
    assert len(settled) >= 8
    centres = settled[:, :3, :3] @ t_joint.centre_m + settled[:, :3, 3]
    assert (
        centres[:, 2].mean() < (start[:, :3, :3] @ t_joint.centre_m + start[:, :3, 3])[:, 2].mean() - 0.01
    )  # they fell
    half = np.array([gen.bin.inner_x_m, gen.bin.inner_y_m]) / 2
    assert (np.abs(centres[:, :2]) < half).all() and (centres[:, 2] > 0).all()
    assert max_penetration_mm(t_joint, settled, np.random.default_rng(0)) <= 1.0


def test_a_mixed_pile_settles_each_object_with_its_own_mesh(t_joint):
    """A box and a T-joint dropped side by side, 5 cm above the floor, each settles onto the
    floor with its own mesh: the lowest vertex of each, placed at its settled pose, lies on the
    floor (a pose computed with the other kind's mesh would not), and one kind's settle gives
    what settle gives for that part alone."""
    from conftest import box_part_model

    from binpick.generation.bin import bin_meshes
    from binpick.generation.physics import SettleSettings, settle, settle_kinds
    from binpick.geometry.transforms import make_T

    box = box_part_model((0.06, 0.04, 0.025))
    g = PARAMS.generate
    boxes = [(m.bounds[0], m.bounds[1]) for m in bin_meshes(g.bin)]
    half = (g.bin.inner_x_m / 2, g.bin.inner_y_m / 2)
    meshes = [(box.mesh_vertices_m, box.mesh_faces), (t_joint.mesh_vertices_m, t_joint.mesh_faces)]
    start = np.stack([make_T(np.eye(3), [-0.08, 0.0, 0.05]), make_T(np.eye(3), [0.08, 0.0, 0.08])])
    settled, inside = settle_kinds(meshes, np.array([0, 1]), start, boxes, SettleSettings(), half)
    assert inside.all()
    for (vertices, _), T in zip(meshes, settled, strict=True):
        lowest = (vertices @ T[:3, :3].T + T[:3, 3])[:, 2].min()
        assert abs(lowest) < 0.002, lowest
    # The box lies on its largest face: its thinnest extent upright.
    assert abs(abs(settled[0][2, 2]) - 1.0) < 0.01
    alone, _ = settle(t_joint.mesh_vertices_m, t_joint.mesh_faces, start[1:], boxes, SettleSettings(), half)
    np.testing.assert_allclose(alone[0][:3, 3], settled[1][:3, 3], atol=1e-3)


def test_start_heights_follow_the_chosen_law():
    from binpick.generation.placement import start_height

    rng = np.random.default_rng(0)
    b = changed(PARAMS.generate.bin, wall_height_m=0.1)
    u = np.array([start_height(rng, changed(PARAMS.generate.placement, heights="u_shaped"), b) for _ in range(4000)])
    assert u.min() >= 0 and u.max() <= 0.1
    # U-shaped: the outer fifths hold far more than the middle fifth (Beta(0.5, 0.5): 0.59 vs 0.13)
    outer, middle = np.mean((u < 0.02) | (u > 0.08)), np.mean((u > 0.04) & (u < 0.06))
    assert outer > 0.5 and middle < 0.2
    d = {
        start_height(rng, changed(PARAMS.generate.placement, heights="discrete", height_levels_m=[0.0, 0.05]), b)
        for _ in range(50)
    }
    assert d == {0.0, 0.05}
    assert start_height(rng, PARAMS.generate.placement, b) == 0.0


def test_clutter_adds_distractors_and_tilts_the_camera(t_joint):
    """Distractors are rendered (label -1, standing above the floor), the camera is tilted. (That
    clutter off leaves the plain scene draw for draw is the golden scene's test: it was recorded
    before clutter existed.)"""
    from binpick.generation.scene import generate_scene
    from binpick.view import ViewParams

    view = ViewParams.of_import(PARAMS.import_capture)
    camera = changed(PARAMS.camera, downscale=4)
    off = PARAMS.generate.clutter.off()
    on = PARAMS.generate.model_copy(update={"clutter": changed(off, n_distractors_max=6, camera_tilt_deg_max=25.0)})
    busy = generate_scene(t_joint, on, camera, view, 3, n_objects=4)
    tilted_only = generate_scene(
        t_joint,
        on.model_copy(update={"clutter": changed(on.clutter, n_distractors_max=0)}),
        camera,
        view,
        3,
        n_objects=4,
    )
    # The camera's optical axis is no longer the bin's vertical, and the same tilt is drawn with
    # or without distractors (they are drawn last).
    assert abs(invert_T(busy.T_cam_from_bin)[2, 2]) < 0.9999
    assert np.allclose(busy.T_cam_from_bin, tilted_only.T_cam_from_bin)

    # Background points standing well above the bin floor that the plain scene does not have: distractors.
    def raised_background(scene):
        pts = scene.xyz_m.reshape(-1, 3)[scene.labels.reshape(-1) < 0]
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        height = transform_points(invert_T(scene.T_cam_from_bin), pts)[:, 2]
        return int((height > 0.01).sum())

    assert raised_background(busy) > raised_background(tilted_only) + 50


def test_the_training_view_is_the_frame_as_the_import_step_cleans_it(t_joint):
    """With the import settings, a scene's view is what the network meets in a capture: every
    point is a pixel of the frame carrying that pixel's label, the distractors the cleaning keeps
    stay in as -1, the floor and the walls do not."""
    from binpick.scene.cleaning import clean_capture

    off = PARAMS.generate.clutter.off()
    gen = PARAMS.generate.model_copy(update={"clutter": changed(off, n_distractors_max=6, outside_share=0.0)})
    camera = changed(PARAMS.camera, downscale=4)
    scene = generate_scene(t_joint, gen, camera, ViewParams.of_import(PARAMS.import_capture), 3, n_objects=4)
    h, w = scene.labels.shape
    cloud = clean_capture(scene.xyz_m.reshape(-1, 3), None, (h, w), PARAMS.import_capture, 0)
    assert np.array_equal(scene.view_points_m, cloud.points_m)
    assert np.array_equal(scene.view_labels, scene.labels.reshape(-1)[cloud.pixel_index])
    # Each point's label is its pixel's: the pixel whose measured point it is.
    pixel = {
        tuple(p): lab
        for p, lab in zip(scene.xyz_m.reshape(-1, 3).tolist(), scene.labels.reshape(-1).tolist(), strict=True)
    }
    assert all(
        pixel[tuple(p)] == lab for p, lab in zip(scene.view_points_m.tolist(), scene.view_labels.tolist(), strict=True)
    )
    # Every part seen is in (the parts' own view is the same points less what the cleaning drops
    # as outliers), and so are distractors standing in the bin.
    own = ViewParams(PARAMS.import_capture.voxel_size_m, PARAMS.import_capture.normal_radius_m)
    parts_only = generate_scene(t_joint, gen, camera, own, 3, n_objects=4)
    assert set(np.unique(parts_only.view_labels)) == set(np.unique(scene.view_labels[scene.view_labels >= 0]))
    assert (scene.view_labels >= 0).sum() >= 0.97 * len(parts_only.view_labels)
    background = scene.view_points_m[scene.view_labels == -1]
    height = transform_points(invert_T(scene.T_cam_from_bin), background)[:, 2]
    assert len(background) > 50 and np.all(height > PARAMS.import_capture.keep_above_plane_m - 0.002)


def test_a_share_of_training_views_is_cropped_to_the_bin_as_a_given_box_crops_a_capture(t_joint):
    """clutter.box_share: seen at a tilt, the uncropped view keeps the walls' tops and the like
    beside the bin's inner box; the view of a scene drawn to be cropped holds no point outside that
    box (its footprint, and a part's size over the rim, as fit-bin --apply crops a capture) and
    every part point of the uncropped view, those heaped over the rim too. The rendered frame
    itself is the same either way."""
    off = PARAMS.generate.clutter.off()
    camera = changed(PARAMS.camera, downscale=4)
    view = ViewParams.of_import(PARAMS.import_capture)
    # A bin whose rim is lower than the heap of 12 parts (up to 104 mm): some lie over it.
    b = changed(PARAMS.generate.bin, wall_height_m=0.04)

    def scene_with(box_share):
        clutter = changed(off, n_distractors_max=8, outside_share=1.0, camera_tilt_deg_max=40.0, box_share=box_share)
        generate = PARAMS.generate.model_copy(update={"clutter": clutter, "bin": b})
        return generate_scene(t_joint, generate, camera, view, 3, 12)

    cropped, whole = scene_with(1.0), scene_with(0.0)
    assert np.array_equal(cropped.xyz_m, whole.xyz_m, equal_nan=True)
    tolerance = 0.003

    def in_bin_frame(scene):
        return transform_points(invert_T(scene.T_cam_from_bin), scene.view_points_m)

    def outside_the_box(scene):
        p = in_bin_frame(scene)
        return np.any(np.abs(p[:, :2]) > np.array([b.inner_x_m, b.inner_y_m]) / 2 + tolerance, axis=1) | (
            p[:, 2] > b.wall_height_m + t_joint.diameter_m + tolerance
        )

    assert outside_the_box(whole).sum() > 50 and np.all(whole.view_labels[outside_the_box(whole)] == -1)
    over_the_rim = in_bin_frame(cropped)[:, 2] > b.wall_height_m + tolerance
    assert np.sum((cropped.view_labels >= 0) & over_the_rim) > 50
    assert not outside_the_box(cropped).any()
    assert np.array_equal(
        np.sort(cropped.view_labels[cropped.view_labels >= 0]), np.sort(whole.view_labels[whole.view_labels >= 0])
    )
