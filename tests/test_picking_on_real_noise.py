"""Picks on what a real camera returns: the contact and seal checks scale with the noise the
capture shows about the pose (a Kinect-class sensor's millimetres are not a contact off the
part, a contact on the wrong surface still is), and a bin box given in params sets the bin's up
axis when the view is oblique."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import box_part_model
from pykdtree.kdtree import KDTree

from binpick.cell.bin_box import BinBox, support_frame
from binpick.geometry.depth_noise import image_coordinates, local_noise_m
from binpick.geometry.transforms import axis_angle_to_R, make_T, transform_points
from binpick.io.grasps import GraspSet, tool_frame
from binpick.picking.plan import UNSEEN, plan_picks

EXTENTS = np.array([0.06, 0.05, 0.02])
FLOOR = np.array([0.0, 0.0, -1.0, 0.6])  # a Kinect-class camera 0.6 m above the floor
NOISE_M = 0.003  # a Kinect v1 class sensor at about 1 m (noise and disparity steps)


@pytest.fixture(scope="module")
def box_part():
    return box_part_model(EXTENTS)


def top_grasp() -> GraspSet:
    return GraspSet(
        "suction",
        ["top"],
        tool_frame(np.array([0.0, 0.0, EXTENTS[2] / 2]), np.array([0.0, 0.0, -1.0]))[None],
        np.zeros(1),
    )


def lying(T_cam_from_floor: np.ndarray) -> np.ndarray:
    """T_cam_from_model of the box lying on a floor (its frame: z up toward the camera)."""
    return T_cam_from_floor @ make_T(np.eye(3), np.array([0.0, 0.0, EXTENTS[2] / 2]))


def measured_top(
    T_cam_from_model: np.ndarray,
    noise_m: float,
    rng: np.random.Generator,
    half_m: np.ndarray = EXTENTS[:2] / 2,
    spacing_m: float = 0.001,
) -> np.ndarray:
    """The box's top face (model +z; its middle 2 half_m) on a grid of spacing_m, with Gaussian
    noise along the camera's rays."""
    a, b = np.meshgrid(np.arange(-half_m[0], half_m[0], spacing_m), np.arange(-half_m[1], half_m[1], spacing_m))
    pts = transform_points(T_cam_from_model, np.column_stack([a.ravel(), b.ravel(), np.full(a.size, EXTENTS[2] / 2)]))
    rays = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    return pts + rays * rng.normal(0.0, noise_m, (len(pts), 1))


def plan(box_part, pick_settings, T, captured, floor=FLOOR, bin_box=None, grasps=None):
    return plan_picks(
        T[None],
        np.array([0.9]),
        top_grasp() if grasps is None else grasps,
        box_part.points_m,
        box_part.normals,
        box_part.centre_m,
        captured,
        floor,
        pick_settings,
        bin_box,
    )


@pytest.mark.parametrize("sigma_m", [0.0003, 0.001, 0.002])
def test_the_local_noise_of_a_plane_is_its_noise(sigma_m):
    rng = np.random.default_rng(1)
    a, b = np.meshgrid(np.arange(-0.05, 0.05, 0.001), np.arange(-0.05, 0.05, 0.001))
    R = axis_angle_to_R(np.array([1.0, 1.0, 0.0]) / np.sqrt(2), np.radians(25.0))
    pts = np.column_stack([a.ravel(), b.ravel(), np.zeros(a.size)]) @ R.T + [0, 0, 0.6]
    pts += (R @ [0, 0, 1.0]) * rng.normal(0, sigma_m, (len(pts), 1))
    tree = KDTree(image_coordinates(pts))
    assert local_noise_m(pts, tree, pts[:2000]) == pytest.approx(sigma_m, rel=0.2)
    assert local_noise_m(pts, tree, pts[:10]) == 0.0  # too few to tell


def test_a_noisy_capture_of_the_right_surface_is_a_contact(box_part, pick_settings):
    rng = np.random.default_rng(2)
    T = lying(make_T(axis_angle_to_R(np.array([1.0, 0.0, 0.0]), np.pi), np.array([0.0, 0.0, 0.6])))
    captured = measured_top(T, NOISE_M, rng)
    result = plan(box_part, pick_settings, T, captured)
    assert result.picks, result.unpicked


def test_a_sparse_capture_of_the_right_surface_is_a_contact_and_of_the_wrong_one_is_not(box_part, pick_settings):
    """Points 4 mm apart (a VGA sensor's downsampled view): a 5 mm cup covers about five of them,
    too few to judge; the contact is judged over a few spacings instead. The surface 15 mm below
    the pose is still refused."""
    rng = np.random.default_rng(5)
    T = lying(make_T(axis_angle_to_R(np.array([1.0, 0.0, 0.0]), np.pi), np.array([0.0, 0.0, 0.6])))
    top = measured_top(T, 0.0005, rng, spacing_m=0.004)
    assert plan(box_part, pick_settings, T, top).picks
    lower = plan(box_part, pick_settings, T, top + [0.0, 0.0, 0.015])
    assert not lower.picks and UNSEEN in lower.unpicked[0][1]


