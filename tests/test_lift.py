"""The grasped part's way out of the heap (binpick/picking/lift.py): a neighbour lying across it
is run into, one touching its side or lying behind the move is not; known answers from boxes
placed by hand."""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from binpick.picking.lift import (
    LEAVE_WALL_DEG,
    across_the_way_out,
    in_footprint,
    lift_blockers,
    walls_touched,
    way_outs,
)

UP = np.array([0.0, 0.0, 1.0])  # this test's frame: z up (the camera's frame is any rigid turn of it)
RADIUS_M, CONTACT_M = 0.003, 0.011


def box_surface(extents: tuple[float, float, float], centre: tuple[float, float, float], n: int = 6000):
    mesh = trimesh.creation.box(extents=extents)
    mesh.apply_translation(centre)
    points, faces = trimesh.sample.sample_surface_even(mesh, n, seed=1)
    return np.asarray(points), mesh.face_normals[faces]


def blockers(obstacles: list[np.ndarray], moves=None) -> set[int]:
    part, normals = box_surface((0.06, 0.04, 0.02), (0.0, 0.0, 0.01))
    sources = np.concatenate([np.full(len(o), k) for k, o in enumerate(obstacles)])
    return set(
        lift_blockers(
            part, normals, moves or [(UP, 0.05), (UP, 0.1)], np.concatenate(obstacles), sources, RADIUS_M, CONTACT_M
        )
    )


def test_a_neighbour_lying_across_the_part_is_run_into_and_one_beside_it_is_not():
    # A bar across the part's top, resting on it (its top surface 2 cm up), and a box touching
    # the part's side, as tall: only the bar is in the way up.
    across, _ = box_surface((0.02, 0.12, 0.02), (0.0, 0.0, 0.03))
    beside, _ = box_surface((0.06, 0.04, 0.02), (0.0, 0.0401, 0.01))
    assert blockers([across, beside]) == {0}
    # Without the bar: free.
    assert blockers([beside]) == set()


def test_what_lies_behind_or_beyond_the_move_is_not_run_into():
    # The floor under the part and a bar 0.3 m above it (beyond the 0.15 m the part travels).
    floor = np.column_stack([np.random.default_rng(2).uniform(-0.1, 0.1, (4000, 2)), np.full(4000, -0.001)])
    high, _ = box_surface((0.02, 0.12, 0.02), (0.0, 0.0, 0.33))
    assert blockers([floor, high]) == set()
    # The same bar 0.1 m up is within the move.
    low, _ = box_surface((0.02, 0.12, 0.02), (0.0, 0.0, 0.13))
    assert blockers([floor, low]) == {1}
    # Moved sideways (along x) first, out from under a shelf over half the part, then up: free.
    shelf, _ = box_surface((0.1, 0.1, 0.01), (-0.06, 0.0, 0.05))
    assert blockers([shelf]) == {0}
    assert blockers([shelf], [(np.array([1.0, 0.0, 0.0]), 0.08), (UP, 0.1)]) == set()


def test_a_tilted_approach_may_also_leave_straight_up_and_a_vertical_one_only_back():
    tilted = np.array([0.0, np.sin(np.radians(40.0)), -np.cos(np.radians(40.0))])
    back, up = way_outs(tilted, UP)
    assert np.allclose(back, -tilted) and np.allclose(up, UP)
    # Within a few degrees of straight down the two ways are one.
    (only,) = way_outs(np.array([0.0, np.sin(np.radians(3.0)), -np.cos(np.radians(3.0))]), UP)
    assert only[2] > 0.99
    # Not allowed (pick.leave_straight_up false): back only, however tilted.
    (back_only,) = way_outs(tilted, UP, straight_up=False)
    assert np.allclose(back_only, -tilted)


def test_a_part_against_a_wall_slides_up_along_it_and_is_not_pushed_into_it():
    part, normals = box_surface((0.06, 0.04, 0.02), (0.0, 0.0, 0.01))
    # A bin wall whose inner face cuts 1 mm into the part's side (a pose a millimetre off).
    ys, zs = np.meshgrid(np.linspace(-0.08, 0.08, 81), np.linspace(0.0, 0.2, 101))
    wall = np.column_stack([np.full(ys.size, 0.029), ys.ravel(), zs.ravel()])
    inward = np.tile([-1.0, 0.0, 0.0], (len(wall), 1))
    sources = np.zeros(len(wall), int)
    straight_up = [(UP, 0.05), (UP, 0.1)]
    # Its points alone, their surface unknown, are run into on the way up ...
    assert set(lift_blockers(part, normals, straight_up, wall, sources, RADIUS_M, CONTACT_M)) == {0}
    # ... its face known, the part slides up along it ...
    assert not lift_blockers(part, normals, straight_up, wall, sources, RADIUS_M, CONTACT_M, inward)
    # ... but pulled out toward it (30 degrees off the vertical) it is pushed into the wall.
    toward = np.array([np.sin(np.radians(30.0)), 0.0, np.cos(np.radians(30.0))])
    assert set(lift_blockers(part, normals, [(toward, 0.05)], wall, sources, RADIUS_M, CONTACT_M, inward)) == {0}


