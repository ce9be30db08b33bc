"""Stage `pick`: for every part the register stage found, a collision-free grasp, ranked
(binpick/picking/plan.py); picks.json in the camera and robot base frames, a rerun recording with the
gripper at the first picks and the refused grasps, the counts in MLflow."""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from binpick.io.atomic import atomic_paths
from binpick.io.cloud import load_cloud
from binpick.io.grasps import load_grasps
from binpick.io.part_model import load_part_model
from binpick.io.picks import save_picks
from binpick.io.poses import load_poses
from binpick.params import Params, load_params
from binpick.part.model import density_kg_m3
from binpick.scene.pick import pick
from review.pick_recording import write_pick_recording
from review.tracking import mlflow_run
from stages.common import entry, parser, start, write_metrics

log = logging.getLogger("binpick.stage.pick")


def run(
    params: Params,
    name: str,
    cloud_path: Path,
    poses_path: Path,
    part_model_path: Path,
    grasps_path: Path,
    out: Path,
    metrics_path: Path | None = None,
    rrd_path: Path | None = None,
) -> dict[str, float]:
    cloud = load_cloud(cloud_path)
    _, poses = load_poses(poses_path)
    part = load_part_model(part_model_path)
    kind = params.pick.gripper
    grasps = load_grasps(grasps_path, params.pick.oval_cup)[kind]
    t0 = time.perf_counter()
    plan = pick(
        cloud,
        poses,
        part,
        grasps,
        params.pick,
        params.import_capture_for(name if name in params.captures else None),
        params.cell,
        density_kg_m3=density_kg_m3(params, part.name),
    )
    pick_s = time.perf_counter() - t0
    metrics = {"pick_s": pick_s, **plan.counts()}
    T_base = np.asarray(params.pick.T_base_from_cam) if params.pick.T_base_from_cam is not None else None
    with atomic_paths(out, rrd_path, metrics_path) as (tmp_out, tmp_rrd, tmp_metrics):
        save_picks(tmp_out, name, part.name, kind, plan, T_base, params.pick.pose_format)
        if tmp_rrd is not None:
            write_pick_recording(tmp_rrd, name, cloud, part, poses, plan, kind, params.pick)
        if tmp_metrics is not None:
            write_metrics(tmp_metrics, metrics)
        with mlflow_run(
            "scenes",
            f"picks-{name}",
            params.tracking.mlflow_uri,
            {"part": part.name, "capture": name, "dvc_stage": f"pick@{name}", "gripper": kind},
        ):
            import mlflow

            mlflow.log_metrics(metrics)
    first = f"; first: part {plan.picks[0].pose_index}, grasp {plan.picks[0].grasp_id}" if plan.picks else ""
    log.info("%s: %d picks for %d parts in %.2f s%s", name, len(plan.picks), len(poses), pick_s, first)
    return metrics


@entry
def main(argv: Sequence[str] | None = None) -> int:
    p = parser(__doc__)
    p.add_argument("--name", required=True, help="capture name")
    p.add_argument("--part", required=True)
    p.add_argument("--cloud", required=True, type=Path)
    p.add_argument("--poses", required=True, type=Path)
    p.add_argument("--part-model", required=True, type=Path)
    p.add_argument("--grasps", required=True, type=Path, help="the part's grasps (.json)")
    p.add_argument("--out", required=True, type=Path, help="picks to write (.json)")
    p.add_argument("--metrics", type=Path)
    p.add_argument("--rrd", type=Path, help="rerun recording of the picks")
    args = p.parse_args(argv)
    start(args)
    run(
        load_params(args.params, args.part),
        args.name,
        args.cloud,
        args.poses,
        args.part_model,
        args.grasps,
        args.out,
        args.metrics,
        args.rrd,
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
