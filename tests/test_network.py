import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from binpick.errors import InputError
from binpick.network.blocks import cover, crop
from binpick.network.checkpoint import CalibratedClustering, load_checkpoint, save_checkpoint, write_state
from binpick.network.infer import ClusterParams, cluster, part_points, segment_scene
from binpick.network.loss import centre_score_targets, fpcc_loss
from binpick.network.model import (
    FPCC,
    EdgeConv,
    FPCCConfig,
    gather_neighbours,
    input_features,
    knn_by_distance_blocks,
    knn_by_tree,
    knn_indices,
    neighbour_max,
)
from binpick.network.train import Views, train_fpcc

from settings import PARAMS, changed


@pytest.mark.parametrize("knn", [knn_indices, knn_by_tree, knn_by_distance_blocks])
def test_knn_matches_brute_force(knn):
    xyz = torch.rand(2, 300, 3)
    idx = knn(xyz, 8)
    d = torch.cdist(xyz, xyz)
    brute = d.topk(8, dim=-1, largest=False).values
    got = torch.gather(d, 2, idx)
    assert idx.shape == (2, 300, 8) and idx.dtype == torch.long
    assert torch.allclose(got, brute)


def test_neighbour_max_matches_gathered_max():
    x, idx = torch.randn(3, 4, 50), knn_indices(torch.rand(3, 50, 3), 5)
    assert torch.equal(neighbour_max(x, idx), gather_neighbours(x, idx).max(dim=-1).values)


@pytest.mark.parametrize("training", [True, False])
def test_edgeconv_equals_the_mlp_applied_to_every_edge(training):
    """The decomposed EdgeConv against the textbook one: MLP on [x_j - x_i, x_i] for every edge, max over j."""
    torch.manual_seed(0)
    layer = EdgeConv(5, 7)
    with torch.no_grad():  # statistics and a scale of either sign, as after training
        bn = layer.mlp[1]
        bn.weight.normal_(), bn.bias.normal_(), bn.running_mean.normal_(), bn.running_var.uniform_(0.5, 2.0)
    layer.train(training)
    x = torch.randn(2, 5, 200)
    idx = knn_indices(torch.rand(2, 200, 3), 6)
    nbr = gather_neighbours(x, idx)  # (B, C, N, k)
    centre = x.unsqueeze(-1).expand_as(nbr)
    expected = layer.mlp(torch.cat([nbr - centre, centre], dim=1)).max(dim=-1).values
    assert torch.allclose(layer(x, idx), expected, atol=1e-5)


@pytest.mark.parametrize("backbone", ["dgcnn", "pointnet"])
def test_forward_shapes(backbone):
    def features(p):
        return input_features(p, torch.nn.functional.normalize(torch.randn(2, 256, 3), dim=-1), "normals", 0.03)

    p = torch.rand(2, 256, 3) * 0.1
    model = FPCC(FPCCConfig(backbone=backbone, k_neighbours=8, width=16, embedding_dim=12, foreground_head=True))
    emb, ctr, fg = model(features(p), p)
    assert emb.shape == (2, 256, 12) and ctr.shape == (2, 256) and fg.shape == (2, 256)
    assert ctr.min() >= 0 and ctr.max() <= 1
    # A network from before the foreground head calls every point a part's.
    _, _, fg = FPCC(FPCCConfig(backbone=backbone, k_neighbours=8, width=16, embedding_dim=12))(features(p), p)
    assert torch.all(torch.sigmoid(fg) == 1.0)


def test_centre_score_targets_linear_and_squared():
    pts = torch.tensor([[0.0, 0, 0], [0.02, 0, 0], [0.01, 0, 0], [1.0, 0, 0]])
    lab = torch.tensor([0, 0, 0, 1])
    lin = centre_score_targets(pts, lab, 0.02, "linear")
    sq = centre_score_targets(pts, lab, 0.02, "squared")
    assert torch.allclose(lin, torch.tensor([0.5, 0.5, 1.0, 1.0]))
    assert torch.allclose(sq, torch.tensor([0.75, 0.75, 1.0, 1.0]))


