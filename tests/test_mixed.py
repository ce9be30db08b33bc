"""Mixed bins: two kinds of part in one capture. Each part's poses land on its own instances, a
region claimed by two parts goes to the better-verified pose, and the picks form one list that
names each pick's part, in the priority given."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from conftest import box_part_model

from binpick.generation.scene import render_scene
from binpick.geometry.symmetry import symmetry_transforms
from binpick.geometry.transforms import make_T
from binpick.io.poses import PartPose
from binpick.picking.grasps import REVOLUTION_GRASP_STEPS, expand_by_symmetry, generate_grasps
from binpick.registration.model import train_ppf
from binpick.scene.mixed import claimed_points, pose_quality, process_mixed, resolve_conflicts
from binpick.scene.process import PartModels
from binpick.seeding import SceneSeeds
from binpick.view import ViewParams

from settings import PARAMS, changed

BOX_EXTENTS_M = (0.06, 0.04, 0.025)


def _lying(part, xy_m, turn_rad):
    """T_bin_from_model of a part lying on the floor: its thinnest axis up, turned about it."""
    v = part.mesh_vertices_m
    thin = int(np.argmin(v.max(axis=0) - v.min(axis=0)))
    R = np.eye(3)[[(thin + 1) % 3, (thin + 2) % 3, thin]]  # rows: the model's axes as seen from the bin
    c, s = np.cos(turn_rad), np.sin(turn_rad)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ R
    lifted = -(v @ R.T)[:, 2].min() + 0.0005
    centre = (v.min(axis=0) + v.max(axis=0)) / 2.0
    t = np.array([xy_m[0], xy_m[1], lifted]) - R @ np.array([centre[0], centre[1], 0.0])
    return make_T(R, t)


def _models(part, ppf, grasps=None):
    p = PARAMS.model_copy(update={"registration": changed(PARAMS.registration, mode="whole_scene")})
    return PartModels(part, ppf, None, p.import_capture, p.registration, grasps, p.pick, None)


@pytest.fixture(scope="module")
def box():
    return box_part_model(np.array(BOX_EXTENTS_M))


@pytest.fixture(scope="module")
def mixed_scene(t_joint, box):
    """Two T-joints and two boxes lying apart on the bin floor, rendered from above."""
    joints = np.stack([_lying(t_joint, (-0.07, -0.04), 0.3), _lying(t_joint, (0.07, 0.05), 2.0)])
    boxes = [_lying(box, (-0.07, 0.06), 0.8), _lying(box, (0.07, -0.06), -0.4)]
    meshes = []
    for T in boxes:
        mesh = trimesh.creation.box(extents=BOX_EXTENTS_M)
        mesh.apply_transform(T)
        meshes.append(mesh)
    scene = render_scene(
        t_joint,
        joints,
        PARAMS.generate,
        changed(PARAMS.camera, downscale=2),
        ViewParams.of_import(PARAMS.import_capture),
        np.random.default_rng(5),
        distractors=meshes,
    )
    T_cam_from_bin = scene.T_cam_from_model[0] @ np.linalg.inv(joints[0])
    return scene, {"t_joint": scene.T_cam_from_model, "box": np.stack([T_cam_from_bin @ T for T in boxes])}


def test_each_part_is_found_on_its_own_instances_and_no_pose_on_the_other_part(t_joint, box, mixed_scene):
    scene, truth = mixed_scene
    models = {}
    for part in (t_joint, box):
        ppf = train_ppf(
            part.points_m, part.normals, part.diameter_m, symmetry_transforms(part.symmetry), PARAMS.registration
        )
        grasps = expand_by_symmetry(
            generate_grasps(part, PARAMS.pick)["suction"], symmetry_transforms(part.symmetry, REVOLUTION_GRASP_STEPS)
        )
        models[part.name] = _models(part, ppf, grasps)
    H, W = scene.labels.shape
    result = process_mixed(
        scene.xyz_m.reshape(-1, 3),
        None,
        (H, W),
        models,
        SceneSeeds.of(PARAMS.seed, "mixed"),
        priority=["box"],
    )

    def centre(name, T):
        part = models[name].part
        return T[:3, :3] @ ((part.mesh_vertices_m.min(0) + part.mesh_vertices_m.max(0)) / 2) + T[:3, 3]

    for name in ("t_joint", "box"):
        found = [centre(name, p.T_cam_from_model) for p in result.poses[name]]
        wanted = [centre(name, T) for T in truth[name]]
        for w in wanted:  # every instance found by its own part
            assert min(np.linalg.norm(f - w) for f in found) < 0.01, (name, found, wanted)
        other = "box" if name == "t_joint" else "t_joint"
        for f in found:  # no pose of this part on an instance of the other (wrong_part_poses = 0)
            assert min(np.linalg.norm(f - centre(other, T)) for T in truth[other]) > 0.03, (name, f)
    # One list across the parts, each pick naming its part; the priority's part first.
    assert result.picks, result.unpicked
    named = [mp.part for mp in result.picks]
    assert set(named) <= {"t_joint", "box"} and named == sorted(named, key=lambda n: n != "box")
    for mp in result.picks:
        assert 0 <= mp.pick.pose_index < len(result.poses[mp.part])


def test_a_region_claimed_by_two_parts_goes_to_the_better_verified_pose():
    # Poses 0 (part a) and 1 (part b) claim the same points; pose 2 (part b) lies elsewhere and pose
    # 3 (part a) overlaps pose 2 by a sliver.
    claims = [np.arange(0, 100), np.arange(10, 110), np.arange(200, 300), np.arange(290, 380)]
    keep, lost = resolve_conflicts(claims, [0.6, 0.8, 0.5, 0.4], ["a", "b", "b", "a"])
    assert keep == [False, True, True, True] and lost == [(0, 1)]
    # The same part's poses never compete here (its own registration told them apart).
    keep, _ = resolve_conflicts(claims[:2], [0.6, 0.8], ["a", "a"])
    assert keep == [True, True]
    # Verification decides: a higher score on less support loses to a well-supported pose.
    weak = PartPose(np.eye(4), score=0.9, visible_support=0.4, seen_through=0.2)
    strong = PartPose(np.eye(4), score=0.7, visible_support=0.95, seen_through=0.0)
    assert pose_quality(strong) > pose_quality(weak)


def test_claimed_points_are_those_on_the_posed_surface():
    rng = np.random.default_rng(0)
    model = rng.uniform(-0.01, 0.01, (200, 3))
    T = make_T(np.eye(3), np.array([0.1, 0.0, 0.5]))
    near = model[:50] @ T[:3, :3].T + T[:3, 3] + 0.0005
    far = near + np.array([0.0, 0.0, 0.05])
    points = np.concatenate([near, far])
    assert claimed_points(points, model, T, 0.002).tolist() == list(range(50))


def test_a_capture_entry_naming_parts_runs_through_the_mixed_stage(t_joint, box, mixed_scene, tmp_path):
    """A capture entry with `parts: [box, t_joint]` (the stage reads the parts' built models from
    the project, as DVC runs it): picks.json names the parts in the entry's order, every pick and
    pose its part, each part's poses on its own instances; the pipeline plan lists the capture for
    the mixed stage only, and an entry naming both `part` and `parts` is refused in one line."""
    import yaml

    from binpick.errors import ParamsError
    from binpick.io.grasps import save_grasps
    from binpick.io.part_model import save_part_model
    from binpick.io.ply import PointCloudData, save_ply
    from binpick.io.ppf_model import save_ppf_model
    from binpick.layout import Layout
    from binpick.params import load_params
    from binpick.project import plan_pipeline
    from stages import mixed as mixed_stage
    from tests.conftest import ROOT

    scene, truth = mixed_scene
    layout = Layout(tmp_path)
    for part in (t_joint, box):
        save_part_model(layout.part_model(part.name), part)
        ppf = train_ppf(
            part.points_m, part.normals, part.diameter_m, symmetry_transforms(part.symmetry), PARAMS.registration
        )
        save_ppf_model(layout.ppf_model(part.name), ppf)
        save_grasps(layout.grasps(part.name), part.name, generate_grasps(part, PARAMS.pick), "generated")
    (tmp_path / "data/parts").mkdir(parents=True)
    trimesh.creation.box(extents=BOX_EXTENTS_M).export(tmp_path / "data/parts/box.stl")
    H, W = scene.labels.shape
    save_ply(tmp_path / "bin.ply", PointCloudData(xyz=scene.xyz_m.reshape(-1, 3) * 1000.0, rgb=None, shape=(H, W)))
    raw = yaml.safe_load((ROOT / "params.yaml").read_text())
    raw["parts"]["box"] = {"mesh": "data/parts/box.stl", "unit": "m"}
    raw["captures"]["bin"] = {"file": "bin.ply", "parts": ["box", "t_joint"], "unit": "mm"}
    raw["pick"]["T_base_from_cam"] = None  # the gripper's checks only: no arm stands by this bin
    params_path = tmp_path / "params.yaml"
    params_path.write_text(yaml.safe_dump(raw, sort_keys=False))

    plan, _ = plan_pipeline(tmp_path, load_params(params_path))
    assert "bin" in plan.mixed and "bin" not in plan.captures
    assert plan.mixed["bin"].as_vars()["parts"] == "box,t_joint"

    mixed_stage.run(params_path, "bin", tmp_path / "picks.json", tmp_path / "mixed.json", root=tmp_path)
    doc = json.loads((tmp_path / "picks.json").read_text())
    assert doc["parts"] == ["box", "t_joint"] and doc["picks"]
    assert all(p["part"] in ("box", "t_joint") for p in doc["picks"] + doc["poses"])
    parts = {"t_joint": t_joint, "box": box}
    for name, part in parts.items():
        middle = (part.mesh_vertices_m.min(0) + part.mesh_vertices_m.max(0)) / 2
        found = [np.asarray(p["T_cam_from_model"]) for p in doc["poses"] if p["part"] == name]
        centres = [T[:3, :3] @ middle + T[:3, 3] for T in found]
        for T in truth[name]:  # every instance found by its own part
            assert min(np.linalg.norm(c - (T[:3, :3] @ middle + T[:3, 3])) for c in centres) < 0.01, name
    assert len(doc["poses"]) == sum(len(t) for t in truth.values())

    raw["captures"]["bin"]["part"] = "box"
    params_path.write_text(yaml.safe_dump(raw, sort_keys=False))
    with pytest.raises(ParamsError, match="not both"):
        load_params(params_path)
