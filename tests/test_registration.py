import numpy as np
import pytest
import trimesh

from binpick.generation.scene import generate_scene, render_scene
from binpick.geometry.pointcloud import estimate_normals, voxel_downsample_indices
from binpick.geometry.symmetry import symmetry_transforms
from binpick.geometry.transforms import axis_angle_to_R, make_T, transform_points
from binpick.io.poses import PartPose
from binpick.io.ppf_model import load_ppf_model, save_ppf_model
from binpick.metrics.pose import pose_errors
from binpick.params import SymmetryParams
from binpick.part.model import make_part_model
from binpick.registration.matching import match_scene, match_segment
from binpick.registration.model import train_ppf
from binpick.registration.verification import refine_along_rays, refine_icp, score_pose
from binpick.view import ViewParams

from settings import PARAMS, changed


@pytest.fixture(scope="module")
def ppf(t_joint):
    return train_ppf(
        t_joint.points_m,
        t_joint.normals,
        t_joint.diameter_m,
        symmetry_transforms(t_joint.symmetry),
        PARAMS.registration,
    )


def test_ppf_model_roundtrip(tmp_path, ppf):
    save_ppf_model(tmp_path / "ppf.npz", ppf)
    back = load_ppf_model(tmp_path / "ppf.npz")
    assert np.array_equal(back.keys, ppf.keys) and back.angle_bins == ppf.angle_bins
    assert np.all(np.diff(back.keys) >= 0)
    assert back.near_symmetries.shape == ppf.near_symmetries.shape == (0, 4, 4)


def test_a_ppf_model_written_before_near_symmetries_and_its_grid_reads_with_none_and_the_params_grid(tmp_path, ppf):
    from binpick.registration.constants import Scales

    save_ppf_model(tmp_path / "ppf.npz", ppf)
    with np.load(tmp_path / "ppf.npz") as z:
        older = {k: z[k] for k in z.files if k not in ("near_symmetries", "sample_step_m")}
    np.savez(tmp_path / "old.npz", **older)
    back = load_ppf_model(tmp_path / "old.npz")
    assert back.near_symmetries.shape == (0, 4, 4) and np.array_equal(back.keys, ppf.keys)
    assert np.isnan(back.sample_step_m) and ppf.sample_step_m > 0
    params = PARAMS.registration
    assert Scales.of(back, params).sample_step_m == params.sample_step_rel * back.diameter_m