def test_loss_ignores_far_pairs_with_a_true_distance():
    # Two instances 1 m apart with identical embeddings: beyond 2 * d_max every pair is masked, so
    # only the same-instance pull (zero here) remains.
    pts = torch.tensor([[[0.0, 0, 0], [0.001, 0, 0], [1.0, 0, 0], [1.001, 0, 0]]])
    lab = torch.tensor([[0, 0, 1, 1]])
    emb = torch.zeros(1, 4, 3)
    ctr = centre_score_targets(pts[0], lab[0], 0.05, "linear")[None]
    total, parts = fpcc_loss(emb, ctr, pts, lab, 0.05, 0.5, 1.5, 1.0, "linear", 4)
    assert parts["embedding_loss"] == 0.0 and parts["centre_loss"] == 0.0
    # Now closer than 2 * d_max: the push term must be active.
    pts_near = pts.clone()
    pts_near[0, 2:, 0] = torch.tensor([0.05, 0.051])
    _, parts = fpcc_loss(emb, ctr, pts_near, lab, 0.05, 0.5, 1.5, 1.0, "linear", 4)
    assert parts["embedding_loss"] > 0.5


def test_cluster_recovers_handmade_instances():
    pts = np.array([[0, 0, 0], [0.01, 0, 0], [0.2, 0, 0], [0.21, 0, 0], [0.5, 0, 0]], float)
    emb = np.array([[0, 0], [0.1, 0], [3, 0], [3.1, 0], [10, 10]], float)
    ctr = np.array([0.9, 0.2, 0.8, 0.3, 0.1])
    labels = cluster(pts, emb, ctr, ClusterParams(0.5, 0.05, 1.0, 1))
    assert labels.tolist() == [0, 0, 1, 1, -1]
    assert (cluster(pts, emb, ctr, ClusterParams(0.5, 0.05, 1.0, 3)) == -1).all()  # all too small
    # Points the network calls no part's are noise and never a centre: without its first point
    # (the best centre) the first instance is centred on the second, which the score allows only
    # at a lower threshold (and, the weaker centre, it is numbered second).
    background = np.array([True, False, False, False, False])
    assert cluster(pts, emb, ctr, ClusterParams(0.5, 0.05, 1.0, 1), ~background).tolist() == [-1, -1, 0, 0, -1]
    assert cluster(pts, emb, ctr, ClusterParams(0.1, 0.05, 1.0, 1), ~background).tolist() == [-1, 1, 0, 0, -1]


def _cluster_by_definition(points, embedding, centre, params):
    """The inference rule read literally: greedy suppression by score, nearest centre or noise."""
    cands = [i for i in np.argsort(-centre, kind="stable") if centre[i] > params.centre_threshold]
    centres = []
    for c in cands:
        if all(
            np.linalg.norm(points[c] - points[k]) >= params.nms_radius_m
            and np.linalg.norm(embedding[c] - embedding[k]) >= params.embedding_threshold
            for k in centres
        ):
            centres.append(c)
    d = np.linalg.norm(embedding[:, None] - embedding[centres][None], axis=2)
    labels = np.where(d.min(axis=1) <= params.embedding_threshold, d.argmin(axis=1), -1)
    sizes = np.bincount(labels[labels >= 0], minlength=len(centres))
    labels[(labels >= 0) & (sizes[np.maximum(labels, 0)] < params.min_points)] = -1
    kept = np.flatnonzero(sizes >= params.min_points)
    return np.array([-1 if lab < 0 else int(np.searchsorted(kept, lab)) for lab in labels])


