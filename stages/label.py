"""Stage `label`: a capture's cleaned points labelled from the poses the register stage trusted
with margin (learning from the cell, binpick.learning): a labelled capture the part's network
can be fine-tuned on once a person has reviewed it (`binpick learn review`)."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from binpick.cell.bin_box import BinBox
from binpick.errors import InputError
from binpick.io.atomic import atomic_paths
from binpick.io.cloud import load_cloud
from binpick.io.labelled_capture import save_labelled_capture
from binpick.io.poses import load_poses
from binpick.io.ppf_model import load_ppf_model
from binpick.labels import IGNORE
from binpick.learning import label_capture
from binpick.params import Params, load_params
from stages.common import entry, parser, start, write_metrics

log = logging.getLogger("binpick.stage.label")


def run(
    params: Params,
    part: str,
    cloud_path: Path,
    poses_path: Path,
    ppf_path: Path,
    out: Path,
    metrics_path: Path | None = None,
) -> dict[str, float]:
    cloud = load_cloud(cloud_path)
    posed_part, poses = load_poses(poses_path)
    if posed_part != part:
        raise InputError(poses_path, f"holds poses of part {posed_part!r}, not {part!r}")
    ppf = load_ppf_model(ppf_path)
    labelled = label_capture(
        cloud,
        poses,
        ppf.dense_points_m,
        ppf.diameter_m,
        params.registration.min_score,
        params.learn.trust_margin,
        params.import_capture.voxel_size_m,
        BinBox.of_import(params.import_capture),
    )
    n = len(labelled.labels)
    metrics = {
        "n_poses": float(len(poses)),
        "n_trusted": float(len(labelled.T_cam_from_model)),
        "labelled_fraction": float(np.mean(labelled.labels != IGNORE)) if n else 0.0,
        "near_mm": 1000.0 * float(labelled.near_m),
    }
    with atomic_paths(out, metrics_path) as (tmp_out, tmp_metrics):
        save_labelled_capture(tmp_out, labelled)
        if tmp_metrics is not None:
            write_metrics(tmp_metrics, metrics)
    log.info(
        "%s: %d of %d poses trusted, %.0f%% of %d points labelled (within %.1f mm), the rest ignored",
        cloud_path,
        metrics["n_trusted"],
        len(poses),
        100 * metrics["labelled_fraction"],
        n,
        metrics["near_mm"],
    )
    return metrics


@entry
def main(argv: Sequence[str] | None = None) -> int:
    p = parser(__doc__)
    p.add_argument("--part", required=True)
    p.add_argument("--cloud", required=True, type=Path, help="clean cloud of the import stage (.npz)")
    p.add_argument("--poses", required=True, type=Path, help="poses of the register stage (poses.json)")
    p.add_argument("--ppf", required=True, type=Path, help="the part's PPF model (its dense surface sample)")
    p.add_argument("--out", required=True, type=Path, help="labelled capture to write (.npz)")
    p.add_argument("--metrics", type=Path)
    args = p.parse_args(argv)
    start(args)
    run(load_params(args.params, args.part), args.part, args.cloud, args.poses, args.ppf, args.out, args.metrics)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
