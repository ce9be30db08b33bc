"""Ingest of real CAD sizes and wrong units: exact diameters of large meshes in linear memory,
decimation, units checked against the camera and bin, assemblies refused."""

import subprocess
import sys

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from binpick.errors import InputError
from binpick.params import PartParams
from binpick.part.ingest import ingest_part
from binpick.part.model import (
    DIAMETER_DIRECTIONS,
    EXACT_DIAMETER_MAX_POINTS,
    _half_sphere_directions,
    _max_pair_distance,
    build_t_joint_mesh,
    diameter,
    simplify_mesh,
)
from tests.conftest import ROOT
from tests.settings import PARAMS


def test_diameter_directions_cover_the_sphere_within_the_stated_angle():
    dirs = _half_sphere_directions(DIAMETER_DIRECTIONS)
    both = np.vstack([dirs, -dirs])  # a width along u is the width along -u
    probes = np.random.default_rng(0).normal(size=(200_000, 3))
    probes /= np.linalg.norm(probes, axis=1, keepdims=True)
    chord, _ = cKDTree(both).query(probes)
    assert 2 * np.arcsin(chord.max() / 2) < 0.04  # the bound DIAMETER_MAX_REL_ERROR assumes


@pytest.mark.parametrize("seed", range(4))
def test_large_point_sets_get_the_exact_diameter(seed):
    rng = np.random.default_rng(seed)
    # Above EXACT_DIAMETER_MAX_POINTS (the estimate's path); the exact answer below costs n^2 / 2 pairs.
    pts = rng.normal(size=(EXACT_DIAMETER_MAX_POINTS + 5_000, 3)) * rng.uniform(0.2, 3.0, size=3)
    if seed % 2:  # every point on the hull: the hard case
        pts /= np.linalg.norm(pts, axis=1, keepdims=True)
        pts *= rng.uniform(0.5, 2.0, size=3)
    pts = pts @ trimesh.transformations.random_rotation_matrix(rng.random(3))[:3, :3].T
    hull = trimesh.convex.convex_hull(pts).vertices
    exact = _max_pair_distance(hull, hull)[0]
    found = diameter(pts)
    assert found <= exact * (1 + 1e-12)
    assert (exact - found) / exact < 1e-3


def test_a_million_vertex_sphere_in_linear_memory():
    sphere = trimesh.creation.uv_sphere(radius=30.0, count=[500, 500])  # ~250 k vertices, all on the hull
    assert np.isclose(diameter(sphere.vertices), 60.0, rtol=1e-3)


def test_large_meshes_are_decimated_keeping_their_shape():
    sphere = trimesh.creation.uv_sphere(radius=30.0, count=[200, 200])
    small = simplify_mesh(sphere, 20_000)
    assert len(small.faces) <= 20_000 < len(sphere.faces)
    radius = np.linalg.norm(small.vertices, axis=1)
    assert np.abs(radius - 30.0).max() < 0.1  # 0.1 mm on a 60 mm sphere
    assert simplify_mesh(small, 20_000) is small


def _params_for(tmp_path, unit):
    return PARAMS.model_copy(update={"parts": {"t_joint": PartParams(mesh="x.stl", unit=unit)}})


def _t_joint_in_inches(tmp_path):
    mesh = build_t_joint_mesh()
    mesh.apply_scale(1 / 25.4)  # a CAD export in inches: 2.7 "inches" long
    path = tmp_path / "t_joint_in.stl"
    mesh.export(path)
    return path


def test_an_inch_part_declared_mm_is_refused_naming_the_unit(tmp_path):
    with pytest.raises(
        InputError, match=r"read as 'mm' the part is 2\.691 mm across.*points per instance.*declare `unit: in`"
    ):
        ingest_part(_params_for(tmp_path, "mm"), "t_joint", _t_joint_in_inches(tmp_path))


def test_auto_guesses_the_unit_that_fits_the_camera_and_bin(tmp_path):
    model, metrics = ingest_part(_params_for(tmp_path, "auto"), "t_joint", _t_joint_in_inches(tmp_path))
    assert metrics["unit"] == "in"
    assert np.isclose(model.diameter_m, 0.068352, rtol=1e-4)


def test_a_part_far_larger_than_the_bin_is_refused(tmp_path):
    mesh = build_t_joint_mesh()
    mesh.apply_scale(20.0)  # 1.4 m in mm
    path = tmp_path / "huge.stl"
    mesh.export(path)
    with pytest.raises(InputError, match="larger than the bin"):
        ingest_part(_params_for(tmp_path, "mm"), "t_joint", path)


def test_an_assembly_of_separate_bodies_is_refused(tmp_path):
    a = trimesh.creation.box(extents=[30.0, 20.0, 10.0])
    b = trimesh.creation.box(extents=[30.0, 20.0, 10.0])
    b.apply_translation([120.0, 0.0, 0.0])  # 90 mm gap
    path = tmp_path / "two.stl"
    trimesh.util.concatenate([a, b]).export(path)
    with pytest.raises(InputError, match="2 separate bodies up to 90 mm apart: an assembly"):
        ingest_part(_params_for(tmp_path, "mm"), "t_joint", path)
    # Touching bodies (a nut on a bolt, nested shells) are one part, with a warning.
    b.apply_translation([-100.0, 5.0, 5.0])  # overlapping, no shared vertices
    trimesh.util.concatenate([a, b]).export(path)
    _, metrics = ingest_part(_params_for(tmp_path, "mm"), "t_joint", path)
    assert metrics["n_bodies"] == 2


def test_the_stage_reports_a_wrong_unit_in_one_line(tmp_path):
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "stages.ingest",
            "--part",
            "t_joint",
            "--mesh",
            str(_t_joint_in_inches(tmp_path)),
            "--out",
            str(tmp_path / "p.npz"),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert [line for line in proc.stderr.splitlines() if line.startswith("error:")][0].endswith("(parts.t_joint.unit)")
    assert not (tmp_path / "p.npz").exists()


def test_the_shared_inch_part(shared_data, tmp_path):
    path = shared_data / "parts" / "featuretype_inch.stl"
    with pytest.raises(InputError, match="declare `unit: in`"):
        ingest_part(_params_for(tmp_path, "mm"), "t_joint", path)
    _, metrics = ingest_part(_params_for(tmp_path, "auto"), "t_joint", path)
    assert metrics["unit"] == "in" and 140 < metrics["diameter_mm"] < 150