def test_cluster_matches_the_rule_read_literally():
    rng = np.random.default_rng(3)
    truth = rng.integers(0, 6, 600)
    points = rng.normal(size=(6, 3))[truth] * 0.1 + rng.normal(scale=0.01, size=(600, 3))
    embedding = rng.normal(size=(6, 16))[truth] * 2.0 + rng.normal(scale=0.3, size=(600, 16))
    centre = rng.random(600)
    for params in (
        ClusterParams(0.5, 0.03, 1.5, 5),
        ClusterParams(0.2, 0.01, 2.5, 1),
        ClusterParams(0.8, 0.1, 1.6, 20),
    ):
        assert np.array_equal(
            cluster(points, embedding, centre, params), _cluster_by_definition(points, embedding, centre, params)
        )


class _OracleNet(torch.nn.Module):
    """Stands in for a trained network: embeds a point by which of three x-bands it lies in and
    scores it by closeness to its band's middle. Lets block merging be tested exactly."""

    config = FPCCConfig()

    def __init__(self):
        super().__init__()
        self.dummy = torch.nn.Parameter(torch.zeros(1))

    def forward(self, features, xyz):
        band = torch.div(xyz[..., 0] + 0.05, 0.1, rounding_mode="floor")  # -> 0, 1, 2
        emb = torch.stack([band * 3.0, torch.zeros_like(band)], dim=-1)
        ctr = 1.0 - (xyz[..., 0] - (band * 0.1)).abs() / 0.05
        return emb, ctr.clamp(0, 1), torch.full_like(ctr, 30.0)


def test_block_inference_labels_every_point_and_merges_across_blocks():
    rng = np.random.default_rng(0)
    pts = np.concatenate(
        [rng.uniform([-0.04 + 0.1 * b, -0.02, 0.5], [0.04 + 0.1 * b, 0.02, 0.51], (700, 3)) for b in range(3)]
    )
    normals = np.tile([0.0, 0.0, -1.0], (len(pts), 1))
    truth = np.repeat(np.arange(3), 700)
    # Blocks of 1,000 points, parts of 700: as in a real bin, a block holds a part or more (a
    # block smaller than a part may hold none of its centre, and cannot label it).
    labels = segment_scene(_OracleNet(), pts, normals, "normals", 0.03, 1000, ClusterParams(0.8, 0.03, 1.0, 10), rng)
    assert len(cover(pts, 1000, np.random.default_rng(1))) >= 3  # really several blocks
    assert (labels >= 0).all()
    # Same partition as the truth, up to renumbering.
    pairs = set(zip(labels.tolist(), truth.tolist(), strict=False))
    assert len(pairs) == 3 and len({a for a, _ in pairs}) == 3


def test_each_point_is_called_a_part_or_not_by_the_block_whose_seed_is_nearest():
    """Points 0..4 on a line, two overlapping blocks that disagree, and a rim point (5) in no
    block: each point takes the judgement of the nearer seed (the first block on a tie), the rim
    point its nearest neighbour's; a point is a part's where its logit is above the cut."""
    points = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0], [4, 0, 0], [4.2, 0, 0]])
    none = np.zeros((0,))
    blocks = [
        (0, np.array([0, 1, 2, 3]), none, none, np.array([2.0, 2.0, -2.0, -2.0])),
        (4, np.array([2, 3, 4]), none, none, np.array([2.0, 1.0, -1.0])),
    ]
    np.testing.assert_array_equal(part_points(points, blocks), [True, True, False, True, False, False])
    np.testing.assert_array_equal(part_points(points, blocks, -1.5), [True, True, False, True, True, True])


def test_the_foreground_cut_is_chosen_where_the_validation_points_separate():
    """Part points with logits in [-1.2, 3], no-part points in [-4, -2.2], points left out of the
    loss (-2) anywhere: the cuts -2.0 and -1.5 both separate them, and the one nearer 0 is chosen;
    views with no no-part point leave the cut at 0."""
    from binpick.network.calibrate import choose_foreground_logit

    rng = np.random.default_rng(0)
    labels = np.concatenate([np.repeat(np.arange(4), 50), np.full(60, -1), np.full(30, -2)])
    logits = np.concatenate([rng.uniform(-1.2, 3.0, 200), rng.uniform(-4.0, -2.2, 60), rng.uniform(-5.0, 5.0, 30)])
    points = rng.normal(size=(len(labels), 3))
    blocks = [(0, np.arange(len(labels)), np.zeros((0,)), np.zeros((0,)), logits)]
    assert choose_foreground_logit([(points, points, labels)], [blocks]) == -1.5
    parts_only = labels >= 0
    only = [(0, np.arange(200), np.zeros((0,)), np.zeros((0,)), logits[parts_only])]
    assert choose_foreground_logit([(points[parts_only], points[parts_only], labels[parts_only])], [only]) == 0.0


