"""The in-process scene path on rendered bins: the poses it returns are the poses the parts were
rendered at, with the models loaded once for several captures."""

from __future__ import annotations

import numpy as np
import pytest

from binpick.generation.scene import generate_scene
from binpick.geometry.symmetry import symmetry_transforms
from binpick.io.part_model import save_part_model
from binpick.io.ppf_model import save_ppf_model
from binpick.metrics.pose import scene_pose_metrics
from binpick.registration.model import train_ppf
from binpick.scene.clean import clean
from binpick.scene.process import PartModels, process
from binpick.scene.register import register
from binpick.seeding import SceneSeeds
from binpick.view import ViewParams

from settings import PARAMS, changed


@pytest.fixture(scope="module")
def model_folder(t_joint, tmp_path_factory):
    """The part's models written as the stages write them."""
    folder = tmp_path_factory.mktemp("models")
    ppf = train_ppf(
        t_joint.points_m,
        t_joint.normals,
        t_joint.diameter_m,
        symmetry_transforms(t_joint.symmetry),
        PARAMS.registration,
    )
    save_part_model(folder / "part.npz", t_joint)
    save_ppf_model(folder / "ppf.npz", ppf)
    return folder


@pytest.fixture(scope="module")
def models(model_folder):
    """The part's models loaded back as the stages and the service do, without a network."""
    return PartModels.load(PARAMS, model_folder / "part.npz", model_folder / "ppf.npz", checkpoint=None)


def _capture(t_joint, seed: int, n_objects: int):
    """A rendered bin as a camera delivers it: organized xyz (H * W, 3), NaN = no return."""
    plain = PARAMS.generate.model_copy(
        update={"clutter": PARAMS.generate.clutter.off()}
    )  # the path, not clutter, is tested here
    scene = generate_scene(
        t_joint,
        plain,
        changed(PARAMS.camera, downscale=2),
        ViewParams.of_import(PARAMS.import_capture),
        seed,
        n_objects,
    )
    H, W = scene.labels.shape
    return scene, scene.xyz_m.reshape(-1, 3), (H, W)


def _pose_metrics(poses, scene, ppf):
    summary, _ = scene_pose_metrics(
        np.array([p.T_cam_from_model for p in poses]).reshape(-1, 4, 4),
        scene.T_cam_from_model,
        scene.visible_fraction,
        ppf.dense_points_m,
        ppf.symmetries,
        ppf.diameter_m,
    )
    return summary


def test_segments_recover_the_rendered_poses(t_joint, models):
    """With the true instances as segments, every well-visible part gets its rendered pose, each
    from its own segment, and no pose lies elsewhere."""
    scene, xyz, shape = _capture(t_joint, seed=31, n_objects=6)
    cloud = clean(xyz, None, shape, models.import_params, seed=0)
    labels = scene.labels.reshape(-1)[cloud.pixel_index].astype(np.int32)  # the true instance of each kept point
    result = register(cloud, labels, models.ppf, changed(models.register_params, mode="segments"), seed=0)
    summary = _pose_metrics(result.poses, scene, models.ppf)
    assert summary["pose_recall"] == 1.0 and summary["pose_precision"] == 1.0, summary
    assert all(p.segment >= 0 for p in result.poses) and len({p.segment for p in result.poses}) == len(result.poses)
    assert result.n_segments == int(labels.max()) + 1


