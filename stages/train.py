"""Stage `train`: the part's FPCC network, trained on its generated scenes."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from binpick.io.part_model import load_part_model
from binpick.network.calibrate import CALIBRATED, recalibrate
from binpick.network.infer import cluster_params, default_device, segment_scene
from binpick.network.train import BEST, LAST, load_views, train_fpcc
from binpick.params import Params, load_params
from binpick.seeding import derive_int, derive_seed
from review.recording import TrainingRecording
from review.tracking import add_model_version, flat_params, mlflow_run, model_name
from stages.common import entry, parser, start, write_metrics

log = logging.getLogger("binpick.stage.train")


def d_max(params: Params, diameter_m: float) -> float:
    """d_max of the centre score: from params, else half the part diameter."""
    return params.train.d_max_m if params.train.d_max_m is not None else diameter_m / 2.0


# Sample predictions: this many validation views, after about this many evenly spread epochs.
SAMPLE_VIEWS = 2
SAMPLE_EPOCHS = 8


def run(
    params: Params,
    part_model_path: Path,
    scenes: Path,
    out: Path,
    work: Path,
    metrics_path: Path | None = None,
    progress: bool = True,
) -> dict[str, float]:
    part = load_part_model(part_model_path)
    train_views, val_views = load_views(scenes / "train"), load_views(scenes / "val")
    dm = d_max(params, part.diameter_m)
    device = default_device()
    log.info("%s: training on %d scenes (%d validation) on %s", part.name, len(train_views), len(val_views), device)
    with mlflow_run(
        f"part-{part.name}", f"train-{part.name}", params.tracking.mlflow_uri, {"dvc_stage": f"train@{part.name}"}
    ) as run_:
        import mlflow

        mlflow.log_params(
            {
                **flat_params("train", params.train),
                "train.d_max_m_resolved": dm,
                "seed": params.seed,
                "device": str(device),
            }
        )
        # Written under a temporary name and moved into place when training ends, so that a killed
        # training leaves no truncated recording under the real name.
        partial = work / ".samples.partial.rrd"
        partial.unlink(missing_ok=True)
        samples = TrainingRecording(
            partial,
            part.name,
            [(val_views.points[i], val_views.labels[i]) for i in range(min(SAMPLE_VIEWS, len(val_views)))],
        )
        every = max(1, params.train.epochs // SAMPLE_EPOCHS)
        cp = cluster_params(params.segment, part.diameter_m)

        def on_epoch(epoch: int, m: dict[str, float], model) -> None:
            mlflow.log_metrics(m, step=epoch)
            if epoch % every == 0 or epoch == params.train.epochs - 1:
                rng = np.random.default_rng(derive_seed(params.seed, "train-samples", part.name))
                predictions = [
                    segment_scene(
                        model,
                        val_views.points[i],
                        val_views.normals[i],
                        params.train.features,
                        dm,
                        params.segment.n_points,
                        cp,
                        rng,
                    )
                    for i in range(len(samples.views))
                ]
                samples.log_epoch(epoch, predictions, m)

        try:
            _, metrics = train_fpcc(
                train_views,
                val_views,
                params.train,
                dm,
                derive_int(params.seed, "train", part.name),
                work,
                part.name,
                part.diameter_m,
                on_epoch=on_epoch,
                device=device,
                progress=progress,
            )
        finally:
            samples.close()
        partial.replace(work / "samples.rrd")
        mlflow.log_artifact(str(work / "samples.rrd"), artifact_path="samples")
        out.parent.mkdir(parents=True, exist_ok=True)
        chosen = recalibrate(
            work / BEST,
            out,
            val_views,
            params.segment,
            params.evaluate.iou_threshold,
            np.random.default_rng(derive_seed(params.seed, "calibrate", part.name)),
        )
        log.info(
            "%s: clustering calibrated on %d validation scenes: centre threshold %.2f, embedding threshold %.2f, "
            "smallest instance %d points, foreground logit above %.1f (P/R %.2f/%.2f)",
            part.name,
            len(val_views),
            chosen["centre_threshold"],
            chosen["embedding_threshold"],
            chosen["min_instance_points"],
            chosen["foreground_logit"],
            chosen["precision"],
            chosen["recall"],
        )
        metrics.update({f"calibrated_{k}" if k in CALIBRATED else f"val_{k}": v for k, v in chosen.items()})
        mlflow.log_metrics(
            {k: metrics[k] for k in [f"calibrated_{k}" for k in CALIBRATED] + ["val_precision", "val_recall"]}
        )
        mlflow.log_artifact(str(out), artifact_path="model")
        version = add_model_version(part.name, out, run_, f"train@{part.name}")
        # The run id and version stay in MLflow: the DVC metrics hold only what a rerun reproduces.
        log.info(
            "%s: MLflow run %s, registered as %s version %s",
            part.name,
            run_.info.run_id,
            model_name(part.name),
            version,
        )
    if metrics_path is not None:
        write_metrics(metrics_path, metrics)
    # The resume points belong to this finished training: the next run of the stage (changed
    # inputs, or `dvc repro --force`) trains from scratch instead of resuming a finished run.
    for name in (LAST, BEST):
        (work / name).unlink(missing_ok=True)
    log.info(
        "%s: best validation loss %.4f at epoch %d -> %s",
        part.name,
        metrics["best_val_loss"],
        metrics["best_epoch"],
        out,
    )
    return metrics


@entry
def main(argv: Sequence[str] | None = None) -> int:
    p = parser(__doc__)
    p.add_argument("--part", required=True)
    p.add_argument("--model", required=True, type=Path, help="part model (.npz)")
    p.add_argument("--scenes", required=True, type=Path, help="data set folder of the generate stage")
    p.add_argument("--out", required=True, type=Path, help="checkpoint to write (.pt)")
    p.add_argument("--work", required=True, type=Path, help="folder for resumable checkpoints")
    p.add_argument("--metrics", type=Path)
    args = p.parse_args(argv)
    start(args)
    run(load_params(args.params, args.part), args.model, args.scenes, args.out, args.work, args.metrics)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