def test_crop_is_contiguous_and_pads_small_scenes():
    pts = np.random.default_rng(0).uniform(0, 1, (1000, 3))
    idx = crop(pts, 100, np.random.default_rng(1))
    assert len(np.unique(idx)) == 100
    small = crop(pts[:40], 100, np.random.default_rng(1))
    assert len(small) == 100 and set(small.tolist()) == set(range(40))


def _toy_views(n_scenes, rng):
    """Scenes of two to four flat square patches 5 cm apart, each its own instance."""
    P, N, L = [], [], []
    for _ in range(n_scenes):
        k = rng.integers(2, 5)
        pts = np.concatenate(
            [rng.uniform([0.05 * i, 0, 0.5], [0.05 * i + 0.03, 0.03, 0.5], (100, 3)) for i in range(k)]
        )
        P.append(pts.astype(np.float32))
        N.append(np.tile(np.array([0, 0, -1], np.float32), (len(pts), 1)))
        L.append(np.repeat(np.arange(k), 100))
    return Views(P, N, L)


def test_training_resumes_to_the_same_weights_as_an_uninterrupted_run(tmp_path, caplog):
    rng = np.random.default_rng(0)
    train, val = _toy_views(6, rng), _toy_views(2, rng)
    params = changed(
        PARAMS.train,
        width=8,
        embedding_dim=4,
        k_neighbours=8,
        n_points=200,
        batch_size=2,
        epochs=3,
        loss_anchors=64,
        patience_epochs=10,
    )
    full, m_full = train_fpcc(train, val, params, 0.02, 5, tmp_path / "a", "toy", 0.06, progress=False)
    train_fpcc(
        train, val, params.model_copy(update={"epochs": 2}), 0.02, 5, tmp_path / "b", "toy", 0.06, progress=False
    )
    # Stand-in for a run that crashed after two epochs: the two-epoch run's last.pt, relabelled
    # with the three-epoch params. Training on must then end exactly where the full run ended.
    state = torch.load(tmp_path / "b" / "last.pt", weights_only=True)
    state["extra"]["train_params"] = params.model_dump()
    write_state(tmp_path / "b" / "last.pt", state)
    with caplog.at_level("INFO", logger="binpick.network.train"):
        resumed, m_res = train_fpcc(train, val, params, 0.02, 5, tmp_path / "b", "toy", 0.06, progress=False)
    assert "resuming from" in caplog.text
    for a, b in zip(full.state_dict().values(), resumed.state_dict().values(), strict=False):
        assert torch.equal(a, b)
    assert m_full["best_val_loss"] == m_res["best_val_loss"]


def test_a_damaged_resume_point_restarts_training_with_a_warning(tmp_path, caplog):
    rng = np.random.default_rng(0)
    train, val = _toy_views(4, rng), _toy_views(2, rng)
    params = changed(
        PARAMS.train,
        width=8,
        embedding_dim=4,
        k_neighbours=8,
        n_points=200,
        batch_size=2,
        epochs=2,
        loss_anchors=64,
        patience_epochs=10,
    )
    (tmp_path / "w").mkdir()
    (tmp_path / "w" / "last.pt").write_bytes(b"PK\x03\x04 truncated by a crash")
    with caplog.at_level("WARNING", logger="binpick.network.train"):
        _, metrics = train_fpcc(train, val, params, 0.02, 5, tmp_path / "w", "toy", 0.06, progress=False)
    assert "starting this training from scratch" in caplog.text and metrics["epochs_run"] == 2


