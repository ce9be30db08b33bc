"""Grasps and picks recover known answers: grasps on a box land on its faces, a grasp applied to
a known pose lands where that pose puts it, a gripper placed into a wall or a neighbour is
refused and one in free space is not, and parts come in the configured order."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
import yaml
from conftest import ROOT, box_part_model
from scipy.spatial import cKDTree

from binpick.cell.bin_box import BinBox
from binpick.errors import InputError
from binpick.geometry.symmetry import symmetry_transforms
from binpick.geometry.transforms import axis_angle_to_R, make_T, transform_points
from binpick.io.grasps import GraspSet, load_grasps, save_grasps, tool_frame
from binpick.io.picks import load_picks, save_picks
from binpick.params import SymmetryParams, load_params
from binpick.part.model import make_part_model
from binpick.picking.arm import turns_for
from binpick.picking.grasps import expand_by_symmetry, jaw_grasps, lip_axis, suction_grasps
from binpick.picking.gripper import (
    Box,
    Cylinder,
    covering_spheres,
    gripper_primitives,
    jaw_primitives,
    lowest_height,
    signed_distance,
    swept,
)
from binpick.picking.lift import LEAVE_WALL_DEG
from binpick.picking.measured import contact_seen
from binpick.picking.obstacles import BIN, CAPTURED
from binpick.picking.plan import FAILED_HERE, GRIP_FAILED, NOT_PLANNED, image_groups, images_in_turn, plan_picks
from binpick.picking.seal import contact_tolerance_m, cup_seal

# A box part 40 x 30 x 20 mm, model frame at its centre.
EXTENTS = np.array([0.04, 0.03, 0.02])
FLOOR = np.array([0.0, 0.0, -1.0, 0.5])  # camera 0.5 m above the floor, looking down (+z)


@pytest.fixture(scope="module")
def box_part():
    return box_part_model(EXTENTS)


def lying(x: float, y: float, yaw_deg: float = 0.0) -> np.ndarray:
    """T_cam_from_model of the box lying on the floor (its z up toward the camera) at x, y."""
    R = axis_angle_to_R(np.array([1.0, 0.0, 0.0]), np.pi) @ axis_angle_to_R(
        np.array([0.0, 0.0, 1.0]), np.radians(yaw_deg)
    )
    return make_T(R, np.array([x, y, 0.5 - EXTENTS[2] / 2]))


def seen_surface(T: np.ndarray, part) -> np.ndarray:
    """The posed part's points that face the camera (a stand-in for what it measured)."""
    pts = transform_points(T, part.points_m)
    nrm = part.normals @ T[:3, :3].T
    return pts[np.einsum("ij,ij->i", nrm, -pts) > 0]


def test_suction_grasps_lie_on_flat_faces_with_inward_approach(box_part, pick_settings):
    grasps = suction_grasps(box_part, pick_settings)
    assert len(grasps) > 0
    half = EXTENTS / 2
    for T in grasps.T_model_from_tool:
        p, z = T[:3, 3], T[:3, 2]
        face = int(np.argmax(np.abs(p) / half))
        assert abs(abs(p[face]) - half[face]) < 1e-4  # on a face ...
        assert np.allclose(z, -np.sign(p[face]) * np.eye(3)[face], atol=1e-3)  # ... approaching into it
        # The cup's lip fits on the face: its centre about its radius from every edge (the
        # check samples the lip in 12 sectors: 0.69 radii at least).
        others = [k for k in range(3) if k != face]
        assert np.all(np.abs(p[others]) <= half[others] - 0.65 * pick_settings.suction.cup_radius_m)
    # Best first: the face centres of the two largest faces are nearest the centre of mass.
    assert np.linalg.norm(grasps.T_model_from_tool[0][:3, 3]) < 0.011


def test_a_large_part_sampled_sparsely_still_gets_suction_grasps(pick_settings):
    """A 0.5 m box with the ingest's 20,000 points holds about 2 points per disc of a 5 mm cup,
    too few to see its lip: the patches are read from a denser sample of the mesh, and the grasps
    lie on the faces with the approach into them."""
    extents = np.array([0.5, 0.3, 0.2])
    big = make_part_model(
        "big_box", trimesh.creation.box(extents=extents), SymmetryParams(), 20000, np.random.default_rng(0), "m"
    )
    grasps = suction_grasps(big, pick_settings)
    assert len(grasps) >= 10
    for T in grasps.T_model_from_tool:
        p, z = T[:3, 3], T[:3, 2]
        face = int(np.argmax(np.abs(p) / (extents / 2)))
        assert abs(abs(p[face]) - extents[face] / 2) < 1e-4 and np.allclose(
            z, -np.sign(p[face]) * np.eye(3)[face], atol=1e-3
        )


def rod_part(radius_m: float, length_m: float, sections: int):
    """A cylinder part along its model z, declared a solid of revolution."""
    mesh = trimesh.creation.cylinder(radius=radius_m, height=length_m, sections=sections)
    return make_part_model("rod", mesh, SymmetryParams(kind="revolution"), 20000, np.random.default_rng(0), "m")


def test_a_suction_grasp_beside_a_step_keeps_a_poses_error_from_it(pick_settings, monkeypatch):
    """A 5 mm plate with a wall rising 15 mm above it along its +x end: the cups on the plate's
    top keep SELF_MARGIN_M from the wall's face (a pose a millimetre off must not set the lip on
    it); without the margin and the lip's seal test some come within it."""
    import binpick.picking.grasps as grasps_module
    from binpick.params import SymmetryParams
    from binpick.part.model import make_part_model

    plate = trimesh.creation.box(extents=(0.06, 0.04, 0.005))
    plate.apply_translation((0.0, 0.0, 0.0025))
    wall = trimesh.creation.box(extents=(0.01, 0.04, 0.02))
    wall.apply_translation((0.035, 0.0, 0.01))  # its face toward the plate at x = 0.03
    part = make_part_model(
        "step", trimesh.util.concatenate([plate, wall]), SymmetryParams(), 20000, np.random.default_rng(0), "m"
    )

    def gaps_to_the_wall() -> np.ndarray:
        T = suction_grasps(part, pick_settings).T_model_from_tool
        on_top = (T[:, 2, 2] < -0.99) & (np.abs(T[:, 2, 3] - 0.005) < 1e-4)
        assert on_top.sum() > 10
        return 0.03 - T[on_top, 0, 3] - pick_settings.suction.cup_radius_m

    assert gaps_to_the_wall().min() >= grasps_module.SELF_MARGIN_M > 0.0
    # Neither the margin nor the lip's seal tried a millimetre off (which meets the wall too).
    monkeypatch.setattr(grasps_module, "SELF_MARGIN_M", 0.0)
    monkeypatch.setattr(grasps_module, "_seals", lambda *args: True)
    assert gaps_to_the_wall().min() < 0.001


def test_a_suction_cups_lip_stays_on_a_washers_face_clear_of_its_hole_and_rim(pick_settings, monkeypatch):
    """A washer (12-30 mm radius, 5 mm thick): every cup on its faces keeps its lip on the face,
    about SEAL_OFFSET_M (1 mm, less the tessellation's few tenths) inside the hole's edge and the
    rim. The point sample's patch test alone lets lips hang over both."""
    import binpick.picking.grasps as grasps_module
    from binpick.params import SymmetryParams
    from binpick.part.model import make_part_model

    washer = trimesh.creation.annulus(r_min=0.012, r_max=0.03, height=0.005)
    part = make_part_model("washer", washer, SymmetryParams(), 20000, np.random.default_rng(0), "m")
    r = pick_settings.suction.cup_radius_m

    def lip_gaps() -> tuple[float, float]:
        T = suction_grasps(part, pick_settings).T_model_from_tool
        on_face = np.abs(np.abs(T[:, 2, 2]) - 1.0) < 1e-3
        assert on_face.sum() > 20
        radius = np.linalg.norm(T[on_face, :2, 3], axis=1)
        return float(np.min(radius - r - 0.012)), float(np.min(0.03 - radius - r))

    assert min(lip_gaps()) > grasps_module.SEAL_OFFSET_M - 0.0005
    monkeypatch.setattr(grasps_module, "_seals", lambda *args: True)
    assert max(lip_gaps()) < 0.0


