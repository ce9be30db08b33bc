"""Mixed-bin clearing benchmark (`binpick bench picking --mix a,b`): bins of several kinds of part
settled together by physics and emptied one pick at a time through the mixed scene path
(binpick/scene/mixed.py: each part's segmentation and registration, conflicts resolved, one
pick list), the first pick judged against the simulator's true state as `bench picking` judges
it (flows/bench/picking.py: contact on a true surface, approach along its normal, a free path).

The first part sets the bin and the camera (name the largest first); each part keeps its own
models and grids. Each bin's camera is tilted from the bin's up axis as in `bench picking`.
Per part (the part the first pick names): pick_success_rate (its good picks / attempts whose
first pick named it), clearance_rate (its instances removed / settled), wrong_part_picks (picks
naming it that touch an instance of another part), missed_picks (picks naming it that touch no
instance at all), collisions (a right part touched, the path through something). Over the mix:
pick_success_rate (good picks / all attempts, attempts without any pick counted as failures),
clearance_rate, wrong_part_picks, missed_picks, collisions, attempts_without_a_pick,
cycle_s_median (reading the capture file to the ordered picks), n_bins, n_attempts. Renderer only.
"""

from __future__ import annotations

import logging
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from binpick.cell.robot import MAX_FAILURES_IN_A_ROW
from binpick.errors import BinpickError
from binpick.generation.bin import bin_meshes
from binpick.generation.physics import SettleSettings, settle_kinds
from binpick.generation.placement import place_objects
from binpick.generation.scene import render_scene
from binpick.geometry.transforms import transform_points
from binpick.io.capture import ImportOptions, load_capture
from binpick.io.part_model import PartModel
from binpick.io.zdf import save_zdf_v1
from binpick.params import Params
from binpick.scene.mixed import process_mixed
from binpick.scene.process import PartModels
from binpick.seeding import SceneSeeds, derive_seed
from binpick.view import ViewParams
from flows.bench import machine
from flows.bench.clutter import TILT_DEG_MAX
from flows.bench.picking import (
    Tally,
    TrueSurface,
    _path_hits,
    _true_touch,
    bench_models,
    bin_surface_points,
    draw_bin,
    picking_settings,
    touch_m,
)

log = logging.getLogger(__name__)


@dataclass
class MixedBin:
    """A mixed bin as the simulator holds it: poses (k, 4, 4) bin frame and kinds (k,) int."""

    T_bin_from_model: np.ndarray
    kinds: np.ndarray


def bench_picking_mix(
    settings: Params,
    names: list[str],
    n_bins: int,
    parts_per_bin: tuple[int, int],
    checkpoints: dict[str, Path],
    gripper: str | None = None,
    seed: int = 0,
    tilt_deg_max: float = TILT_DEG_MAX,
) -> dict[str, object]:
    """settings: the project's params; names: the parts of the mix (two or more, the first sets
    the bin and camera); checkpoints: part -> trained FPCC checkpoint (without one, a part is
    registered over the whole scene); gripper: overrides pick.gripper."""
    parts = mix_parts(settings, names)
    kind = gripper or settings.pick.gripper

    def with_gripper(p: Params) -> Params:
        return p.model_copy(update={"pick": p.pick.model_copy(update={"gripper": kind})})

    p = with_gripper(picking_settings(settings, parts[0]))
    models = {
        q.name: bench_models(q, with_gripper(mix_settings(settings, q, p)), checkpoints.get(q.name)) for q in parts
    }
    truths = {q.name: TrueSurface(q, p.pick.suction.cup_radius_m, touch_m(p.pick, kind)) for q in parts}
    tallies = {q.name: Tally() for q in parts}
    no_pick = 0
    cycles: list[float] = []
    tilts: list[float] = []
    with tempfile.TemporaryDirectory(prefix="binpick-picking-mix-") as tmp:
        for b in range(n_bins):
            bin_seed = derive_seed(seed, "bench-picking-mix", ",".join(names), b)
            n, tilt_deg, T_bin_from_camera = draw_bin(bin_seed, b, n_bins, parts_per_bin, tilt_deg_max, p)
            tilts.append(tilt_deg)
            one, none = _clear_mixed_bin(
                parts, models, p, kind, n, bin_seed, Path(tmp), cycles, truths, T_bin_from_camera
            )
            no_pick += none
            for name, t in one.items():
                tallies[name].add(t)
            log.info(
                "mixed bin %d of %d (camera tilted %.0f degrees): %s; %d without a pick",
                b + 1,
                n_bins,
                tilt_deg,
                ", ".join(f"{name} {t.removed} of {t.settled} removed in {t.attempts}" for name, t in one.items()),
                none,
            )
    total = Tally()
    for t in tallies.values():
        total.add(t)
    attempts = total.attempts + no_pick
    return {
        "machine": machine(),
        "renderer_only": True,
        "mix": names,
        "gripper": kind,
        "parts_per_bin": list(parts_per_bin),
        "tilt_deg": [round(t, 1) for t in tilts],
        "parts": {name: _keys(t) for name, t in tallies.items()},
        **_keys(total),
        "pick_success_rate": total.good / attempts if attempts else 0.0,
        "attempts_without_a_pick": float(no_pick),
        "n_attempts": float(attempts),
        "n_bins": float(n_bins),
        "cycle_s_median": float(np.median(cycles)) if cycles else 0.0,
        "cycle_s": [round(float(c), 4) for c in cycles],
    }