def test_a_checkpoint_with_flipped_bytes_is_refused(tmp_path):
    model = FPCC(FPCCConfig(k_neighbours=4, width=8, embedding_dim=6)).eval()
    save_checkpoint(tmp_path / "m.pt", model, None, 3, {"loss": 1.0}, {"d_max_m": 0.02})
    data = bytearray((tmp_path / "m.pt").read_bytes())
    # Flip bytes inside the largest weight tensor's stored data (torch still reads the file).
    state = torch.load(tmp_path / "m.pt", weights_only=True)
    name, tensor = max(state["model"].items(), key=lambda kv: kv[1].numel())
    raw = tensor.reshape(-1).view(torch.uint8).numpy().tobytes()
    at = bytes(data).find(raw[:64])
    assert at > 0, name
    data[at + 10] ^= 0xFF
    (tmp_path / "bad.pt").write_bytes(bytes(data))
    torch.load(tmp_path / "bad.pt", weights_only=True)  # still loads: only the checksum can tell
    with pytest.raises(InputError, match="damaged: its weights do not match the checksum"):
        load_checkpoint(tmp_path / "bad.pt")


def test_checkpoint_rebuilds_the_network_alone(tmp_path):
    model = FPCC(FPCCConfig(k_neighbours=4, width=8, embedding_dim=6)).eval()
    save_checkpoint(tmp_path / "m.pt", model, None, 3, {"loss": 1.0}, {"d_max_m": 0.02})
    back, state = load_checkpoint(tmp_path / "m.pt")
    x = torch.rand(1, 64, 3)
    f = input_features(x, torch.nn.functional.normalize(torch.randn(1, 64, 3), dim=-1), "normals", 0.02)
    assert torch.equal(model(f, x)[0], back(f, x)[0])
    assert state["epoch"] == 3 and state["extra"]["d_max_m"] == 0.02


class _CloseBandsNet(_OracleNet):
    """The oracle with its three instances only 1.3 apart in embedding space."""

    def forward(self, features, xyz):
        emb, ctr, fg = super().forward(features, xyz)
        return emb * (1.3 / 3.0), ctr, fg


def test_calibration_finds_the_embedding_threshold_that_separates_the_instances():
    """Instances 1.3 apart in embedding space: any threshold above 1.3 merges them (the default
    1.5 does), 1.2 keeps them apart; calibration on labelled views must find it."""
    from binpick.metrics.segmentation import scene_counts
    from binpick.network.calibrate import calibrate_clustering
    from binpick.network.infer import DEFAULT_CENTRE_THRESHOLD, DEFAULT_EMBEDDING_THRESHOLD

    rng = np.random.default_rng(0)
    views = []
    for _ in range(2):
        pts = np.concatenate(
            [rng.uniform([-0.04 + 0.1 * b, -0.02, 0.5], [0.04 + 0.1 * b, 0.02, 0.51], (300, 3)) for b in range(3)]
        )
        views.append((pts, np.tile([0.0, 0.0, -1.0], (len(pts), 1)), np.repeat(np.arange(3), 300)))
    net = _CloseBandsNet()
    default = segment_scene(
        net,
        views[0][0],
        views[0][1],
        "normals",
        0.03,
        2048,
        ClusterParams(DEFAULT_CENTRE_THRESHOLD, 0.03, DEFAULT_EMBEDDING_THRESHOLD, 10),
        np.random.default_rng(1),
    )
    assert scene_counts(default, views[0][2], 0.5).summary()["precision"] < 0.5
    chosen = calibrate_clustering(net, views, "normals", 0.03, 2048, 0.03, 10, 1.5, 0.5, np.random.default_rng(1))
    assert chosen["embedding_threshold"] < 1.3 and chosen["precision"] == chosen["recall"] == 1.0


