"""Stage `generate`: labelled synthetic bin scenes of a part, split into train / val / test."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from binpick.generation.scene import generate_scene
from binpick.io.atomic import atomic_dir
from binpick.io.part_model import PartModel, load_part_model
from binpick.io.pipeline_vars import load_distractors
from binpick.io.scene import save_scene
from binpick.params import Params, load_params
from binpick.part.ingest import ingest_part
from binpick.seeding import derive_seed
from binpick.view import ViewParams
from stages.common import entry, parser, start, write_metrics
from stages.common.fanout import fan_out

log = logging.getLogger("binpick.stage.generate")

SPLITS = ("train", "val", "test")


def make_scene(shared: tuple[PartModel, Params, str, tuple[PartModel, ...]], job: tuple[str, int]) -> int:
    """One scene of the data set, written to <folder>/<split>/scene_<index>.npz; its seed comes
    from the job alone, so the files do not depend on the worker or the order. Returns the
    number of the part's objects placed."""
    part, params, folder, others = shared
    split, index = job
    seed = derive_seed(params.seed, "generate", part.name, split, index)
    view = ViewParams.of_import(params.import_capture)
    scene = generate_scene(part, params.generate, params.camera, view, seed, others=others)
    save_scene(Path(folder) / split / f"scene_{index:06d}.npz", scene)
    return len(scene.T_cam_from_model)


def run(
    params: Params,
    part_model_path: Path,
    out: Path,
    metrics_path: Path | None = None,
    progress: bool = True,
    others: Sequence[PartModel] = (),
) -> dict[str, float]:
    """others: the other parts of a mixed bin the scenes mix in (labelled -1)."""
    part = load_part_model(part_model_path)
    g = params.generate
    jobs = [(split, i) for split, n in zip(SPLITS, (g.n_train, g.n_val, g.n_test), strict=False) for i in range(n)]
    with atomic_dir(out) as tmp:
        for split in SPLITS:
            (tmp / split).mkdir()
        placed = fan_out(
            make_scene,
            (part, params, str(tmp.resolve()), tuple(others)),
            jobs,
            params.orchestration,
            f"generate {part.name}",
            progress,
        )
    metrics = {
        "n_scenes": float(len(jobs)),
        "objects_per_scene_mean": float(np.mean(placed)),
        "objects_per_scene_min": float(np.min(placed)),
    }
    if metrics_path is not None:
        write_metrics(metrics_path, metrics)
    log.info(
        "%s: %d scenes in %s, %.1f objects per scene", part.name, len(jobs), out, metrics["objects_per_scene_mean"]
    )
    expected = g.placement.n_objects_min * (1.0 - g.clutter.parts_share if others else 1.0)
    if metrics["objects_per_scene_mean"] < expected:
        # The bin or the view is too small for the part: few scenes hold a part, some none.
        log.warning(
            "%s: only %.1f of the %d to %d objects per scene were placed (fewest %d): does the part (%.3f m across) "
            "fit the bin "
            "(generate.bin) and the camera's view (camera.distance_m)? Give the part its own in its params entry.",
            part.name,
            metrics["objects_per_scene_mean"],
            g.placement.n_objects_min,
            g.placement.n_objects_max,
            int(metrics["objects_per_scene_min"]),
            part.diameter_m,
        )
    return metrics


@entry
def main(argv: Sequence[str] | None = None) -> int:
    p = parser(__doc__)
    p.add_argument("--part", required=True)
    p.add_argument("--model", required=True, type=Path, help="part model (.npz)")
    p.add_argument("--out", required=True, type=Path, help="data set folder to write (train/, val/, test/)")
    p.add_argument("--distractors", default="", help="the other parts to mix in (binpick check's list; '' = none)")
    p.add_argument("--metrics", type=Path)
    args = p.parse_args(argv)
    start(args)
    others = [
        ingest_part(load_params(args.params, o.name), o.name, Path(o.mesh))[0]
        for o in (load_distractors(args.distractors) if args.distractors else [])
    ]
    if others:
        log.info("%s: mixing in %s", args.part, ", ".join(o.name for o in others))
    run(load_params(args.params, args.part), args.model, args.out, args.metrics, others=others)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
