"""Stage `evaluate`: instance segmentation quality of the part's network on held-out scenes."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

from binpick.io.digest import file_sha256
from binpick.io.scene import list_scenes, load_scene
from binpick.metrics.segmentation import SegmentationCounts
from binpick.network.checkpoint import InferenceSettings, read_checkpoint
from binpick.network.evaluate import segment_and_count
from binpick.network.infer import Segmenter, load_segmenter
from binpick.params import Params, load_params
from review.tracking import accept_checkpoint, flat_params, mlflow_run, model_name
from stages.common import entry, parser, start, write_metrics
from stages.common.fanout import fan_out

log = logging.getLogger("binpick.stage.evaluate")


# Per-process cache of the network, so that each worker loads the checkpoint once.
_MODELS: dict[str, Segmenter] = {}


def evaluate_scene(shared: tuple[str, Params], job: tuple[int, str]) -> SegmentationCounts:
    """Segment one held-out scene with the checkpoint and count its matches against the labels;
    the sampling seed comes from the scene's index, so any worker gives the same counts."""
    checkpoint, params = shared
    index, path = job
    key = f"{checkpoint}@{Path(checkpoint).stat().st_mtime_ns}"  # a retrained file is reloaded
    if key not in _MODELS:
        _MODELS.clear()
        _MODELS[key] = load_segmenter(Path(checkpoint), params.segment)
    _, counts = segment_and_count(
        _MODELS[key], load_scene(Path(path)), params.segment, params.evaluate.iou_threshold, params.seed, index
    )
    return counts


def run(
    params: Params, checkpoint: Path, scenes: Path, metrics_path: Path | None = None, progress: bool = True
) -> dict[str, float]:
    part = InferenceSettings.from_extra(read_checkpoint(checkpoint, "cpu")["extra"], checkpoint).part
    paths = list_scenes(scenes / "test")
    jobs = [(i, str(path)) for i, path in enumerate(paths)]
    # Locally one process: the network already uses every core; a Dask cluster spreads the scenes.
    counts = fan_out(
        evaluate_scene,
        (str(checkpoint.resolve()), params),
        jobs,
        params.orchestration,
        f"evaluate {part}",
        progress,
        max_workers=1,
    )
    total = SegmentationCounts()
    for c in counts:
        total = total.add(c)
    metrics = {**total.summary(), "n_scenes": float(len(paths))}
    ev = params.evaluate
    passed = metrics["precision"] >= ev.accept_precision and metrics["recall"] >= ev.accept_recall
    with mlflow_run(f"part-{part}", f"evaluate-{part}", params.tracking.mlflow_uri, {"dvc_stage": f"evaluate@{part}"}):
        import mlflow

        mlflow.log_params({**flat_params("segment", params.segment), **flat_params("evaluate", params.evaluate)})
        mlflow.log_metrics(metrics)
        version = accept_checkpoint(part, checkpoint, ev.accept_alias) if passed else None
        if passed and version is None:
            log.warning("%s: %s is not in the model registry; no alias set", part, checkpoint)
        elif passed:
            log.info("%s: %s version %s is now %r", part, model_name(part), version, ev.accept_alias)
        else:
            log.info("%s: below the acceptance thresholds; alias %r unchanged", part, ev.accept_alias)
    # Accepted means the figures passed; the registry alias is set besides when the run is registered.
    metrics["accepted"] = float(passed)
    if metrics_path is not None:
        # The service serves a network only when this digest is the served file's (mtimes do not
        # survive a clone and `dvc checkout`).
        write_metrics(metrics_path, {**metrics, "checkpoint_sha256": file_sha256(checkpoint)})
    log.info(
        "%s: precision %.3f, recall %.3f on %d test scenes", part, metrics["precision"], metrics["recall"], len(paths)
    )
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