class _SliverNet(_OracleNet):
    """The oracle, but the last eighth of every band along x is embedded apart, with a high centre
    score: a sliver of each part becomes an instance of its own."""

    def forward(self, features, xyz):
        emb, ctr, fg = super().forward(features, xyz)
        band = torch.div(xyz[..., 0] + 0.05, 0.1, rounding_mode="floor")
        sliver = xyz[..., 0] - band * 0.1 > 0.03
        emb = emb + torch.stack([torch.zeros_like(band), sliver * 3.0], dim=-1)
        return emb, torch.where(sliver, torch.full_like(ctr, 0.9), ctr), fg


def test_calibration_drops_slivers_by_instance_size():
    from binpick.network.calibrate import calibrate_clustering
    from binpick.network.infer import cluster_params

    rng = np.random.default_rng(0)
    views = []
    for _ in range(2):
        pts = np.concatenate(
            [rng.uniform([-0.04 + 0.1 * b, -0.02, 0.5], [0.04 + 0.1 * b, 0.02, 0.51], (300, 3)) for b in range(3)]
        )
        views.append((pts, np.tile([0.0, 0.0, -1.0], (len(pts), 1)), np.repeat(np.arange(3), 300)))
    sliver_points = max(int(np.sum(p[:, 0] - np.floor((p[:, 0] + 0.05) / 0.1) * 0.1 > 0.03)) for p, _, _ in views) // 3
    kept_all = segment_scene(
        _SliverNet(), views[0][0], views[0][1], "normals", 0.03, 2048, ClusterParams(0.5, 0.03, 1.5, 10), rng
    )
    assert len(np.unique(kept_all[kept_all >= 0])) == 6  # three parts and their three slivers
    chosen = calibrate_clustering(
        _SliverNet(), views, "normals", 0.03, 2048, 0.03, 10, 1.5, 0.5, np.random.default_rng(1)
    )
    assert chosen["precision"] == chosen["recall"] == 1.0
    assert sliver_points < chosen["min_instance_points"] < 300 - sliver_points
    calibrated = CalibratedClustering(
        chosen["centre_threshold"], chosen["embedding_threshold"], int(chosen["min_instance_points"])
    )
    assert (
        cluster_params(changed(PARAMS.segment, min_points=10), 0.1, calibrated).min_points
        == chosen["min_instance_points"]
    )


def test_segment_params_override_calibrated_thresholds():
    from binpick.network.infer import cluster_params

    calibrated = CalibratedClustering(
        centre_threshold=0.5, embedding_threshold=1.2, min_instance_points=60, foreground_logit=-1.5
    )
    assert cluster_params(PARAMS.segment, 0.1, calibrated).embedding_threshold == 1.2
    assert cluster_params(PARAMS.segment, 0.1, calibrated).foreground_logit == -1.5
    assert cluster_params(changed(PARAMS.segment, foreground_logit=0.5), 0.1, calibrated).foreground_logit == 0.5
    assert cluster_params(PARAMS.segment, 0.1, None).foreground_logit == 0.0
    assert cluster_params(changed(PARAMS.segment, embedding_threshold=1.7), 0.1, calibrated).embedding_threshold == 1.7
    assert cluster_params(PARAMS.segment, 0.1, None).centre_threshold == 0.3  # an old checkpoint: the defaults
    assert cluster_params(changed(PARAMS.segment, min_points=25), 0.1, None).min_points == 25
    assert cluster_params(changed(PARAMS.segment, min_instance_points=80), 0.1, calibrated).min_points == 80


