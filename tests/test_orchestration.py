"""Fan-out over a Dask cluster through Prefect's DaskTaskRunner gives what the local process pool
gives; the same seed gives the same data set files, network weights and evaluation metrics."""

import hashlib

import numpy as np
import pytest
import torch

from tests.conftest import ROOT


def _params(tmp_path, **orchestration):
    from binpick.params import Params, load_raw, resolve

    raw = load_raw(ROOT / "params.yaml")
    raw["profiles"]["quick"].update(
        {
            "camera": {"downscale": 8},
            "generate": {"n_train": 4, "n_val": 2, "n_test": 3, "placement": {"n_objects_min": 2, "n_objects_max": 4}},
            "train": {
                "n_points": 256,
                "width": 8,
                "embedding_dim": 8,
                "k_neighbours": 8,
                "epochs": 2,
                "batch_size": 2,
                "loss_anchors": 64,
            },
            "segment": {"n_points": 512},
        }
    )
    raw["orchestration"] = {**raw["orchestration"], **orchestration}
    raw["tracking"] = {"mlflow_uri": f"sqlite:///{tmp_path / 'mlflow.db'}"}
    return Params.model_validate(resolve(raw, "t_joint"))


def _digests(folder):
    return {
        p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


@pytest.fixture(scope="module")
def part_path(tmp_path_factory, t_joint):
    from binpick.io.part_model import save_part_model

    path = tmp_path_factory.mktemp("part") / "part.npz"
    save_part_model(path, t_joint)
    return path


@pytest.mark.slow
def test_dask_fan_out_on_a_two_worker_cluster_matches_the_local_pool(tmp_path, part_path):
    from distributed import LocalCluster
    from prefect.testing.utilities import prefect_test_harness

    from binpick.network.train import load_views, train_fpcc
    from stages import evaluate, generate

    local = _params(tmp_path, workers=2)
    generate.run(local, part_path, tmp_path / "local", progress=False)

    # Training twice from the same seed gives the same weights, bit for bit.
    views = [load_views(tmp_path / "local" / split) for split in ("train", "val")]
    nets = [
        train_fpcc(
            *views,
            local.train,
            0.03,
            seed=5,
            checkpoint_dir=tmp_path / f"work{k}",
            part="t_joint",
            part_diameter_m=0.068,
            progress=False,
        )[0]
        for k in range(2)
    ]
    for (name, a), b in zip(nets[0].state_dict().items(), nets[1].state_dict().values(), strict=False):
        assert torch.equal(a, b), name
    checkpoint = tmp_path / "work0" / "best.pt"
    assert checkpoint.read_bytes() == (tmp_path / "work1" / "best.pt").read_bytes()  # byte for byte

    metrics_local = evaluate.run(local, checkpoint, tmp_path / "local", progress=False)
    with (
        LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster,
        prefect_test_harness(server_startup_timeout=120),
    ):
        assert len(cluster.workers) == 2
        on_dask = _params(tmp_path, task_runner="dask", dask_address=cluster.scheduler_address)
        generate.run(on_dask, part_path, tmp_path / "dask", progress=False)
        metrics_dask = evaluate.run(on_dask, checkpoint, tmp_path / "local", progress=False)
    digests = _digests(tmp_path / "local")
    assert len(digests) == 2 * 9  # a scene file and its label image per scene
    assert _digests(tmp_path / "dask") == digests
    assert metrics_dask == metrics_local
    assert metrics_local["n_scenes"] == 3 and np.isfinite(metrics_local["precision"])

    # The segmentation benchmark scores with the evaluate stage's routine: the same numbers.
    from flows.bench.segmentation import bench_segment

    bench = bench_segment(
        checkpoint,
        tmp_path / "local",
        local.segment,
        local.import_capture.voxel_size_m,
        local.seed,
        local.evaluate.iou_threshold,
        repeats=1,
    )
    assert (bench["precision"], bench["recall"]) == (metrics_local["precision"], metrics_local["recall"])
    assert set(bench["baseline_dbscan"]) >= {"precision", "recall"} and bench["infer_ms_per_scene_16384"] > 0
