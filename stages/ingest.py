"""Stage `ingest`: a part's CAD mesh, in its declared unit, becomes a part model in metres."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from binpick.errors import InputError
from binpick.io.mesh import load_mesh
from binpick.io.part_model import save_part_model
from binpick.params import Params, load_params
from binpick.parts import make_part_model
from binpick.seeding import derive_seed
from stages.common import entry, parser, start, write_metrics

log = logging.getLogger("binpick.stage.ingest")


def run(params: Params, part: str, mesh_path: Path, out: Path, metrics_path: Path | None = None) -> dict[str, float]:
    spec = params.parts[part]
    mesh, unit = load_mesh(mesh_path, spec.unit)
    extent = float(np.max(mesh.extents))
    if not params.ingest.min_extent_m <= extent <= params.ingest.max_extent_m:
        raise InputError(
            mesh_path,
            f"part is {extent:.4g} m long in unit {unit!r}, outside {params.ingest.min_extent_m}-"
            f"{params.ingest.max_extent_m} m: declare the right unit in params.yaml (parts.{part}.unit)",
        )
    model = make_part_model(part, mesh, spec.symmetry, params.ingest.n_surface_points, np.random.default_rng(derive_seed(params.seed, "ingest", part)), unit)
    save_part_model(out, model)
    metrics = {
        "diameter_mm": 1000.0 * model.diameter_m,
        "n_faces": float(len(model.mesh_faces)),
        "unit": unit,
        "watertight": float(model.watertight),
        "extent_x_mm": 1000.0 * float(np.ptp(model.mesh_vertices_m[:, 0])),
        "extent_y_mm": 1000.0 * float(np.ptp(model.mesh_vertices_m[:, 1])),
        "extent_z_mm": 1000.0 * float(np.ptp(model.mesh_vertices_m[:, 2])),
    }
    if metrics_path is not None:
        write_metrics(metrics_path, metrics)
    log.info("%s: %s -> %s (diameter %.1f mm, unit %s)", part, mesh_path, out, metrics["diameter_mm"], unit)
    return metrics


@entry
def main(argv: Sequence[str] | None = None) -> int:
    p = parser(__doc__)
    p.add_argument("--part", required=True)
    p.add_argument("--mesh", required=True, type=Path, help="CAD file (STL, PLY, OBJ, OFF)")
    p.add_argument("--out", required=True, type=Path, help="part model to write (.npz)")
    p.add_argument("--metrics", type=Path, help="metrics JSON to write")
    args = p.parse_args(argv)
    start(args)
    run(load_params(args.params, args.part), args.part, args.mesh, args.out, args.metrics)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