def test_scenes_that_show_no_part_are_left_out_of_training_and_none_at_all_is_refused(tmp_path, t_joint, caplog):
    """A part too big for the bin gets scenes with no part in them: training leaves those out
    (with a warning) instead of failing on an empty crop, and refuses a folder of only those."""
    import dataclasses

    from binpick.errors import InputError
    from binpick.generation.scene import generate_scene
    from binpick.io.scene import save_scene
    from binpick.network.train import load_views
    from binpick.view import ViewParams

    scene = generate_scene(
        t_joint, PARAMS.generate, changed(PARAMS.camera, downscale=8), ViewParams(0.002, 0.006), seed=3, n_objects=2
    )
    empty = dataclasses.replace(
        scene,
        view_points_m=np.zeros((0, 3), np.float32),
        view_normals=np.zeros((0, 3), np.float32),
        view_labels=np.zeros(0, np.int16),
    )
    save_scene(tmp_path / "mixed" / "scene_000000.npz", scene, png=False)
    save_scene(tmp_path / "mixed" / "scene_000001.npz", empty, png=False)
    save_scene(tmp_path / "none" / "scene_000000.npz", empty, png=False)
    with caplog.at_level("WARNING", logger="binpick.network.train"):
        views = load_views(tmp_path / "mixed")
    assert len(views) == 1 and len(views.points[0]) == len(scene.view_points_m) > 0
    assert "1 of 2 scenes show no part" in caplog.text
    with pytest.raises(InputError, match="no scene shows the part"):
        load_views(tmp_path / "none")


def test_cover_reaches_every_point_with_few_passes():
    # A strip of 100 x 20 grid points (1 cm apart) in blocks of 500, balls clipped by the strip:
    # 6-8 passes over 20 first seeds (seeds drawn among the uncovered points took 7-10).
    x, y = np.meshgrid(np.arange(100) * 0.01, np.arange(20) * 0.01)
    pts = np.stack([x.ravel(), y.ravel(), np.full(x.size, 0.5)], axis=1)
    blocks = cover(pts, 500, np.random.default_rng(3))
    assert all(len(idx) == 500 for _, idx in blocks)
    assert 4 <= len(blocks) <= 8
    in_block = np.zeros(len(pts), bool)
    for _, idx in blocks:
        in_block[idx] = True
    # A point outside every block is on a block's rim: its nearest grid neighbour (1 cm) is in one.
    left = np.flatnonzero(~in_block)
    if len(left):
        d, _ = cKDTree(pts[in_block]).query(pts[left])
        assert d.max() <= 0.01 + 1e-9


def test_each_next_block_is_seeded_at_the_uncovered_point_farthest_outside_the_blocks_so_far():
    """Random points in a box (float32, as captures are): every seed after the first is, among
    the points neither in a block nor within a point spacing of one, the one farthest outside
    every block's ball, measured here afresh from the blocks returned."""
    rng = np.random.default_rng(8)
    pts = rng.uniform(0.0, 0.3, (6000, 3)).astype(np.float32)
    blocks = cover(pts, 400, np.random.default_rng(2))
    assert len(blocks) > 5
    spacing = float(np.median(cKDTree(pts).query(pts[::6], k=2)[0][:, 1]))
    outside = np.full(len(pts), np.inf)
    covered = np.zeros(len(pts), bool)
    for (seed, idx), (next_seed, _) in zip(blocks[:-1], blocks[1:], strict=True):
        covered[idx] = True
        radius = np.linalg.norm(pts[idx[-1]].astype(float) - pts[seed])
        outside = np.minimum(outside, np.linalg.norm(pts.astype(float) - pts[seed], axis=1) - radius)
        covered |= outside <= spacing
        assert not covered[next_seed]
        assert outside[next_seed] >= outside[~covered].max() - 1e-6


