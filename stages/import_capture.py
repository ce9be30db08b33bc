"""Stage `import_capture`: a capture file becomes a clean scene (metres, camera frame): invalid and
out-of-range points dropped, floor and bin walls removed, voxel grid, normals."""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

from binpick.errors import BinpickError
from binpick.io.atomic import atomic_paths
from binpick.io.capture import DEFAULT_TEXT_COLUMNS, ImportOptions, load_capture
from binpick.io.cloud import save_cloud
from binpick.params import Params, load_params
from binpick.scene.cleaning import clean_capture
from binpick.seeding import SceneSeeds, capture_digest
from stages.common import entry, log_timings, parser, start, write_metrics

log = logging.getLogger("binpick.stage.import_capture")


def run(
    params: Params,
    capture_path: Path,
    options: ImportOptions,
    out: Path,
    metrics_path: Path | None = None,
    name: str | None = None,
) -> dict[str, float]:
    t0 = time.perf_counter()
    capture = load_capture(capture_path, options)
    try:
        digest = capture_digest(capture.xyz_m, capture.rgb)
        cloud = clean_capture(
            capture.xyz_m,
            capture.rgb,
            capture.shape,
            params.import_capture_for(name),
            SceneSeeds.of_capture_digest(params.seed, digest).clean,
        )
    except BinpickError as exc:
        raise BinpickError(f"{capture_path}: {exc}") from None
    metrics = {
        "import_s": time.perf_counter() - t0,
        "n_points_in": float(len(capture.xyz_m)),
        "n_points_out": float(len(cloud.points_m)),
        "removed_floor_fraction": float(cloud.removed_fraction[0]),
        "removed_walls_fraction": float(cloud.removed_fraction[1]),
        "n_walls": float(len(cloud.wall_planes)),
        **{f"floor_plane_{k}": float(v) for k, v in zip("abcd", cloud.floor_plane, strict=False)},
    }
    with atomic_paths(out, metrics_path) as (tmp_out, tmp_metrics):
        save_cloud(tmp_out, replace(cloud, capture_digest=digest))
        if tmp_metrics is not None:
            write_metrics(tmp_metrics, metrics)
            if name:
                log_timings(
                    "scenes",
                    f"import-{name}",
                    params.tracking.mlflow_uri,
                    f"import_capture@{name}",
                    metrics,
                    {"capture": name},
                )
    log.info(
        "%s: %d points -> %d after cleaning (%.2f s)",
        capture_path,
        len(capture.xyz_m),
        len(cloud.points_m),
        metrics["import_s"],
    )
    return metrics


@entry
def main(argv: Sequence[str] | None = None) -> int:
    p = parser(__doc__)
    p.add_argument("--name", default="", help="a capture listed in params.yaml: its unit, columns and intrinsics apply")
    p.add_argument("--capture", required=True, type=Path, help="capture file (.ply, .pcd, .zdf, .csv/.xyz, depth .png)")
    p.add_argument("--unit", help="unit of the coordinates or depth values (default mm, as Zivid writes)")
    p.add_argument(
        "--columns", help=f"text captures: column names (default {','.join(DEFAULT_TEXT_COLUMNS)}), e.g. x,y,z,r,g,b,_"
    )
    p.add_argument("--intrinsics", help="depth images: JSON file with fx, fy, cx, cy")
    p.add_argument("--out", required=True, type=Path, help="clean cloud to write (.npz)")
    p.add_argument("--metrics", type=Path)
    args = p.parse_args(argv)
    start(args)
    params = load_params(args.params)
    listed = params.captures.get(args.name) if args.name else None
    if args.name and listed is None:
        raise BinpickError(f"{args.params}: capture {args.name!r} is not listed under 'captures'")
    if listed is not None:
        params = load_params(args.params, listed.part_names[0])  # the part's import_capture overrides apply
    unit = args.unit or (listed.unit if listed else "mm")
    columns = args.columns.split(",") if args.columns else (listed.columns if listed else list(DEFAULT_TEXT_COLUMNS))
    intrinsics = args.intrinsics or (listed.intrinsics if listed else "")
    options = ImportOptions(
        unit=unit, columns=tuple(c.strip() for c in columns), intrinsics=Path(intrinsics) if intrinsics else None
    )
    run(params, args.capture, options, args.out, args.metrics, args.name or None)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