def mix_parts(settings: Params, names: list[str]) -> list[PartModel]:
    """The benchmark parts of a mix, in the order named (two or more; one error line otherwise)."""
    from flows.bench.parts import bench_parts

    if len(names) < 2:
        raise BinpickError(f"a mix names two or more parts, got {', '.join(names) or 'none'}")
    parts = bench_parts(names, n_points=settings.ingest.n_surface_points)
    missing = set(names) - {q.name for q in parts}
    if missing:
        raise BinpickError(f"--mix: no benchmark part {', '.join(sorted(missing))} (../shared/data/parts absent?)")
    return sorted(parts, key=lambda q: names.index(q.name))


def mix_settings(settings: Params, part: PartModel, first: Params) -> Params:
    """A part's settings in a mixed bin seen by the first part's camera: its own (grids, plane
    threshold, height kept above the floor: as its network was trained at), with the range that
    reaches the first part's camera's bin. The ring screw's own 2 m cut the far half of the gear
    shaft's bin 1.94 m away; the gear shaft's plane threshold and height above the floor (14 and
    19 mm) would cut a lying T-joint down to a slab no pass finds."""
    own = picking_settings(settings, part)
    reach = max(own.import_capture.max_range_m, first.import_capture.max_range_m)
    return own.model_copy(update={"import_capture": own.import_capture.model_copy(update={"max_range_m": reach})})


def _keys(t: Tally) -> dict[str, float]:
    return {
        "pick_success_rate": t.good / t.attempts if t.attempts else 0.0,
        "clearance_rate": t.removed / t.settled if t.settled else 0.0,
        "wrong_part_picks": float(t.other_part),
        "missed_picks": float(t.missed),
        "collisions": float(t.collisions),
        "n_attempts": float(t.attempts),
        "parts_settled": float(t.settled),
    }