def test_a_solid_of_revolution_is_grasped_along_its_smooth_normal(pick_settings):
    """A rod of 12 facets declared a solid of revolution: its side grasps approach along the
    cylinder's own normal (straight at the axis), not their facet's, which lies up to 15 degrees
    around from it."""
    rod = rod_part(radius_m=0.02, length_m=0.1, sections=12)
    grasps = suction_grasps(rod, pick_settings)
    side = [T for T in grasps.T_model_from_tool if abs(T[2, 2]) < 0.5]
    assert len(side) >= 5
    for T in side:
        radial = T[:3, 3] * [1.0, 1.0, 0.0]
        assert np.degrees(np.arccos(np.clip(-T[:3, 2] @ (radial / np.linalg.norm(radial)), -1, 1))) < 1.0


def oval_cup(pick_settings, half_length_m: float, radius_m: float):
    """The pick settings with a bellows cup sealing within 4 mm and 40 degrees: oval (lip
    2 half_length_m long, 2 radius_m wide), or round (half_length_m None)."""
    suction = pick_settings.suction.model_copy(
        update={
            "cup_radius_m": radius_m,
            "cup_half_length_m": half_length_m,
            "max_deviation_m": 0.004,
            "max_normal_deg": 40.0,
            "tool_radius_m": 0.02,
        }
    )
    return pick_settings.model_copy(update={"suction": suction})


def test_the_least_curved_direction_of_a_cylinder_is_its_axis():
    """Normals of a cylinder patch around a random axis (and of a flat strip along it): the lip's
    long axis comes out along the cylinder's axis, across the patch's normal."""
    rng = np.random.default_rng(3)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    n = np.cross(axis, rng.normal(size=3))
    n /= np.linalg.norm(n)
    side = np.cross(axis, n)
    angles = rng.uniform(-0.6, 0.6, 300)
    normals = np.outer(np.cos(angles), n) + np.outer(np.sin(angles), side)
    found = lip_axis(normals, n)
    assert abs(found @ axis) == pytest.approx(1.0, abs=1e-9)
    assert abs(found @ n) < 1e-9


def test_an_oval_cup_lies_along_a_shaft_where_a_round_cup_of_its_hold_finds_no_seal(pick_settings):
    """A rod of 20 mm radius: a 60 x 20 mm oval cup seals along its side (the lip 2.7 mm from flat
    across it), each grasp's long axis along the rod, and the same lip turned a quarter turn
    across the rod does not seal; a round cup of the oval's area (17.3 mm radius, 10 mm from flat
    across the rod) finds no grasp on the side."""
    rod = rod_part(radius_m=0.02, length_m=0.15, sections=48)
    oval = oval_cup(pick_settings, 0.03, 0.01)
    grasps = suction_grasps(rod, oval)
    side = [T for T in grasps.T_model_from_tool if abs(T[2, 2]) < 0.1]
    assert len(side) >= 5
    rays = trimesh.ray.ray_triangle.RayMeshIntersector(trimesh.Trimesh(rod.mesh_vertices_m, rod.mesh_faces))
    for T in side:
        assert abs(T[2, 0]) > np.cos(np.radians(1.0))  # the tool's x along the rod's z
        assert cup_seal(rays, T, oval.suction) is True
        across = T @ make_T(axis_angle_to_R(np.array([0.0, 0.0, 1.0]), np.pi / 2), np.zeros(3))
        assert cup_seal(rays, across, oval.suction) is False
    round_cup = oval_cup(pick_settings, None, float(np.sqrt(0.03 * 0.01)))
    assert not any(abs(T[2, 2]) < 0.1 for T in suction_grasps(rod, round_cup).T_model_from_tool)


def test_a_bellows_cup_seals_on_a_surface_half_its_travel_off_the_planned_contact_and_no_farther(pick_settings):
    """A cup whose plan puts the lip 3 mm short of the rod's side (the pose 3 mm toward the
    camera) or 3 mm into it: a flat cup meets air or presses in (no part there, within 2 mm);
    a bellows cup of 8 mm travel seals both ways; 7 mm off is beyond it too."""
    rod = rod_part(radius_m=0.02, length_m=0.15, sections=48)
    flat = oval_cup(pick_settings, 0.03, 0.01)
    bellows = flat.model_copy(update={"suction": flat.suction.model_copy(update={"stroke_m": 0.008})})
    T = next(T for T in suction_grasps(rod, flat).T_model_from_tool if abs(T[2, 2]) < 0.1)
    rays = trimesh.ray.ray_triangle.RayMeshIntersector(trimesh.Trimesh(rod.mesh_vertices_m, rod.mesh_faces))

    def off(T: np.ndarray, along_m: float) -> np.ndarray:
        """The tool moved along its approach: > 0 into the part."""
        return make_T(T[:3, :3], T[:3, 3] + along_m * T[:3, 2])

    for along_m in (-0.003, 0.003):
        assert cup_seal(rays, off(T, along_m), flat.suction) is None
        assert cup_seal(rays, off(T, along_m), bellows.suction) is True
    assert cup_seal(rays, off(T, -0.007), bellows.suction) is None
    assert contact_tolerance_m(bellows.suction) == pytest.approx(0.006)


def test_an_oval_cups_grasps_keep_their_long_axis_in_the_file_and_turn_only_half_a_turn(tmp_path, pick_settings):
    rod = rod_part(radius_m=0.02, length_m=0.15, sections=48)
    grasps = suction_grasps(rod, oval_cup(pick_settings, 0.03, 0.01))
    path = tmp_path / "grasps.json"
    save_grasps(path, "rod", {"suction": grasps}, "generated", oval_cup=True)
    back = load_grasps(path, oval_cup=True)["suction"]
    assert np.allclose(back.T_model_from_tool, grasps.T_model_from_tool, atol=1e-8)
    save_grasps(path, "rod", {"suction": grasps}, "generated")  # a round cup's file: no long axis
    with pytest.raises(InputError, match="needs the grasp's long_axis"):
        load_grasps(path, oval_cup=True)
    assert turns_for("suction", 30.0, oval_cup=True) == pytest.approx([0.0, np.pi])
    assert len(turns_for("suction", 30.0)) == 12


def test_with_more_candidates_than_tried_each_grasps_images_take_turns():
    """Three grasps with four images each (ids as expand_by_symmetry names them): within a cap
    of 5 the least tilted image of every grasp comes first, in the grasps' order, then the
    second least tilted of the first two; below the cap the list is left as it is."""
    ids = ["a", "b", "c"] + [f"{g}@{k}" for g in "abc" for k in (1, 2, 3)]
    grasp_of = image_groups(ids)
    assert grasp_of.tolist() == [0, 1, 2, 0, 0, 0, 1, 1, 1, 2, 2, 2]
    tilt = np.array([0.5, 0.9, 0.1, 0.2, 0.7, 0.3, 0.8, 0.05, 0.6, 0.4, 0.0, 0.9])
    candidates = np.arange(len(ids))
    chosen = images_in_turn(candidates, grasp_of, tilt, 5)
    assert [ids[k] for k in chosen] == ["a@1", "b@2", "c@2", "a@3", "b@3"]
    assert images_in_turn(candidates, grasp_of, tilt, 12).tolist() == candidates.tolist()


