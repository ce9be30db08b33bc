"""Stage `grasps`: the part's grasps for a suction cup and a parallel-jaw gripper, in its model
frame: read from the grasp file its params entry names, or generated from the CAD model; either
way expanded by the part's symmetry. Writes grasps.json and a rerun recording of the part with them.
Warns when a way the part comes to rest leaves it no grasp within the picker's widest cone
(binpick/picking/coverage.py), and names a smaller suction cup that would reach it."""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from pathlib import Path

from binpick.geometry.symmetry import symmetry_transforms
from binpick.io.atomic import atomic_paths
from binpick.io.grasps import GraspSet, load_grasps, save_grasps
from binpick.io.part_model import PartModel, load_part_model
from binpick.params import Params, load_params
from binpick.picking.coverage import (
    covered_share,
    describe_side,
    grasp_sides,
    smaller_cup_covering,
    smaller_cup_radii,
    stable_poses,
    widest_cone_deg,
)
from binpick.picking.grasps import REVOLUTION_GRASP_STEPS, expand_by_symmetry, generate_grasps
from review.pick_recording import write_grasp_recording
from stages.common import entry, log_timings, parser, start, write_metrics

log = logging.getLogger("binpick.stage.grasps")

# A resting side at least this likely with no grasp is warned about (a rarer one still counts in
# the metrics' covered share).
WARN_PROBABILITY = 0.01


def run(
    params: Params,
    part_model_path: Path,
    out: Path,
    grasp_file: Path | None = None,
    metrics_path: Path | None = None,
    rrd_path: Path | None = None,
) -> dict[str, float]:
    part = load_part_model(part_model_path)
    t0 = time.perf_counter()
    if grasp_file is not None:
        sets = load_grasps(grasp_file, params.pick.suction.oval)
    else:
        sets = generate_grasps(part, params.pick)
    symmetries = symmetry_transforms(part.symmetry, REVOLUTION_GRASP_STEPS)
    sets = {kind: expand_by_symmetry(s, symmetries) for kind, s in sets.items()}
    grasps_s = time.perf_counter() - t0
    metrics = {"grasps_s": grasps_s, **{f"n_{kind}": float(len(s)) for kind, s in sets.items()}}
    if len(sets[params.pick.gripper]) == 0:
        log.warning("%s: no %s grasps (pick.gripper): its parts will have no picks", part.name, params.pick.gripper)
    metrics.update(_resting_coverage(params, part, sets, generated=grasp_file is None))
    with atomic_paths(out, rrd_path, metrics_path) as (tmp_out, tmp_rrd, tmp_metrics):
        save_grasps(
            tmp_out,
            part.name,
            sets,
            str(grasp_file) if grasp_file is not None else "generated",
            params.pick.suction.oval,
        )
        if tmp_rrd is not None:
            write_grasp_recording(tmp_rrd, part, sets, params.pick)
        if tmp_metrics is not None:
            write_metrics(tmp_metrics, metrics)
            log_timings(
                f"part-{part.name}", f"grasps-{part.name}", params.tracking.mlflow_uri, f"grasps@{part.name}", metrics
            )
    log.info("%s: %s in %.2f s", part.name, ", ".join(f"{len(s)} {k}" for k, s in sets.items()), grasps_s)
    return metrics


def _resting_coverage(params: Params, part: PartModel, sets: dict[str, GraspSet], generated: bool) -> dict[str, float]:
    """resting_covered_<kind>: the share of drops that leave the part a grasp within the widest
    cone; a warning per uncovered side for the gripper in use, with a smaller cup that covers them."""
    T_rest, p_rest = stable_poses(part)
    cone = widest_cone_deg(params.pick)
    metrics: dict[str, float] = {}
    for kind, grasps in sets.items():
        sides = grasp_sides(T_rest, p_rest, grasps, cone)
        metrics[f"resting_covered_{kind}"] = covered_share(sides)
        if kind != params.pick.gripper:
            continue
        bare = [s for s in sides if s.n_grasps == 0 and s.probability >= WARN_PROBABILITY]
        for side in bare:
            log.warning(
                "%s: resting with %s (%.0f %% of drops, stable poses of the mesh) no %s grasp approaches within "
                "%g degrees of straight down: parts lying so stay in the bin",
                part.name,
                describe_side(side.up_model),
                100 * side.probability,
                kind,
                cone,
            )
        if bare and kind == "suction" and generated and not params.pick.suction.oval:
            s = params.pick.suction
            r = smaller_cup_covering(part, params.pick, T_rest, p_rest, WARN_PROBABILITY)
            tried = smaller_cup_radii(s.cup_radius_m)
            if r is None and tried:
                log.warning("%s: nor does a smaller suction cup, down to %.0f mm across", part.name, 2000 * min(tried))
            elif r is not None:
                log.warning(
                    "%s: a %.0f mm cup reaches every side (parts.%s.pick.suction: {cup_radius_m: %g, holding_force_n: "
                    "%.1f}: the force scales with the lip's area at the same vacuum)",
                    part.name,
                    2000 * r,
                    part.name,
                    r,
                    s.holding_force_n * (r / s.cup_radius_m) ** 2,
                )
    return metrics


@entry
def main(argv: Sequence[str] | None = None) -> int:
    p = parser(__doc__)
    p.add_argument("--part", required=True)
    p.add_argument("--model", required=True, type=Path, help="part model (.npz)")
    p.add_argument("--out", required=True, type=Path, help="grasps to write (.json)")
    p.add_argument("--grasp-file", default="", help="the part's own grasp file ('' = generate from the model)")
    p.add_argument("--metrics", type=Path)
    p.add_argument("--rrd", type=Path, help="rerun recording of the part with its grasps")
    args = p.parse_args(argv)
    start(args)
    run(
        load_params(args.params, args.part),
        args.model,
        args.out,
        Path(args.grasp_file) if args.grasp_file else None,
        args.metrics,
        args.rrd,
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