@pytest.mark.parametrize("seed", [41, 42])
def test_the_whole_path_reuses_loaded_models_for_each_capture(t_joint, models, seed):
    """process() without a network matches the whole cleaned scene; the same PartModels serve
    every capture, and the same capture with the same seeds gives the same poses."""
    whole = PartModels(
        models.part, models.ppf, None, models.import_params, changed(models.register_params, mode="whole_scene")
    )
    scene, xyz, shape = _capture(t_joint, seed=seed, n_objects=5)
    result = process(xyz, None, shape, whole, SceneSeeds.of(PARAMS.seed, f"capture-{seed}"))
    summary = _pose_metrics(result.poses, scene, whole.ppf)
    assert summary["pose_precision"] == 1.0, summary
    assert summary["pose_recall"] >= 0.75, summary
    assert set(result.timings_s) == {"clean_s", "segment_s", "register_s"}
    assert (result.labels == -1).all() and len(result.labels) == len(result.cloud.points_m)
    again = process(xyz, None, shape, whole, SceneSeeds.of(PARAMS.seed, f"capture-{seed}"))
    # Bit for bit: the ICP's sums run in one fixed order (Open3D's did not).
    assert len(again.poses) == len(result.poses)
    for a, b in zip(again.poses, result.poses, strict=True):
        assert np.array_equal(a.T_cam_from_model, b.T_cam_from_model) and a.score == b.score


def test_segment_modes_need_labels(t_joint, models):
    _, xyz, shape = _capture(t_joint, seed=31, n_objects=2)
    cloud = clean(xyz, None, shape, models.import_params, seed=0)
    with pytest.raises(ValueError, match="needs segment labels"):
        register(cloud, None, models.ppf, changed(models.register_params, mode="segments"), seed=0)


def test_poses_where_the_camera_saw_through_are_dropped(t_joint, models):
    """Verification against what the camera saw: the rendered poses keep almost all of their
    surface on or behind the measurements; the same part lifted 3 cm toward the camera (floating
    in free space) is seen through."""
    from binpick.registration.verification import seen_through
    from binpick.registration.visibility import DepthView

    scene, xyz, shape = _capture(t_joint, seed=31, n_objects=6)
    cloud = clean(xyz, None, shape, models.import_params, seed=0)
    view = DepthView(cloud.seen_depth_m, cloud.seen_K)
    well_visible = [T for T, v in zip(scene.T_cam_from_model, scene.visible_fraction, strict=True) if v > 0.5]
    assert max(seen_through(models.ppf, T, view) for T in well_visible) < 0.05
    limit = models.register_params.max_seen_through
    T = well_visible[0].copy()
    lifted = T.copy()
    lifted[:3, 3] -= 0.03 * T[:3, 3] / np.linalg.norm(T[:3, 3])  # 3 cm along its ray, toward the camera
    assert seen_through(models.ppf, lifted, view) > 0.9 > limit
    # The whole path keeps every rendered pose.
    labels = scene.labels.reshape(-1)[cloud.pixel_index].astype(np.int32)
    result = register(cloud, labels, models.ppf, changed(models.register_params, mode="segments"), seed=0)
    assert result.n_seen_through == 0 and all(p.seen_through <= limit for p in result.poses)
    # ... and most of what the camera should see of each is measured (visible support).
    assert result.n_unsupported == 0 and min(p.visible_support for p in result.poses) > 0.8
    # ... and none reaches into the floor.
    assert result.n_in_the_floor == 0


def test_poses_reaching_into_the_floor_are_dropped(t_joint, models):
    """The rendered parts rest on the floor the cleaning found (their lowest point within a few
    millimetres of it); a part pushed 0.4 diameters along the floor's normal reaches that much
    deeper, and is refused, though the floor hides it from the seen-through check."""
    from binpick.registration.constants import MAX_BELOW_FLOOR_REL
    from binpick.registration.verification import below_floor_share, in_the_floor

    scene, xyz, shape = _capture(t_joint, seed=31, n_objects=6)
    cloud = clean(xyz, None, shape, models.import_params, seed=0)
    floor = cloud.floor_plane
    shares = [below_floor_share(models.ppf, T, floor) for T in scene.T_cam_from_model]
    assert max(shares) < 0.1 and not any(in_the_floor(models.ppf, T, floor) for T in scene.T_cam_from_model)
    T = scene.T_cam_from_model[int(np.argmax(shares))]
    pushed = T.copy()
    pushed[:3, 3] -= 0.4 * models.ppf.diameter_m * floor[:3]
    assert below_floor_share(models.ppf, pushed, floor) == pytest.approx(max(shares) + 0.4, abs=1e-9)
    assert in_the_floor(models.ppf, pushed, floor) and max(shares) + 0.4 > MAX_BELOW_FLOOR_REL
    # No floor found (NaN): nothing to check against.
    assert below_floor_share(models.ppf, pushed, np.full(4, np.nan)) == 0.0