def test_older_checkpoints_keep_their_verification_thresholds(tmp_path):
    """Checkpoints trained before the verify stage carry the thresholds chosen at training: the
    scene path uses them when the part has no verification.json, verification.json wins when it
    has; a checkpoint from before the support threshold reads with none (the default applies)."""
    from binpick.io.verification import Verification, save_verification
    from binpick.network.checkpoint import InferenceSettings, read_checkpoint, read_settings, write_state
    from binpick.network.infer import load_segmenter
    from binpick.scene.process import chosen_verification

    model = FPCC(FPCCConfig(k_neighbours=4, width=8, embedding_dim=6)).eval()
    extra = InferenceSettings("toy", 0.06, "normals", 0.02, PARAMS.train).to_extra()
    save_checkpoint(tmp_path / "m.pt", model, None, 3, {"loss": 1.0}, extra)
    for name, chosen in (
        ("both.pt", {"max_seen_through": 0.41, "min_visible_support": 0.66}),
        ("old.pt", {"max_seen_through": 0.41}),
    ):
        state = read_checkpoint(tmp_path / "m.pt")
        state["extra"] = {**state["extra"], "verification": chosen}
        state.pop("sha256")
        write_state(tmp_path / name, state)
    assert (
        read_settings(tmp_path / "old.pt").max_seen_through,
        read_settings(tmp_path / "old.pt").min_visible_support,
    ) == (0.41, None)
    both = load_segmenter(tmp_path / "both.pt", PARAMS.segment)
    assert chosen_verification(tmp_path / "absent.json", both) == Verification(0.41, 0.66)
    save_verification(tmp_path / "verification.json", Verification(0.38, 0.52, "abc"))
    assert chosen_verification(tmp_path / "verification.json", both) == Verification(0.38, 0.52, "abc")
    assert chosen_verification(None, load_segmenter(tmp_path / "m.pt", PARAMS.segment)) is None


def test_a_support_cut_chosen_with_another_incidence_limit_is_not_used(tmp_path):
    """A verification.json written with today's incidence limit gives its support cut; one written
    before the limit (its support counted all facing surface, lower shares) gives the default,
    and its seen-through cut still applies."""
    import json

    from binpick.io.verification import Verification, load_verification, save_verification
    from binpick.registration.constants import DEFAULT_MIN_VISIBLE_SUPPORT, SUPPORT_MAX_INCIDENCE_DEG
    from binpick.scene.register import with_verification

    params = PARAMS.registration.model_copy(update={"max_seen_through": None, "min_visible_support": None})
    save_verification(tmp_path / "now.json", Verification(0.38, 0.87, "abc", SUPPORT_MAX_INCIDENCE_DEG))
    now = with_verification(params, load_verification(tmp_path / "now.json"))
    assert (now.max_seen_through, now.min_visible_support) == (0.38, 0.87)
    old = {"max_seen_through": 0.4, "min_visible_support": 0.37, "checkpoint_sha256": "abc"}
    (tmp_path / "before.json").write_text(json.dumps(old))
    before = with_verification(params, load_verification(tmp_path / "before.json"))
    assert (before.max_seen_through, before.min_visible_support) == (0.4, DEFAULT_MIN_VISIBLE_SUPPORT)


def test_the_loss_teaches_points_not_of_a_part_to_be_no_centre_and_leaves_ignored_points_out():
    """A part's points (0), a distractor beside it (-1) and unexplained points (-2): the distractor's
    centre scores are pulled to 0 and its embedding pushed from the part's; the ignored points get
    no gradient at all."""
    rng = np.random.default_rng(0)
    part = rng.normal(0, 0.005, (40, 3))
    distractor = rng.normal(0, 0.005, (30, 3)) + [0.03, 0, 0]
    unexplained = rng.normal(0, 0.005, (30, 3)) + [-0.03, 0, 0]
    pts = torch.tensor(np.concatenate([part, distractor, unexplained])[None], dtype=torch.float32)
    lab = torch.tensor([[0] * 40 + [-1] * 30 + [-2] * 30])
    # Every point near the part's embedding (not on it: a distance's gradient is undefined at 0).
    emb = torch.tensor(rng.normal(0, 0.01, (1, 100, 4)), dtype=torch.float32, requires_grad=True)
    ctr = torch.full((1, 100), 0.8, requires_grad=True)  # and scored as a centre
    total, _ = fpcc_loss(emb, ctr, pts, lab, 0.05, 0.5, 1.5, 1.0, "linear", 100, torch.Generator().manual_seed(0))
    total.backward()
    assert torch.all(ctr.grad[0, 40:70] > 0)  # descending lowers the distractor's centre scores
    assert emb.grad[0, 40:70].abs().sum() > 0  # and moves its embedding
    assert torch.count_nonzero(ctr.grad[0, 70:]) == 0 and torch.count_nonzero(emb.grad[0, 70:]) == 0
