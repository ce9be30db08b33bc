"""Stage `ingest`: a part's CAD mesh, in its declared unit, becomes a part model in metres
(checks and simplification: binpick/part/ingest.py)."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

from binpick.io.atomic import atomic_paths
from binpick.io.part_model import save_part_model
from binpick.params import Params, load_params
from binpick.part.ingest import ingest_part
from stages.common import entry, parser, start, write_metrics

log = logging.getLogger("binpick.stage.ingest")


def run(
    params: Params, part: str, mesh_path: Path, out: Path, metrics_path: Path | None = None
) -> dict[str, float | str]:
    model, metrics = ingest_part(params, part, mesh_path)
    with atomic_paths(out, metrics_path) as (tmp_out, tmp_metrics):
        save_part_model(tmp_out, model)
        if tmp_metrics is not None:
            write_metrics(tmp_metrics, metrics)
    log.info("%s -> %s", part, out)
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