def test_jaw_grasps_close_across_the_box(box_part, pick_settings):
    grasps = jaw_grasps(box_part, pick_settings)
    assert len(grasps) > 0
    for T, width in zip(grasps.T_model_from_tool, grasps.width_m, strict=True):
        closing = np.abs(T[:3, 0])
        axis = int(np.argmax(closing))
        assert closing[axis] > 0.99
        assert width == pytest.approx(EXTENTS[axis], abs=1e-4)
        assert width < pick_settings.jaw.opening_max_m
        assert abs(T[:3, 2] @ T[:3, 0]) < 1e-9  # approach across the closing axis
        # The fingers, opened to approach, clear the part.
        local = (box_part.points_m - T[:3, 3]) @ T[:3, :3]
        opening = min(pick_settings.jaw.opening_max_m, width + 2 * pick_settings.jaw.open_margin_m)
        assert signed_distance(local, jaw_primitives(pick_settings.jaw, opening)).min() > 0


def test_a_shaft_thicker_than_half_the_finger_is_gripped_across_only_with_a_pad_at_the_tip(pick_settings):
    """A 50 mm rod in 40 mm fingers: padded along the whole finger the tool centre point lies
    20 mm in front of the palm, inside the rod, so no grasp closes across its body; with a 10 mm
    pad at the tip the palm stands 35 mm back and grasps close across the body on chords of the
    rod, the fingers' tips 5 mm past the tool centre point."""
    rod = rod_part(radius_m=0.025, length_m=0.2, sections=48)
    jaw = pick_settings.jaw.model_copy(update={"finger_length_m": 0.04, "opening_max_m": 0.08})
    whole = pick_settings.model_copy(update={"jaw": jaw})
    tip = pick_settings.model_copy(update={"jaw": jaw.model_copy(update={"pad_length_m": 0.01})})

    def across(grasps):
        """Closing across the axis, approaching from the side (not from an end, past the rod)."""
        pairs = zip(grasps.T_model_from_tool, grasps.width_m, strict=True)
        return [(T, w) for T, w in pairs if abs(T[2, 0]) < 0.1 and abs(T[2, 2]) < 0.1]

    assert across(jaw_grasps(rod, whole)) == []
    body = across(jaw_grasps(rod, tip))
    assert len(body) >= 5
    for T, width in body:
        # A chord of the rod, its contacts' normals within the friction cone of the closing axis.
        off_axis = float(np.linalg.norm(T[:2, 3]))
        assert off_axis <= 0.025 * np.sin(np.radians(tip.jaw.friction_deg))
        assert width == pytest.approx(2.0 * np.sqrt(0.025**2 - off_axis**2), abs=5e-4)
        fingers = jaw_primitives(tip.jaw, width)[:2]
        assert [f.hi[2] for f in fingers] == pytest.approx([0.005, 0.005])
        assert [f.lo[2] for f in fingers] == pytest.approx([-0.035, -0.035])


def test_signed_distance_and_floor_height_of_primitives():
    box = Box(np.array([-0.01, -0.01, -0.02]), np.array([0.01, 0.01, 0.0]))
    cyl = Cylinder(0.005, -0.05, -0.02)
    pts = np.array([[0.0, 0.0, -0.01], [0.02, 0.0, -0.01], [0.0, 0.0, -0.06], [0.0, 0.0, 0.0]])
    d = signed_distance(pts, [box, cyl])
    assert d == pytest.approx([-0.01, 0.01, 0.01, 0.0])
    assert signed_distance(pts[2:3], swept([cyl], 0.02))[0] == pytest.approx(-0.005)
    # Tool pointing straight down (its z along -up) 0.1 m above a floor z = 0 (normal +z).
    T = make_T(axis_angle_to_R(np.array([1.0, 0.0, 0.0]), np.pi), np.array([0.0, 0.0, 0.1]))
    assert lowest_height([box], T, np.array([0.0, 0.0, 1.0, 0.0])) == pytest.approx(0.1)
    assert lowest_height([cyl], T, np.array([0.0, 0.0, 1.0, 0.0])) == pytest.approx(0.12)


def test_covering_spheres_hold_every_point_near_the_gripper(pick_settings):
    """The collision check measures only points inside the covering spheres: every point within
    the margin of the swept gripper (by the exact signed distance) must lie in one of them."""
    rng = np.random.default_rng(3)
    for body in (
        swept(jaw_primitives(pick_settings.jaw, 0.03), 0.05),
        swept([Cylinder(0.005, -0.02, 0.0), Cylinder(0.015, -0.17, -0.02)], 0.05),
    ):
        for margin in (0.002, 0.05):
            points = rng.uniform([-0.15, -0.15, -0.35], [0.15, 0.15, 0.1], size=(200000, 3))
            near = points[signed_distance(points, body) <= margin]
            centres, radii = covering_spheres(body, margin)
            inside = (np.linalg.norm(near[:, None, :] - centres[None], axis=2) <= radii[None]).any(axis=1)
            assert len(near) > 100 and inside.all()


def test_a_grasp_applied_to_a_known_pose_lands_where_the_pose_puts_it(box_part, pick_settings):
    grasps = suction_grasps(box_part, pick_settings)
    T = lying(0.01, -0.02, yaw_deg=30.0)
    plan = plan_picks(
        T[None],
        np.array([0.8]),
        grasps,
        box_part.points_m,
        box_part.normals,
        box_part.centre_m,
        seen_surface(T, box_part),
        FLOOR,
        pick_settings,
    )
    assert len(plan.picks) == 1 and not plan.unpicked
    pick = plan.picks[0]
    grasp = grasps.T_model_from_tool[pick.grasp_index]
    assert np.allclose(pick.T_cam_from_grasp, T @ grasp)
    # The top face (model +z, toward the camera) is the one within the cone: contact on top,
    # approach straight down the camera's view (+z), pre-grasp straight above it.
    assert pick.T_cam_from_grasp[2, 3] == pytest.approx(0.5 - EXTENTS[2], abs=1e-4)
    assert pick.T_cam_from_grasp[:3, 2] == pytest.approx([0.0, 0.0, 1.0], abs=1e-3)
    assert pick.T_cam_from_pregrasp[:3, 3] == pytest.approx(
        pick.T_cam_from_grasp[:3, 3] - [0, 0, pick_settings.pregrasp_distance_m], abs=1e-4
    )
    assert pick.clearance_m > pick_settings.clearance_m
    assert pick.height_m == pytest.approx(EXTENTS[2] / 2, abs=1e-4)


def test_clearance_is_the_distance_to_the_nearest_obstacle(box_part, pick_settings):
    """One obstacle point beside the tool, 60 mm above the grasp, at a known distance from the
    tool's cylinder (radius tool_radius_m): the pick reports that distance as its clearance, in
    each range the widening search covers, and the cap when nothing is near (no floor given)."""
    grasps = suction_grasps(box_part, pick_settings)
    T = lying(0.0, 0.0)
    seen = seen_surface(T, box_part)
    no_floor = np.full(4, np.nan)
    alone = plan_picks(
        T[None],
        np.array([0.8]),
        grasps,
        box_part.points_m,
        box_part.normals,
        box_part.centre_m,
        seen,
        no_floor,
        pick_settings,
    ).picks[0]
    assert alone.clearance_m == pytest.approx(0.05)  # the cap
    G = alone.T_cam_from_grasp
    for gap in (0.008, 0.015, 0.035):
        point = G[:3, 3] - 0.06 * G[:3, 2] + (pick_settings.suction.tool_radius_m + gap) * G[:3, 0]
        plan = plan_picks(
            T[None],
            np.array([0.8]),
            grasps,
            box_part.points_m,
            box_part.normals,
            box_part.centre_m,
            np.vstack([seen, point]),
            no_floor,
            pick_settings,
        )
        assert plan.picks[0].grasp_id == alone.grasp_id
        assert plan.picks[0].clearance_m == pytest.approx(gap, abs=1e-6)


