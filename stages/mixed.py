"""Stage `mixed`: a capture of several kinds of part (a capture entry naming `parts`) through the
mixed scene path (binpick/scene/mixed.py): cleaned once per import setting of the parts, each
part's segmentation and registration, conflicts between parts resolved, one pick list naming
each pick's part. picks.json holds the answer the service gives for the same capture (the same
seeds, from the capture's content), with every kept pose."""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from binpick.errors import BinpickError
from binpick.io.atomic import atomic_paths
from binpick.io.capture import ImportOptions, load_capture
from binpick.io.picks import write_picks_document
from binpick.layout import Layout
from binpick.params import load_params
from binpick.scene.mixed import process_mixed
from binpick.scene.process import PartModels
from binpick.seeding import SceneSeeds
from review.tracking import mlflow_run
from stages.common import entry, parser, start, write_metrics

log = logging.getLogger("binpick.stage.mixed")


def run(params_path: Path, name: str, out: Path, metrics_path: Path | None = None, root: Path = Path()) -> dict:
    """The capture `name` of params.yaml (its entry names `parts`) answered from the parts' built
    models under `root`; picks.json to `out`."""
    params = load_params(params_path)
    listed = params.captures.get(name)
    if listed is None or not listed.parts:
        raise BinpickError(f"{params_path}: capture {name!r} is not listed under 'captures' with `parts`")
    layout = Layout(root)
    models: dict[str, PartModels] = {}
    resolved = {part: load_params(params_path, part) for part in listed.parts}
    for part, p in resolved.items():
        checkpoint = layout.checkpoint(part)
        loaded = PartModels.load(
            p,
            layout.part_model(part),
            layout.ppf_model(part),
            checkpoint if checkpoint.is_file() else None,
            layout.grasps(part),
            layout.verification(part),
        )
        # The part's import settings with this capture's own overrides (its sensor's).
        models[part] = replace(loaded, import_params=p.import_capture_for(name))
    grippers: dict[str, str] = {part: p.pick.gripper for part, p in resolved.items()}
    first = resolved[listed.parts[0]]
    options = ImportOptions(
        unit=listed.unit,
        columns=tuple(listed.columns),
        intrinsics=root / listed.intrinsics if listed.intrinsics else None,
    )
    t0 = time.perf_counter()
    frame = load_capture(root / listed.file, options)
    try:
        result = process_mixed(
            frame.xyz_m,
            frame.rgb,
            frame.shape,
            models,
            SceneSeeds.of_capture(params.seed, frame.xyz_m, frame.rgb),
            params.pick.part_priority,
            quota=params.pick.part_quota,
        )
    except BinpickError as exc:
        raise BinpickError(f"{listed.file}: {exc}") from None
    seconds = time.perf_counter() - t0
    T_base = np.asarray(first.pick.T_base_from_cam) if first.pick.T_base_from_cam is not None else None
    doc = result.document(name, grippers, T_base, first.pick.pose_format)
    metrics: dict[str, float] = {
        "mixed_s": seconds,
        **{k: float(v) for k, v in result.timings_s.items()},
        **{f"n_poses_{part}": float(len(found)) for part, found in result.poses.items()},
        **doc["counts"],
    }
    with atomic_paths(out, metrics_path) as (tmp_out, tmp_metrics):
        write_picks_document(tmp_out, doc)
        if tmp_metrics is not None:
            write_metrics(tmp_metrics, metrics)
        with mlflow_run(
            "scenes",
            f"mixed-{name}",
            params.tracking.mlflow_uri,
            {"parts": ",".join(listed.parts), "capture": name, "dvc_stage": f"mixed@{name}"},
        ):
            import mlflow

            mlflow.log_metrics(metrics)
    log.info(
        "%s: %s; %d picks, %d conflicts in %.2f s",
        name,
        ", ".join(f"{len(found)} {part}" for part, found in result.poses.items()),
        len(result.picks),
        len(result.conflicts),
        seconds,
    )
    return metrics


@entry
def main(argv: Sequence[str] | None = None) -> int:
    p = parser(__doc__)
    p.add_argument("--name", required=True, help="a capture listed in params.yaml whose entry names `parts`")
    p.add_argument("--out", required=True, type=Path, help="picks to write (.json)")
    p.add_argument("--metrics", type=Path)
    args = p.parse_args(argv)
    start(args)
    run(Path(args.params), args.name, args.out, args.metrics)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
