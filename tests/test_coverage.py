"""Which ways a part comes to rest leave it a grasp (binpick/picking/coverage.py): counted from
rotations and approaches set by hand, and on a tube whose end rings are narrower than the cup."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from binpick.geometry.transforms import axis_angle_to_R, make_T
from binpick.params import SymmetryParams
from binpick.part.model import make_part_model
from binpick.picking.coverage import (
    covered_share,
    describe_side,
    grasps_in_cone,
    resting_sides,
    smaller_cup_covering,
    stable_poses,
    suction_sides,
)


def test_a_part_resting_upside_down_has_no_grasp_from_its_top_face():
    """Grasps all approach the model's top face (along -z): resting as modelled they come straight
    down; turned over (180 degrees about x) straight up, so that side has none and the covered
    share is the upright pose's probability."""
    upright = make_T(np.eye(3), np.zeros(3))
    over = make_T(axis_angle_to_R(np.array([1.0, 0.0, 0.0]), np.pi), np.zeros(3))
    tilted = make_T(axis_angle_to_R(np.array([1.0, 0.0, 0.0]), np.radians(50.0)), np.zeros(3))
    T = np.stack([upright, over, tilted])
    approaches = np.tile([0.0, 0.0, -1.0], (4, 1))
    assert grasps_in_cone(T, approaches, 40.0).tolist() == [4, 0, 0]
    assert grasps_in_cone(T, approaches, 65.0).tolist() == [4, 0, 4]
    sides = resting_sides(T, np.array([0.5, 0.3, 0.2]), grasps_in_cone(T, approaches, 40.0))
    assert [s.n_grasps for s in sides] == [4, 0, 0]
    assert [describe_side(s.up_model) for s in sides[:2]] == ["its model +z up", "its model -z up"]
    assert covered_share(sides) == pytest.approx(0.5)


def test_poses_a_few_degrees_apart_are_one_side_with_its_poorest_count():
    a = make_T(np.eye(3), np.zeros(3))
    b = make_T(axis_angle_to_R(np.array([0.0, 1.0, 0.0]), np.radians(10.0)), np.zeros(3))
    sides = resting_sides(np.stack([a, b]), np.array([0.6, 0.4]), np.array([3, 1]))
    assert len(sides) == 1 and sides[0].probability == pytest.approx(1.0) and sides[0].n_grasps == 1


@pytest.fixture(scope="module")
def tube():
    """A tube 60 mm long, 40 mm across, its wall 7 mm thick, along its model z."""
    mesh = trimesh.creation.annulus(r_min=0.013, r_max=0.02, height=0.06, sections=48)
    return make_part_model("tube", mesh, SymmetryParams(kind="revolution"), 20000, np.random.default_rng(0), "m")


def test_a_tube_standing_on_its_end_ring_has_no_grasp_for_a_cup_wider_than_the_ring(tube, pick_settings):
    """The end rings are 7 mm wide: the 10 mm cup seals only on the outer wall, so a tube standing
    on end has no grasp within the cone and one lying on its side has; of the smaller cups tried
    (8, 6, 4 mm across) the largest whose lip stays on the ring with the pose a millimetre off
    either way (grasps.SEAL_OFFSET_M: 2 mm narrower than the ring), 4 mm, reaches every side."""
    assert pick_settings.suction.cup_radius_m == pytest.approx(0.005)
    T, probability = stable_poses(tube)
    assert probability.sum() == pytest.approx(1.0)
    sides = suction_sides(tube, pick_settings, T, probability)
    bare = [s for s in sides if s.n_grasps == 0]
    assert {describe_side(s.up_model) for s in bare} == {"its model +z up", "its model -z up"}
    assert all(abs(s.up_model[2]) < 0.1 for s in sides if s.n_grasps > 0)
    standing = sum(s.probability for s in bare)
    assert 0.0 < standing < 0.5
    assert covered_share(sides) == pytest.approx(1.0 - standing)
    assert smaller_cup_covering(tube, pick_settings, T, probability, 0.01) == pytest.approx(0.002)
