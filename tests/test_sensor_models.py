"""Sensor models against the geometry each imitates (binpick/generation/sensor.py)."""

import numpy as np
import pytest
import trimesh

from binpick.generation.camera import Render, render
from binpick.generation.scene import generate_scene
from binpick.generation.sensor import (
    apply_sensor_model,
    concavity,
    mix_edge_pixels,
    projector_shadow,
    quantise_disparity,
    specular_cos,
)
from binpick.geometry.camera import PinholeCamera
from binpick.view import ViewParams

from settings import PARAMS, ROOT, changed

# A fine camera 0.5 m above a floor: 0.5 mm pixels there.
INTR = PinholeCamera(400, 300, 1000.0, 1000.0, 199.5, 149.5)
FLOOR_M = 0.5
MATTE = PARAMS.generate.sensor.materials["matte"]


def box(lo, hi):
    b = trimesh.creation.box(extents=np.subtract(hi, lo))
    b.apply_translation((np.asarray(lo) + np.asarray(hi)) / 2)
    return (np.asarray(b.vertices), np.asarray(b.faces))


def floor_and_block(height_m=0.05, half_m=0.03):
    """A floor facing the camera at FLOOR_M and a block of height_m standing on it, centred on the axis."""
    return [
        box((-0.5, -0.5, FLOOR_M), (0.5, 0.5, FLOOR_M + 0.01)),
        box((-half_m, -half_m, FLOOR_M - height_m), (half_m, half_m, FLOOR_M)),
    ]


def plain_model(**update):
    """The Kinect-class preset with every effect off, then `update`."""
    off = dict(
        shadows=False,
        depth_sigma_m=0.0,
        depth_sigma_per_m2=0.0,
        incidence_noise_gain=0.0,
        dropout_start_deg=90.0,
        max_incidence_deg=90.0,
        dropout_fraction=0.0,
        mixed_pixel_share=0.0,
        multipath_m=0.0,
        disparity_step_px=0.0,
        depth_step_m=0.0,
    )
    return PARAMS.generate.sensor.models["kinect_v1"].model_copy(update={**off, **update})


@pytest.mark.parametrize("baseline_m", [0.05, 0.1])
def test_the_shadow_behind_a_block_has_the_width_the_geometry_gives(baseline_m):
    height, half = 0.05, 0.03
    meshes = floor_and_block(height, half)
    clean = render(meshes, [-1, 0], INTR)
    shadow = projector_shadow(clean.xyz_m, meshes, np.array([baseline_m, 0.0, 0.0]))
    row = INTR.height // 2
    x = clean.xyz_m[row, :, 0]
    on_floor = clean.xyz_m[row, :, 2] > FLOOR_M - 1e-6
    # The projector at +x lights the floor beyond the block's -x edge only from b * h / z_top
    # farther out than the camera sees it; on the +x side the camera's own view hides the shadow.
    top = FLOOR_M - height
    expected = baseline_m * height / top
    band = shadow[row] & on_floor & (x < 0)
    pixel_m = FLOOR_M / INTR.fx
    assert abs(band.sum() * pixel_m - expected) <= 1.5 * pixel_m
    assert x[band].max() <= -half * FLOOR_M / top + pixel_m  # it starts where the camera's view of the floor starts
    assert not (shadow[row] & (x > 0)).any()
    assert not shadow[~np.isfinite(clean.xyz_m[..., 2])].any()


@pytest.mark.parametrize("angle_deg, side", [(0.0, (-1, 0)), (90.0, (0, -1)), (180.0, (1, 0))])
def test_the_mount_turns_the_shadow_to_the_side_away_from_the_projector(angle_deg, side):
    height, half, baseline_m = 0.05, 0.03, 0.1
    meshes = floor_and_block(height, half)
    clean = render(meshes, [-1, 0], INTR)
    model = plain_model(shadows=True, baseline_m=baseline_m, projector_angle_deg=angle_deg)
    out = apply_sensor_model(clean, meshes, INTR, model, MATTE, np.random.default_rng(0))
    lost = np.isfinite(clean.xyz_m[..., 2]) & ~np.isfinite(out.xyz_m[..., 2])
    x, y = clean.xyz_m[..., 0], clean.xyz_m[..., 1]
    beyond = half * FLOOR_M / (FLOOR_M - height)  # where the camera's view of the floor starts
    sx, sy = side
    towards = x * sx + y * sy  # along the side the shadow must fall on
    across = np.abs(x * sy - y * sx)  # along the block's edge on that side
    shadow_side = (towards > beyond - 1e-3) & (across < half)
    assert lost[shadow_side].sum() * (FLOOR_M / INTR.fx) ** 2 == pytest.approx(
        baseline_m * height / (FLOOR_M - height) * 2 * half * FLOOR_M / (FLOOR_M - height), rel=0.15
    )
    assert not lost[(towards < 0) | ((across < half) & ~shadow_side)].any()


def test_no_baseline_no_shadow():
    meshes = floor_and_block()
    clean = render(meshes, [-1, 0], INTR)
    assert not projector_shadow(clean.xyz_m, meshes, np.zeros(3)).any()


