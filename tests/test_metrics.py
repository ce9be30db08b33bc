import numpy as np

from binpick.geometry.symmetry import symmetry_transforms
from binpick.geometry.transforms import axis_angle_to_R, make_T
from binpick.metrics.pose import (
    add,
    add_s,
    mssd,
    pose_errors,
    rotation_error_deg,
    scene_pose_metrics,
    translation_error_m,
)
from binpick.metrics.segmentation import iou_matrix, scene_counts
from binpick.params import SymmetryParams


def test_iou_and_counts_on_a_tiny_case():
    gt = np.array([0, 0, 0, 0, 1, 1, 1, 1, -1, -1])
    pred = np.array([5, 5, 5, -1, 7, 7, 7, 7, 7, 7])
    iou, p_ids, g_ids = iou_matrix(pred, gt)
    assert p_ids.tolist() == [5, 7] and g_ids.tolist() == [0, 1]
    assert np.allclose(iou, [[0.75, 0.0], [0.0, 4 / 6]])
    c = scene_counts(pred, gt, 0.5).summary()
    assert c["precision"] == 1.0 and c["recall"] == 1.0
    assert np.isclose(c["mean_coverage"], (0.75 + 4 / 6) / 2)


def test_one_to_one_differs_from_the_reference_variant():
    # One ground-truth instance split into parts of IoU 0.6 and 0.4: with one-to-one matching
    # only one counts at IoU 0.35; the reference code counts both.
    c = scene_counts(np.array([0] * 6 + [1] * 4), np.zeros(10, int), 0.35)
    assert c.tp == 1 and c.tp_reference == 2


def test_tiny_ground_truth_is_ignored():
    gt = np.array([0] * 50 + [1] * 3)
    pred = np.array([0] * 50 + [-1] * 3)
    c = scene_counts(pred, gt, 0.5, min_gt_points=10).summary()
    assert c["recall"] == 1.0 and c["n_gt"] == 1


def test_pose_errors_recover_known_offsets():
    pts = np.random.default_rng(0).uniform(-0.03, 0.03, (500, 3))
    T = make_T(axis_angle_to_R(np.array([0, 0, 1.0]), 0.3), np.array([0.0, 0.0, 0.5]))
    shifted = T.copy()
    shifted[:3, 3] += [0.002, 0.0, 0.0]
    assert np.isclose(
        translation_error_m(shifted, T, np.array([5.0, 0, 0])), 0.002
    )  # a pure shift moves every point alike
    assert np.isclose(add(shifted, T, pts), 0.002)
    rotated = T @ make_T(axis_angle_to_R(np.array([1.0, 0, 0]), np.radians(10)), np.zeros(3))
    assert np.isclose(rotation_error_deg(rotated, T), 10.0)
    e = pose_errors(shifted, T, pts, np.eye(4)[None], 0.1)
    assert np.isclose(e["trans_err_mm"], 2.0) and e["add_ok"] == 1.0 and e["ok_5deg_5mm"] == 1.0


def test_symmetric_twin_has_no_error():
    syms = symmetry_transforms(SymmetryParams(kind="n_fold", axis=(0, 1, 0), order=2))
    # A point set with the same 2-fold symmetry about y.
    half = np.random.default_rng(1).uniform(-0.03, 0.03, (300, 3))
    pts = np.vstack([half, half * [-1, 1, -1]])
    T = make_T(np.eye(3), np.array([0, 0, 0.5]))
    twin = T @ syms[1]
    assert rotation_error_deg(twin, T) > 179 and rotation_error_deg(twin, T, syms) < 1e-6
    assert mssd(twin, T, pts, syms) < 1e-9
    assert add_s(twin, T, pts) < 1e-9
    assert pose_errors(twin, T, pts, syms, 0.1)["rot_err_deg"] < 1e-6


def test_scene_matching_counts_found_parts():
    pts = np.random.default_rng(2).uniform(-0.02, 0.02, (200, 3))
    gts = np.stack([make_T(np.eye(3), np.array([x, 0, 0.5])) for x in (-0.1, 0.0, 0.1)])
    ests = gts[[2, 0]].copy()
    ests[0, 0, 3] += 0.001
    summary, per = scene_pose_metrics(ests, gts, np.array([1.0, 0.2, 0.9]), pts, np.eye(4)[None], 0.05)
    assert summary["n_pickable"] == 2 and summary["pose_recall"] == 1.0 and summary["pose_precision"] == 1.0
    assert per[0]["gt_index"] == 2 and np.isclose(per[0]["trans_err_mm"], 1.0)


def test_foreign_labelled_scenes_are_evaluated(tmp_path):
    from binpick.io.labelled import LAYOUTS, load_labelled, transfer_labels

    rng = np.random.default_rng(0)
    pts = rng.uniform(0, 100, (300, 3))  # millimetres
    gt = (pts[:, 0] > 50).astype(int)
    np.savetxt(tmp_path / "gt.txt", np.column_stack([pts, gt]))
    pred = gt.copy()
    pred[:30] = -1  # a tool that left some points out
    np.savetxt(tmp_path / "pred.txt", np.column_stack([pts, rng.random(300), pred]))
    g = load_labelled(tmp_path / "gt.txt", LAYOUTS["x y z label"], "mm")
    p = load_labelled(tmp_path / "pred.txt", LAYOUTS["x y z score label"], "mm")
    assert np.allclose(g.points_m, pts / 1000) and p.scores is not None
    labels = transfer_labels(p.points_m, p.labels, g.points_m, 1e-6)
    c = scene_counts(labels, g.labels, 0.5).summary()
    assert c["precision"] == 1.0 and c["recall"] == 1.0 and c["mean_coverage"] < 1.0