@pytest.mark.parametrize("wrong", ["lower", "tilted"])
def test_a_contact_on_the_wrong_surface_is_refused_at_that_noise(box_part, pick_settings, wrong):
    """At the same noise: the surface measured 15 mm below the pose's contact (the pose floats
    above its part), or a patch around the contact turned 60 degrees from the cup (a pose turned
    about an edge)."""
    rng = np.random.default_rng(3)
    T = lying(make_T(axis_angle_to_R(np.array([1.0, 0.0, 0.0]), np.pi), np.array([0.0, 0.0, 0.6])))
    if wrong == "lower":
        captured = measured_top(T, NOISE_M, rng) + [0.0, 0.0, 0.015]
    else:
        turn = make_T(axis_angle_to_R(np.array([1.0, 0.0, 0.0]), np.radians(60.0)), np.zeros(3))
        contact = make_T(np.eye(3), T[:3, 3] + T[:3, 2] * EXTENTS[2] / 2)
        captured = measured_top(contact @ turn @ np.linalg.inv(contact) @ T, NOISE_M, rng, np.array([0.008, 0.008]))
    refused = plan(box_part, pick_settings, T, captured)
    assert not refused.picks and UNSEEN in refused.unpicked[0][1]


@pytest.mark.parametrize("tilt_deg", [30.0, 45.0])
def test_a_tilted_bin_box_gives_the_approach_cone_its_up_axis(box_part, pick_settings, tilt_deg):
    """An oblique camera: the bin's floor tilted by tilt_deg from the image plane. The plane found
    in the capture is a wall (or none): the bin box's z axis is the up axis, and the part lying on
    the bin floor is taken straight down that axis."""
    R = axis_angle_to_R(np.array([1.0, 0.0, 0.0]), np.pi) @ axis_angle_to_R(
        np.array([1.0, 0.0, 0.0]), np.radians(tilt_deg)
    )
    T_cam_from_bin = make_T(R, np.array([0.0, 0.0, 0.6]))
    box = BinBox(T_cam_from_bin, np.array([-0.2, -0.15, 0.005]), np.array([0.2, 0.15, 0.15]))
    T = lying(T_cam_from_bin)
    captured = measured_top(T, 0.0003, np.random.default_rng(4))
    bin_up = R[:, 2]
    wall = np.append(R[:, 0], -(R[:, 0] @ (T_cam_from_bin[:3, 3] + 0.2 * R[:, 0])))  # the +x wall's plane
    for found in (np.full(4, np.nan), wall):
        up, plane = support_frame(found, box)
        assert up == pytest.approx(bin_up, abs=1e-9)
        assert plane is not None and plane[:3] @ T_cam_from_bin[:3, 3] + plane[3] == pytest.approx(0.0, abs=1e-9)
        result = plan(box_part, pick_settings, T, captured, found, box)
        assert result.up_cam == pytest.approx(bin_up, abs=1e-9)
        assert len(result.picks) == 1
        approach = result.picks[0].T_cam_from_grasp[:3, 2]
        assert approach @ -bin_up == pytest.approx(1.0, abs=1e-9)
        assert result.picks[0].height_m == pytest.approx(EXTENTS[2] / 2, abs=1e-6)
    # Without the box, the camera's axis: the straight-down grasp is tilt_deg off it.
    alone = plan(box_part, pick_settings, T, captured, np.full(4, np.nan))
    assert alone.up_cam == pytest.approx([0.0, 0.0, -1.0])
    # A plane found in the capture that agrees with the box's floor (the measured floor) is kept.
    measured_floor = np.append(bin_up, -(bin_up @ T_cam_from_bin[:3, 3]) + 0.004)
    up, plane = support_frame(measured_floor, box)
    assert plane == pytest.approx(measured_floor)