def test_multipath_biases_a_concave_corner_and_nothing_else():
    # A floor and a wall rising from it at x = 0.05 (concave corner), seen from above; the block's
    # top edge is convex.
    wall = box((0.05, -0.5, FLOOR_M - 0.1), (0.06, 0.5, FLOOR_M))
    meshes = [
        box((-0.5, -0.5, FLOOR_M), (0.5, 0.5, FLOOR_M + 0.01)),
        wall,
        box((-0.2, -0.03, FLOOR_M - 0.05), (-0.14, 0.03, FLOOR_M)),
    ]
    cam = PinholeCamera(400, 300, 300.0, 300.0, 199.5, 149.5)
    # Tilt the view so the camera sees the wall's face: the camera sits at x = -0.2 looking along +z.
    shift = np.array([0.2, 0.0, 0.0])
    meshes = [(v + shift, f) for v, f in meshes]
    clean = render(meshes, [-1, -1, 0], cam)
    radius = 0.02
    c = concavity(clean.xyz_m, clean.normals, radius, cam.fx)
    xyz = clean.xyz_m
    floor = np.abs(xyz[..., 2] - FLOOR_M) < 1e-6
    x_bin = xyz[..., 0] - shift[0]
    near_corner = floor & (x_bin > 0.05 - 0.006) & (x_bin < 0.05)
    far = floor & (x_bin < 0.05 - 1.5 * radius) & (np.abs(x_bin + 0.17) > 0.03 + 1.5 * radius)
    block_top = np.abs(xyz[..., 2] - (FLOOR_M - 0.05)) < 1e-6
    inner_top = block_top & (np.abs(x_bin + 0.17) < 0.02) & (np.abs(xyz[..., 1]) < 0.02)
    assert c[near_corner].mean() > 0.2
    assert c[far].max() == 0.0
    assert c[block_top & ~inner_top].max() < 0.02  # the convex top edge
    assert c[inner_top].max() == 0.0
    # Applied: the corner reads long by up to multipath_m, the plain floor not at all.
    model = plain_model(multipath_m=0.002, multipath_radius_m=radius)
    out = apply_sensor_model(clean, meshes, cam, model, MATTE, np.random.default_rng(0))
    longer = np.linalg.norm(out.xyz_m, axis=-1) - np.linalg.norm(clean.xyz_m, axis=-1)
    assert 0.0006 < longer[near_corner].mean() <= 0.002 + 1e-6
    assert np.abs(longer[far]).max() < 1e-6


def test_mixed_pixels_lie_between_the_two_depths_at_edges_only():
    meshes = floor_and_block(0.05, 0.03)
    clean = render(meshes, [-1, 0], INTR)
    xyz, labels = mix_edge_pixels(clean.xyz_m, clean.labels, 0.01, 1.0, np.random.default_rng(1))
    moved = np.abs(xyz[..., 2] - clean.xyz_m[..., 2]) > 1e-7
    z = xyz[..., 2][moved]
    assert moved.sum() > 100
    assert (z >= FLOOR_M - 0.05 - 1e-6).all() and (z <= FLOOR_M + 1e-6).all()
    # Only pixels next to the block's outline moved.
    x, y = np.abs(clean.xyz_m[..., 0]), np.abs(clean.xyz_m[..., 1])
    edge_dist = np.abs(np.maximum(x, y) * np.where(clean.labels == 0, 1.0, (FLOOR_M - 0.05) / FLOOR_M) - 0.03)
    assert edge_dist[moved].max() < 3 * FLOOR_M / INTR.fx
    # Along its own ray: x / z and y / z unchanged.
    assert np.allclose(
        xyz[moved][:, :2] / xyz[moved][:, 2:], clean.xyz_m[moved][:, :2] / clean.xyz_m[moved][:, 2:], atol=1e-6
    )
    # A pixel moved more than halfway takes the other side's label.
    assert ((labels != clean.labels) & moved).any()


def test_disparity_quantisation_puts_depths_on_the_sensor_grid():
    fx, b, step = 550.0, 0.075, 0.125
    z = np.linspace(0.5, 1.5, 1000)
    q = quantise_disparity(z, fx, b, step)
    k = fx * b / (q * step)
    assert np.allclose(k, np.round(k), atol=1e-6)
    # The step between neighbouring levels grows with the squared range: z^2 * step / (fx * b).
    for depth in (0.6, 1.2):
        levels = np.unique(q[np.abs(z - depth) < 0.05])
        assert np.allclose(np.diff(levels).mean(), depth**2 * step / (fx * b), rtol=0.1)
    assert np.abs(q - z).max() <= 1.5**2 * step / (fx * b)