def test_a_grasp_with_little_room_about_the_gripper_waits_for_the_parts_others(box_part, pick_settings):
    """A point 4 mm beside the tool of the part's first pick (within room_m, beyond clearance_m):
    another of its grasps, with room, is taken; where no grasp has the room asked, the first one
    is."""
    grasps = suction_grasps(box_part, pick_settings)
    T = lying(0.0, 0.0)
    seen = seen_surface(T, box_part)
    assert pick_settings.clearance_m < 0.004 < pick_settings.room_m

    def first_pick(captured):
        return plan_one_box(T, grasps, box_part, captured, pick_settings).picks[0]

    alone = first_pick(seen)

    def beside(G):
        return G[:3, 3] - 0.06 * G[:3, 2] + (pick_settings.suction.tool_radius_m + 0.004) * G[:3, 0]

    other = first_pick(np.vstack([seen, beside(alone.T_cam_from_grasp)]))
    assert other.grasp_id != alone.grasp_id and other.clearance_m >= pick_settings.room_m
    # Room asked beyond the clearance's cap (every grasp is tight): the first is taken all the same.
    roomy = pick_settings.model_copy(update={"room_m": 0.06})
    tight = plan_one_box(T, grasps, box_part, seen, roomy).picks[0]
    assert tight.grasp_id == alone.grasp_id and tight.clearance_m < roomy.room_m


def plan_one_box(T, grasps, box_part, captured, settings, bin_box=None):
    """The pick plan of one box posed at T (score 0.9) among the captured points, over FLOOR (and in
    bin_box when given)."""
    return plan_picks(
        T[None],
        np.array([0.9]),
        grasps,
        box_part.points_m,
        box_part.normals,
        box_part.centre_m,
        captured,
        FLOOR,
        settings,
        bin_box,
    )


def test_a_grasp_where_a_grip_failed_is_not_tried_again(box_part, pick_settings):
    grasps = suction_grasps(box_part, pick_settings)
    T = lying(0.0, 0.0)
    captured = seen_surface(T, box_part)
    first = plan_one_box(T, grasps, box_part, captured, pick_settings).picks[0]
    failed_at = first.T_cam_from_grasp[:3, 3]
    plan = plan_picks(
        T[None], np.array([0.9]), grasps, box_part.points_m, box_part.normals, box_part.centre_m, captured,
        FLOOR, pick_settings, failed_contacts_m=failed_at[None],
    )  # fmt: skip
    # Another grasp on the same part, its cup clear of the lip that did not seal.
    (again,) = plan.picks
    assert again.grasp_id != first.grasp_id
    lip_m = 2.0 * pick_settings.suction.cup_radius_m
    assert np.linalg.norm(again.T_cam_from_grasp[:3, 3] - failed_at) > lip_m
    # Where every grasp failed, the part is not picked, and the reason says so.
    tcp = (T @ grasps.T_model_from_tool)[:, :3, 3]
    none = plan_picks(
        T[None], np.array([0.9]), grasps, box_part.points_m, box_part.normals, box_part.centre_m, captured,
        FLOOR, pick_settings, failed_contacts_m=tcp,
    )  # fmt: skip
    assert not none.picks and FAILED_HERE in none.unpicked[0][1]


def test_a_gripper_into_a_neighbour_is_refused(box_part, pick_settings):
    grasps = suction_grasps(box_part, pick_settings)
    target = lying(0.0, 0.0)
    # A neighbour resting across the target's top, 25 mm above it: every top grasp's tool hits it.
    above = make_T(target[:3, :3], target[:3, 3] - np.array([0.0, 0.0, 0.045]))
    T = np.stack([target, above])
    captured = np.concatenate([seen_surface(target, box_part), seen_surface(above, box_part)])
    plan = plan_picks(
        T,
        np.array([0.9, 0.5]),
        grasps,
        box_part.points_m,
        box_part.normals,
        box_part.centre_m,
        captured,
        FLOOR,
        pick_settings,
    )
    assert [p.pose_index for p in plan.picks] == [1]  # the top one is free
    ((index, reason),) = plan.unpicked
    assert index == 0 and "part 1" in reason
    assert any(r.pose_index == 0 and "1" in r.reason.split(", ") for r in plan.rejected)


def test_a_gripper_into_a_wall_is_refused_and_one_in_free_space_is_not(box_part, pick_settings):
    grasps = suction_grasps(box_part, pick_settings)
    T = lying(0.0, 0.0)
    captured = seen_surface(T, box_part)
    free = plan_one_box(T, grasps, box_part, captured, pick_settings)
    assert len(free.picks) == 1 and not free.rejected
    # Measured walls (points of two vertical planes) above the part, closer together than the
    # tool is wide: no grasp on its top can be reached.
    ys, zs = np.meshgrid(np.linspace(-0.05, 0.05, 60), np.linspace(0.38, 0.47, 60))
    wall = np.concatenate([np.column_stack([np.full(ys.size, x), ys.ravel(), zs.ravel()]) for x in (-0.01, 0.01)])
    blocked = plan_one_box(T, grasps, box_part, np.concatenate([captured, wall]), pick_settings)
    assert not blocked.picks and CAPTURED in blocked.unpicked[0][1]
    # A bin given in params barely larger than the part (walls 1-2 mm from its sides): the tool,
    # 30 mm across, cannot come down to its top.
    T_cam_from_bin = make_T(axis_angle_to_R(np.array([1.0, 0.0, 0.0]), np.pi), np.array([0.0, 0.0, 0.5]))
    box = BinBox(T_cam_from_bin, np.array([-0.022, -0.016, 0.0]), np.array([0.022, 0.016, 0.1]))
    walled = plan_one_box(T, grasps, box_part, captured, pick_settings, box)
    assert not walled.picks and BIN in walled.unpicked[0][1]


def test_a_large_parts_measured_surface_is_its_own_not_an_obstacle(pick_settings):
    """A 0.5 m box lying under the camera, its top face measured on a 1 mm grid with 0.3 mm of
    noise: those points are the target's own, whatever its sample's density (20,000 points lie
    5.6 mm apart on it, farther than own_points_m), and the cup comes down on the top face. A
    point 10 mm above the face under the grasp is not its own: that grasp is refused."""
    extents = np.array([0.5, 0.3, 0.2])
    big = make_part_model(
        "big_box", trimesh.creation.box(extents=extents), SymmetryParams(), 20000, np.random.default_rng(0), "m"
    )
    grasps = suction_grasps(big, pick_settings)
    floor = np.array([0.0, 0.0, -1.0, 0.8])
    T = make_T(axis_angle_to_R(np.array([1.0, 0.0, 0.0]), np.pi), np.array([0.0, 0.0, 0.8 - extents[2] / 2]))
    xs, ys = np.meshgrid(np.arange(-0.25, 0.25, 0.001), np.arange(-0.15, 0.15, 0.001))
    top = np.column_stack([xs.ravel(), ys.ravel(), 0.6 + np.random.default_rng(1).normal(0.0, 0.0003, xs.size)])
    plan = plan_picks(
        T[None], np.array([0.9]), grasps, big.points_m, big.normals, big.centre_m, top, floor, pick_settings
    )
    assert len(plan.picks) == 1 and not plan.rejected
    G = plan.picks[0].T_cam_from_grasp
    assert G[2, 3] == pytest.approx(0.6, abs=1e-4)
    above = G[:3, 3] - 0.01 * G[:3, 2]
    again = plan_picks(
        T[None],
        np.array([0.9]),
        grasps,
        big.points_m,
        big.normals,
        big.centre_m,
        np.vstack([top, above]),
        floor,
        pick_settings,
    )
    assert again.picks[0].grasp_id != plan.picks[0].grasp_id
    assert any(r.grasp_id == plan.picks[0].grasp_id and r.reason == CAPTURED for r in again.rejected)


