import numpy as np
import pytest

from binpick.generation.scene import generate_scene
from binpick.geometry.pointcloud import estimate_normals, voxel_downsample_indices
from binpick.geometry.symmetry import symmetry_transforms
from binpick.geometry.transforms import axis_angle_to_R, make_T, transform_points
from binpick.io.poses import PartPose
from binpick.io.ppf_model import load_ppf_model, save_ppf_model
from binpick.metrics.pose import pose_errors
from binpick.registration.matching import match_segment
from binpick.registration.model import train_ppf
from binpick.registration.verification import score_pose
from binpick.view import ViewParams

from settings import PARAMS, changed


@pytest.fixture(scope="module")
def ppf(t_joint):
    return train_ppf(t_joint.points_m, t_joint.normals, t_joint.diameter_m, symmetry_transforms(t_joint.symmetry), PARAMS.registration)


def test_ppf_model_roundtrip(tmp_path, ppf):
    save_ppf_model(tmp_path / "ppf.npz", ppf)
    back = load_ppf_model(tmp_path / "ppf.npz")
    assert np.array_equal(back.keys, ppf.keys) and back.angle_bins == ppf.angle_bins
    assert np.all(np.diff(back.keys) >= 0)
    assert back.near_symmetries.shape == ppf.near_symmetries.shape == (0, 4, 4)


def test_a_ppf_model_written_before_near_symmetries_reads_as_having_none(tmp_path, ppf):
    save_ppf_model(tmp_path / "ppf.npz", ppf)
    with np.load(tmp_path / "ppf.npz") as z:
        older = {k: z[k] for k in z.files if k != "near_symmetries"}
    np.savez(tmp_path / "old.npz", **older)
    back = load_ppf_model(tmp_path / "old.npz")
    assert back.near_symmetries.shape == (0, 4, 4) and np.array_equal(back.keys, ppf.keys)


def test_recovers_the_pose_of_a_rendered_part(t_joint, ppf):
    scene = generate_scene(t_joint, PARAMS.generate, changed(PARAMS.camera, downscale=2), ViewParams(0.002, 0.006), seed=21, n_objects=4)
    xyz, labels = scene.xyz_m.reshape(-1, 3), scene.labels.reshape(-1)
    syms = symmetry_transforms(t_joint.symmetry)
    checked = 0
    for i, T_gt in enumerate(scene.T_cam_from_model):
        if scene.visible_fraction[i] < 0.6:
            continue
        pts = xyz[(labels == i) & np.isfinite(xyz[:, 2])]
        pts = pts[voxel_downsample_indices(pts, 0.002)]
        est = match_segment(ppf, pts, estimate_normals(pts, 0.006), PARAMS.registration, np.random.default_rng(0))
        e = pose_errors(est.T_cam_from_model, T_gt, t_joint.points_m, syms, t_joint.diameter_m)
        assert e["rot_err_deg"] < 2.0 and e["trans_err_mm"] < 2.0, e
        assert 0.5 < est.score <= 1.0
        checked += 1
    assert checked >= 2


def test_score_drops_for_a_wrong_pose(t_joint, ppf):
    T = make_T(np.eye(3), np.array([0.0, 0.0, 0.5]))
    p = transform_points(T, t_joint.points_m[::4])
    visible = p[t_joint.normals[::4] @ T[:3, :3].T @ np.array([0, 0, 1.0]) < 0]
    good = score_pose(ppf, T, visible, 0.0015)
    # About z: the main pipe lies along x, and turning about x would map it onto itself.
    wrong = score_pose(ppf, T @ make_T(axis_angle_to_R(np.array([0, 0, 1.0]), 0.6), np.zeros(3)), visible, 0.0015)
    assert good > 0.9 and wrong < 0.5


def test_duplicate_poses_are_suppressed_up_to_symmetry(ppf):
    from binpick.registration.matching import suppress_duplicates

    T = make_T(np.eye(3), np.array([0.0, 0.0, 0.5]))
    twin = T @ ppf.symmetries[1]  # the same physical pose, written the other way round
    other = make_T(np.eye(3), np.array([0.1, 0.0, 0.5]))
    ests = [PartPose(twin, 0.6), PartPose(T, 0.7), PartPose(other, 0.5)]
    assert suppress_duplicates(ppf, ests, PARAMS.registration) == [1, 2]


def test_a_wrong_fit_on_a_fragment_of_a_part_found_whole_is_suppressed(t_joint, ppf):
    """One part split into two segments: the big one gives the right pose, the fragment a pose
    turned 30 degrees and shifted (no pose duplicate). The fragment's supporting points are all
    explained by the right pose, so it goes; a second part elsewhere stays."""
    from binpick.registration.matching import suppress_duplicates

    scene = generate_scene(t_joint, PARAMS.generate, changed(PARAMS.camera, downscale=4), ViewParams(0.002, 0.006), seed=21, n_objects=6)
    pts = scene.view_points_m.astype(np.float64)
    right, elsewhere = scene.T_cam_from_model[0], scene.T_cam_from_model[1]
    wrong = right @ make_T(axis_angle_to_R(np.array([0.0, 0.0, 1.0]), np.radians(30)), np.array([0.004, 0.0, 0.0]))
    ests = [PartPose(right, 0.7), PartPose(wrong, 0.5), PartPose(elsewhere, 0.4)]
    assert suppress_duplicates(ppf, ests, PARAMS.registration) == [0, 1, 2]  # pose duplicates only
    assert suppress_duplicates(ppf, ests, PARAMS.registration, pts) == [0, 2]


