"""Stage `generate`: labelled synthetic bin scenes of a part, split into train / val / test."""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context
from pathlib import Path

import numpy as np
from tqdm import tqdm

from binpick.generation.scene import ViewParams, generate_scene
from binpick.io.atomic import atomic_dir
from binpick.io.part_model import PartModel, load_part_model
from binpick.io.scene import save_scene
from binpick.params import Params, load_params
from binpick.seeding import derive_seed
from stages.common import entry, parser, start, write_metrics

log = logging.getLogger("binpick.stage.generate")

SPLITS = ("train", "val", "test")

# Per-process state of the workers, set once by _init_worker.
_WORKER: dict = {}


def view_params(params: Params) -> ViewParams:
    """The network's view is cleaned like an imported capture: same voxel grid and normal radius."""
    return ViewParams(
        voxel_size_m=params.scene_import.voxel_size_m,
        normal_radius_m=params.scene_import.normal_radius_m,
    )


def _init_worker(part: PartModel, params: Params) -> None:
    _WORKER["part"], _WORKER["params"] = part, params


def _make_one(split: str, index: int, folder: str) -> tuple[str, int, int]:
    part: PartModel = _WORKER["part"]
    params: Params = _WORKER["params"]
    seed = derive_seed(params.seed, "generate", part.name, split, index)
    scene = generate_scene(part, params.generate, params.camera, view_params(params), seed)
    save_scene(Path(folder) / split / f"scene_{index:06d}.npz", scene)
    return split, index, len(scene.T_cam_from_model)


def run(params: Params, part_model_path: Path, out: Path, metrics_path: Path | None = None, progress: bool = True) -> dict[str, float]:
    part = load_part_model(part_model_path)
    g = params.generate
    jobs = [(split, i) for split, n in zip(SPLITS, (g.n_train, g.n_val, g.n_test)) for i in range(n)]
    workers = g.workers or os.cpu_count() or 1
    placed: list[int] = []
    with atomic_dir(out) as tmp:
        for split in SPLITS:
            (tmp / split).mkdir()
        bar = tqdm(total=len(jobs), desc=f"generate {part.name}", unit="scene", disable=not progress)
        if workers == 1:
            _init_worker(part, params)
            for split, i in jobs:
                placed.append(_make_one(split, i, str(tmp))[2])
                bar.update()
        else:
            # spawn, not fork: Open3D's thread pools do not survive a fork.
            with ProcessPoolExecutor(workers, mp_context=get_context("spawn"), initializer=_init_worker, initargs=(part, params)) as pool:
                futures = [pool.submit(_make_one, split, i, str(tmp)) for split, i in jobs]
                for f in as_completed(futures):
                    placed.append(f.result()[2])
                    bar.update()
        bar.close()
    metrics = {
        "n_scenes": float(len(jobs)),
        "objects_per_scene_mean": float(np.mean(placed)),
        "objects_per_scene_min": float(np.min(placed)),
    }
    if metrics_path is not None:
        write_metrics(metrics_path, metrics)
    log.info("%s: %d scenes in %s, %.1f objects per scene", part.name, len(jobs), out, metrics["objects_per_scene_mean"])
    return metrics


@entry
def main(argv: Sequence[str] | None = None) -> int:
    p = parser(__doc__)
    p.add_argument("--part", required=True)
    p.add_argument("--model", required=True, type=Path, help="part model (.npz)")
    p.add_argument("--out", required=True, type=Path, help="data set folder to write (train/, val/, test/)")
    p.add_argument("--metrics", type=Path)
    args = p.parse_args(argv)
    start(args)
    run(load_params(args.params, args.part), args.model, args.out, args.metrics)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