def test_a_pose_with_too_much_surface_seen_through_is_picked_last(box_part, pick_settings):
    """Two free parts: the higher one's pose has more of its surface where the camera saw through
    it than pick.max_seen_through: its pick comes after the lower, trusted one, and says so; a
    pose without a measured share (verification off) is trusted."""
    grasps = suction_grasps(box_part, pick_settings)
    low = lying(-0.05, 0.0)
    high = make_T(low[:3, :3], np.array([0.05, 0.0, 0.5 - EXTENTS[2] / 2 - 0.03]))
    T = np.stack([high, low])
    captured = np.concatenate([seen_surface(t, box_part) for t in T])
    limit = pick_settings.max_seen_through
    plan = plan_picks(
        T,
        np.array([0.9, 0.9]),
        grasps,
        box_part.points_m,
        box_part.normals,
        box_part.centre_m,
        captured,
        FLOOR,
        pick_settings,
        seen_through=np.array([limit + 0.01, limit - 0.01]),
    )
    assert [(p.pose_index, p.trusted) for p in plan.picks] == [(1, True), (0, False)]
    unknown = plan_picks(
        T,
        np.array([0.9, 0.9]),
        grasps,
        box_part.points_m,
        box_part.normals,
        box_part.centre_m,
        captured,
        FLOOR,
        pick_settings,
        seen_through=np.array([np.nan, np.nan]),
    )
    assert [(p.pose_index, p.trusted) for p in unknown.picks] == [(0, True), (1, True)]  # highest first


def two_low_parts_and_a_high_one(box_part, pick_settings):
    """The suction grasps, and poses (3, 4, 4): two parts on the floor, one 3 cm higher; what the
    camera sees of them."""
    grasps = suction_grasps(box_part, pick_settings)
    low_good, low_bad = lying(-0.06, 0.0), lying(0.06, 0.0)
    high = make_T(low_good[:3, :3], np.array([0.0, 0.06, 0.5 - EXTENTS[2] / 2 - 0.03]))
    T = np.stack([low_bad, low_good, high])
    return grasps, T, np.concatenate([seen_surface(t, box_part) for t in T])


def test_parts_come_highest_first_then_by_score(box_part, pick_settings):
    grasps, T, captured = two_low_parts_and_a_high_one(box_part, pick_settings)
    plan = plan_picks(
        T,
        np.array([0.4, 0.9, 0.3]),
        grasps,
        box_part.points_m,
        box_part.normals,
        box_part.centre_m,
        captured,
        FLOOR,
        pick_settings,
    )
    assert [p.pose_index for p in plan.picks] == [2, 1, 0]
    by_score = plan_picks(
        T,
        np.array([0.4, 0.9, 0.3]),
        grasps,
        box_part.points_m,
        box_part.normals,
        box_part.centre_m,
        captured,
        FLOOR,
        pick_settings.model_copy(update={"order": ["score", "height"]}),
    )
    assert [p.pose_index for p in by_score.picks] == [1, 0, 2]


def test_only_the_picks_asked_for_are_planned_and_they_are_the_first_of_the_full_list(box_part, pick_settings):
    grasps, T, captured = two_low_parts_and_a_high_one(box_part, pick_settings)
    args = (grasps, box_part.points_m, box_part.normals, box_part.centre_m, captured, FLOOR)
    for order, first_two in ((["height", "score", "clearance"], [2, 1]), (["score", "height"], [1, 0])):
        settings = pick_settings.model_copy(update={"order": order})
        full = plan_picks(T, np.array([0.4, 0.9, 0.3]), *args, settings)
        for n in (1, 2):
            few = plan_picks(T, np.array([0.4, 0.9, 0.3]), *args, settings, max_picks=n)
            assert [p.pose_index for p in few.picks] == first_two[:n]
            assert [p.T_cam_from_grasp.tolist() for p in few.picks] == [
                p.T_cam_from_grasp.tolist() for p in full.picks[:n]
            ]
            # The others are listed, by pose, as not planned; fewer grasps were tried.
            assert few.unpicked == sorted((i, NOT_PLANNED) for i in {0, 1, 2} - set(first_two[:n]))
            assert few.n_candidates < full.n_candidates


def test_a_grasp_whose_contact_the_camera_did_not_measure_is_refused(box_part, pick_settings):
    """A pose turned so that its grasp lies in the air (nothing measured there) gets no pick."""
    grasps = suction_grasps(box_part, pick_settings)
    T = lying(0.0, 0.0)
    measured = seen_surface(T, box_part)
    # The part measured 15 mm lower than its pose says: the pose's top face is in the air.
    plan = plan_one_box(T, grasps, box_part, measured + [0.0, 0.0, 0.015], pick_settings)
    assert not plan.picks and "not where the camera measured" in plan.unpicked[0][1]


def test_a_jaw_grasp_across_a_shaft_sees_the_shafts_top_between_its_fingers(pick_settings):
    """A rod of 25 mm radius lying across the view, gripped from the camera at its axis by long
    fingers with pads at their tips: the camera measures only the rod's top, 25 mm behind the
    pads' centres but between the fingers, and the contact counts as measured; the same surface
    measured 0.1 m farther away (the pose in the air) does not."""
    phi = np.radians(np.linspace(-80.0, 80.0, 33))
    y = np.linspace(-0.05, 0.05, 21)
    P, Y = np.meshgrid(phi, y)
    top = np.column_stack([0.025 * np.sin(P.ravel()), Y.ravel(), 0.5 - 0.025 * np.cos(P.ravel())])
    T_cam_from_tool = make_T(np.eye(3), np.array([0.0, 0.0, 0.5]))  # approach +z, closing along x
    jaw = pick_settings.jaw.model_copy(update={"finger_length_m": 0.08, "pad_length_m": 0.02, "opening_max_m": 0.085})
    settings = pick_settings.model_copy(update={"jaw": jaw})
    for captured, seen in ((top, True), (top + [0.0, 0.0, 0.1], False)):
        tree = cKDTree(captured)
        assert contact_seen(T_cam_from_tool, "jaw", 0.05, captured, tree, settings) is seen