def test_whole_scene_matching_finds_every_part_without_segments(t_joint, ppf):
    """The network's view of a rendered bin, no labels: every pickable part is found once, at
    its ground-truth pose, and nothing else."""
    from binpick.metrics.pose import scene_pose_metrics
    from binpick.registration.matching import match_scene

    scene = generate_scene(t_joint, PARAMS.generate, changed(PARAMS.camera, downscale=4), ViewParams(0.002, 0.006), seed=21, n_objects=6)
    found = match_scene(ppf, scene.view_points_m.astype(np.float64), scene.view_normals.astype(np.float64), PARAMS.registration, np.random.default_rng(0), max_instances=10)
    summary, _ = scene_pose_metrics(
        np.array([e.T_cam_from_model for e in found]).reshape(-1, 4, 4), scene.T_cam_from_model, scene.visible_fraction,
        ppf.dense_points_m, ppf.symmetries, ppf.diameter_m,
    )
    assert summary["n_pickable"] >= 4
    assert summary["pose_recall"] >= 0.8 and summary["pose_precision"] >= 0.8, summary
    assert summary["rot_err_deg_median"] < 1.0 and summary["trans_err_mm_median"] < 1.0
    assert all(0.0 <= e.score <= 1.0 for e in found)
    assert [e.score for e in found] == sorted((e.score for e in found), reverse=True)


def test_whole_scene_matching_skips_parts_already_found(t_joint, ppf):
    """With the poses of some parts given as found (as the segments mode gives them), the
    whole-scene pass returns the other parts only."""
    from binpick.metrics.pose import scene_pose_metrics
    from binpick.registration.matching import match_scene

    scene = generate_scene(t_joint, PARAMS.generate, changed(PARAMS.camera, downscale=4), ViewParams(0.002, 0.006), seed=21, n_objects=6)
    known, rest = scene.T_cam_from_model[:3], scene.T_cam_from_model[3:]
    found = match_scene(ppf, scene.view_points_m.astype(np.float64), scene.view_normals.astype(np.float64), PARAMS.registration, np.random.default_rng(0), known=list(known))
    summary, _ = scene_pose_metrics(
        np.array([e.T_cam_from_model for e in found]).reshape(-1, 4, 4), rest, scene.visible_fraction[3:],
        ppf.dense_points_m, ppf.symmetries, ppf.diameter_m,
    )
    assert summary["pose_precision"] == 1.0 and summary["pose_recall"] >= 2 / 3, summary


def test_scene_pairs_match_the_training_features():
    """The scene side (one compiled pass) must quantise exactly like the model table, built from
    _features, _keys and _alpha, or votes miss their model pairs."""
    from binpick.registration.model import _align_to_x, _alpha, _features, _keys
    from binpick.registration.voting import _scene_pairs

    rng = np.random.default_rng(3)
    pts = rng.uniform(-0.05, 0.05, (300, 3))
    nrm = rng.normal(size=(300, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    refs = np.sort(rng.choice(300, 40, replace=False))
    radius, step, bins = 0.06, 0.004, 30
    T = _align_to_x(pts, nrm)
    starts, keys, alpha = _scene_pairs(pts, nrm, np.ascontiguousarray(T[:, :3, :3]), np.ascontiguousarray(T[:, :3, 3]), refs, radius, step, bins)
    first = np.concatenate([np.full(starts[a + 1] - starts[a], r) for a, r in enumerate(refs)])
    d = np.linalg.norm(pts[refs][:, None] - pts[None], axis=2)
    expected_second = [np.flatnonzero((d[a] <= radius) & (np.arange(300) != r)) for a, r in enumerate(refs)]
    second = np.concatenate(expected_second)
    assert len(keys) == len(second) > 1000
    assert np.array_equal(keys, _keys(_features(pts[first], nrm[first], pts[second], nrm[second]), step, bins))
    assert np.allclose(alpha, _alpha(T[first], pts[second]), atol=1e-9)


def test_a_segment_a_found_pose_explains_is_a_fragment_and_one_holding_another_part_is_not(t_joint, ppf):
    """Segments cut from a rendered scene by its true labels: a part's own points are explained
    by its true pose, not by a pose turned away or by another part's; its points together with a
    second part's are not explained by the first part's pose alone."""
    from binpick.registration.matching import explained_by

    scene = generate_scene(t_joint, PARAMS.generate, changed(PARAMS.camera, downscale=2), ViewParams(0.002, 0.006), seed=21, n_objects=4)
    xyz, labels = scene.xyz_m.reshape(-1, 3), scene.labels.reshape(-1)
    a, b = np.argsort(-scene.visible_fraction)[:2]
    part_a = xyz[(labels == a) & np.isfinite(xyz[:, 2])].astype(np.float64)
    part_b = xyz[(labels == b) & np.isfinite(xyz[:, 2])].astype(np.float64)
    T_a, T_b = scene.T_cam_from_model[a], scene.T_cam_from_model[b]
    turned = T_a @ make_T(axis_angle_to_R(np.array([0.0, 0.0, 1.0]), np.radians(40)), np.zeros(3))
    reg = PARAMS.registration
    assert explained_by(ppf, part_a, reg, [T_a]) and explained_by(ppf, part_a, reg, [T_b, T_a])
    assert not explained_by(ppf, part_a, reg, []) and not explained_by(ppf, part_a, reg, [turned]) and not explained_by(ppf, part_a, reg, [T_b])
    assert not explained_by(ppf, np.concatenate([part_a, part_b]), reg, [T_a])