def _clear_mixed_bin(
    parts: list[PartModel],
    models: dict[str, PartModels],
    p: Params,
    kind: str,
    n_parts: int,
    seed: np.random.SeedSequence,
    folder: Path,
    cycles: list[float],
    truths: dict[str, TrueSurface],
    T_bin_from_camera: np.ndarray,
) -> tuple[dict[str, Tally], int]:
    """One bin dropped, settled and emptied; each part's tally and the attempts without a pick."""
    rng = np.random.default_rng(seed)
    g = p.generate
    meshes = [(q.mesh_vertices_m, q.mesh_faces) for q in parts]
    boxes = [(m.bounds[0], m.bounds[1]) for m in bin_meshes(g.bin)]
    half = (g.bin.inner_x_m / 2.0, g.bin.inner_y_m / 2.0)
    kinds = [int(x) for x in rng.integers(0, len(parts), n_parts)]
    placed = place_objects([q.points_m for q in parts], n_parts, g.bin, g.placement, rng, kinds)
    assert placed.kinds is not None  # kinds were given
    settled, inside = settle_kinds(
        meshes, placed.kinds, placed.T_bin_from_model, boxes, SettleSettings(max_time_s=g.placement.settle_max_s), half
    )
    state = MixedBin(settled[inside], np.asarray(placed.kinds, dtype=np.int64)[inside])
    tallies = {q.name: Tally(settled=int(np.sum(state.kinds == i))) for i, q in enumerate(parts)}
    bin_points = bin_surface_points(g.bin)
    view = ViewParams.of_import(p.import_capture)
    capture = folder / "capture.zdf"
    failures = no_pick = attempt = 0
    while len(state.kinds) and failures < MAX_FAILURES_IN_A_ROW:
        mine = state.kinds == 0
        others = [
            trimesh.Trimesh(parts[k].mesh_vertices_m, parts[k].mesh_faces, process=False).apply_transform(T)
            for T, k in zip(state.T_bin_from_model[~mine], state.kinds[~mine], strict=True)
        ]
        scene = render_scene(
            parts[0], state.T_bin_from_model[mine], g, p.camera, view, rng, T_bin_from_camera, distractors=others
        )
        save_zdf_v1(capture, scene.xyz_m * 1000.0)
        t0 = time.perf_counter()
        frame = load_capture(capture, ImportOptions("mm"))
        try:
            result = process_mixed(
                frame.xyz_m, frame.rgb, frame.shape, models, SceneSeeds.of(0, f"picking-mix-{attempt}")
            )
        except BinpickError as exc:
            log.warning("the mixed scene path refused the capture: %s", exc)
            result = None
        picks = result.picks if result is not None else []
        cycles.append(time.perf_counter() - t0)
        attempt += 1
        if not picks:
            no_pick += 1
            failures += 1
            left = ", ".join(f"{np.sum(state.kinds == i)} {q.name}" for i, q in enumerate(parts))
            why = (
                "; ".join(f"{part} {i}: {reason}" for part, rows in result.unpicked.items() for i, reason in rows)
                if result is not None
                else "refused"
            )
            log.info("no pick for %s left (%s)", left, why or "no pose found")
            continue
        first = picks[0]
        i = [q.name for q in parts].index(first.part)
        tally = tallies[first.part]
        tally.attempts += 1
        failures += 1  # until the pick proves good
        T_cam = scene.T_cam_from_bin @ state.T_bin_from_model
        ours = np.flatnonzero(state.kinds == i)
        hit = _true_touch(first.pick, kind, T_cam[ours], truths[first.part])
        if hit is None:
            touched = [
                q.name
                for j, q in enumerate(parts)
                if j != i and _true_touch(first.pick, kind, T_cam[state.kinds == j], truths[q.name]) is not None
            ]
            if touched:
                tally.other_part += 1
                log.info("the first pick names %s and touches an instance of %s", first.part, ", ".join(touched))
            else:
                tally.missed += 1
            continue
        target = int(ours[hit])
        object_points = [parts[k].points_m for k in state.kinds]
        bin_cam = transform_points(scene.T_cam_from_bin, bin_points)
        if _path_hits(first.pick, kind, p, target, T_cam, object_points, bin_cam):
            tally.collisions += 1
            continue
        tally.good += 1
        tally.removed += 1
        failures = 0
        rest = MixedBin(np.delete(state.T_bin_from_model, target, axis=0), np.delete(state.kinds, target))
        if len(rest.kinds):
            moved, inside = settle_kinds(
                meshes,
                rest.kinds,
                rest.T_bin_from_model,
                boxes,
                SettleSettings(max_time_s=g.placement.settle_max_s, drop_gap_m=0.0),
                half,
            )
            rest = MixedBin(moved[inside], rest.kinds[inside])
        state = rest
    return tallies, no_pick