def test_a_suction_contact_on_a_patch_tilted_from_the_cup_is_refused(box_part, pick_settings):
    """Measured points on the cup's contact plane within its seal tolerance are not enough: a
    patch tilted 30 degrees from the approach (a pose turned the wrong way about an edge) has
    three quarters of the cup's points that close to the plane, and no cup seals on it."""
    top = GraspSet(
        "suction",
        ["top"],
        tool_frame(np.array([0.0, 0.0, EXTENTS[2] / 2]), np.array([0.0, 0.0, -1.0]))[None],
        np.zeros(1),
    )
    T = lying(0.0, 0.0)
    contact = transform_points(T, np.array([[0.0, 0.0, EXTENTS[2] / 2]]))[0]
    a, b = np.meshgrid(np.linspace(-0.008, 0.008, 33), np.linspace(-0.008, 0.008, 33))

    def patch(tilt_deg):
        R = axis_angle_to_R(np.array([1.0, 0.0, 0.0]), np.radians(tilt_deg))
        return contact + np.column_stack([a.ravel(), b.ravel(), np.zeros(a.size)]) @ R.T

    for tilt_deg, picked in ((0.0, True), (8.0, True), (30.0, False)):
        plan = plan_one_box(T, top, box_part, patch(tilt_deg), pick_settings)
        assert bool(plan.picks) == picked, tilt_deg
        if not picked:
            assert "not where the camera measured" in plan.unpicked[0][1]


def test_a_part_whose_grasps_all_point_sideways_is_out_of_the_cone(box_part, pick_settings):
    only_side = GraspSet(
        "suction", ["side"], tool_frame(np.array([EXTENTS[0] / 2, 0, 0]), np.array([-1.0, 0, 0]))[None], np.zeros(1)
    )
    T = lying(0.0, 0.0)
    plan = plan_one_box(T, only_side, box_part, seen_surface(T, box_part), pick_settings)
    assert not plan.picks and "cone" in plan.unpicked[0][1]


def test_a_leaning_part_is_taken_from_the_fallback_cone_only_when_the_cone_has_nothing(box_part, pick_settings):
    """A box leaning 50 degrees about its long axis (against a wall, say): one face approaches 40
    degrees from straight down, another 50. Measured points hovering over the 40-degree face
    block it, so only the fallback cone reaches the part, along the 50-degree face's inward
    normal; without a fallback cone it has no pick."""
    T = lying(0.0, 0.0)
    T = make_T(T[:3, :3] @ axis_angle_to_R(np.array([1.0, 0.0, 0.0]), np.radians(50.0)), T[:3, 3] - [0.0, 0.0, 0.01])
    up = np.array([0.0, 0.0, -1.0])
    faces = [T[:3, :3] @ n for n in ([0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [0.0, -1.0, 0.0])]
    at_50 = next(n for n in faces if abs(np.degrees(np.arccos(n @ up)) - 50.0) < 1e-6)
    at_40 = next(n for n in faces if abs(np.degrees(np.arccos(n @ up)) - 40.0) < 1e-6)
    # A lid of measured points 3 cm over the 40-degree face (8 x 5 cm across its normal).
    across = np.cross(at_40, [1.0, 0.0, 0.0])
    a, b = np.meshgrid(np.linspace(-0.04, 0.04, 60), np.linspace(-0.025, 0.025, 40))
    centre_40 = T[:3, 3] + at_40 * EXTENTS[1] / 2
    lid = centre_40 + 0.03 * at_40 + a.reshape(-1, 1) * [1.0, 0.0, 0.0] + b.reshape(-1, 1) * across
    captured = np.concatenate([seen_surface(T, box_part), lid])
    grasps = suction_grasps(box_part, pick_settings)

    def plan(fallback_deg):
        cones = pick_settings.model_copy(update={"approach_cone_deg": 45.0, "fallback_cone_deg": fallback_deg})
        return plan_one_box(T, grasps, box_part, captured, cones)

    (pick,) = plan(60.0).picks
    assert pick.T_cam_from_grasp[:3, 2] == pytest.approx(-at_50, abs=1e-6)
    assert any(CAPTURED in r.reason for r in plan(60.0).rejected)  # the 40-degree face, tried first
    narrow = plan(None)
    assert not narrow.picks and CAPTURED in narrow.unpicked[0][1]


def test_symmetry_expands_grasps_and_drops_repeats(pick_settings):
    g = GraspSet(
        "suction",
        ["a", "b"],
        np.stack(
            [
                tool_frame(np.array([0.01, 0, 0.0]), np.array([0, 0, -1.0])),
                tool_frame(np.array([0.0, 0.0, 0.0]), np.array([0, 0, -1.0])),
            ]
        ),
        np.zeros(2),
    )
    sym = symmetry_transforms(SymmetryParams(kind="n_fold", axis=(0.0, 0.0, 1.0), order=4))
    out = expand_by_symmetry(g, sym)
    # 'a' has three new images about z; 'b' lies on the axis: its images are itself.
    assert out.ids == ["a", "b", "a@1", "a@2", "a@3"]
    assert out.T_model_from_tool[2][:3, 3] == pytest.approx([0.0, 0.01, 0.0], abs=1e-12)


def test_grasp_files_round_trip_and_bad_ones_fail_in_one_line(tmp_path, box_part, pick_settings):
    sets = {"suction": suction_grasps(box_part, pick_settings), "jaw": jaw_grasps(box_part, pick_settings)}
    path = tmp_path / "grasps.json"
    save_grasps(path, "box", sets, "generated")
    back = load_grasps(path)
    for kind in sets:
        assert back[kind].ids == sets[kind].ids
        assert np.allclose(back[kind].T_model_from_tool, sets[kind].T_model_from_tool, atol=1e-8)
        assert np.allclose(back[kind].width_m, sets[kind].width_m)
    cases = {
        '{"suction": [{"point_m": [0, 0, 0]}]}': "missing 'approach'",
        '{"suction": [{"point_m": [0, 0, 0], "approach": [0, 0, 0]}]}': "must not be zero",
        '{"jaw": [{"centre_m": [0, 0, 0], "approach": [0, 0, 1], "closing": [0, 1, 1], "width_m": 0.01}]}': (
            "perpendicular"
        ),
        '{"unit": "mm", "suction": []}': "metres",
        '{"suction": [{"id": "x", "point_m": [0, 0, 0], "approach": [0, 0, 1]}, '
        '{"id": "x", "point_m": [0, 0, 0], "approach": [0, 0, 1]}]}': "used twice",
        "[1, 2]": "not a binpick grasp file",
    }
    for text, words in cases.items():
        path.write_text(text)
        with pytest.raises(InputError, match=words) as info:
            load_grasps(path)
        assert "\n" not in str(info.value) and str(path) in str(info.value)


def test_picks_are_given_in_the_base_frame_too(tmp_path, box_part, pick_settings):
    grasps = suction_grasps(box_part, pick_settings)
    T = lying(0.0, 0.0)
    plan = plan_one_box(T, grasps, box_part, seen_surface(T, box_part), pick_settings)
    T_base_from_cam = make_T(axis_angle_to_R(np.array([0.3, -0.2, 0.9]), 1.1), np.array([0.4, -0.1, 0.8]))
    path = tmp_path / "picks.json"
    save_picks(path, "c", "box", "suction", plan, T_base_from_cam)
    doc = load_picks(path)
    first = doc["picks"][0]
    assert np.allclose(
        np.array(first["base"]["grasp"]), T_base_from_cam @ np.array(first["camera"]["grasp"]), atol=1e-8
    )
    assert doc["calibrated"] is True
    path.write_text(json.dumps({"format": "something else"}))
    with pytest.raises(InputError, match="not a binpick pick list"):
        load_picks(path)


def test_pick_settings_refuse_a_non_rigid_base_transform(tmp_path):
    from binpick.errors import ParamsError

    raw = yaml.safe_load((ROOT / "params.yaml").read_text())
    raw["pick"]["T_base_from_cam"] = [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(raw))
    with pytest.raises(ParamsError, match="pick.T_base_from_cam must be a rigid"):
        load_params(path)
    raw["pick"]["T_base_from_cam"] = None
    raw["cell"]["T_flange_from_tcp"] = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.17], [0, 0, 1, 1]]
    path.write_text(yaml.safe_dump(raw))
    with pytest.raises(ParamsError, match="cell.T_flange_from_tcp must be a rigid"):
        load_params(path)


