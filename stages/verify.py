"""Stage `verify`: the part's pose verification thresholds (register.max_seen_through,
register.min_visible_support), chosen on its validation scenes with its trained network
(binpick/scene/verification_threshold.py). Its own stage, so that a change to registration or picking
re-runs this choice and not the training."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

from binpick.io.atomic import atomic_paths
from binpick.io.part_model import load_part_model
from binpick.io.ppf_model import load_ppf_model
from binpick.io.scene import list_scenes, load_scene
from binpick.io.verification import Verification, save_verification
from binpick.network.checkpoint import read_checkpoint
from binpick.network.infer import load_segmenter
from binpick.params import Params, load_params
from binpick.registration.constants import SUPPORT_MAX_INCIDENCE_DEG
from binpick.scene.process import PartModels
from binpick.scene.verification_threshold import calibrate_verification
from review.tracking import mlflow_run
from stages.common import entry, parser, start, write_metrics

log = logging.getLogger("binpick.stage.verify")


def run(
    params: Params,
    part_model_path: Path,
    ppf_path: Path,
    checkpoint: Path,
    scenes: Path,
    out: Path,
    metrics_path: Path | None = None,
) -> dict[str, float]:
    part = load_part_model(part_model_path)
    models = PartModels(
        part,
        load_ppf_model(ppf_path),
        load_segmenter(checkpoint, params.segment),
        params.import_capture,
        params.registration,
    )
    val = [load_scene(p) for p in list_scenes(scenes / "val")]
    threshold, support, stats = calibrate_verification(val, models, params.seed, part.name)
    log.info(
        "%s: pose verification on %d validation scenes: at most %.2f seen through (%d right poses up to %.2f, %d "
        "wrong from %.2f), "
        "at least %.2f visible support (right poses from %.2f, wrong up to %.2f)",
        part.name,
        len(val),
        threshold,
        stats["n_right"],
        stats["right_max"],
        stats["n_wrong"],
        stats["wrong_min"],
        support,
        stats["right_support_min"],
        stats["wrong_support_max"],
    )
    metrics = {"max_seen_through": threshold, "min_visible_support": support}
    with mlflow_run(
        f"part-{part.name}", f"verify-{part.name}", params.tracking.mlflow_uri, {"dvc_stage": f"verify@{part.name}"}
    ):
        import mlflow

        # What it was chosen on goes to MLflow only: which borderline validation poses ICP's
        # threads find can differ between runs, and the DVC metrics hold what a rerun reproduces.
        mlflow.log_metrics({**metrics, **{f"verification_{k}": v for k, v in stats.items()}})
    with atomic_paths(out, metrics_path) as (tmp_out, tmp_metrics):
        save_verification(
            tmp_out,
            Verification(threshold, support, str(read_checkpoint(checkpoint)["sha256"]), SUPPORT_MAX_INCIDENCE_DEG),
        )
        if tmp_metrics is not None:
            write_metrics(tmp_metrics, metrics)
    return metrics


@entry
def main(argv: Sequence[str] | None = None) -> int:
    p = parser(__doc__)
    p.add_argument("--part", required=True)
    p.add_argument("--model", required=True, type=Path, help="part model (.npz)")
    p.add_argument("--ppf", required=True, type=Path, help="the part's PPF model (.npz)")
    p.add_argument("--checkpoint", required=True, type=Path, help="the part's trained network (.pt)")
    p.add_argument(
        "--scenes", required=True, type=Path, help="data set folder of the generate stage (its val/ split is used)"
    )
    p.add_argument("--out", required=True, type=Path, help="verification thresholds to write (.json)")
    p.add_argument("--metrics", type=Path)
    args = p.parse_args(argv)
    start(args)
    run(load_params(args.params, args.part), args.model, args.ppf, args.checkpoint, args.scenes, args.out, args.metrics)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
