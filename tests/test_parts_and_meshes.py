import numpy as np
import pytest
import trimesh

from binpick.errors import InputError
from binpick.io.mesh import load_mesh, save_mesh
from binpick.io.part_model import load_part_model, save_part_model
from binpick.part.model import build_t_joint_mesh, diameter, sample_surface
from tests.conftest import ROOT


def test_shipped_default_part_is_the_built_one():
    shipped = trimesh.load(ROOT / "data" / "parts" / "t_joint.stl", force="mesh")
    built = build_t_joint_mesh()
    assert shipped.is_watertight and built.is_watertight
    assert np.allclose(shipped.bounds, built.bounds, atol=1e-4)
    assert np.isclose(shipped.volume, built.volume, rtol=1e-5)


def test_surface_sample_lies_on_the_mesh_with_outward_normals(t_joint):
    mesh = trimesh.Trimesh(t_joint.mesh_vertices_m, t_joint.mesh_faces)
    pts, normals = t_joint.points_m[:2000].astype(np.float64), t_joint.normals[:2000].astype(np.float64)
    _, dist, _ = trimesh.proximity.closest_point(mesh, pts)
    assert np.median(dist) < 1e-8 and dist.max() < 2e-5  # float32 storage; 0.02 mm at worst
    # Half a millimetre along the normal is outside, against it inside.
    assert not mesh.contains(pts + 5e-4 * normals).any()
    assert mesh.contains(pts - 5e-4 * normals).mean() > 0.99


def test_diameter_of_a_box():
    box = trimesh.creation.box(extents=[1.0, 2.0, 2.0])
    assert np.isclose(diameter(box.vertices), 3.0)
    pts, _ = sample_surface(box.vertices, box.faces, 5000, np.random.default_rng(0))
    assert diameter(pts) <= 3.0 + 1e-9


@pytest.mark.parametrize("unit,scale", [("mm", 1e-3), ("m", 1.0), ("in", 0.0254)])
def test_units_become_metres(tmp_path, unit, scale):
    box = trimesh.creation.box(extents=[10.0, 20.0, 30.0])
    path = tmp_path / "box.stl"
    save_mesh(path, box.vertices, box.faces)
    mesh, applied = load_mesh(path, unit)
    assert applied == unit
    assert np.allclose(sorted(mesh.extents), np.array([10.0, 20.0, 30.0]) * scale)


def test_auto_unit_guess(tmp_path):
    box = trimesh.creation.box(extents=[50.0, 20.0, 20.0])
    path = tmp_path / "box.ply"
    save_mesh(path, box.vertices, box.faces)
    mesh, applied = load_mesh(path, "auto")
    assert applied == "mm" and np.isclose(mesh.extents.max(), 0.05)


def test_bad_mesh_files_name_the_file(tmp_path):
    with pytest.raises(InputError, match="not found"):
        load_mesh(tmp_path / "missing.stl", "mm")
    empty = tmp_path / "empty.stl"
    empty.write_bytes(b"")
    with pytest.raises(InputError, match="empty.stl: file is empty"):
        load_mesh(empty, "mm")
    junk = tmp_path / "junk.stl"
    junk.write_bytes(b"solid x\nthis is not an stl\n")
    with pytest.raises(InputError, match="junk.stl"):
        load_mesh(junk, "mm")
    wrong = tmp_path / "part.step"
    wrong.write_text("ISO-10303-21;")
    with pytest.raises(InputError, match="unsupported mesh extension"):
        load_mesh(wrong, "mm")


def test_part_model_roundtrip(tmp_path, t_joint):
    save_part_model(tmp_path / "part.npz", t_joint)
    back = load_part_model(tmp_path / "part.npz")
    assert back.name == t_joint.name and back.symmetry == t_joint.symmetry
    assert np.array_equal(back.points_m, t_joint.points_m) and back.diameter_m == t_joint.diameter_m


@pytest.mark.parametrize(
    "name,unit,extent_m",
    [
        ("zju_three_way_pipe.stl", "mm", 0.062),
        ("featuretype_inch.stl", "in", 5 * 0.0254),
        ("hex_nut.ply", "mm", 0.046),
        ("ipa_gear_shaft.stl", "m", 0.436),
        ("ipa_ring_screw.stl", "m", 0.154),
    ],
)
def test_real_parts_load_in_metres(shared_data, name, unit, extent_m):
    mesh, _ = load_mesh(shared_data / "parts" / name, unit)
    assert np.isclose(mesh.extents.max(), extent_m, rtol=0.02)
    assert mesh.is_watertight


@pytest.mark.parametrize(
    "name", ["ipa_gear_shaft", "ipa_ring_screw", "zju_three_way_pipe", "hex_nut", "featuretype_inch"]
)
def test_declared_symmetries_of_the_benchmark_parts_map_each_onto_itself(shared_data, name):
    """A wrong symmetry turns right poses into errors (and the reverse): every declared transform
    must put the part's surface back onto itself, within the 1 mm of sensor noise the benchmarks
    add (the gear shaft's teeth break its revolution by 0.8 mm)."""
    import trimesh

    from binpick.geometry.symmetry import symmetry_transforms
    from flows.bench.parts import SHARED_PARTS

    spec = SHARED_PARTS[name]
    mesh, _ = load_mesh(shared_data / "parts" / spec.file, spec.unit)
    sample = mesh.sample(1500, seed=0)
    transforms = symmetry_transforms(spec.symmetry, revolution_steps=12)
    worst = max(trimesh.proximity.closest_point(mesh, sample @ S[:3, :3].T + S[:3, 3])[1].max() for S in transforms)
    assert worst < 0.001, worst