def test_the_tool_on_the_flange_follows_the_gripper_unless_set_and_then_must_agree_with_it(tmp_path):
    from binpick.errors import ParamsError

    raw = yaml.safe_load((ROOT / "params.yaml").read_text())
    raw["cell"]["T_flange_from_tcp"] = None
    path = tmp_path / "params.yaml"

    def flange_z(settings: dict) -> float:
        path.write_text(yaml.safe_dump(settings))
        T = np.asarray(load_params(path).cell.T_flange_from_tcp)
        assert np.allclose(T[:3, :3], np.eye(3)) and np.allclose(T[:2, 3], 0.0)
        return float(T[2, 3])

    s, j = raw["pick"]["suction"], raw["pick"]["jaw"]
    assert flange_z(raw) == pytest.approx(s["cup_length_m"] + s["tool_length_m"])
    raw["pick"]["gripper"] = "jaw"
    j.update(finger_length_m=0.08, pad_length_m=0.02, palm_depth_m=0.03, tool_length_m=0.1)
    assert flange_z(raw) == pytest.approx(0.08 - 0.01 + 0.03 + 0.1)
    # The length is where the gripper the checks sweep ends (its two descriptions agree).
    pick = load_params(path).pick
    for kind in ("suction", "jaw"):
        rearmost = min(float(q.lo[2]) if isinstance(q, Box) else q.z0 for q in gripper_primitives(pick, kind))
        assert -rearmost == pytest.approx(pick.model_copy(update={"gripper": kind}).gripper_length_m)
    # Set by hand 1 cm short of the modelled jaws: refused, naming both; set right: kept.
    raw["cell"]["T_flange_from_tcp"] = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.19], [0, 0, 0, 1]]
    path.write_text(yaml.safe_dump(raw))
    with pytest.raises(ParamsError, match=r"cell.T_flange_from_tcp puts the flange .* jaw gripper ends 0.200 m"):
        load_params(path)
    raw["cell"]["T_flange_from_tcp"][2][3] = 0.2
    assert flange_z(raw) == pytest.approx(0.2)
    # Without an arm nothing is mounted: not checked.
    raw["cell"].update(arm=None, T_flange_from_tcp=[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.19], [0, 0, 0, 1]])
    assert flange_z(raw) == pytest.approx(0.19)


def test_pick_settings_refuse_a_fallback_cone_narrower_than_the_cone(tmp_path):
    from binpick.errors import ParamsError

    text = (ROOT / "params.yaml").read_text()
    assert "fallback_cone_deg: 65.0" in text
    path = tmp_path / "params.yaml"
    path.write_text(text.replace("fallback_cone_deg: 65.0", "fallback_cone_deg: 30.0"))
    with pytest.raises(ParamsError, match="fallback_cone_deg"):
        load_params(path)


def test_a_part_the_gripper_failed_to_hold_is_not_picked_and_still_blocks_its_neighbour(box_part, pick_settings):
    grasps = suction_grasps(box_part, pick_settings)
    target = lying(0.0, 0.0)
    above = make_T(target[:3, :3], target[:3, 3] - np.array([0.0, 0.0, 0.045]))  # across the target's top
    free = lying(0.12, 0.0)
    T = np.stack([target, above, free])
    captured = np.concatenate([seen_surface(t, box_part) for t in T])
    args = (grasps, box_part.points_m, box_part.normals, box_part.centre_m, captured, FLOOR, pick_settings)
    plan = plan_picks(T, np.array([0.9, 0.5, 0.7]), *args, skip=np.array([False, True, False]))
    assert [p.pose_index for p in plan.picks] == [2]
    reasons = dict(plan.unpicked)
    assert reasons[1] == GRIP_FAILED and "part 1" in reasons[0]  # still an obstacle to the one below


def test_a_part_dragged_into_its_neighbour_along_a_tilted_approach_leaves_straight_up(box_part, pick_settings):
    """A box leaning 40 degrees (its face toward +y): its only grasps in a 45-degree cone come in
    40 degrees from straight down. A taller block stands 3.5 cm off its side along +y, out of the
    tool's way but in the part's: pulled back along the approach the part moves 3.2 cm along
    +y and runs into it. Straight up it comes free: the pick leaves that way (its post-grasp
    pose retreat_distance_m above the grasp) where pick.leave_straight_up allows it. A bar over the
    part blocks both ways."""
    R = axis_angle_to_R(np.array([1.0, 0.0, 0.0]), np.pi) @ axis_angle_to_R(np.array([1.0, 0.0, 0.0]), np.radians(40))
    lowest = transform_points(make_T(R, np.zeros(3)), box_part.points_m)[:, 2].max()
    T = make_T(R, np.array([0.0, 0.0, 0.5 - lowest]))  # resting on the floor
    block = trimesh.creation.box(extents=(0.06, 0.02, 0.03))
    block.apply_translation((0.0, 0.035, 0.5 - 0.015))
    block_top = block.vertices[:, 2].min() + 1e-4
    top = trimesh.sample.sample_surface_even(block, 4000, seed=1)[0]
    top = top[top[:, 2] < block_top]
    cones = pick_settings.model_copy(
        update={
            "approach_cone_deg": 45.0,
            "fallback_cone_deg": None,
            "leave_straight_up": True,
            "lift_past_parts": False,
        }
    )
    grasps = suction_grasps(box_part, cones)

    def plan(captured, settings=cones):
        return plan_one_box(T, grasps, box_part, captured, settings)

    (pick,) = plan(np.concatenate([seen_surface(T, box_part), top])).picks
    assert np.degrees(np.arccos(pick.T_cam_from_grasp[2, 2])) == pytest.approx(40.0, abs=1e-6)
    assert np.allclose(pick.retreat_cam, [0.0, 0.0, -1.0])
    assert np.allclose(
        pick.T_cam_from_postgrasp[:3, 3], pick.T_cam_from_grasp[:3, 3] + [0.0, 0.0, -cones.retreat_distance_m]
    )
    # Not allowed to leave straight up (the default): no pick, the part drags into the block.
    back_only = plan(
        np.concatenate([seen_surface(T, box_part), top]), cones.model_copy(update={"leave_straight_up": False})
    )
    assert not back_only.picks and "the part lifts into captured points" in back_only.unpicked[0][1]
    # Without the block the part leaves back along the approach, as the gripper came in.
    (free,) = plan(seen_surface(T, box_part)).picks
    assert np.allclose(free.retreat_cam, -free.T_cam_from_grasp[:3, 2])
    # A bar of measured points 1 cm over the part's low (-y) edge: in the way both ways out.
    edge = seen_surface(T, box_part)
    a, b = np.meshgrid(np.linspace(-0.04, 0.04, 80), np.linspace(-0.02, -0.01, 10))
    bar_z = edge[np.abs(edge[:, 1] + 0.015) < 0.005, 2].min() - 0.01
    bar = np.column_stack([a.ravel(), b.ravel(), np.full(a.size, bar_z)])
    blocked = plan(np.concatenate([edge, top, bar]))
    assert not blocked.picks and "the part lifts into captured points" in blocked.unpicked[0][1]
    # Nothing comes out free and only measured points (no bin) are in the way: with
    # lift_past_parts the part is taken past them, and the pick says what it pushes.
    (past,) = plan(np.concatenate([edge, top, bar]), cones.model_copy(update={"lift_past_parts": True})).picks
    assert past.lifts_past == ("captured points",)
    assert pick.lifts_past == () and free.lifts_past == ()
    # The block's face a bin wall found at import (its plane given): the bin is not pushed. Back
    # along the approach runs into it; the pick leaves straight up past the measured bar ...
    wall = np.array([[0.0, 1.0, 0.0, -0.025]])  # y = 0.025, the block's face toward the part

    def plan_in_bin(captured, **update):
        return plan_picks(
            T[None], np.array([0.9]), grasps, box_part.points_m, box_part.normals, box_part.centre_m, captured,
            FLOOR, cones.model_copy(update={"lift_past_parts": True, **update}), wall_planes=wall, wall_band_m=0.003,
        )  # fmt: skip

    (up_past,) = plan_in_bin(np.concatenate([edge, top, bar])).picks
    # Up, tilted away from the wall the part rests against (lift.LEAVE_WALL_DEG): -y here.
    leave = np.radians(LEAVE_WALL_DEG)
    assert up_past.lifts_past == ("captured points",)
    assert np.allclose(up_past.retreat_cam, [0.0, -np.sin(leave), -np.cos(leave)])
    # ... and allowed only back along the approach, it is not taken: the wall stops it.
    walled = plan_in_bin(np.concatenate([edge, top]), leave_straight_up=False)
    assert not walled.picks and "the part lifts into bin" in walled.unpicked[0][1]


