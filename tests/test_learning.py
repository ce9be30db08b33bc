"""Learning from the cell: captures labelled from the poses the cell trusted, and a loss that
learns from their labelled points alone."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from binpick.cell.bin_box import BinBox
from binpick.generation.scene import generate_scene
from binpick.geometry.transforms import invert_T, transform_points
from binpick.io.labelled_capture import load_labelled_capture, save_labelled_capture
from binpick.io.poses import PartPose
from binpick.labels import IGNORE, NOT_A_PART
from binpick.learning import label_capture, pseudo_labels, trusted
from binpick.network.loss import fpcc_loss
from binpick.scene.clean import clean
from binpick.view import ViewParams

from settings import PARAMS, changed

MIN_SCORE = 0.3
MARGIN = 0.15


@pytest.fixture(scope="module")
def captured(t_joint):
    """A rendered bin of 6 parts as the import stage cleans it, with each cleaned point's true
    instance (from the rendered label image; -1 = bin or floor)."""
    plain = PARAMS.generate.model_copy(update={"clutter": PARAMS.generate.clutter.off()})
    scene = generate_scene(
        t_joint,
        plain,
        changed(PARAMS.camera, downscale=2),
        ViewParams.of_import(PARAMS.import_capture),
        11,
        n_objects=6,
    )
    H, W = scene.labels.shape
    cloud = clean(scene.xyz_m.reshape(-1, 3), None, (H, W), PARAMS.import_capture, 0)
    truth = scene.labels.reshape(-1)[cloud.pixel_index]
    return scene, cloud, truth


def _poses(scene, trusted_ids):
    """The rendered poses, those in trusted_ids scored with margin, the others just passing."""
    return [
        PartPose(T, MIN_SCORE + (MARGIN + 0.05 if i in trusted_ids else 0.05))
        for i, T in enumerate(scene.T_cam_from_model)
    ]


def _labelled(cloud, scene, part, trusted_ids, bin_box=None):
    return label_capture(
        cloud,
        _poses(scene, trusted_ids),
        part.points_m,
        part.diameter_m,
        MIN_SCORE,
        MARGIN,
        PARAMS.import_capture.voxel_size_m,
        bin_box,
    )


def test_a_capture_labelled_from_known_poses_labels_every_point_of_those_parts(captured, t_joint):
    scene, cloud, truth = captured
    seen = [i for i in range(len(scene.T_cam_from_model)) if (truth == i).sum() >= 50]
    assert len(seen) >= 4, "the rendered bin should show at least 4 parts"
    trusted_ids = set(seen[:-1])
    untrusted = seen[-1]
    labelled = _labelled(cloud, scene, t_joint, trusted_ids)
    # Trusted poses keep the rendered order, so trusted pose j is instance sorted(trusted_ids)[j].
    instance_of = np.array(sorted(trusted_ids))
    assert len(labelled.T_cam_from_model) == len(trusted_ids)
    for j, i in enumerate(instance_of):
        np.testing.assert_array_equal(
            labelled.labels[truth == i], j, err_msg=f"a point of trusted part {i} is not labelled as it"
        )
    # The part that just passed, and whatever is not a part, is ignored: not called another part.
    assert np.all(labelled.labels[truth == untrusted] == IGNORE)
    assert np.all(labelled.labels[truth < 0] == IGNORE)


def test_labels_survive_the_file(captured, t_joint, tmp_path):
    scene, cloud, _ = captured
    labelled = label_capture(
        cloud,
        _poses(scene, {0, 1}),
        t_joint.points_m,
        t_joint.diameter_m,
        MIN_SCORE,
        MARGIN,
        PARAMS.import_capture.voxel_size_m,
    )
    save_labelled_capture(tmp_path / "c.npz", labelled)
    back = load_labelled_capture(tmp_path / "c.npz")
    np.testing.assert_array_equal(back.labels, labelled.labels)
    np.testing.assert_array_equal(back.T_cam_from_model, labelled.T_cam_from_model)


def test_a_point_goes_to_the_nearest_trusted_surface_within_reach():
    # Two unit-spaced planes of model points; a point 1 mm off the first is its, 4 mm off is nobody's.
    grid = np.stack(np.meshgrid(np.linspace(-0.02, 0.02, 41), np.linspace(-0.02, 0.02, 41), [0.0]), axis=-1).reshape(
        -1, 3
    )
    T0, T1 = np.eye(4), np.eye(4)
    T0[:3, 3] = [0.0, 0.0, 0.5]
    T1[:3, 3] = [0.0, 0.0, 0.51]
    points = np.array([[0.0, 0.0, 0.501], [0.0, 0.0, 0.5085], [0.0, 0.0, 0.504], [0.1, 0.0, 0.5]])
    labels = pseudo_labels(points, np.stack([T0, T1]), grid, near_m=0.002)
    np.testing.assert_array_equal(labels, [0, 1, IGNORE, IGNORE])


def test_trust_needs_the_margin():
    poses = [PartPose(np.eye(4), s) for s in (0.3, 0.44, 0.45, 0.9)]
    np.testing.assert_array_equal(trusted(poses, 0.3, 0.15), [False, False, True, True])


def test_ignored_points_add_nothing_to_the_loss():
    """Moving the embeddings and centre scores of ignored points leaves the loss and its
    gradient on the labelled points as they were; labelling them changes it."""
    g = torch.Generator().manual_seed(0)
    N = 64
    points = torch.rand(1, N, 3, generator=g) * 0.05
    labels = torch.randint(0, 3, (1, N), generator=g)
    labels[0, 40:] = IGNORE
    emb = torch.rand(1, N, 8, generator=g)
    ctr = torch.rand(1, N, generator=g)

    def loss(e, c, lab):
        total, _ = fpcc_loss(e, c, points, lab, 0.05, 0.5, 1.5, 1.0, "linear", 32, torch.Generator().manual_seed(1))
        return total

    base = loss(emb, ctr, labels)
    moved_emb, moved_ctr = emb.clone(), ctr.clone()
    moved_emb[0, 40:] += 5.0
    moved_ctr[0, 40:] = 0.0
    assert loss(moved_emb, moved_ctr, labels).item() == pytest.approx(base.item(), abs=1e-7)
    relabelled = labels.clone()
    relabelled[0, 40:] = 0
    assert abs(loss(moved_emb, moved_ctr, relabelled).item() - base.item()) > 1e-3
    # A crop of ignored points alone gives no loss and no gradient, and does not fail.
    e = emb.clone().requires_grad_(True)
    none = loss(e, ctr, torch.full((1, N), IGNORE))
    none.backward()
    assert none.item() == 0.0 and float(e.grad.abs().sum()) == 0.0


def test_points_beyond_the_bin_are_no_part_and_trusted_parts_keep_theirs(captured, t_joint):
    """A box of the bin's -x half (a bin whose +x half lies beyond its wall): the untrusted
    parts' points on the +x side become NOT_A_PART, on the -x side stay IGNORE; a trusted part's
    points keep its instance on either side."""
    scene, cloud, truth = captured
    seen = [i for i in range(len(scene.T_cam_from_model)) if (truth == i).sum() >= 50]
    trusted_ids = set(seen[:2])
    box = BinBox(scene.T_cam_from_bin, np.array([-1.0, -1.0, 0.0]), np.array([0.0, 1.0, 1.0]))
    labelled = _labelled(cloud, scene, t_joint, trusted_ids, box)
    x_bin = transform_points(invert_T(scene.T_cam_from_bin), cloud.points_m.astype(np.float64))[:, 0]
    near = float(labelled.near_m)
    for j, i in enumerate(sorted(trusted_ids)):
        np.testing.assert_array_equal(labelled.labels[truth == i], j)
    other = ~np.isin(truth, sorted(trusted_ids))
    assert (other & (x_bin > near)).sum() >= 50, "the +x half should show untrusted points"
    assert np.all(labelled.labels[other & (x_bin > near)] == NOT_A_PART)
    assert np.all(labelled.labels[other & (x_bin <= 0.0)] == IGNORE)


def test_the_foreground_head_learns_from_a_captured_view_only_when_it_knows_both_classes():
    """A capture's view of part points and ignored points gives the foreground head no gradient
    (one class would teach "everything is a part"); one point known as no part, or a synthetic
    view with no ignored point, teaches it."""
    g = torch.Generator().manual_seed(0)
    N = 64
    points = torch.rand(1, N, 3, generator=g) * 0.05
    emb = torch.rand(1, N, 8, generator=g)
    ctr = torch.rand(1, N, generator=g)

    def fg_grad(labels):
        fg = torch.zeros(1, N, requires_grad=True)
        e = emb.clone().requires_grad_(True)
        total, _ = fpcc_loss(
            e, ctr, points, labels, 0.05, 0.5, 1.5, 1.0, "linear", 32, torch.Generator().manual_seed(1), fg
        )
        total.backward()
        return 0.0 if fg.grad is None else float(fg.grad.abs().sum())

    captured = torch.randint(0, 3, (1, N), generator=g)
    captured[0, 40:] = IGNORE
    assert fg_grad(captured) == 0.0
    with_background = captured.clone()
    with_background[0, 50] = NOT_A_PART
    assert fg_grad(with_background) > 0.0
    synthetic_parts_only = torch.randint(0, 3, (1, N), generator=g)
    assert fg_grad(synthetic_parts_only) > 0.0
