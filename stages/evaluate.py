"""Stage `evaluate`: instance segmentation quality of the part's network on held-out scenes."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from binpick.io.scene import list_scenes, load_scene
from binpick.metrics.segmentation import SegmentationCounts, scene_counts
from binpick.network.checkpoint import load_checkpoint
from binpick.network.infer import cluster_params, segment_scene
from binpick.network.train import default_device
from binpick.params import Params, load_params
from binpick.seeding import derive_seed
from stages.common import accept_checkpoint, entry, flat_params, mlflow_run, parser, registered_name, start, write_metrics

log = logging.getLogger("binpick.stage.evaluate")


def run(params: Params, checkpoint: Path, scenes: Path, metrics_path: Path | None = None) -> dict[str, float]:
    model, state = load_checkpoint(checkpoint, default_device())
    extra = state["extra"]
    cp = cluster_params(params.segment, extra["part_diameter_m"])
    paths = list_scenes(scenes / "test")
    total = SegmentationCounts()
    for i, path in enumerate(paths):
        scene = load_scene(path)
        rng = np.random.default_rng(derive_seed(params.seed, "evaluate", extra["part"], i))
        labels = segment_scene(model, scene.view_points_m, scene.view_normals, extra["features"], extra["d_max_m"], params.segment.n_points, cp, rng)
        total = total.add(scene_counts(labels, scene.view_labels, params.evaluate.iou_threshold, params.segment.min_points))
    metrics = {**total.summary(), "n_scenes": float(len(paths))}
    ev = params.evaluate
    passed = metrics["precision"] >= ev.accept_precision and metrics["recall"] >= ev.accept_recall
    with mlflow_run(f"part-{extra['part']}", f"evaluate-{extra['part']}", params.tracking.mlflow_uri, {"dvc_stage": f"evaluate@{extra['part']}"}):
        import mlflow

        mlflow.log_params({**flat_params("segment", params.segment), **flat_params("evaluate", params.evaluate)})
        mlflow.log_metrics(metrics)
        version = accept_checkpoint(extra["part"], checkpoint, ev.accept_alias) if passed else None
        if passed and version is None:
            log.warning("%s: %s is not in the model registry; no alias set", extra["part"], checkpoint)
        elif passed:
            log.info("%s: %s version %s is now %r", extra["part"], registered_name(extra["part"]), version, ev.accept_alias)
        else:
            log.info("%s: below the acceptance thresholds; alias %r unchanged", extra["part"], ev.accept_alias)
    metrics["accepted"] = float(version is not None)
    if metrics_path is not None:
        write_metrics(metrics_path, metrics)
    log.info("%s: precision %.3f, recall %.3f on %d test scenes", extra["part"], metrics["precision"], metrics["recall"], len(paths))
    return metrics


@entry
def main(argv: Sequence[str] | None = None) -> int:
    p = parser(__doc__)
    p.add_argument("--part", required=True)
    p.add_argument("--checkpoint", required=True, type=Path)
    p.add_argument("--scenes", required=True, type=Path, help="data set folder of the generate stage")
    p.add_argument("--metrics", type=Path)
    args = p.parse_args(argv)
    start(args)
    run(load_params(args.params, args.part), args.checkpoint, args.scenes, args.metrics)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