def nearest_of_cells(T_cam_from_model: np.ndarray, noise_m: float, rng: np.random.Generator, k: int = 3) -> np.ndarray:
    """The box's top as the seen depth gives it: measured on a 1/k mm grid with Gaussian noise
    along the rays, each 1 mm cell keeping its nearest measurement (toward the camera)."""
    fine = measured_top(T_cam_from_model, noise_m, rng, np.array([0.02, 0.02]), 0.001 / k)  # the top's middle
    n = int(round(np.sqrt(len(fine))))
    depth = np.linalg.norm(fine, axis=1).reshape(n, n)
    cells = depth[: n - n % k, : n - n % k].reshape(n // k, k, n // k, k).transpose(0, 2, 1, 3).reshape(-1, k * k)
    index = np.arange(n * n).reshape(n, n)[: n - n % k, : n - n % k]
    index = index.reshape(n // k, k, n // k, k).transpose(0, 2, 1, 3).reshape(-1, k * k)
    return fine[index[np.arange(len(cells)), np.argmin(cells, axis=1)]]


def test_the_seen_depths_nearest_of_a_cell_is_the_parts_own_surface_and_a_bar_above_it_is_not(box_part, pick_settings):
    """The top measured with 2 mm noise, each cell keeping the nearest of four measurements: the
    points sit about 2 mm toward the camera, some beyond 4 sigmas of their own scatter from the
    posed surface (4 captures of 40 gave a pick when they counted as obstacles). They are the
    part's own: a pick in at least nine of ten captures (the nearest of four has a long tail
    toward the camera: in 1 of 40 a point stayed in the way). A bar 10 mm above the top beside
    the cup's lip is still in the tool's way."""
    T = lying(make_T(axis_angle_to_R(np.array([1.0, 0.0, 0.0]), np.pi), np.array([0.0, 0.0, 0.6])))
    captures = [nearest_of_cells(T, 0.002, np.random.default_rng(seed), 2) for seed in range(10)]
    offsets = (captures[0] - transform_points(T, np.array([[0.0, 0.0, EXTENTS[2] / 2]]))) @ T[:3, 2]
    assert 0.0015 < np.median(offsets) < 0.0025  # toward the camera (the top's outward normal)
    assert sum(bool(plan(box_part, pick_settings, T, c).picks) for c in captures) >= 9
    captured = captures[0]
    assert plan(box_part, pick_settings, T, captured).picks
    local = transform_points(np.linalg.inv(T), captured)
    beside = (local[:, 0] > 0.0055) & (local[:, 0] < 0.0065) & (np.abs(local[:, 1]) < 0.005)
    barred = captured.copy()
    barred[beside] = transform_points(T, local[beside] + [0.0, 0.0, 0.010])
    refused = plan(box_part, pick_settings, T, barred)
    assert not refused.picks and "captured points" in refused.unpicked[0][1]


@pytest.fixture(scope="module")
def stepped_part():
    """A disc 50 mm across and 12 mm thick with a boss 12 mm across standing 8 mm on its centre
    (a cup's lid has such steps: a plateau, a recess, a rim); model z up, its base at z = 0."""
    import trimesh

    from binpick.params import SymmetryParams
    from binpick.part.model import make_part_model

    profile = [[0.0, 0.0], [0.025, 0.0], [0.025, 0.012], [0.006, 0.012], [0.006, 0.020], [0.0, 0.020]]
    mesh = trimesh.creation.revolve(np.array(profile), sections=64)
    return make_part_model("stepped", mesh, SymmetryParams(), 20000, np.random.default_rng(0), "m")


def measured_stepped(T_cam_from_model: np.ndarray, spacing_m: float, rng: np.random.Generator) -> np.ndarray:
    """The stepped part's top (the boss and the ring round it) on a grid of spacing_m, 0.5 mm of
    noise along the camera's rays."""
    a, b = np.meshgrid(np.arange(-0.024, 0.024, spacing_m), np.arange(-0.024, 0.024, spacing_m))
    r = np.hypot(a, b).ravel()
    top = np.column_stack([a.ravel(), b.ravel(), np.where(r < 0.006, 0.020, 0.012)])[r < 0.025]
    pts = transform_points(T_cam_from_model, top)
    return pts + pts / np.linalg.norm(pts, axis=1, keepdims=True) * rng.normal(0.0, 0.0005, (len(pts), 1))


@pytest.mark.parametrize("wrong", [None, "lower", "turned"])
def test_a_sparse_capture_judges_a_small_cups_contact_against_the_parts_own_steps(stepped_part, pick_settings, wrong):
    """Points 6 mm apart (a VGA frame's cloud): an 8 mm cup on the boss covers one to three of
    them, so the contact is judged over a 15 mm disc, which takes in the ring 8 mm below the boss.
    Against the contact's plane most of the disc lies off it; against the posed part's surface it
    is the part, measured. The same points under a pose floating 8 mm above them, or turned 45
    degrees about the contact, are still refused."""
    settings = pick_settings.model_copy(
        update={"suction": pick_settings.suction.model_copy(update={"cup_radius_m": 0.004})}
    )
    T = make_T(axis_angle_to_R(np.array([1.0, 0.0, 0.0]), np.pi), np.array([0.0, 0.0, 0.6]))
    captured = measured_stepped(T, 0.006, np.random.default_rng(4))
    if wrong == "lower":
        T = T @ make_T(np.eye(3), np.array([0.0, 0.0, 0.008]))
    elif wrong == "turned":
        contact = T @ make_T(np.eye(3), np.array([0.0, 0.0, 0.020]))
        turn = make_T(axis_angle_to_R(np.array([1.0, 0.0, 0.0]), np.radians(45.0)), np.zeros(3))
        T = contact @ turn @ np.linalg.inv(contact) @ T
    on_boss = GraspSet(
        "suction", ["boss"], tool_frame(np.array([0.0, 0.0, 0.020]), np.array([0.0, 0.0, -1.0]))[None], np.zeros(1)
    )
    result = plan(stepped_part, settings, T, captured, grasps=on_boss)
    if wrong is None:
        assert result.picks, result.unpicked
    else:
        assert not result.picks and UNSEEN in result.unpicked[0][1], result.unpicked