def test_the_footprint_filter_keeps_every_point_within_the_radius_of_the_footprint():
    # A long thin footprint turned 30 degrees (a gear shaft seen along its lift) and points
    # scattered over a bin ten times its size: every point a brute-force search puts within the
    # radius is kept, and points farther than the radius plus two cells' diagonal are not.
    rng = np.random.default_rng(3)
    along = np.column_stack([rng.uniform(-0.22, 0.22, 4000), rng.uniform(-0.02, 0.02, 4000)])
    c, s = np.cos(np.radians(30.0)), np.sin(np.radians(30.0))
    footprint = along @ np.array([[c, s], [-s, c]])
    points = rng.uniform(-0.5, 0.5, (50_000, 2))
    kept = in_footprint(footprint, points, RADIUS_M)
    nearest, _ = cKDTree(footprint).query(points)
    assert np.all(kept[nearest <= RADIUS_M])
    assert np.any(nearest <= RADIUS_M)
    assert not np.any(kept[nearest > RADIUS_M + 2 * np.sqrt(2) * RADIUS_M])
    assert kept.sum() < 0.1 * len(points)


def test_the_points_across_the_way_out_hold_every_blocker_of_every_way_within_the_cone():
    # 300 small boxes scattered about the part, 5-60 mm up; ways out tilted up to 60 degrees in
    # eight directions, 5 cm along and then up: the blockers found among the points kept are
    # those found among all, and most points are left out.
    rng = np.random.default_rng(5)
    part, normals = box_surface((0.06, 0.04, 0.02), (0.0, 0.0, 0.01))
    centres = np.column_stack([rng.uniform(-0.4, 0.4, (300, 2)), rng.uniform(0.005, 0.06, 300)])
    boxes = [box_surface((0.01, 0.01, 0.01), tuple(c), n=60)[0] for c in centres]
    obstacles = np.concatenate(boxes)
    sources = np.repeat(np.arange(len(boxes)), [len(b) for b in boxes])
    tilt = np.radians(60.0)
    reach = (0.05 + CONTACT_M) * np.sin(tilt) + RADIUS_M
    kept = across_the_way_out(part, UP, obstacles, reach)
    assert kept.sum() < 0.2 * len(obstacles)
    found_any = False
    for angle in np.radians(np.arange(0.0, 360.0, 45.0)):
        for t in (0.0, tilt / 2, tilt):
            way = np.array([np.sin(t) * np.cos(angle), np.sin(t) * np.sin(angle), np.cos(t)])
            moves = [(way, 0.05), (UP, 0.1)]
            every = lift_blockers(part, normals, moves, obstacles, sources, RADIUS_M, CONTACT_M)
            among_kept = lift_blockers(part, normals, moves, obstacles[kept], sources[kept], RADIUS_M, CONTACT_M)
            assert among_kept == every
            found_any |= bool(every)
    assert found_any


def test_a_part_resting_against_walls_leaves_them_and_does_not_slide_along_them():
    # The box (0.06 x 0.04 x 0.02, centred at the origin, on the floor) in a corner: a wall 1 mm
    # off its +x side (x = 0.031) and one on its -y side (y = -0.02); a third 0.1 m off.
    part, _ = box_surface((0.06, 0.04, 0.02), (0.0, 0.0, 0.01))
    planes = np.array([[1.0, 0.0, 0.0, -0.031], [0.0, -2.0, 0.0, -0.04], [0.0, 1.0, 0.0, -0.12]])
    touched = walls_touched(part, np.array([0.0, 0.0, 0.01]), planes, 0.002)
    assert np.allclose(sorted(map(tuple, touched)), [(-1.0, 0.0, 0.0), (0.0, 1.0, 0.0)])
    leave = np.radians(LEAVE_WALL_DEG)
    # Straight down: up, tilted away from both walls alike.
    (up,) = way_outs(-UP, UP, walls=touched)
    assert np.allclose(up, [-np.sin(leave) / np.sqrt(2), np.sin(leave) / np.sqrt(2), np.cos(leave)])
    # Against one wall: an approach tilted 20 degrees away from it leaves back along it first; one
    # tilted toward the wall (back along it drags the part into the wall) only up, tilted away.
    one = touched[:1]
    tilt = np.radians(20.0)
    away, toward = np.array([np.sin(tilt), 0.0, -np.cos(tilt)]), np.array([-np.sin(tilt), 0.0, -np.cos(tilt)])
    back, up = way_outs(away, UP, walls=one)
    assert np.allclose(back, -away) and np.allclose(up, [-np.sin(leave), 0.0, np.cos(leave)])
    (up_only,) = way_outs(toward, UP, walls=one)
    assert np.allclose(up_only, [-np.sin(leave), 0.0, np.cos(leave)])
    # No wall touched: as before, and straight_up false keeps the approach's way alone.
    assert len(way_outs(toward, UP, walls=np.zeros((0, 3)))) == 2
    (only_back,) = way_outs(toward, UP, straight_up=False, walls=one)
    assert np.allclose(only_back, -toward)