def test_poses_on_points_the_network_calls_no_parts_are_dropped(t_joint, models):
    """The network's foreground head and the geometry must agree: with one part's points marked
    "no part", its pose is dropped and the others kept; with every part's points marked a part's,
    none is dropped. Unless the capture measures at least part_share_waived_at_support of the
    pose's surface in view: then the geometry alone keeps it."""
    scene, xyz, shape = _capture(t_joint, seed=31, n_objects=6)
    cloud = clean(xyz, None, shape, models.import_params, seed=0)
    labels = scene.labels.reshape(-1)[cloud.pixel_index].astype(np.int32)
    params = changed(models.register_params, mode="segments", part_share_waived_at_support=None)
    every = register(cloud, labels, models.ppf, params, seed=0, is_part=labels >= 0)
    assert every.n_not_part == 0 and len(every.poses) >= 3
    target = every.poses[0].segment
    is_part = (labels >= 0) & (labels != target)
    marked = register(cloud, labels, models.ppf, params, seed=0, is_part=is_part)
    assert marked.n_not_part == 1
    assert sorted(p.segment for p in marked.poses) == sorted(p.segment for p in every.poses if p.segment != target)
    support = every.poses[0].visible_support
    for waiver, kept in ((support, True), (min(1.0, support + 0.01), False)):
        again = register(
            cloud, labels, models.ppf, changed(params, part_share_waived_at_support=waiver), seed=0, is_part=is_part
        )
        assert (target in [p.segment for p in again.poses]) == kept and again.n_not_part == int(not kept)


def test_the_stages_give_a_capture_the_answer_the_service_gave(t_joint, model_folder, models, tmp_path):
    """Every step draws its seeds from the capture's content: the import and register stages, run
    on the capture file under any name, give the poses the in-process path (the service's) gave."""
    from binpick.io.capture import ImportOptions, load_capture
    from binpick.io.cloud import Segments, save_segments
    from binpick.io.ply import PointCloudData, save_ply
    from binpick.io.poses import load_poses
    from stages import import_capture
    from stages import register as register_stage

    scene, xyz, (H, W) = _capture(t_joint, 11, 4)
    capture = tmp_path / "kept-request-20261204.ply"
    save_ply(capture, PointCloudData(xyz=xyz * 1000.0, rgb=None, shape=(H, W)))
    frame = load_capture(capture, ImportOptions("mm"))
    served = process(
        frame.xyz_m, frame.rgb, frame.shape, models, SceneSeeds.of_capture(PARAMS.seed, frame.xyz_m, frame.rgb)
    )
    assert len(served.poses) >= 3

    params = PARAMS.model_copy(update={"registration": models.register_params})
    import_capture.run(params, capture, ImportOptions("mm"), tmp_path / "cloud.npz")
    n = len(served.cloud.points_m)
    save_segments(tmp_path / "segments.npz", Segments(np.full(n, -1, np.int32), np.ones(n, bool)))
    register_stage.run(
        params,
        "any-name",
        tmp_path / "cloud.npz",
        tmp_path / "segments.npz",
        model_folder / "ppf.npz",
        model_folder / "part.npz",
        tmp_path / "poses.json",
    )
    _, batch = load_poses(tmp_path / "poses.json")
    assert len(batch) == len(served.poses)
    for a, b in zip(batch, served.poses, strict=True):
        np.testing.assert_allclose(a.T_cam_from_model, b.T_cam_from_model, atol=1e-6)
