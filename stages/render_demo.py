"""Stage `render_demo`: render a bin of the part from the virtual camera at full resolution and
save it as a Zivid-style export (organized PLY, millimetres) with its ground-truth poses, so that
the demo runs the real import path."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from binpick.generation.scene import generate_scene
from binpick.io.atomic import atomic_paths
from binpick.io.part_model import load_part_model
from binpick.io.ply import PointCloudData, save_ply
from binpick.io.poses import PartPose, save_poses
from binpick.params import Params, load_params
from binpick.seeding import derive_seed
from binpick.view import ViewParams
from stages.common import entry, parser, start

log = logging.getLogger("binpick.stage.render_demo")
MM_PER_M = 1000.0


def grey_shading(xyz_m: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 grey values from depth, standing in for the camera's colour image."""
    z = xyz_m[..., 2]
    ok = np.isfinite(z)
    if not ok.any():
        return np.zeros(z.shape + (3,), np.uint8)
    lo, hi = np.nanmin(z), np.nanmax(z)
    g = np.where(ok, 230 - 180 * (z - lo) / max(hi - lo, 1e-9), 0)
    return np.repeat(g[..., None], 3, axis=-1).astype(np.uint8)


def run(params: Params, part_model_path: Path, out: Path, truth: Path) -> int:
    part = load_part_model(part_model_path)
    camera = params.camera.model_copy(update={"downscale": params.render_demo.downscale})
    seed = derive_seed(params.seed, "demo_capture", part.name)  # the stage's former name: same scenes
    # The demo bin stays the plain one whatever clutter the training scenes have: its figures
    # stay comparable from run to run.
    generate = params.generate.model_copy(update={"clutter": params.generate.clutter.off()})
    scene = generate_scene(
        part,
        generate,
        camera,
        ViewParams.of_import(params.import_capture),
        seed,
        n_objects=params.render_demo.n_objects,
    )
    H, W = scene.labels.shape
    records = [
        PartPose(T, 1.0, i, visible_fraction=float(v))
        for i, (T, v) in enumerate(zip(scene.T_cam_from_model, scene.visible_fraction, strict=False))
    ]
    with atomic_paths(out, truth) as (tmp_out, tmp_truth):  # the capture and its truth together
        assert tmp_truth is not None  # asked for
        save_ply(
            tmp_out,
            PointCloudData(
                xyz=scene.xyz_m.reshape(-1, 3) * MM_PER_M, rgb=grey_shading(scene.xyz_m).reshape(-1, 3), shape=(H, W)
            ),
        )
        save_poses(tmp_truth, part.name, records)
    log.info("%s: %dx%d capture with %d parts -> %s", part.name, W, H, len(records), out)
    return len(records)


@entry
def main(argv: Sequence[str] | None = None) -> int:
    p = parser(__doc__)
    p.add_argument("--part", required=True)
    p.add_argument("--model", required=True, type=Path, help="part model (.npz)")
    p.add_argument("--out", required=True, type=Path, help="capture to write (.ply, millimetres)")
    p.add_argument("--truth", required=True, type=Path, help="ground-truth poses to write (.json)")
    args = p.parse_args(argv)
    start(args)
    run(load_params(args.params, args.part), args.model, args.out, args.truth)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
