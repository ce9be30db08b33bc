"""Stage `ppf`: train the part's point pair feature model and save it."""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from pathlib import Path

from binpick.geometry.symmetry import symmetry_transforms
from binpick.io.part_model import load_part_model
from binpick.io.ppf_model import save_ppf_model
from binpick.params import Params, load_params
from binpick.registration.model import train_ppf
from stages.common import entry, log_timings, parser, start, write_metrics

log = logging.getLogger("binpick.stage.ppf")


def run(params: Params, part_model_path: Path, out: Path, metrics_path: Path | None = None) -> dict[str, float]:
    part = load_part_model(part_model_path)
    t0 = time.perf_counter()
    model = train_ppf(
        part.points_m, part.normals, part.diameter_m, symmetry_transforms(part.symmetry), params.registration
    )
    train_s = time.perf_counter() - t0
    save_ppf_model(out, model)
    metrics = {"train_s": train_s, "model_points": float(len(model.points_m)), "pairs": float(len(model.keys))}
    if metrics_path is not None:
        write_metrics(metrics_path, metrics)
        log_timings(f"part-{part.name}", f"ppf-{part.name}", params.tracking.mlflow_uri, f"ppf@{part.name}", metrics)
    log.info("%s: PPF model of %d points, %d pairs in %.2f s", part.name, len(model.points_m), len(model.keys), train_s)
    return metrics


@entry
def main(argv: Sequence[str] | None = None) -> int:
    p = parser(__doc__)
    p.add_argument("--part", required=True)
    p.add_argument("--model", required=True, type=Path, help="part model (.npz)")
    p.add_argument("--out", required=True, type=Path, help="PPF model to write (.npz)")
    p.add_argument("--metrics", type=Path)
    args = p.parse_args(argv)
    start(args)
    run(load_params(args.params, args.part), args.model, args.out, args.metrics)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