def test_dropout_and_noise_follow_the_incidence_angle():
    H, W = 200, 200
    intr = PinholeCamera(W, H, 400.0, 400.0, 99.5, 99.5)
    dirs = intr.ray_directions()
    xyz = (dirs * 0.6).astype(np.float32)
    model = plain_model(depth_sigma_m=0.001, incidence_noise_gain=0.5, dropout_start_deg=40.0, max_incidence_deg=80.0)
    shares, stds = [], []
    for deg in (0.0, 50.0, 60.0, 85.0):
        a = np.radians(deg)
        # Tilted normals give the incidence; positions stay on the fronto-parallel plane (the model reads normals).
        n = np.array([np.sin(a), 0.0, -np.cos(a)], np.float32)
        normals = np.broadcast_to(n, xyz.shape).copy()
        centre = (slice(80, 120), slice(80, 120))  # rays within 3 degrees of the axis
        out = apply_sensor_model(
            Render(xyz, normals, np.zeros((H, W), np.int32)), [], intr, model, MATTE, np.random.default_rng(2)
        )
        ok = np.isfinite(out.xyz_m[..., 2])
        shares.append(ok[centre].mean())
        stds.append(np.nanstd((out.xyz_m - xyz)[..., 2][centre]))
    assert shares[0] == 1.0
    assert shares[1] == pytest.approx(1 - 10 / 40, abs=0.05)
    assert shares[2] == pytest.approx(1 - 20 / 40, abs=0.05)
    assert shares[3] == 0.0
    a = np.radians(50.0)
    assert stds[0] == pytest.approx(0.001, rel=0.15)
    assert stds[1] == pytest.approx(0.001 * (1 + 0.5 * a**2 / (np.pi / 2 - a) ** 2), rel=0.15)


def test_a_shiny_part_loses_its_highlight_and_a_matte_one_does_not():
    H, W = 100, 100
    intr = PinholeCamera(W, H, 200.0, 200.0, 49.5, 49.5)
    xyz = (intr.ray_directions() * 0.5).astype(np.float32)
    normals = np.broadcast_to(np.array([0, 0, -1], np.float32), xyz.shape).copy()
    labels = np.zeros((H, W), np.int32)
    projector = np.array([0.1, 0.0, 0.0])
    # Where the half vector of the camera and projector directions is the normal: x = 0.05 (midway).
    cos_h = specular_cos(xyz, normals, projector)
    brightest = np.unravel_index(np.argmax(cos_h), cos_h.shape)
    assert xyz[brightest][0] == pytest.approx(0.05, abs=0.5 / 200)
    model = plain_model(baseline_m=0.1)
    shiny = PARAMS.generate.sensor.materials["shiny"].model_copy(
        update={"dropout_fraction": 0.0, "max_incidence_deg": 90.0}
    )
    out = apply_sensor_model(Render(xyz, normals, labels), [], intr, model, shiny, np.random.default_rng(0))
    lost = ~np.isfinite(out.xyz_m[..., 2])
    assert lost[brightest] and lost.sum() == (cos_h >= np.cos(np.radians(shiny.specular_lobe_deg))).sum()
    matte = apply_sensor_model(Render(xyz, normals, labels), [], intr, model, MATTE, np.random.default_rng(0))
    assert np.isfinite(matte.xyz_m[..., 2]).all()
    background = apply_sensor_model(Render(xyz, normals, labels - 1), [], intr, model, shiny, np.random.default_rng(0))
    assert np.isfinite(background.xyz_m[..., 2]).all()  # the material is the part's alone


def test_generation_draws_the_sensor_presets_and_their_cameras(t_joint):
    sensor = PARAMS.generate.sensor.model_copy(update={"presets": ["kinect_v1", "zivid2plus_m60"]})
    gen = PARAMS.generate.model_copy(update={"sensor": sensor, "clutter": PARAMS.generate.clutter.off()})
    camera = changed(PARAMS.camera, downscale=4)
    view = ViewParams(0.002, 0.006)
    shapes = {generate_scene(t_joint, gen, camera, view, seed, n_objects=4).xyz_m.shape[:2] for seed in range(6)}
    # Kinect-class frames render whole (640 x 480); the 5 MP Zivid at about the reference's 480 px.
    assert shapes == {(480, 640), (2048 // 5, 2448 // 5)}
    again = generate_scene(t_joint, gen, camera, view, 3, n_objects=4)
    assert np.array_equal(again.xyz_m, generate_scene(t_joint, gen, camera, view, 3, n_objects=4).xyz_m, equal_nan=True)
    plain = generate_scene(
        t_joint,
        PARAMS.generate.model_copy(update={"clutter": PARAMS.generate.clutter.off()}),
        camera,
        view,
        3,
        n_objects=4,
    )
    assert np.array_equal(plain.T_cam_from_model, again.T_cam_from_model)  # the sensor draws from its own stream


def test_a_part_entry_sets_its_surface(tmp_path):
    import yaml

    from binpick.params import load_params

    raw = yaml.safe_load((ROOT / "params.yaml").read_text())
    raw["parts"]["t_joint"]["surface"] = "machined"
    p = tmp_path / "params.yaml"
    p.write_text(yaml.safe_dump(raw))
    assert load_params(p, "t_joint").generate.sensor.surface == "machined"
    assert load_params(ROOT / "params.yaml", "t_joint").generate.sensor.surface == "matte"
