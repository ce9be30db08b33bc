"""Stage `segment`: every point of a clean scene gets a part instance label (or -1) from the
part's FPCC network, and whether the network calls it a part's at all."""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from binpick.io.atomic import atomic_paths
from binpick.io.cloud import load_cloud, save_segments
from binpick.network.infer import load_segmenter
from binpick.params import Params, load_params
from binpick.scene.segment import segment
from binpick.seeding import scene_seeds
from stages.common import entry, log_timings, parser, start, write_metrics

log = logging.getLogger("binpick.stage.segment")


def run(
    params: Params,
    cloud_path: Path,
    checkpoint: Path,
    out: Path,
    metrics_path: Path | None = None,
    name: str | None = None,
) -> dict[str, float]:
    cloud = load_cloud(cloud_path)
    segmenter = load_segmenter(checkpoint, params.segment)
    t0 = time.perf_counter()
    segments = segment(cloud, segmenter, scene_seeds(params.seed, cloud.capture_digest, cloud_path).segment)
    labels = segments.labels
    seconds = time.perf_counter() - t0
    n_inst = int(labels.max()) + 1 if len(labels) else 0
    metrics = {
        "segment_s": seconds,
        "n_instances": float(n_inst),
        "noise_fraction": float(np.mean(labels < 0)) if len(labels) else 0.0,
        "not_a_part_fraction": float(np.mean(~segments.is_part)) if len(labels) else 0.0,
    }
    with atomic_paths(out, metrics_path) as (tmp_out, tmp_metrics):
        save_segments(tmp_out, segments)
        if tmp_metrics is not None:
            write_metrics(tmp_metrics, metrics)
            if name:
                log_timings(
                    "scenes",
                    f"segment-{name}",
                    params.tracking.mlflow_uri,
                    f"segment@{name}",
                    metrics,
                    {"capture": name},
                )
    log.info("%s: %d instances in %.2f s", cloud_path, n_inst, seconds)
    return metrics


@entry
def main(argv: Sequence[str] | None = None) -> int:
    p = parser(__doc__)
    p.add_argument("--name", default="", help="capture name (for its MLflow run)")
    p.add_argument("--part", required=True)
    p.add_argument("--cloud", required=True, type=Path, help="clean cloud of the import stage (.npz)")
    p.add_argument("--checkpoint", required=True, type=Path, help="the part's FPCC checkpoint (.pt)")
    p.add_argument("--out", required=True, type=Path, help="segments to write (.npz)")
    p.add_argument("--metrics", type=Path)
    args = p.parse_args(argv)
    start(args)
    run(load_params(args.params, args.part), args.cloud, args.checkpoint, args.out, args.metrics, args.name or None)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