def test_recovers_the_pose_of_a_rendered_part(t_joint, ppf):
    scene = generate_scene(
        t_joint, PARAMS.generate, changed(PARAMS.camera, downscale=2), ViewParams(0.002, 0.006), seed=21, n_objects=4
    )
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

    scene = generate_scene(
        t_joint, PARAMS.generate, changed(PARAMS.camera, downscale=4), ViewParams(0.002, 0.006), seed=21, n_objects=6
    )
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

    scene = generate_scene(
        t_joint, PARAMS.generate, changed(PARAMS.camera, downscale=4), ViewParams(0.002, 0.006), seed=21, n_objects=6
    )
    found = match_scene(
        ppf,
        scene.view_points_m.astype(np.float64),
        scene.view_normals.astype(np.float64),
        PARAMS.registration,
        np.random.default_rng(0),
        max_instances=10,
    )
    summary, _ = scene_pose_metrics(
        np.array([e.T_cam_from_model for e in found]).reshape(-1, 4, 4),
        scene.T_cam_from_model,
        scene.visible_fraction,
        ppf.dense_points_m,
        ppf.symmetries,
        ppf.diameter_m,
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

    scene = generate_scene(
        t_joint, PARAMS.generate, changed(PARAMS.camera, downscale=4), ViewParams(0.002, 0.006), seed=21, n_objects=6
    )
    known, rest = scene.T_cam_from_model[:3], scene.T_cam_from_model[3:]
    found = match_scene(
        ppf,
        scene.view_points_m.astype(np.float64),
        scene.view_normals.astype(np.float64),
        PARAMS.registration,
        np.random.default_rng(0),
        known=list(known),
    )
    summary, _ = scene_pose_metrics(
        np.array([e.T_cam_from_model for e in found]).reshape(-1, 4, 4),
        rest,
        scene.visible_fraction[3:],
        ppf.dense_points_m,
        ppf.symmetries,
        ppf.diameter_m,
    )
    assert summary["pose_precision"] == 1.0 and summary["pose_recall"] >= 2 / 3, summary


def test_whole_scene_matching_votes_only_from_the_points_called_a_part(t_joint, ppf):
    """Points the network calls no part's start no vote: with three parts' points marked so, the
    whole-scene pass finds the other parts and none of those three, though their points are still
    in the cloud it fits and scores on."""
    from binpick.metrics.pose import scene_pose_metrics

    scene = generate_scene(
        t_joint, PARAMS.generate, changed(PARAMS.camera, downscale=4), ViewParams(0.002, 0.006), seed=21, n_objects=6
    )
    hidden = [0, 1, 2]
    found = match_scene(
        ppf,
        scene.view_points_m.astype(np.float64),
        scene.view_normals.astype(np.float64),
        PARAMS.registration,
        np.random.default_rng(0),
        votes_from=~np.isin(scene.view_labels, hidden),
    )
    T_found = np.array([e.T_cam_from_model for e in found]).reshape(-1, 4, 4)
    args = (ppf.dense_points_m, ppf.symmetries, ppf.diameter_m)
    on_hidden, _ = scene_pose_metrics(T_found, scene.T_cam_from_model[hidden], scene.visible_fraction[hidden], *args)
    on_rest, _ = scene_pose_metrics(T_found, scene.T_cam_from_model[3:], scene.visible_fraction[3:], *args)
    assert on_hidden["pose_recall"] == 0.0, on_hidden
    assert on_rest["pose_precision"] == 1.0 and on_rest["pose_recall"] >= 2 / 3, on_rest


def test_scene_pairs_match_the_training_features():
    """The scene side (one compiled pass) must quantise exactly like the model table, built from
    _features, _keys and _alpha, or votes miss their model pairs; and it must find every partner
    within the radius, in index order, wherever the grid's cells cut the scene."""
    from binpick.registration.model import _alpha, _features, _keys
    from binpick.registration.voting import _scene_pairs, prepare_scene

    rng = np.random.default_rng(3)
    # A scene several radii wide, points on cell borders included, so that partners lie in the
    # reference's neighbouring cells as well as its own.
    radius, step, bins = 0.06, 0.004, 30
    pts = np.concatenate([rng.uniform(-0.2, 0.2, (1200, 3)), np.arange(-3, 4)[:, None] * radius + np.zeros((7, 3))])
    n = len(pts)
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    refs = np.sort(np.concatenate([rng.choice(1200, 150, replace=False), np.arange(1200, n)]))
    scene = prepare_scene(pts, nrm, radius)
    starts, keys, alpha = _scene_pairs(pts, scene, refs, radius, step, bins)
    first = np.concatenate([np.full(starts[a + 1] - starts[a], r) for a, r in enumerate(refs)])
    d = np.linalg.norm(pts[refs][:, None] - pts[None], axis=2)
    expected_second = [np.flatnonzero((d[a] <= radius) & (np.arange(n) != r)) for a, r in enumerate(refs)]
    second = np.concatenate(expected_second)
    assert len(keys) == len(second) > 1000
    assert np.array_equal(np.diff(starts), [len(e) for e in expected_second])
    assert np.array_equal(keys, _keys(_features(pts[first], nrm[first], pts[second], nrm[second]), step, bins))
    T = np.zeros((n, 4, 4))
    T[:, :3, :3], T[:, :3, 3], T[:, 3, 3] = scene.R_align, scene.t_align, 1.0
    assert np.allclose(alpha, _alpha(T[first], pts[second]), atol=1e-9)


def test_greedy_clustering_finds_planted_clusters_and_joins_each_pose_where_a_scan_of_every_cluster_does():
    """Twenty poses spread over a metre, each voted for by jittered copies and by copies turned
    by the part's symmetry (a half turn with an offset): twenty clusters with the planted votes.
    Then random poses, many near one another: the grid joins each to the earliest cluster a scan
    of all of them in creation order finds, so the clusters and their votes are the same."""
    from binpick.registration.clustering import _greedy_clusters

    rng = np.random.default_rng(5)
    flip = make_T(axis_angle_to_R(np.array([1.0, 0.0, 0.0]), np.pi), np.array([0.0, 0.01, 0.0]))
    symmetries = np.stack([np.eye(4), flip])
    min_cos, max_dist = np.cos(np.radians(12.0)), 0.006

    def rotation(rng):
        axis = rng.normal(size=3)
        return axis_angle_to_R(axis / np.linalg.norm(axis), rng.uniform(0.0, np.pi))

    truth = [make_T(rotation(rng), rng.uniform([-0.5, -0.35, 1.6], [0.5, 0.35, 2.0])) for _ in range(20)]
    poses, weights, owner = [], [], []
    for c, T in enumerate(truth):
        for k in range(8):
            jitter = make_T(axis_angle_to_R(np.array([0.0, 0.0, 1.0]), np.radians(2.0)), rng.uniform(-1e-3, 1e-3, 3))
            candidate = T @ jitter
            poses.append(candidate @ np.linalg.inv(flip) if k % 2 else candidate)
            weights.append(float(k + 1))
            owner.append(c)
    order = np.argsort(-np.asarray(weights), kind="stable")
    poses_sorted = np.ascontiguousarray(np.asarray(poses)[order])
    reps, votes = _greedy_clusters(poses_sorted, np.asarray(weights)[order], symmetries, min_cos, max_dist)
    assert len(reps) == 20
    planted = np.bincount(np.asarray(owner), weights=np.asarray(weights))
    assert sorted(votes) == sorted(planted)

    def scan(poses, weights):
        reps, votes = [], []
        for k, T in enumerate(poses):
            for c, r in enumerate(reps):
                twins = poses[r] @ symmetries
                near = np.sum((twins[:, :3, 3] - T[:3, 3]) ** 2, axis=1) < max_dist**2
                cos = (np.einsum("sij,ij->s", twins[:, :3, :3], T[:3, :3]) - 1.0) / 2.0
                if np.any(near & (cos > min_cos)):
                    votes[c] += weights[k]
                    break
            else:
                reps.append(k)
                votes.append(weights[k])
        return reps, votes

    crowd = np.stack([make_T(rotation(rng), rng.uniform(-0.02, 0.02, 3)) for _ in range(400)])
    crowd_weights = rng.uniform(1.0, 5.0, 400)
    reps, votes = _greedy_clusters(crowd, crowd_weights, symmetries, min_cos, max_dist)
    expected_reps, expected_votes = scan(crowd, crowd_weights)
    assert 20 < len(expected_reps) < 400
    assert list(reps) == expected_reps and np.allclose(votes, expected_votes)
    # Poses spread over 10 m, each with a near copy: far more 6 mm cubes than the grid may hold,
    # so the cubes grow, and the clusters are still those of the scan.
    spread = np.stack([make_T(rotation(rng), rng.uniform(-5.0, 5.0, 3)) for _ in range(150)])
    near = spread @ make_T(axis_angle_to_R(np.array([0.0, 1.0, 0.0]), np.radians(3.0)), np.full(3, 0.002))
    wide = np.ascontiguousarray(np.concatenate([spread, near])[rng.permutation(300)])
    wide_weights = rng.uniform(1.0, 5.0, 300)
    reps, votes = _greedy_clusters(wide, wide_weights, symmetries, min_cos, max_dist)
    expected_reps, expected_votes = scan(wide, wide_weights)
    assert len(expected_reps) < 300
    assert list(reps) == expected_reps and np.allclose(votes, expected_votes)


def test_largest_patch_counts_the_biggest_linked_patch_of_the_kept_points():
    """Three grids of points 1 mm apart, 30 mm from one another (100, 64 and 36 points), linked
    within 1.5 mm: the largest patch is the 100. Keeping all but a line through the middle of
    the first splits it into 40 and 50, so the 64 is the largest; keeping one point, it is 1."""
    from scipy.spatial import cKDTree

    from binpick.registration.matching import _largest_patch

    def grid(n, x0):
        ij = np.stack(np.meshgrid(np.arange(n), np.arange(n)), axis=-1).reshape(-1, 2)
        return np.c_[x0 + 0.001 * ij, np.zeros(len(ij))]

    pts = np.concatenate([grid(10, 0.0), grid(8, 0.03), grid(6, 0.06)])
    links = cKDTree(pts).query_pairs(0.0015, output_type="ndarray")
    kept = np.ones(len(pts), bool)
    assert _largest_patch(links, kept) == 100
    kept[:100] = ~np.isclose(pts[:100, 1], 0.004)
    assert _largest_patch(links, kept) == 64
    kept[:] = False
    kept[7] = True
    assert _largest_patch(links, kept) == 1


def test_a_segment_a_found_pose_explains_is_a_fragment_and_one_holding_another_part_is_not(t_joint, ppf):
    """Segments cut from a rendered scene by its true labels: a part's own points are explained
    by its true pose, not by a pose turned away or by another part's; its points together with a
    second part's are not explained by the first part's pose alone."""
    from binpick.registration.matching import explained_by

    scene = generate_scene(
        t_joint, PARAMS.generate, changed(PARAMS.camera, downscale=2), ViewParams(0.002, 0.006), seed=21, n_objects=4
    )
    xyz, labels = scene.xyz_m.reshape(-1, 3), scene.labels.reshape(-1)
    a, b = np.argsort(-scene.visible_fraction)[:2]
    part_a = xyz[(labels == a) & np.isfinite(xyz[:, 2])].astype(np.float64)
    part_b = xyz[(labels == b) & np.isfinite(xyz[:, 2])].astype(np.float64)
    T_a, T_b = scene.T_cam_from_model[a], scene.T_cam_from_model[b]
    turned = T_a @ make_T(axis_angle_to_R(np.array([0.0, 0.0, 1.0]), np.radians(40)), np.zeros(3))
    reg = PARAMS.registration
    assert explained_by(ppf, part_a, reg, [T_a]) and explained_by(ppf, part_a, reg, [T_b, T_a])
    assert (
        not explained_by(ppf, part_a, reg, [])
        and not explained_by(ppf, part_a, reg, [turned])
        and not explained_by(ppf, part_a, reg, [T_b])
    )
    assert not explained_by(ppf, np.concatenate([part_a, part_b]), reg, [T_a])


# A long thin part like the gear shaft (151 x 32 mm): a 16 mm shaft with two 32 mm collars off
# centre, declared a surface of revolution about x.
SHAFT_SYMMETRY = SymmetryParams(kind="revolution", axis=(1.0, 0.0, 0.0))


@pytest.fixture(scope="module")
def shaft():
    from binpick.part.model import make_part_model

    pieces = []
    for x0, x1, radius in ((-0.075, 0.075, 0.008), (-0.035, -0.025, 0.016), (0.025, 0.035, 0.016)):
        piece = trimesh.creation.cylinder(radius=radius, height=x1 - x0, sections=48)
        piece.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
        piece.apply_translation([(x0 + x1) / 2, 0, 0])
        pieces.append(piece)
    return make_part_model(
        "shaft", trimesh.util.concatenate(pieces), SHAFT_SYMMETRY, 20000, np.random.default_rng(0), "m"
    )


def test_a_long_thin_part_gets_a_finer_voting_grid_and_a_compact_one_keeps_its_own(t_joint, shaft):
    from binpick.registration.model import voting_step

    params = changed(PARAMS.registration, min_voting_points=800)
    coarse = params.sample_step_rel * shaft.diameter_m
    assert len(voxel_downsample_indices(shaft.points_m, coarse)) < 400  # the premise: few points at the params' grid
    step = voting_step(shaft.points_m, coarse, 800)
    assert step < coarse and len(voxel_downsample_indices(shaft.points_m, step)) >= 800
    model = train_ppf(shaft.points_m, shaft.normals, shaft.diameter_m, symmetry_transforms(SHAFT_SYMMETRY), params)
    assert model.sample_step_m == step and len(model.points_m) >= 800
    assert np.isclose(model.distance_step_m / step, params.distance_step_rel / params.sample_step_rel)
    own = t_joint.diameter_m * params.sample_step_rel
    assert voting_step(t_joint.points_m, own, 800) == own


def test_two_long_parts_side_by_side_in_one_segment_are_both_found(shaft):
    """A segmentation that merged two shafts lying 4 mm apart: the segment's pose lies on one
    of them and the whole scene's pass finds the other; with the params' coarse grid alone
    (min_voting_points 1: 288 model points) the two are not both found."""
    symmetries = symmetry_transforms(SHAFT_SYMMETRY)
    T_a = make_T(np.eye(3), np.array([0.0, -0.018, 0.016]))
    T_b = make_T(axis_angle_to_R(np.array([0.0, 0.0, 1.0]), np.pi), np.array([0.01, 0.018, 0.016]))
    scene = render_scene(
        shaft,
        np.stack([T_a, T_b]),
        PARAMS.generate,
        changed(PARAMS.camera, downscale=2),
        ViewParams(0.002, 0.006),
        np.random.default_rng(3),
    )
    xyz, labels = scene.xyz_m.reshape(-1, 3), scene.labels.reshape(-1)
    pts = xyz[(labels >= 0) & np.isfinite(xyz[:, 2])]
    pts = pts[voxel_downsample_indices(pts, 0.002)]
    nrm = estimate_normals(pts, 0.006)
    fits = {}
    for n in (800, 1):
        params = changed(PARAMS.registration, min_voting_points=n)
        model = train_ppf(shaft.points_m, shaft.normals, shaft.diameter_m, symmetries, params)
        seg = match_segment(model, pts, nrm, params, np.random.default_rng(0))
        found = [seg] + match_scene(model, pts, nrm, params, np.random.default_rng(1), known=[seg.T_cam_from_model])
        fits[n] = sorted(
            i
            for i, T_gt in enumerate(scene.T_cam_from_model)
            for f in found
            if pose_errors(f.T_cam_from_model, T_gt, shaft.points_m, symmetries, shaft.diameter_m)["add_mm"] < 5.0
        )
    assert fits[800] == [0, 1], fits
    assert len(fits[1]) < 2, fits


def test_a_shaft_fitted_onto_a_plain_cylinder_lacks_visible_support(shaft):
    """A plain cylinder of the shaft's girth lies beside a shaft: the shaft's pose on the
    cylinder has its collars in the air, 8 mm off the cylinder (about the seen-through margin, so
    that check hardly sees them), and a good part of what the camera should see of it head-on
    unmeasured; the shaft's own pose has nearly all of it measured. Hidden and unmeasured surface
    is neutral: the same pose with half the frame's depth missing is supported as well."""
    from pykdtree.kdtree import KDTree

    from binpick.registration.constants import DEFAULT_MAX_SEEN_THROUGH, DEFAULT_MIN_VISIBLE_SUPPORT, Scales
    from binpick.registration.verification import seen_through, visible_support
    from binpick.registration.visibility import depth_view
    from binpick.scene.verification_threshold import SUPPORT_RANGE, choose_threshold

    model = train_ppf(
        shaft.points_m, shaft.normals, shaft.diameter_m, symmetry_transforms(SHAFT_SYMMETRY), PARAMS.registration
    )
    T_shaft = make_T(np.eye(3), np.array([0.0, -0.03, 0.016]))
    T_cylinder = make_T(axis_angle_to_R(np.array([0.0, 0.0, 1.0]), 0.3), np.array([0.0, 0.03, 0.008]))
    cylinder = trimesh.creation.cylinder(radius=0.008, height=0.15, sections=48)
    cylinder.apply_transform(T_cylinder @ trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    scene = render_scene(
        shaft,
        T_shaft[None],
        PARAMS.generate,
        changed(PARAMS.camera, downscale=2),
        ViewParams(0.002, 0.006),
        np.random.default_rng(3),
        distractors=[cylinder],
    )
    xyz = scene.xyz_m.reshape(-1, 3)
    measured = xyz[np.isfinite(xyz[:, 2])]
    tree = KDTree(np.ascontiguousarray(measured[voxel_downsample_indices(measured, 0.002)], dtype=np.float64))
    inlier = Scales.of(model, PARAMS.registration).inlier_m
    view = depth_view(xyz, scene.labels.shape, 0.002)
    right = scene.T_cam_from_model[0]
    on_cylinder = (
        scene.T_cam_from_bin
        @ make_T(np.eye(3), np.array([0.0, 0.0, 0.008]))
        @ T_cylinder
        @ make_T(np.eye(3), np.array([0.0, 0.0, -0.008]))
    )
    support_right = visible_support(model, right, view, tree, inlier)
    support_wrong = visible_support(model, on_cylinder, view, tree, inlier)
    assert support_right > 0.9, support_right
    assert support_right - support_wrong > 0.2, (support_right, support_wrong)
    # The verify stage, shown these two, chooses a cut that keeps the one and drops the other.
    cut = choose_threshold([support_right], [support_wrong], DEFAULT_MIN_VISIBLE_SUPPORT, SUPPORT_RANGE, False)
    assert support_wrong < cut <= support_right, (cut, support_right, support_wrong)
    assert seen_through(model, on_cylinder, view) < DEFAULT_MAX_SEEN_THROUGH  # the other check lets it pass
    # Missing depth says nothing: every other row of the frame unmeasured changes little.
    holes = scene.xyz_m.copy()
    holes[::2] = np.nan
    sparse = depth_view(holes.reshape(-1, 3), scene.labels.shape, 0.002)
    assert visible_support(model, right, sparse, tree, inlier) > 0.9


def _lone_t_joint(t_joint):
    """A T-joint on the floor rendered as our camera sees it: its measured points (n, 3) and its pose."""
    scene = render_scene(
        t_joint,
        make_T(np.eye(3), np.array([0.0, 0.0, 0.012]))[None],
        PARAMS.generate,
        changed(PARAMS.camera, downscale=2),
        ViewParams(0.002, 0.006),
        np.random.default_rng(3),
    )
    xyz = scene.xyz_m.reshape(-1, 3).astype(np.float64)
    return xyz[np.isfinite(xyz[:, 2])], scene.T_cam_from_model[0]


def _with_ray_noise(xyz, sigma_m):
    """The points (n, 3) moved along their rays by normal noise of sigma_m (a noisier sensor)."""
    return xyz * (1.0 + np.random.default_rng(5).normal(0.0, sigma_m, len(xyz)) / np.linalg.norm(xyz, axis=1))[:, None]


def test_the_support_cut_eases_with_the_noise_the_capture_shows(t_joint, ppf):
    """A T-joint rendered as our camera sees it shows less depth noise than half the score's
    inlier distance (1.4 mm): the cut stays; with 2 mm more along each ray (a Kinect-class
    sensor) it shows more than one and a half, and the cut is eased by the whole relief."""
    from pykdtree.kdtree import KDTree

    from binpick.geometry.depth_noise import image_coordinates, local_noise_m
    from binpick.registration.constants import SUPPORT_NOISE_RELIEF, Scales
    from binpick.registration.verification import support_cut

    inlier = Scales.of(ppf, PARAMS.registration).inlier_m
    assert support_cut(0.7, 0.0, inlier) == 0.7 and support_cut(0.7, 0.5 * inlier, inlier) == 0.7
    assert support_cut(0.7, inlier, inlier) == pytest.approx(0.7 - SUPPORT_NOISE_RELIEF / 2)
    assert support_cut(0.7, 1.5 * inlier, inlier) == support_cut(0.7, 3 * inlier, inlier) == 0.7 - SUPPORT_NOISE_RELIEF
    xyz, T = _lone_t_joint(t_joint)
    noisy = _with_ray_noise(xyz, 0.002)
    for points, cut in ((xyz, 0.7), (noisy, 0.7 - SUPPORT_NOISE_RELIEF)):
        points = np.ascontiguousarray(points[voxel_downsample_indices(points, 0.002)])
        near = points[np.linalg.norm(points - (T[:3, :3] @ t_joint.centre_m + T[:3, 3]), axis=1) < 0.04]
        noise = local_noise_m(points, KDTree(image_coordinates(points)), near)
        assert support_cut(0.7, noise, inlier) == pytest.approx(cut), noise


@pytest.mark.parametrize("seed", [0, 3])
def test_a_segment_with_a_neighbours_stub_gets_the_pose_the_camera_saw(t_joint, ppf, seed):
    """A T-joint lying on the floor, its branch mostly hidden under a plate, and its segment also
    holding a neighbour's stub of pipe on the other side (an under-split segment): the T turned
    half a turn about its run, its branch on the stub, explains the segment's points better than
    the true pose, but half of that branch hangs over floor the camera saw. With the capture's view
    the true pose wins; without it, the turned one."""
    from pykdtree.kdtree import KDTree

    from binpick.geometry.transforms import invert_T
    from binpick.part.model import _cylinder_along
    from binpick.registration.visibility import DepthView
    from binpick.scene.clean import clean

    rng = np.random.default_rng(seed)
    turn = rng.uniform(0.0, 2 * np.pi)
    T_bin_from_spot = make_T(
        axis_angle_to_R(np.array([0.0, 0.0, 1.0]), turn), np.array([*rng.uniform(-0.05, 0.05, 2), 0.0])
    )
    T_spot_from_model = make_T(np.eye(3), np.array([0.0, 0.0, 0.012]))  # run along x on the floor, branch along +y
    stub = _cylinder_along("y", 0.012, -0.025, -0.004)  # half the branch's free length, on the -y side
    stub.apply_translation([0.0, 0.0, 0.012])  # lying on the floor, level with the run
    plate = trimesh.creation.box(extents=[0.05, 0.04, 0.002])
    plate.apply_translation([0.0, 0.038, 0.045])  # hides the branch beyond 18 mm of the run's axis
    distractors = [m.apply_transform(T_bin_from_spot) for m in (stub, plate)]
    plain = PARAMS.generate.model_copy(update={"clutter": PARAMS.generate.clutter.off()})
    scene = render_scene(
        t_joint,
        (T_bin_from_spot @ T_spot_from_model)[None],
        plain,
        changed(PARAMS.camera, downscale=2),
        ViewParams.of_import(PARAMS.import_capture),
        rng,
        distractors=distractors,
    )
    H, W = scene.labels.shape
    cloud = clean(scene.xyz_m.reshape(-1, 3), None, (H, W), PARAMS.import_capture, seed=0)
    labels = scene.labels.reshape(-1)[cloud.pixel_index]
    local = transform_points(invert_T(scene.T_cam_from_bin @ T_bin_from_spot), cloud.points_m)
    on_stub = (labels < 0) & (local[:, 1] < -0.004) & (np.abs(local[:, 0]) < 0.015) & (local[:, 2] > 0.003)
    segment = (labels == 0) | on_stub
    assert on_stub.sum() > 0.2 * (labels == 0).sum()
    view = DepthView(cloud.seen_depth_m, cloud.seen_K)
    cloud_tree = KDTree(np.ascontiguousarray(cloud.points_m, dtype=np.float64))
    syms = symmetry_transforms(t_joint.symmetry)

    def rot_err(*seen) -> float:
        est = match_segment(
            ppf,
            cloud.points_m[segment],
            cloud.normals[segment],
            PARAMS.registration,
            np.random.default_rng(seed),
            *seen,
        )
        return pose_errors(est.T_cam_from_model, scene.T_cam_from_model[0], t_joint.points_m, syms, t_joint.diameter_m)[
            "rot_err_deg"
        ]

    assert rot_err(view, cloud_tree) < 3.0
    assert rot_err() > 150.0  # the trap is real: the segment's points alone prefer the turned T


def test_the_whole_scene_score_leaves_out_surface_the_sensor_did_not_measure(t_joint, ppf):
    """Half the part's facing surface has no points: in the projector's shadow (nothing measured
    there) it does not count against the pose; measured but without points near the pose, it
    does; below MIN_MEASURED_SHARE of the surface measured, the score is held down."""
    from binpick.registration.constants import MIN_MEASURED_SHARE, Scales
    from binpick.registration.visibility import DepthView, _zbuffer

    T = make_T(np.eye(3), np.array([0.0, 0.0, 0.5]))
    p = transform_points(T, t_joint.points_m)
    facing = p[np.einsum("ij,ij->i", t_joint.normals @ T[:3, :3].T, -p) > 0]
    lit = facing[facing[:, 0] >= np.median(facing[:, 0])]
    K = np.array([[1000.0, 0.0, 320.0], [0.0, 1000.0, 240.0], [0.0, 0.0, 1.0]])

    def seen(points):
        return DepthView(_zbuffer(points, K, (480, 640)), K)

    inlier = Scales.of(ppf, PARAMS.registration).inlier_m
    blind = score_pose(ppf, T, lit, inlier, whole_scene=True)
    assert blind == pytest.approx(0.5, abs=0.05)
    assert score_pose(ppf, T, lit, inlier, whole_scene=True, view=seen(lit)) > 0.95
    assert score_pose(ppf, T, lit, inlier, whole_scene=True, view=seen(facing)) == blind
    few = facing[facing[:, 0] >= np.quantile(facing[:, 0], 0.8)]
    assert score_pose(ppf, T, few, inlier, whole_scene=True, view=seen(few)) == pytest.approx(
        0.2 / MIN_MEASURED_SHARE, abs=0.05
    )


def test_a_noisy_capture_widens_the_inlier_distance_and_a_clean_one_keeps_it(t_joint, ppf):
    """A T-joint rendered as our camera sees it (0.3 mm of noise) keeps the params; with 2 mm
    more along each ray (a Kinect-class sensor) the inlier distance grows to the noise measured,
    and the right pose, under min_score at the plain distance, scores above it, still above a
    pose turned 0.6 rad."""
    from pykdtree.kdtree import KDTree

    from binpick.geometry.depth_noise import image_coordinates, local_noise_m
    from binpick.registration.constants import NOISE_INLIER_SIGMAS, Scales
    from binpick.scene.register import with_capture_noise

    xyz, T = _lone_t_joint(t_joint)
    turned = T @ make_T(axis_angle_to_R(np.array([0, 0, 1.0]), 0.6), np.zeros(3))
    plain = PARAMS.registration
    for added_m in (0.0, 0.002):
        noisy = _with_ray_noise(xyz, added_m)
        points = np.ascontiguousarray(noisy[voxel_downsample_indices(noisy, 0.002)])
        noise = local_noise_m(points, KDTree(image_coordinates(points)), points)
        widened = with_capture_noise(plain, noise, ppf.diameter_m)
        if added_m == 0.0:
            assert widened is plain, noise
            continue
        inlier = Scales.of(ppf, widened).inlier_m
        assert inlier == pytest.approx(NOISE_INLIER_SIGMAS * noise) and 0.002 <= noise <= 0.003
        near = points[np.linalg.norm(points - (T[:3, :3] @ t_joint.centre_m + T[:3, 3]), axis=1) < 0.05]
        right_plain = score_pose(ppf, T, near, Scales.of(ppf, plain).inlier_m)
        right, wrong = score_pose(ppf, T, near, inlier), score_pose(ppf, turned, near, inlier)
        assert right_plain < plain.min_score <= right and right > wrong + 0.05, (right_plain, right, wrong)


def _two_lying_t_joints(t_joint, shadow_from_x_m=None, only_second_seen=False):
    """Two T-joints lying on the floor 13 cm apart (bin frame x -0.07 and +0.06), as the
    whole-scene pass gets them: points (n, 3) and normals on the 2 mm grid, which part each point
    is (n,), the view (the camera's z-buffer, visibility.py) and the true poses (2, 4, 4).
    shadow_from_x_m: the second part's points beyond this bin x are not measured (a projector's
    shadow: in neither the points nor the view); only_second_seen: the view is that of a render
    of the second part alone (the camera saw the floor where the first lies)."""
    from binpick.geometry.transforms import invert_T
    from binpick.registration.visibility import DepthView, _zbuffer
    from binpick.view import view_normals

    poses = np.stack([make_T(np.eye(3), np.array([x, 0.0, 0.012])) for x in (-0.07, 0.06)])
    camera, grid = changed(PARAMS.camera, downscale=2), ViewParams(0.002, 0.006)
    scene = render_scene(t_joint, poses, PARAMS.generate, camera, grid, np.random.default_rng(3))
    h, w = scene.labels.shape
    xyz, labels = scene.xyz_m.reshape(-1, 3).astype(np.float64), scene.labels.reshape(-1)
    measured = np.isfinite(xyz[:, 2])
    if shadow_from_x_m is not None:
        x_bin = transform_points(invert_T(scene.T_cam_from_bin), xyz)[:, 0]
        measured &= ~((labels == 1) & (x_bin > shadow_from_x_m))
    seen = xyz[measured]
    if only_second_seen:
        alone = render_scene(t_joint, poses[1:], PARAMS.generate, camera, grid, np.random.default_rng(3)).xyz_m
        seen = alone.reshape(-1, 3)[np.isfinite(alone.reshape(-1, 3)[:, 2])]
    view = DepthView(_zbuffer(seen, scene.K, (h, w)), scene.K)
    on_part = measured & (labels >= 0)
    keep = voxel_downsample_indices(xyz[on_part], 0.002)
    points = xyz[on_part][keep]
    return points, view_normals(points, grid).astype(np.float64), labels[on_part][keep], view, scene.T_cam_from_model


def _found_parts(found, T_true, ppf):
    """Which true part each found pose lies on (within 5 degrees and 5 mm), -1 for none."""
    out = []
    for f in found:
        errors = [
            pose_errors(f.T_cam_from_model, T, ppf.dense_points_m, ppf.symmetries, ppf.diameter_m) for T in T_true
        ]
        ok = [e["rot_err_deg"] < 5.0 and e["trans_err_mm"] < 5.0 for e in errors]
        out.append(int(np.argmax(ok)) if any(ok) else -1)
    return out


def test_the_whole_scene_pass_looks_on_while_a_part_as_large_as_a_tenth_of_its_surface_is_left(t_joint, ppf):
    """Once the first T-joint is posed, what is left is the second one with more than half of it in
    the projector's shadow: 0.15 of the model's voting-grid points, below a fifth (the old stopping
    share) and above MIN_FREE_SHARE. The pass goes on and poses it."""
    from binpick.registration.constants import MIN_FREE_SHARE, Scales

    points, normals, which, view, T_true = _two_lying_t_joints(t_joint, shadow_from_x_m=0.065)
    grid = voxel_downsample_indices(points, Scales.of(ppf, PARAMS.registration).sample_step_m)
    left = np.sum(which[grid] == 1) / len(ppf.points_m)
    assert MIN_FREE_SHARE < left < 0.2, left
    found = match_scene(ppf, points, normals, PARAMS.registration, np.random.default_rng(0), view=view)
    assert sorted(_found_parts(found, T_true, ppf)) == [0, 1]


def test_the_whole_scene_pass_passes_over_a_pose_the_camera_saw_through(t_joint, ppf):
    """The view saw the floor where the first T-joint's points lie (a pose there lies where the
    camera saw through it, as a flipped pose's branch does in the air): with the verification's
    limit the pass returns the second part alone; without it, both."""
    from binpick.registration.constants import DEFAULT_MAX_SEEN_THROUGH

    points, normals, _, view, T_true = _two_lying_t_joints(t_joint, only_second_seen=True)
    rng = np.random.default_rng
    limited = match_scene(
        ppf, points, normals, PARAMS.registration, rng(0), view=view, max_seen_through=DEFAULT_MAX_SEEN_THROUGH
    )
    assert _found_parts(limited, T_true, ppf) == [1]
    unlimited = match_scene(ppf, points, normals, PARAMS.registration, rng(0), view=view)
    assert sorted(_found_parts(unlimited, T_true, ppf)) == [0, 1]


def test_a_segment_pose_the_camera_saw_through_does_not_hide_its_points_from_the_whole_scene_pass(
    t_joint, ppf, monkeypatch
):
    """Both T-joints in one segment, fitted with a pose the verification drops (the first T-joint's,
    where the camera saw the floor): the whole-scene pass is told of the verified poses only, so
    the points that pose lay on are not taken as explained, and the second T-joint is found."""
    import binpick.scene.register as scene_register
    from binpick.io.cloud import CleanCloud

    points, normals, _, view, T_true = _two_lying_t_joints(t_joint, only_second_seen=True)
    n = len(points)
    cloud = CleanCloud(
        points.astype(np.float32),
        normals.astype(np.float32),
        np.zeros((n, 3), np.uint8),
        -np.ones(n, np.int64),
        np.zeros(2, np.int64),
        np.full(4, np.nan),
        np.zeros((0, 4)),
        np.zeros(3),
        view.depth_m.astype(np.float32),
        view.K,
    )
    seen_through_pose = PartPose(T_true[0], score=0.9)
    monkeypatch.setattr(scene_register, "match_segment", lambda *args, **kwargs: seen_through_pose)
    told: list[list[np.ndarray]] = []
    real_match_scene = scene_register.match_scene

    def match_scene(*args, **kwargs):
        told.append(list(kwargs["known"]))
        return real_match_scene(*args, **kwargs)

    monkeypatch.setattr(scene_register, "match_scene", match_scene)
    params = PARAMS.registration.model_copy(update={"mode": "segments_then_scene"})
    result = scene_register.register(cloud, np.zeros(n, np.int64), ppf, params, 0)
    assert told == [[]]  # the segment's pose was dropped before the pass, not handed to it
    assert _found_parts(result.poses, T_true, ppf) == [1] and result.n_seen_through == 1


def test_a_shaft_under_depth_noise_is_posed_where_it_lies_along_the_rays_not_toward_the_camera():
    """A shaft (radius 15 mm, 0.2 m long) lying 1 m from the camera, measured with 5 mm of noise
    along the camera's rays: nearest-point ICP from the true pose slides toward the camera (the
    points displaced along grazing rays lie outside the curved surface); pairing each point with
    the model point on its ray keeps the pose where it was."""
    mesh = trimesh.creation.cylinder(radius=0.015, height=0.2, sections=64)
    part = make_part_model("shaft", mesh, SymmetryParams(kind="revolution"), 20000, np.random.default_rng(0), "m")
    ppf = train_ppf(
        part.points_m, part.normals, part.diameter_m, symmetry_transforms(part.symmetry), PARAMS.registration
    )
    # Axis across the image (camera x) and 30 degrees out of it, so that one end face is seen
    # (it holds the slide along the axis); centre on the optical axis 1 m away.
    R = axis_angle_to_R(np.array([0.0, 1.0, 0.0]), np.radians(60.0))
    T_true = make_T(R, np.array([0.0, 0.0, 1.0]))
    surface, face = trimesh.sample.sample_surface_even(mesh, 60000, seed=1)
    points = transform_points(T_true, surface)
    normals = mesh.face_normals[face] @ T_true[:3, :3].T
    seen = points[np.einsum("ij,ij->i", normals, points) < 0]  # a convex part: what faces the camera is seen
    rays = seen / np.linalg.norm(seen, axis=1, keepdims=True)
    noisy = seen + rays * np.random.default_rng(2).normal(0.0, 0.005, (len(seen), 1))
    centre = T_true[:3, 3]

    def toward_camera_m(T: np.ndarray) -> float:
        return float((centre - T[:3, 3]) @ (centre / np.linalg.norm(centre)))

    nearest = refine_icp(ppf, T_true, noisy, 0.02, 30)
    along_rays = refine_along_rays(ppf, T_true, noisy, 0.02, 30)
    assert toward_camera_m(nearest) > 0.0003  # 0.53-0.62 mm over four noise draws
    assert abs(toward_camera_m(along_rays)) < 0.00015  # 0.01-0.09 mm
    # Nor does it move across the rays (the noise has no component there).
    assert np.linalg.norm(along_rays[:2, 3] - centre[:2]) < 0.0003