def test_a_tool_moved_off_its_axis_hits_what_lies_on_its_way_and_not_beside_it(pick_settings):
    from binpick.picking.gripper import suction_primitives
    from binpick.picking.obstacles import moved_tool_hits

    tool = suction_primitives(pick_settings.suction)  # the tool body: 15 mm radius, 2-17 cm behind the lip
    points = np.array([[0.03, 0.0, -0.05], [0.03, 0.03, -0.05], [0.09, 0.0, -0.05]])
    sources = np.array([-1, 3, -2])

    def hits(offset):
        return moved_tool_hits(
            tool, np.eye(4), np.asarray(offset), cKDTree(points), points, sources, 0, np.zeros(3, bool), 0.002
        )

    # Moved 5 cm along x: through the first point, 3 cm from the second's line, 2.5 cm short of the third.
    assert hits([0.05, 0.0, 0.0]) == {CAPTURED}
    assert hits([0.08, 0.0, 0.0]) == {CAPTURED, BIN}
    assert hits([0.0, 0.0, -0.05]) == set()


def test_wall_points_carry_their_walls_normal_and_a_bins_faces_face_inward():
    from binpick.picking.obstacles import surface_normals

    # Two walls: x = 0.1 (normal +x) and y = -0.2 (normal -y); points on, near and off them.
    walls = np.array([[1.0, 0.0, 0.0, -0.1], [0.0, -1.0, 0.0, -0.2]])
    points = np.array([[0.1, 0.0, 0.5], [0.103, 0.05, 0.5], [0.0, -0.2, 0.6], [0.0, 0.0, 0.5]])
    normals = surface_normals(points, walls, 0.004)
    np.testing.assert_allclose(normals[:3], [[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    assert np.isnan(normals[3]).all()
    # A bin seen from above (its z toward the camera): every face's normal points to its middle.
    T_cam_from_bin = make_T(axis_angle_to_R(np.array([1.0, 0.0, 0.0]), np.pi), np.array([0.0, 0.0, 0.5]))
    box = BinBox(T_cam_from_bin, np.array([-0.15, -0.1, 0.0]), np.array([0.15, 0.1, 0.08]))
    points, inward = box.surface(0.01)
    middle = transform_points(T_cam_from_bin, np.array([[0.0, 0.0, 0.04]]))[0]
    to_middle = middle - points
    assert np.all(np.einsum("ij,ij->i", inward, to_middle) > 0)
    np.testing.assert_allclose(np.linalg.norm(inward, axis=1), 1.0)


def wall_with_a_hole(x_m: float, hole_half_m: float) -> np.ndarray:
    """Captured points of a wall x = x_m from the floor (z 0.5) to its rim (z 0.4), y -0.1..0.1,
    2 mm apart, less the stretch |y| < hole_half_m the part in front hid from the camera."""
    ys, zs = np.meshgrid(np.linspace(-0.1, 0.1, 101), np.linspace(0.4, 0.5, 51))
    keep = np.abs(ys.ravel()) >= hole_half_m
    return np.column_stack([np.full(keep.sum(), x_m), ys.ravel()[keep], zs.ravel()[keep]])


def test_the_unseen_stretch_of_a_wall_is_filled_on_its_plane_up_to_its_rim():
    from binpick.picking.obstacles import unseen_walls

    wall = np.array([1.0, 0.0, 0.0, -0.021])
    captured = wall_with_a_hole(0.021, 0.04)
    up = FLOOR[:3]  # toward the camera
    points, normals = unseen_walls(captured, wall[None], up, FLOOR, 0.004, 0.003, 0.004)
    # On the plane, inside the hole, between the floor and the rim; the hole covered.
    np.testing.assert_allclose(points[:, 0], 0.021, atol=1e-9)
    assert np.all(np.abs(points[:, 1]) < 0.04) and np.all((points[:, 2] >= 0.4 - 1e-9) & (points[:, 2] <= 0.5 + 1e-9))
    probes = np.column_stack([np.full(50, 0.021), np.linspace(-0.035, 0.035, 50), np.linspace(0.405, 0.495, 50)])
    assert cKDTree(points).query(probes)[0].max() <= 0.003
    np.testing.assert_allclose(normals, np.tile(wall[:3], (len(points), 1)))
    # A wall seen whole has no unseen stretch.
    assert len(unseen_walls(wall_with_a_hole(0.021, 0.0), wall[None], up, FLOOR, 0.004, 0.003, 0.004)[0]) == 0


def test_a_tool_into_the_stretch_of_a_wall_the_part_hid_is_refused(box_part, pick_settings):
    # The box lies 1 mm from a wall whose stretch behind it the camera did not see; a grasp near
    # the top face's wall-side edge brings the 30 mm tool through that stretch.
    T = lying(0.0, 0.0)
    wall = np.array([[1.0, 0.0, 0.0, -0.021]])
    captured = np.concatenate([seen_surface(T, box_part), wall_with_a_hole(0.021, 0.04)])
    edge = GraspSet(
        "suction", ["edge"], tool_frame(np.array([0.012, 0.0, 0.01]), np.array([0.0, 0.0, -1.0]))[None], np.zeros(1)
    )

    def plan(walls):
        return plan_picks(
            T[None], np.array([0.9]), edge, box_part.points_m, box_part.normals, box_part.centre_m, captured,
            FLOOR, pick_settings, wall_planes=walls, wall_band_m=0.004,
        )  # fmt: skip

    assert len(plan(None).picks) == 1  # the measured wall is 25 mm from the tool
    refused = plan(wall)
    assert not refused.picks and BIN in refused.unpicked[0][1]


def test_refusal_causes_are_listed_most_first_and_equals_by_name():
    """The reason a part got no pick lists its causes most frequent first; two as frequent come by
    name, whatever order the grasps met them in (picks.json is the same in every run)."""
    from collections import Counter

    from binpick.picking.plan import _most_first

    met = Counter(["the part lifts into part 5", "captured points", "captured points", "the part lifts into part 5"])
    met.update(["a tool collision"])
    assert _most_first(met) == [("captured points", 2), ("the part lifts into part 5", 2), ("a tool collision", 1)]
    assert _most_first(Counter(reversed(list(met.elements())))) == _most_first(met)
