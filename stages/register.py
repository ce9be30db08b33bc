"""Stage `register`: the part's CAD model fitted onto every segment by PPF matching and ICP,
a pose and a score per part; errors against ground truth when the capture has it; a rerun
recording of the result."""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from binpick.errors import InputError
from binpick.io.atomic import atomic_paths
from binpick.io.cloud import load_cloud, load_segments
from binpick.io.part_model import load_part_model
from binpick.io.poses import load_poses, save_poses
from binpick.io.ppf_model import load_ppf_model
from binpick.io.verification import load_verification
from binpick.metrics.pose import scene_pose_metrics
from binpick.params import Params, load_params
from binpick.scene.register import register, with_verification
from binpick.seeding import scene_seeds
from review.recording import write_scene_recording
from review.tracking import mlflow_run
from stages.common import entry, parser, start, write_metrics

log = logging.getLogger("binpick.stage.register")


def run(
    params: Params,
    name: str,
    cloud_path: Path,
    segments_path: Path,
    ppf_path: Path,
    part_model_path: Path,
    out: Path,
    truth_path: Path | None = None,
    metrics_path: Path | None = None,
    rrd_path: Path | None = None,
    verification: Path | None = None,
) -> dict[str, float]:
    cloud = load_cloud(cloud_path)
    segments = load_segments(segments_path)
    if len(segments.labels) != len(cloud.points_m):
        raise InputError(segments_path, f"has {len(segments.labels)} labels for {len(cloud.points_m)} cloud points")
    ppf = load_ppf_model(ppf_path)
    part = load_part_model(part_model_path)
    t0 = time.perf_counter()
    chosen = load_verification(verification) if verification is not None else None
    result = register(
        cloud,
        segments.labels,
        ppf,
        with_verification(params.registration, chosen),
        scene_seeds(params.seed, cloud.capture_digest, cloud_path).register,
        segments.is_part,
    )
    register_s = time.perf_counter() - t0
    estimates = result.poses
    metrics: dict[str, float] = {
        "register_s": register_s,
        "ms_per_instance_median": float(np.median(result.per_instance_ms)) if result.per_instance_ms else 0.0,
        "n_segments": float(result.n_segments),
        "n_duplicates_suppressed": float(result.n_duplicates_suppressed),
        "n_seen_through": float(result.n_seen_through),
        "n_unsupported": float(result.n_unsupported),
        "n_not_part": float(result.n_not_part),
        "n_in_the_floor": float(result.n_in_the_floor),
        "capture_noise_mm": 1000.0 * result.capture_noise_m,
        "n_found": float(len(estimates)),
        "score_mean": float(np.mean([e.score for e in estimates])) if estimates else 0.0,
    }
    truth = None
    if truth_path is not None:
        _, truth = load_poses(truth_path)
        summary, _ = scene_pose_metrics(
            np.array([e.T_cam_from_model for e in estimates]).reshape(-1, 4, 4),
            np.array([t.T_cam_from_model for t in truth]).reshape(-1, 4, 4),
            np.array([1.0 if t.visible_fraction is None else t.visible_fraction for t in truth]),
            ppf.dense_points_m,
            ppf.symmetries,
            ppf.diameter_m,
        )
        metrics.update(summary)
    timings = {"register_s": register_s}
    # Poses, recording and metrics are committed together, after the MLflow run was logged.
    with atomic_paths(out, rrd_path, metrics_path) as (tmp_out, tmp_rrd, tmp_metrics):
        save_poses(tmp_out, part.name, estimates)
        if tmp_rrd is not None:
            write_scene_recording(
                tmp_rrd,
                name,
                cloud,
                segments.labels,
                part,
                estimates,
                truth,
                {k.removesuffix("_s"): v for k, v in timings.items()},
            )
        if tmp_metrics is not None:
            write_metrics(tmp_metrics, metrics)
        _log_run(params, name, part.name, metrics, timings, estimates)
    log.info(
        "%s: %d poses (%s, %.0f segments) in %.2f s",
        name,
        len(estimates),
        params.registration.mode,
        metrics["n_segments"],
        register_s,
    )
    return metrics


def _log_run(
    params: Params, name: str, part: str, metrics: dict[str, float], timings: dict[str, float], estimates: list
) -> None:
    with mlflow_run(
        "scenes",
        f"scene-{name}",
        params.tracking.mlflow_uri,
        {"part": part, "capture": name, "dvc_stage": f"register@{name}"},
    ):
        import mlflow

        mlflow.log_metrics({k: v for k, v in {**metrics, **timings}.items() if np.isfinite(v)})
        for k, e in enumerate(estimates):
            mlflow.log_metric("pose_score", e.score, step=k)
        mlflow.log_dict(
            {
                "part": part,
                "poses": [
                    {"segment": e.segment, "score": e.score, "T_cam_from_model": e.T_cam_from_model.tolist()}
                    for e in estimates
                ],
            },
            "poses.json",
        )


@entry
def main(argv: Sequence[str] | None = None) -> int:
    p = parser(__doc__)
    p.add_argument("--name", required=True, help="capture name (for seeds, runs and recordings)")
    p.add_argument("--part", required=True)
    p.add_argument("--cloud", required=True, type=Path)
    p.add_argument("--segments", required=True, type=Path)
    p.add_argument("--ppf", required=True, type=Path, help="the part's PPF model (.npz)")
    p.add_argument("--part-model", required=True, type=Path, help="the part model (.npz)")
    p.add_argument("--out", required=True, type=Path, help="poses to write (.json)")
    p.add_argument("--truth", default="", help="ground-truth poses (.json), '' for none")
    p.add_argument("--metrics", type=Path)
    p.add_argument("--rrd", type=Path, help="rerun recording to write")
    p.add_argument(
        "--verification", type=Path, help="the part's verification thresholds (verify stage); none: register's defaults"
    )
    args = p.parse_args(argv)
    start(args)
    run(
        load_params(args.params, args.part),
        args.name,
        args.cloud,
        args.segments,
        args.ppf,
        args.part_model,
        args.out,
        Path(args.truth) if args.truth else None,
        args.metrics,
        args.rrd,
        args.verification,
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
