"""Mixed bins: two kinds of part in one capture. Each part's poses land on its own instances, a
region claimed by two parts goes to the pose that explains more of the capture, and the picks
form one list that names each pick's part, in the priority given."""

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
from binpick.scene.mixed import claimed_points, explained_weight, pose_quality, process_mixed, resolve_conflicts
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


def test_a_region_claimed_by_two_parts_goes_to_the_pose_that_explains_more():
    # Poses 0 (part a) and 1 (part b) claim the same points; pose 2 (part b) lies elsewhere and pose
    # 3 (part a) overlaps pose 2 by a sliver.
    claims = [np.arange(0, 100), np.arange(10, 110), np.arange(200, 300), np.arange(290, 380)]
    keep, lost = resolve_conflicts(claims, [60.0, 80.0, 50.0, 36.0], ["a", "b", "b", "a"])
    assert keep == [False, True, True, True] and lost == [(0, 1)]
    # A small part's pose on a stretch of a long one (its claim inside the long one's) verifies
    # better than the long part's own pose, but explains far fewer of the measured points.
    long_part = PartPose(np.eye(4), score=0.42, visible_support=0.93, seen_through=0.0)
    on_it = PartPose(np.eye(4), score=0.55, visible_support=0.97, seen_through=0.0)
    long_claim, on_it_claim = np.arange(0, 2000), np.arange(500, 700)
    assert pose_quality(on_it) > pose_quality(long_part)
    weights = [explained_weight(long_part, long_claim), explained_weight(on_it, on_it_claim)]
    keep, lost = resolve_conflicts([long_claim, on_it_claim], weights, ["shaft", "pipe"])
    assert keep == [True, False] and lost == [(1, 0)]
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


def test_a_quota_keeps_the_first_picks_of_each_part_named_and_leaves_the_rest():
    """Quota {a: 1, b: 0}: of the list a0 b0 a1 c0 a2 the answer keeps a0 and c0 (c is not
    named: no limit), in their order; b0, a1, a2 are left over."""
    from binpick.picking.plan import Pick
    from binpick.scene.mixed import MixedPick, within_quota

    T = np.eye(4)
    order = [("a", 0), ("b", 0), ("a", 1), ("c", 0), ("a", 2)]
    picks = [MixedPick(part, Pick(i, "g", 0, 0.0, T, T, T, 1.0, 0.01, 0.0)) for part, i in order]
    kept, over = within_quota(picks, {"a": 1, "b": 0})
    assert [(m.part, m.pick.pose_index) for m in kept] == [("a", 0), ("c", 0)]
    assert [(m.part, m.pick.pose_index) for m in over] == [("b", 0), ("a", 1), ("a", 2)]
    assert within_quota(picks, {}) == (picks, [])


def test_training_scenes_mix_in_the_other_parts_named_and_dvc_tracks_their_meshes(t_joint, box, tmp_path):
    """generate.clutter.parts: a pile of T-joints with boxes mixed in holds both, each box a
    distractor (its 8 corners, not a T-joint instance) and the T-joints the scene's instances; the
    project lists the boxes for the T-joint's generate stage in a file that changes with the box's
    mesh, and a stage refuses to run while that list is stale."""
    import yaml

    from binpick.errors import ParamsError
    from binpick.generation.scene import _mixed_pile, generate_scene
    from binpick.io.pipeline_vars import load_distractors
    from binpick.project import check_project, verify_pipeline_vars
    from tests.conftest import ROOT

    g = changed(PARAMS.generate, clutter=changed(PARAMS.generate.clutter, parts_share=0.5))
    own, mixed_in = _mixed_pile(t_joint, [box], 10, g, np.random.default_rng(0), np.random.default_rng(1))
    assert len(own) + len(mixed_in) == 10 and len(own) >= 2 and len(mixed_in) >= 2
    assert all(len(m.vertices) == 8 for m in mixed_in)  # boxes, in the bin frame
    scene = generate_scene(t_joint, g, changed(PARAMS.camera, downscale=4), ViewParams(0.002, 0.006), 3, 10, [box])
    alone = generate_scene(t_joint, g, changed(PARAMS.camera, downscale=4), ViewParams(0.002, 0.006), 3, 10)
    assert len(scene.T_cam_from_model) < len(alone.T_cam_from_model) == 10
    assert np.unique(scene.labels[scene.labels >= 0]).size <= len(scene.T_cam_from_model)

    (tmp_path / "data/parts").mkdir(parents=True)
    (tmp_path / "data/parts/t_joint.stl").write_bytes((ROOT / "data/parts/t_joint.stl").read_bytes())
    trimesh.creation.box(extents=BOX_EXTENTS_M).export(tmp_path / "data/parts/box.stl")
    raw = yaml.safe_load((ROOT / "params.yaml").read_text())
    raw["parts"]["box"] = {"mesh": "data/parts/box.stl", "unit": "m"}
    raw["parts"]["t_joint"]["generate"] = {"clutter": {"parts": ["box", "t_joint"]}}  # itself: skipped
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(raw, sort_keys=False))
    plan = check_project(tmp_path)
    listed = plan.pipeline.parts["t_joint"].distractors
    assert listed and not plan.pipeline.parts["box"].distractors
    before = load_distractors(tmp_path / listed)
    assert [o.name for o in before] == ["box"]
    verify_pipeline_vars(tmp_path)
    trimesh.creation.box(extents=(0.05, 0.04, 0.025)).export(tmp_path / "data/parts/box.stl")
    with pytest.raises(ParamsError, match="t_joint"):
        verify_pipeline_vars(tmp_path)
    check_project(tmp_path)
    assert load_distractors(tmp_path / listed)[0].fingerprint != before[0].fingerprint
    verify_pipeline_vars(tmp_path)
