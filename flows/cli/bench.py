"""`binpick bench ...`: each benchmark writes its measurements as JSON (docs/benchmarks.md)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import typer

from binpick.env import project_root
from flows.cli.common import PARAMS, bench_app, checkpoints, fail, trained_part_paths, write_json

if TYPE_CHECKING:
    from binpick.params import Params

# Options several benchmarks share, declared once.
OUT = typer.Option(..., help="JSON file to write")
BENCH_PARTS_OPTION = typer.Option(None, help="parts (default: t_joint, the gear shaft, ring screw and three-way pipe)")
SHARED_PARTS_OPTION = typer.Option(None, help="parts to use (default: the built-in part and every shared part)")
MIN_PARTS = typer.Option(10, min=1, help="parts per bin, at least")
MAX_PARTS = typer.Option(20, min=1, help="parts per bin, at most")


def part_settings(params: Path, names: list[str]) -> dict[str, Params]:
    """The params resolved for each of these parts the project lists (its entry's overrides: a
    part's own gripper, bin or camera), which the benchmarks use for that part."""
    from binpick.params import load_params, load_raw

    listed = load_raw(params).get("parts") or {}
    return {n: load_params(params, n) for n in names if n in listed}


@bench_app.command("import")
def bench_import_cmd(
    out: Path = OUT,
    repeats: int = typer.Option(7, min=1),
    params: Path = PARAMS,
) -> None:
    """Import + clean + downsample of a full 1920 x 1200 organized frame (PLY, PCD, ZDF)."""
    from binpick.params import load_params
    from flows.bench.importing import bench_import

    settings = load_params(params)
    write_json(out, bench_import(settings, repeats))


@bench_app.command("ingest")
def bench_ingest_cmd(out: Path = OUT, params: Path = PARAMS) -> None:
    """Ingest of CAD meshes of 10^4 to 2 x 10^6 faces: time, peak memory, diameter error."""
    from binpick.params import load_params
    from flows.bench.ingest import bench_ingest

    settings = load_params(params)
    write_json(out, bench_ingest(settings))


@bench_app.command("clutter")
def bench_clutter_cmd(
    out: Path = OUT,
    scenes: int = typer.Option(4, min=1, help="cluttered scenes per part"),
    part: list[str] = typer.Option(
        None, help="parts (default: t_joint, the gear shaft, ring screw, three-way pipe and IC-BIN coffee cup)"
    ),
    tilt_deg_max: float = typer.Option(
        45.0, min=0.0, max=59.0, help="the camera's largest tilt from the bin's up axis, degrees"
    ),
    mix: str = typer.Option(
        None,
        help="instead: bins mixing these parts (comma separated, e.g. t_joint,zju_three_way_pipe) through the "
        "mixed scene path: per part precision / recall and wrong_part_poses",
    ),
    params: Path = PARAMS,
) -> None:
    """Pose precision/recall and wrong poses outside the bin on bins with distractors and tilted
    views (per band of tilt too), through the real scene path, against the scoring without bin
    crop and verification. With --mix: bins of several kinds of part (flows/bench/mix.py)."""
    from binpick.params import load_params
    from flows.bench.clutter import DEFAULT_PARTS, bench_clutter

    root = project_root()
    if mix:
        from flows.bench.mix import bench_mix

        mixed = [n.strip() for n in mix.split(",") if n.strip()]
        write_json(out, bench_mix(load_params(params), mixed, scenes, checkpoints(root, mixed)))
        return
    names = part or list(DEFAULT_PARTS)
    try:
        result = bench_clutter(
            load_params(params),
            names,
            scenes,
            checkpoints(root, names),
            tilt_deg_max=tilt_deg_max,
            part_settings=part_settings(params, names),
        )
    except ValueError as exc:
        fail(str(exc))
    write_json(out, result)


@bench_app.command("cell")
def bench_cell_cmd(
    out: Path = OUT,
    bins: int = typer.Option(2, min=1, help="bins per part"),
    min_parts: int = MIN_PARTS,
    max_parts: int = MAX_PARTS,
    part: list[str] = BENCH_PARTS_OPTION,
    params: Path = PARAMS,
) -> None:
    """Empty simulated bins with the arm (cell.arm) in physics: every pick executed from the
    arm's joint plan; picks per hour, collisions, drops, double picks; against today's
    gripper-only picks handed to the arm (baseline_*). The first bin of each part is recorded
    beside FILE as <FILE without .json>-<part>.rrd (rerun)."""
    from binpick.params import load_params
    from flows.bench.cell import DEFAULT_PARTS, bench_cell

    if min_parts > max_parts:
        fail(f"--min-parts {min_parts} is above --max-parts {max_parts}")
    root = project_root()
    names = part or list(DEFAULT_PARTS)
    try:
        result = bench_cell(
            load_params(params),
            names,
            bins,
            (min_parts, max_parts),
            checkpoints(root, names),
            record_prefix=out.with_suffix(""),
            part_settings=part_settings(params, names),
        )
    except ValueError as exc:
        fail(str(exc))
    write_json(out, result)


@bench_app.command("picking")
def bench_picking_cmd(
    out: Path = OUT,
    bins: int = typer.Option(10, min=1, help="bins per part"),
    min_parts: int = MIN_PARTS,
    max_parts: int = MAX_PARTS,
    part: list[str] = BENCH_PARTS_OPTION,
    gripper: str = typer.Option(None, help="suction or jaw (default: pick.gripper)"),
    tilt_deg_max: float = typer.Option(
        45.0, min=0.0, max=59.0, help="each bin's camera is tilted from the bin's up axis by up to this, degrees"
    ),
    mix: str = typer.Option(
        None,
        help="instead: bins mixing these parts (comma separated, the largest first, e.g. t_joint,zju_three_way_pipe) "
        "through the mixed scene path: per part pick_success_rate and wrong_part_picks",
    ),
    params: Path = PARAMS,
) -> None:
    """Empty simulated bins one pick at a time through the real scene path; every pick checked
    against the simulator's true state (right part touched, path free). Bins are seen from
    straight above to tilt_deg_max, per band of tilt in `by_tilt`. With --mix: bins of several
    kinds of part (flows/bench/mix_picking.py)."""
    from binpick.params import load_params
    from flows.bench.picking import DEFAULT_PARTS, bench_picking

    if min_parts > max_parts:
        fail(f"--min-parts {min_parts} is above --max-parts {max_parts}")
    if gripper not in (None, "suction", "jaw"):
        fail(f"--gripper must be suction or jaw, not {gripper!r}")
    root = project_root()
    if mix:
        from flows.bench.mix_picking import bench_picking_mix

        mixed = [n.strip() for n in mix.split(",") if n.strip()]
        write_json(
            out,
            bench_picking_mix(
                load_params(params),
                mixed,
                bins,
                (min_parts, max_parts),
                checkpoints(root, mixed),
                gripper,
                tilt_deg_max=tilt_deg_max,
            ),
        )
        return
    names = part or list(DEFAULT_PARTS)
    try:
        result = bench_picking(
            load_params(params),
            names,
            bins,
            (min_parts, max_parts),
            checkpoints(root, names),
            gripper,
            tilt_deg_max=tilt_deg_max,
            part_settings=part_settings(params, names),
        )
    except ValueError as exc:
        fail(str(exc))
    write_json(out, result)


@bench_app.command("sensors")
def bench_sensors_cmd(
    out: Path = OUT,
    part: list[str] = typer.Option(None, help="parts (default: t_joint)"),
    train_scenes: int = typer.Option(48, min=2, help="synthetic training scenes per network"),
    val_scenes: int = typer.Option(6, min=1, help="validation scenes per network"),
    test_scenes: int = typer.Option(6, min=1, help="cluttered test bins per test sensor"),
    captures: int = typer.Option(12, min=1, help="captures of the fine-tuning sensor the cell labels itself"),
    finetune_sensor: str = typer.Option("kinect_v1", help="the sensor model the cell's captures come from"),
    leave_one_out: bool = typer.Option(True, help="train a network without each preset and test it on that preset"),
    trust_margin: float = typer.Option(
        None, min=0.0, max=1.0, help="the labelling's trust margin (default: learn.trust_margin)"
    ),
    bin_box: str = typer.Option(
        "none",
        help="the box each capture is cropped to: none (the cleaning finds the bin), fitted (what binpick "
        "fit-bin fits from the capture, where it would not refuse it) or given (the bin as drawn)",
    ),
    params: Path = PARAMS,
) -> None:
    """Networks trained on today's camera, on the randomised sensor models and without each
    preset, tested on every preset; then the today network fine-tuned on captures it labelled
    itself. Figures from our renderer (docs/guide/captures.md, "Training for your sensor", says what it leaves out)."""
    from binpick.params import load_params
    from flows.bench.sensors import bench_sensors

    names = part or ["t_joint"]
    try:
        result = bench_sensors(
            load_params(params),
            names,
            train_scenes,
            val_scenes,
            test_scenes,
            captures,
            finetune_sensor,
            leave_one_out,
            trust_margin=trust_margin,
            bin_box=bin_box,
            part_settings=part_settings(params, names),
        )
    except ValueError as exc:
        fail(str(exc))
    write_json(out, result)


@bench_app.command("scene")
def bench_scene_cmd(
    out: Path = OUT,
    part: list[str] = BENCH_PARTS_OPTION,
    params: Path = PARAMS,
) -> None:
    """The in-process scene path per step on 1920 x 1200 captures of 8- and 20-part bins, and the
    pick service end to end (process start to first answer, warm requests over HTTP and TCP)."""
    from binpick.params import load_params
    from flows.bench.scene import DEFAULT_PARTS, bench_scene

    root = project_root()
    names = part or list(DEFAULT_PARTS)
    try:
        result = bench_scene(load_params(params), params.read_text(), names, checkpoints(root, names))
    except ValueError as exc:
        fail(str(exc))
    write_json(out, result)


@bench_app.command("soak")
def bench_soak_cmd(
    out: Path = OUT,
    requests: int = typer.Option(1000, min=1, help="sequential requests"),
    clients: int = typer.Option(4, min=1, help="concurrent clients after them"),
    per_client: int = typer.Option(25, min=1, help="requests per concurrent client"),
    params: Path = PARAMS,
) -> None:
    """Load and soak test of the pick service on generated 8-part bins of the built-in part:
    failed answers, memory over the run, the same answer for the same capture."""
    from binpick.params import load_params
    from flows.bench.scene import bench_soak

    checkpoint = checkpoints(project_root(), ["t_joint"])["t_joint"]
    try:
        result = bench_soak(
            load_params(params),
            params.read_text(),
            requests,
            clients,
            per_client,
            checkpoint if checkpoint.is_file() else None,
        )
    except ValueError as exc:
        fail(str(exc))
    write_json(out, result)


@bench_app.command("generate")
def bench_generate_cmd(
    out: Path = OUT,
    scenes: int = typer.Option(3, min=1, help="scenes per part and object count"),
    baseline_scenes: int = typer.Option(2, min=1, help="baseline scenes per part and object count"),
    part: list[str] = SHARED_PARTS_OPTION,
    params: Path = PARAMS,
) -> None:
    """Placement + 1920 x 1200 rendering against the original rejection sampling, at 5, 10, 20 objects."""
    from binpick.params import load_params
    from flows.bench.generation import bench_generate

    try:
        result = bench_generate(load_params(params), part or None, scenes, baseline_scenes)
    except ValueError as exc:
        fail(str(exc))
    write_json(out, result)


@bench_app.command("segment")
def bench_segment_cmd(
    out: Path = OUT,
    part: str = typer.Option("t_joint", help="a trained part (its checkpoint and generated scenes)"),
    checkpoint: Path = typer.Option(None, help="default: data/fpcc/<part>/model.pt"),
    scenes: Path = typer.Option(None, help="default: data/scenes/<part>"),
    params: Path = PARAMS,
) -> None:
    """FPCC precision/recall against DBSCAN on held-out scenes, inference time, training throughput."""
    from binpick.params import load_params
    from flows.bench.segmentation import bench_segment

    checkpoint, scenes = trained_part_paths(part, checkpoint, scenes)
    try:
        p = load_params(params, part)
        result = bench_segment(
            checkpoint, scenes, p.segment, p.import_capture.voxel_size_m, p.seed, p.evaluate.iou_threshold
        )
    except ValueError as exc:
        fail(str(exc))
    write_json(out, {"part": part, **result})


@bench_app.command("ppf")
def bench_ppf_cmd(
    out: Path = OUT,
    trials: int = typer.Option(20, min=1, help="views per part"),
    part: list[str] = SHARED_PARTS_OPTION,
    method: list[str] = typer.Option(None, help="methods to run (default: all)"),
    params: Path = PARAMS,
) -> None:
    """PPF registration against OpenCV PPF + ICP and Open3D FPFH + RANSAC + ICP on the same views."""
    from binpick.params import load_params
    from flows.bench.ppf import METHODS, bench_ppf

    for m in method or []:
        if m not in METHODS:
            fail(f"unknown method {m!r} (have: {', '.join(METHODS)})")
    if "opencv_ppf_icp" in (method or METHODS):
        try:
            import cv2  # noqa: F401
        except ImportError:
            fail("the OpenCV peer needs opencv-contrib-python-headless: pip install -e .[bench]")
    try:
        result = bench_ppf(load_params(params), part or None, trials, method or None)
    except ValueError as exc:
        fail(str(exc))
    write_json(out, result)


@bench_app.command("report")
def bench_report_cmd(
    folder: Path = typer.Argument(..., help="a folder of benchmark JSON files (binpick bench ... --out)"),
    out: Path = typer.Option(None, help="where the plots and index.html go; default FOLDER/report"),
) -> None:
    """The benchmark files of a folder as a page of plots: precision / recall per part, cycle time
    distributions, timings per step, picks per hour (index.html and plots.md beside the PNGs)."""
    from flows.bench.report import report

    target = out or folder / "report"
    written = report(folder, target)
    typer.echo(f"wrote {len(written)} plots and {target / 'index.html'}")
