"""The `binpick` command."""

from __future__ import annotations

import contextlib
import logging
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from binpick.env import configure_environment, project_root
from binpick.errors import BinpickError
from binpick.layout import Layout
from binpick.log import setup_logging

if TYPE_CHECKING:
    from binpick.io.capture import ImportOptions
    from binpick.params import CaptureParams, Params

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False, help=__doc__)
bench_app = typer.Typer(no_args_is_help=True, help="Benchmarks: each writes its measurements as JSON.")
app.add_typer(bench_app, name="bench")
learn_app = typer.Typer(no_args_is_help=True, help="Learning from the cell: review labelled captures, fine-tune on them.")
app.add_typer(learn_app, name="learn")
log = logging.getLogger("binpick")


_VERBOSE = False


def _fail(message: str) -> None:
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(2)


@contextlib.contextmanager
def quiet_prefect() -> Iterator[None]:
    """A failing flow ends in our one `error:` line; Prefect's own report of it (the exception
    with its traceback, for the task, the sub-flow and the flow) is shown only with --verbose."""
    if _VERBOSE:
        yield
        return
    loggers = [logging.getLogger(name) for name in ("prefect.flow_runs", "prefect.task_runs", "prefect.engine", "prefect")]
    before = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        for lg, level in zip(loggers, before, strict=True):
            lg.setLevel(level)


@app.callback()
def _main(verbose: bool = typer.Option(False, "--verbose", "-v", help="debug logging, and Prefect's reports of failures")) -> None:
    global _VERBOSE
    _VERBOSE = verbose
    configure_environment()
    setup_logging(verbose)


@app.command("default-part")
def default_part(out: Path = typer.Option(Layout(Path()).parts_folder / "t_joint.stl", help="STL to write (millimetres)")) -> None:
    """Write the built-in T-joint pipe part as an STL file (millimetres)."""
    from binpick.io.mesh import save_mesh
    from binpick.parts import build_t_joint_mesh

    mesh = build_t_joint_mesh()
    save_mesh(out, mesh.vertices, mesh.faces)
    typer.echo(f"wrote {out} ({len(mesh.faces)} faces, {mesh.extents.round(1).tolist()} mm)")


def review_commands(root: Path, capture: str = "demo") -> list[str]:
    """The commands that open the latest results (loopback only)."""
    bin_dir = Path(sys.executable).parent
    return [
        f"{bin_dir / 'mlflow'} ui --backend-store-uri sqlite:///{Layout(root).mlflow_store} --host 127.0.0.1 --port 5000",
        f"{bin_dir / 'rerun'} {root / 'data' / 'results' / capture / 'scene.rrd'}",
        f"{bin_dir / 'rerun'} {root / 'data' / 'results' / capture / 'picks.rrd'}",
        # rerun binds to every interface unless told otherwise
        f"{bin_dir / 'rerun'} --web-viewer --bind 127.0.0.1 {root / 'data' / 'results' / capture / 'scene.rrd'}",
    ]


def summary_table(results: dict[str, dict[str, float]], minutes: float) -> str:
    ev, reg, pick = results.get("evaluate", {}), results.get("register", {}), results.get("pick", {})

    def f(d: dict[str, float], key: str, fmt: str = "{:.3f}") -> str:
        return fmt.format(d[key]) if key in d else "n/a"

    rows = [
        ("segmentation precision (IoU >= 0.5, test scenes)", f(ev, "precision")),
        ("segmentation recall (IoU >= 0.5, test scenes)", f(ev, "recall")),
        ("parts found in the demo capture", f"{f(reg, 'n_found', '{:.0f}')} of {f(reg, 'n_ground_truth', '{:.0f}')} ({f(reg, 'n_pickable', '{:.0f}')} at least half visible)"),
        ("pose recall (ADD < 0.1 d, half-visible parts)", f(reg, "pose_recall")),
        ("pose precision (ADD < 0.1 d)", f(reg, "pose_precision")),
        ("rotation error, median", f(reg, "rot_err_deg_median", "{:.2f} deg")),
        ("translation error, median", f(reg, "trans_err_mm_median", "{:.2f} mm")),
        ("parts with a collision-free pick", f"{f(pick, 'n_picks', '{:.0f}')} of {f(pick, 'n_parts', '{:.0f}')}"),
        ("wall time", f"{minutes:.1f} min"),
    ]
    width = max(len(r[0]) for r in rows)
    return "\n".join(f"  {name:<{width}}  {value}" for name, value in rows)


@app.command()
def demo() -> None:
    """Run the main job on the built-in part through the Prefect flow and print a summary."""
    root = _project()
    from flows.dvc_tasks import StageFailed
    from flows.pipeline import demo as demo_flow

    t0 = time.perf_counter()
    try:
        with quiet_prefect():
            results = demo_flow(root)
    except (StageFailed, BinpickError) as exc:
        _fail(str(exc))
    typer.echo("\nbinpick demo: the built-in part, trained and found in a rendered bin\n")
    typer.echo(summary_table(results, (time.perf_counter() - t0) / 60.0))
    typer.echo("\nReview the run:")
    for cmd in review_commands(root):
        typer.echo(f"  {cmd}")


def _project() -> Path:
    root = project_root()
    if not (root / "dvc.yaml").is_file():
        _fail(f"{Path.cwd()}: not inside a binpick project (no params.yaml and dvc.yaml found)")
    return root


@app.command()
def check() -> None:
    """Validate params.yaml as a whole and write data/pipeline.yaml, the names and paths dvc.yaml
    runs on (every project command does this first; run it before a bare `dvc repro`)."""
    from binpick.project import check_project

    root = _project()
    try:
        result = check_project(root)
    except BinpickError as exc:
        _fail(str(exc))
    aside = [f"{k}.{n}" for k, entries in result.set_aside.items() for n in entries]
    typer.echo(
        f"params.yaml is valid: {len(result.pipeline.parts)} parts, {len(result.pipeline.captures)} captures in the pipeline"
        + (f"; set aside: {', '.join(aside)}" if aside else "")
        + ("; data/pipeline.yaml updated" if result.vars_changed else "")
    )


@app.command()
def repro() -> None:
    """Check the project, then `dvc repro --keep-going`: a part or capture whose stage fails is set
    aside (data/set_aside.yaml) and the rest of the pipeline still runs."""
    from binpick.project import check_project
    from flows.repro import repro_all

    root = _project()
    try:
        check_project(root)
        outcome = repro_all(root)
    except BinpickError as exc:
        _fail(str(exc))
    typer.echo(outcome.summary("ran"))
    if outcome.failed:
        raise typer.Exit(1)


@app.command()
def watch() -> None:
    """Once: add new meshes in data/parts/ to params.yaml and train every part not up to date; a
    part that fails is set aside until its mesh or entry changes."""
    root = _project()
    from flows.dvc_tasks import StageFailed
    from flows.watcher import watch_parts

    try:
        with quiet_prefect():
            outcome = watch_parts(root)
    except (StageFailed, BinpickError) as exc:
        _fail(str(exc))
    typer.echo(outcome.summary("trained"))
    if outcome.failed:
        raise typer.Exit(1)


@app.command()
def scenes(
    folder: Path = typer.Argument(..., help="folder of captures inside the project, e.g. data/captures/monday"),
    part: str = typer.Option(..., help="the part in these bins (listed in params.yaml)"),
    unit: str = typer.Option("mm", help="unit of the capture files: mm, m or in"),
) -> None:
    """Import, segment and register every capture in a folder (new files are added to params.yaml);
    a capture that fails is set aside and the others go on."""
    root = _project()
    if unit not in ("mm", "m", "in"):
        _fail(f"unit {unit!r} is not one of mm, m, in")
    from flows.dvc_tasks import StageFailed
    from flows.pipeline import process_folder

    try:
        with quiet_prefect():
            outcome, results = process_folder(root, folder.resolve() if folder.is_absolute() else Path.cwd() / folder, part, unit)
    except (StageFailed, BinpickError) as exc:
        _fail(str(exc))
    for name, metrics in results.items():
        typer.echo(f"{name}: {metrics.get('n_found', 0):.0f} parts, mean score {metrics.get('score_mean', 0.0):.2f}")
    typer.echo(outcome.summary("processed"))
    if outcome.failed:
        raise typer.Exit(1)


@app.command()
def serve(
    interval_s: float = typer.Option(None, "--interval-s", min=1, help="run every N seconds instead of the cron schedule in params"),
    port: int = typer.Option(4200, help="port of the local Prefect server (when PREFECT_API_URL is not set)"),
    params: Path = typer.Option(Path("params.yaml")),
) -> None:
    """Run the watcher on the schedule in params (default nightly) until stopped; starts a local
    Prefect server on 127.0.0.1 unless PREFECT_API_URL names a shared one."""
    root = project_root()
    if not (root / "dvc.yaml").is_file():
        _fail(f"{Path.cwd()}: not inside a binpick project (no params.yaml and dvc.yaml found)")
    from binpick.params import load_params
    from flows.serve import serve_watcher

    try:
        serve_watcher(root, load_params(root / params if not params.is_absolute() else params).orchestration, interval_s, port)
    except BinpickError as exc:
        _fail(str(exc))
    except KeyboardInterrupt:
        typer.echo("stopped")


@app.command()
def service(
    host: str = typer.Option(None, help="address to bind (default service.host, 127.0.0.1)"),
    http_port: int = typer.Option(None, min=1, max=65535, help="default service.http_port"),
    tcp_port: int = typer.Option(None, min=0, max=65535, help="the JSON line protocol; 0 = off (default service.tcp_port)"),
    params: Path = typer.Option(Path("params.yaml")),
) -> None:
    """The pick service: loads every trained part once, then answers "picks for this capture"
    over HTTP/JSON and a JSON line protocol until stopped (see README, "The pick service")."""
    import socket

    from binpick.params import load_params
    from flows.service import run_service

    root = project_root()
    params = params if params.is_absolute() else root / params
    try:
        s = load_params(params).service
    except BinpickError as exc:
        _fail(str(exc))
    for port in (http_port or s.http_port, s.tcp_port if tcp_port is None else tcp_port):
        if not port:
            continue
        with socket.socket() as probe:
            try:
                probe.bind((host or s.host, port))
            except OSError as exc:
                _fail(f"cannot listen on {host or s.host}:{port} ({exc.strerror}); another program holds it, or choose another port")
    try:
        run_service(root, params, host, http_port, tcp_port)
    except BinpickError as exc:
        _fail(str(exc))
    except KeyboardInterrupt:
        typer.echo("stopped")


@app.command()
def requests(
    last: int = typer.Option(10, min=1, help="how many of the newest kept requests to list"),
    open_id: str = typer.Option(None, "--open", help="print the command that opens this request's recording (an id, or 'latest')"),
    add: str = typer.Option(None, "--add", help="add this kept request (an id, or 'latest') to params.yaml as a capture, for dvc repro"),
    params: Path = typer.Option(Path("params.yaml")),
) -> None:
    """The service's kept requests, newest first: when, part, picks, timings; open one in rerun,
    or add one to the batch pipeline as a capture."""
    import json
    import shutil
    import sys

    from binpick.params import add_captures, load_params
    from flows.service_keeper import list_requests

    root = project_root()
    params = params if params.is_absolute() else root / params
    try:
        p = load_params(params)
    except BinpickError as exc:
        _fail(str(exc))
    kept = list_requests(root / p.service.keep_dir / "requests")
    if not kept:
        _fail(f"no kept requests under {root / p.service.keep_dir / 'requests'} (is `binpick service` running, and asked?)")

    def find(wanted: str) -> Path:
        for folder in kept:
            if wanted in ("latest", folder.name):
                return folder
        _fail(f"no kept request {wanted!r} (newest: {kept[0].name})")
        raise AssertionError

    if open_id:
        folder = find(open_id)
        typer.echo(f"{Path(sys.executable).parent / 'rerun'} {folder / 'scene.rrd'}")
        return
    if add:
        folder = find(add)
        info = json.loads((folder / "request.json").read_text())
        capture = next(iter(sorted(folder.glob("capture.*"))), None)
        if capture is None:
            _fail(f"{folder}: the capture was not kept")
        target = Layout(root).service_captures / f"{folder.name}{capture.suffix}"
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(capture, target)
        name = folder.name.replace("T", "_", 1)[:64]
        try:
            add_captures(params, {name: target.relative_to(root).as_posix()}, info["part"], info.get("unit", "mm"))
        except BinpickError as exc:
            target.unlink(missing_ok=True)
            _fail(str(exc))
        typer.echo(f"added capture {name} ({target.relative_to(root)}, part {info['part']}): `make repro` processes it")
        return
    for folder in kept[:last]:
        try:
            info = json.loads((folder / "request.json").read_text())
        except (OSError, ValueError):
            typer.echo(f"{folder.name}  (being written)")
            continue
        t, c = info["timings_s"], info["counts"]
        typer.echo(f"{folder.name}  {info['part']}: {c['n_picks']:.0f} picks of {c['n_parts']:.0f} parts, {t['total_s']:.2f} s")


@learn_app.command("review")
def learn_review_cmd(
    part: str = typer.Option(..., help="the part whose labelled captures to review"),
    approve: bool = typer.Option(False, "--approve", help="approve every pending labelled capture (except --reject ones)"),
    reject: list[str] = typer.Option(None, help="a pending capture whose labels are wrong (with --approve)"),
) -> None:
    """Show the labelled captures nobody has reviewed (a rerun recording), then approve them,
    rejecting wrong ones: only approved captures are learnt from."""
    import sys

    from flows.learn import review

    if reject and not approve:
        _fail("--reject goes with --approve (look first: run without either)")
    root = project_root()
    try:
        result = review(root, part, approve, list(reject or []))
    except BinpickError as exc:
        _fail(str(exc))
    if approve:
        typer.echo(f"{part}: approved {len(result.approved)}, rejected {len(result.rejected)}"
                   + (f" ({', '.join(result.rejected)})" if result.rejected else "") + "; recorded in data/real/" + f"{part}/reviewed.json")
    elif result.recording is None:
        typer.echo(f"{part}: no labelled capture is waiting for review")
    else:
        typer.echo(f"{part}: {len(result.pending)} labelled captures to review ({', '.join(result.pending)}). Look at them with\n"
                   f"  {Path(sys.executable).parent / 'rerun'} {result.recording.relative_to(root)}\n"
                   f"then `binpick learn review --part {part} --approve [--reject CAPTURE ...]`")


@learn_app.command("finetune")
def learn_finetune_cmd(
    part: str = typer.Option(..., help="the part whose network to fine-tune"),
    force: bool = typer.Option(False, "--force", help="fine-tune even if fewer than learn.min_new_scenes approved captures are new"),
    params: Path = typer.Option(Path("params.yaml")),
) -> None:
    """Fine-tune the part's served network on its synthetic scenes plus the approved captures;
    serve the result (MLflow alias learn.serve_alias) only when it is no worse on held-back
    captures and on the synthetic test scenes."""
    from binpick.params import load_params
    from flows.learn import finetune

    root = project_root()
    try:
        result = finetune(root, load_params(params if params.is_absolute() else root / params, part), part, force)
    except BinpickError as exc:
        _fail(str(exc))
    if not result["finetuned"]:
        typer.echo(f"{part}: {result['new']} of {result['approved']} approved captures are new; not fine-tuned (see learn.min_new_scenes, or --force)")
        return
    figures = ", ".join(f"{k}: {result[f'before_{k}']:.2f} -> {result[f'after_{k}']:.2f}"
                        for k in ("real_precision", "real_recall", "synthetic_precision", "synthetic_recall"))
    typer.echo(f"{part}: fine-tuned on {result['n_train_real']} captures, judged on {result['n_heldout_real']}: {figures}; "
               + (f"served (version {result['version']})" if result["served"] else "worse, not served"))


@app.command()
def grab(out: Path = typer.Option(..., help="capture to write (.ply, millimetres)"), params: Path = typer.Option(Path("params.yaml"))) -> None:
    """Grab one frame from a connected Zivid camera and save it as a capture (needs the zivid package)."""
    from binpick.params import load_params
    from binpick.zivid_camera import grab_to_file

    try:
        H, W = grab_to_file(out, load_params(params).zivid_camera)
    except BinpickError as exc:
        _fail(str(exc))
    typer.echo(f"wrote {out} ({W} x {H})")


@app.command()
def review(capture: str = typer.Option("demo", help="capture whose recording to show")) -> None:
    """Print the commands that open the latest run in the MLflow UI and the rerun viewer (native or
    in the browser), all bound to 127.0.0.1."""
    root = project_root()
    rrd = Layout(root).scene_recording(capture)
    if not rrd.is_file():
        _fail(f"{rrd}: no recording yet (run `make demo` or `dvc repro register@{capture}` first)")
    for cmd in review_commands(root, capture):
        typer.echo(cmd)


def _listed_capture(p: Params, params: Path, capture: str, root: Path) -> tuple[CaptureParams, ImportOptions]:
    """A capture listed in params.yaml and the options it is read with (one error line if absent)."""
    from binpick.io.capture import ImportOptions

    if capture not in p.captures:
        _fail(f"{params}: capture {capture!r} is not listed under 'captures' (have: {', '.join(sorted(p.captures)) or 'none'})")
    entry = p.captures[capture]
    return entry, ImportOptions(unit=entry.unit, columns=tuple(entry.columns), intrinsics=root / entry.intrinsics if entry.intrinsics else None)


@app.command("fit-bin")
def fit_bin(
    capture: str = typer.Option(..., help="a capture listed in params.yaml that shows the cell's bin"),
    apply: bool = typer.Option(False, "--apply", help="write the box into the capture's params entry (import_capture)"),
    force: bool = typer.Option(False, "--force", help="keep a box that does not look like a bin for the part and the camera"),
    params: Path = typer.Option(Path("params.yaml")),
) -> None:
    """Fit the bin as a box from one capture (support plane, then the region standing on it where
    the camera looks, its smallest enclosing rectangle and height); write a recording to check it
    (data/results/<capture>/bin.rrd) and print the import_capture settings that crop to it. Keep
    them in the capture's entry (--apply), or in the import_capture section for every capture of
    the cell. A box larger than a bin gets, too small or long for the part, or seen from the side
    is refused (exit 1) unless --force."""
    import numpy as np
    import yaml

    from binpick.bin_fit import fit_bin_box, implausible
    from binpick.geometry.pointcloud import fit_plane_ransac
    from binpick.geometry.transforms import invert_T, transform_points
    from binpick.io.capture import load_capture
    from binpick.params import load_params
    from binpick.view import ViewParams, view_grid
    from stages.common.recording import write_bin_recording

    root = project_root()
    try:
        p = load_params(params)
        entry, options = _listed_capture(p, params, capture, root)
        settings = load_params(params, entry.part).import_capture_for(capture)
        cap = load_capture(root / entry.file, options)
        xyz = cap.xyz_m.reshape(-1, 3)
        valid = np.all(np.isfinite(xyz), axis=1) & (np.einsum("ij,ij->i", xyz, xyz) >= settings.min_range_m**2)
        pts = xyz[valid]
        grid = pts[view_grid(pts, ViewParams(max(settings.voxel_size_m, 0.002), settings.normal_radius_m))]
        floor, inliers = fit_plane_ransac(grid, settings.plane_threshold_m, settings.plane_ransac_iterations, p.seed, settings.plane_ransac_confidence)
        if floor[3] < 0:
            floor = -floor
        box = fit_bin_box(grid, floor, settings.keep_above_plane_m)
    except BinpickError as exc:
        _fail(str(exc))
    except ValueError as exc:
        _fail(f"{root / entry.file}: {exc}")
    in_bin = transform_points(invert_T(box.T_cam_from_bin), pts)
    inside = np.all((in_bin >= box.inner_min_m) & (in_bin <= box.inner_max_m), axis=1)
    rrd = Layout(root).bin_recording(capture)
    write_bin_recording(rrd, capture, pts, cap.rgb[valid] if cap.rgb is not None else None, inside, box.T_cam_from_bin, box.inner_min_m, box.inner_max_m)
    size = 1000 * (box.inner_max_m - box.inner_min_m)
    typer.echo(f"{capture}: bin {size[0]:.0f} x {size[1]:.0f} mm, {1000 * box.inner_max_m[2]:.0f} mm high; "
               f"{100 * inside.mean():.0f}% of the points inside; check it: {Path(sys.executable).parent / 'rerun'} {rrd}")
    part_model = Layout(root).part_model(entry.part)
    diameter = None
    if part_model.is_file():
        from binpick.io.part_model import load_part_model

        diameter = load_part_model(part_model).diameter_m
    problems = implausible(box, diameter)
    if problems:
        message = f"{root / entry.file}: the fitted box does not look like a bin: {'; '.join(problems)}"
        if not force:
            _fail(message + " (check the recording; --force keeps it)")
        log.warning("%s (kept: --force)", message)
    snippet = {"import_capture": box.as_import_settings()}
    if apply:
        from binpick.params import set_capture_overrides

        try:
            set_capture_overrides(root / params if not params.is_absolute() else params, capture, box.as_import_settings())
        except BinpickError as exc:
            _fail(str(exc))
        typer.echo(f"wrote captures.{capture}.import_capture in {params}")
    else:
        typer.echo(yaml.safe_dump({"captures": {capture: snippet}}, default_flow_style=None, sort_keys=False).rstrip())


@app.command("hand-eye")
def hand_eye(
    pairs: Path = typer.Option(..., help='JSON: {"pairs": [{"capture": FILE, "T_base_from_flange": 4x4 metres, "unit": "mm", "image": PNG?, "intrinsics": JSON?}, ...]}'),
    setup: str = typer.Option("eye-to-hand", help="eye-to-hand (camera fixed, board on the flange) or eye-in-hand"),
    pattern: str = typer.Option("9x6", help="inner corners of the checkerboard, columns x rows"),
    square_mm: float = typer.Option(25.0, min=0.1, help="side of a checkerboard square"),
    out: Path = typer.Option(Layout(Path()).hand_eye, help="result to write"),
    apply: bool = typer.Option(False, "--apply", help="eye-to-hand: write T_base_from_cam into params.yaml (pick.T_base_from_cam)"),
    params: Path = typer.Option(Path("params.yaml")),
) -> None:
    """Hand-eye calibration from robot flange poses and captures of a checkerboard (OpenCV): the
    camera's pose in the robot base frame (eye-to-hand: T_base_from_cam) or on the flange
    (eye-in-hand: T_flange_from_cam), with residuals in mm and degrees. With --apply, picks are
    given in the robot base frame from then on."""
    import json

    import numpy as np

    from binpick.hand_eye import board_pose, solve_hand_eye
    from binpick.io.atomic import write_text
    from binpick.io.capture import ImportOptions, load_capture
    from binpick.io.depth_image import load_intrinsics
    from binpick.registration.visibility import fit_intrinsics

    if setup not in ("eye-to-hand", "eye-in-hand"):
        _fail(f"--setup {setup!r} is not eye-to-hand or eye-in-hand")
    try:
        cols, rows = (int(x) for x in pattern.lower().split("x"))
    except ValueError:
        _fail(f"--pattern {pattern!r} is not COLSxROWS, e.g. 9x6")
    try:
        import cv2  # noqa: F401
    except ImportError:
        _fail("hand-eye calibration needs OpenCV: pip install -e .[bench]")
    try:
        doc = json.loads(pairs.read_text())
        entries = doc["pairs"]
        flange = np.array([np.asarray(e["T_base_from_flange"], dtype=float).reshape(4, 4) for e in entries])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        _fail(f"{pairs}: not a list of pairs with capture and T_base_from_flange ({type(exc).__name__}: {exc})")
    targets = []
    try:
        for e in entries:
            capture = pairs.parent / e["capture"]
            intrinsics = pairs.parent / e["intrinsics"] if e.get("intrinsics") else None
            cap = load_capture(capture, ImportOptions(unit=e.get("unit", "mm"), intrinsics=intrinsics))
            if cap.shape is None:
                _fail(f"{capture}: not an organized capture: the board must be found in its image")
            H, W = cap.shape
            xyz = cap.xyz_m.reshape(H, W, 3)
            if intrinsics is not None:
                fx, fy, cx, cy = load_intrinsics(intrinsics)
                K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
            else:
                K = fit_intrinsics(cap.xyz_m.reshape(-1, 3), (H, W))
            if e.get("image"):
                from PIL import Image

                image = np.asarray(Image.open(pairs.parent / e["image"]).convert("RGB"))
            else:
                image = np.asarray(cap.rgb, dtype=np.uint8).reshape(H, W, 3)
            T = board_pose(image, (cols, rows), square_mm / 1000.0, K, xyz)
            if T is None:
                _fail(f"{capture}: no {cols}x{rows} checkerboard found in its image")
            targets.append(T)
        result = solve_hand_eye(flange, np.array(targets), "eye_to_hand" if setup == "eye-to-hand" else "eye_in_hand")
    except BinpickError as exc:
        _fail(str(exc))
    key = "T_base_from_cam" if result.setup == "eye_to_hand" else "T_flange_from_cam"
    answer = {"setup": result.setup, key: result.T.round(9).tolist(), "n_poses": result.n_poses,
              "residual_mm_median": result.residual_mm_median, "residual_mm_max": result.residual_mm_max,
              "residual_deg_median": result.residual_deg_median, "residual_deg_max": result.residual_deg_max}
    if apply and result.setup != "eye_to_hand":
        _fail("--apply sets pick.T_base_from_cam, which an eye-in-hand result is not (it moves with the flange)")
    write_text(out, json.dumps(answer, indent=1) + "\n")
    typer.echo(f"{key} from {result.n_poses} poses: residuals {result.residual_mm_median:.2f} mm / {result.residual_deg_median:.2f} deg "
               f"(median), {result.residual_mm_max:.2f} mm / {result.residual_deg_max:.2f} deg (largest); wrote {out}")
    if apply:
        from binpick.params import set_section_key

        try:
            set_section_key(params, "pick", "T_base_from_cam", answer[key])
        except BinpickError as exc:
            _fail(str(exc))
        typer.echo(f"set pick.T_base_from_cam in {params}: picks are given in the robot base frame")


@app.command()
def overlay(
    capture: str = typer.Option(..., help="a capture listed in params.yaml, processed (poses.json exists)"),
    out: Path = typer.Option(None, help="PNG to write; default data/results/<capture>/overlay.png"),
    image: Path = typer.Option(None, help="colour image of the capture (e.g. an RGB-D camera's rgb/0000.png); default: the capture's own colours"),
    params: Path = typer.Option(Path("params.yaml")),
) -> None:
    """Draw a capture's poses over its colour image (each pose's visible model surface, tinted, with
    its index and score), for a look by eye beside the rerun recording."""
    from PIL import Image

    from binpick.io.atomic import atomic_path
    from binpick.overlay import overlay_capture
    from binpick.params import load_params

    root = project_root()
    try:
        entry, options = _listed_capture(load_params(params), params, capture, root)
        layout = Layout(root)
        drawn = overlay_capture(root / entry.file, options, layout.poses(capture), layout.part_model(entry.part), image)
        target = out or layout.overlay(capture)
        with atomic_path(target) as tmp:
            Image.fromarray(drawn).save(tmp)
    except BinpickError as exc:
        _fail(str(exc))
    typer.echo(f"wrote {target}")


def _checkpoints(root: Path, names: list[str]) -> dict[str, Path]:
    """Where each part's trained network lives (the benchmarks use those that exist)."""
    return {n: Layout(root).checkpoint(n) for n in names}


def _write_json(out: Path, result: dict) -> None:
    import json

    from binpick.io.atomic import write_text

    write_text(out, json.dumps(result, indent=1, sort_keys=True) + "\n")
    typer.echo(json.dumps({k: v for k, v in result.items() if not isinstance(v, dict)}, indent=1, sort_keys=True))
    typer.echo(f"wrote {out}")


@bench_app.command("import")
def bench_import_cmd(
    out: Path = typer.Option(..., help="JSON file to write"), repeats: int = typer.Option(7, min=1), params: Path = typer.Option(Path("params.yaml"))
) -> None:
    """Import + clean + downsample of a full 1920 x 1200 organized frame (PLY, PCD, ZDF)."""
    from binpick.bench.importing import bench_import
    from binpick.params import load_params

    try:
        settings = load_params(params)
    except BinpickError as exc:
        _fail(str(exc))
    _write_json(out, bench_import(settings, repeats))


@bench_app.command("ingest")
def bench_ingest_cmd(out: Path = typer.Option(..., help="JSON file to write"), params: Path = typer.Option(Path("params.yaml"))) -> None:
    """Ingest of CAD meshes of 10^4 to 2 x 10^6 faces: time, peak memory, diameter error."""
    from binpick.bench.ingest import bench_ingest
    from binpick.params import load_params

    try:
        settings = load_params(params)
    except BinpickError as exc:
        _fail(str(exc))
    _write_json(out, bench_ingest(settings))


@bench_app.command("clutter")
def bench_clutter_cmd(
    out: Path = typer.Option(..., help="JSON file to write"),
    scenes: int = typer.Option(4, min=1, help="cluttered scenes per part"),
    part: list[str] = typer.Option(None, help="parts (default: t_joint, the gear shaft, ring screw, three-way pipe and IC-BIN coffee cup)"),
    tilt_deg_max: float = typer.Option(45.0, min=0.0, max=59.0, help="the camera's largest tilt from the bin's up axis, degrees"),
    params: Path = typer.Option(Path("params.yaml")),
) -> None:
    """Pose precision/recall and wrong poses outside the bin on bins with distractors and tilted
    views (per band of tilt too), through the real scene path, against the scoring without bin
    crop and verification."""
    from binpick.bench.clutter import DEFAULT_PARTS, bench_clutter
    from binpick.params import load_params

    root = project_root()
    names = part or list(DEFAULT_PARTS)
    try:
        result = bench_clutter(load_params(params), names, scenes, _checkpoints(root, names), tilt_deg_max=tilt_deg_max)
    except (BinpickError, ValueError) as exc:
        _fail(str(exc))
    _write_json(out, result)


@bench_app.command("picking")
def bench_picking_cmd(
    out: Path = typer.Option(..., help="JSON file to write"),
    bins: int = typer.Option(10, min=1, help="bins per part"),
    min_parts: int = typer.Option(10, min=1, help="parts per bin, at least"),
    max_parts: int = typer.Option(20, min=1, help="parts per bin, at most"),
    part: list[str] = typer.Option(None, help="parts (default: t_joint, the gear shaft, ring screw and three-way pipe)"),
    gripper: str = typer.Option(None, help="suction or jaw (default: pick.gripper)"),
    tilt_deg_max: float = typer.Option(45.0, min=0.0, max=59.0, help="each bin's camera is tilted from the bin's up axis by up to this, degrees"),
    params: Path = typer.Option(Path("params.yaml")),
) -> None:
    """Empty simulated bins one pick at a time through the real scene path; every pick checked
    against the simulator's true state (right part touched, path free). Bins are seen from
    straight above to tilt_deg_max, per band of tilt in `by_tilt`."""
    from binpick.bench.picking import DEFAULT_PARTS, bench_picking
    from binpick.params import load_params

    if min_parts > max_parts:
        _fail(f"--min-parts {min_parts} is above --max-parts {max_parts}")
    if gripper not in (None, "suction", "jaw"):
        _fail(f"--gripper must be suction or jaw, not {gripper!r}")
    root = project_root()
    names = part or list(DEFAULT_PARTS)
    try:
        result = bench_picking(load_params(params), names, bins, (min_parts, max_parts), _checkpoints(root, names), gripper, tilt_deg_max=tilt_deg_max)
    except (BinpickError, ValueError) as exc:
        _fail(str(exc))
    _write_json(out, result)


@bench_app.command("sensors")
def bench_sensors_cmd(
    out: Path = typer.Option(..., help="JSON file to write"),
    part: list[str] = typer.Option(None, help="parts (default: t_joint)"),
    train_scenes: int = typer.Option(48, min=2, help="synthetic training scenes per network"),
    val_scenes: int = typer.Option(6, min=1, help="validation scenes per network"),
    test_scenes: int = typer.Option(6, min=1, help="cluttered test bins per test sensor"),
    captures: int = typer.Option(12, min=1, help="captures of the fine-tuning sensor the cell labels itself"),
    finetune_sensor: str = typer.Option("kinect_v1", help="the sensor model the cell's captures come from"),
    leave_one_out: bool = typer.Option(True, help="train a network without each preset and test it on that preset"),
    trust_margin: float = typer.Option(None, min=0.0, max=1.0, help="the labelling's trust margin (default: learn.trust_margin)"),
    params: Path = typer.Option(Path("params.yaml")),
) -> None:
    """Networks trained on today's camera, on the randomised sensor models and without each
    preset, tested on every preset; then the today network fine-tuned on captures it labelled
    itself. Figures from our renderer (README "Sensor models" says what it leaves out)."""
    from binpick.bench.sensors import bench_sensors
    from binpick.params import load_params

    try:
        result = bench_sensors(load_params(params), part or ["t_joint"], train_scenes, val_scenes, test_scenes, captures, finetune_sensor, leave_one_out,
                               trust_margin=trust_margin)
    except (BinpickError, ValueError) as exc:
        _fail(str(exc))
    _write_json(out, result)


@bench_app.command("scene")
def bench_scene_cmd(
    out: Path = typer.Option(..., help="JSON file to write"),
    part: list[str] = typer.Option(None, help="parts (default: t_joint, the gear shaft, ring screw and three-way pipe)"),
    params: Path = typer.Option(Path("params.yaml")),
) -> None:
    """The in-process scene path per step on 1920 x 1200 captures of 8- and 20-part bins, and the
    pick service end to end (process start to first answer, warm requests over HTTP and TCP)."""
    from binpick.bench.scene import DEFAULT_PARTS, bench_scene
    from binpick.params import load_params

    root = project_root()
    names = part or list(DEFAULT_PARTS)
    try:
        result = bench_scene(load_params(params), params.read_text(), names, _checkpoints(root, names))
    except (BinpickError, ValueError) as exc:
        _fail(str(exc))
    _write_json(out, result)


@bench_app.command("soak")
def bench_soak_cmd(
    out: Path = typer.Option(..., help="JSON file to write"),
    requests: int = typer.Option(1000, min=1, help="sequential requests"),
    clients: int = typer.Option(4, min=1, help="concurrent clients after them"),
    per_client: int = typer.Option(25, min=1, help="requests per concurrent client"),
    params: Path = typer.Option(Path("params.yaml")),
) -> None:
    """Load and soak test of the pick service on generated 8-part bins of the built-in part:
    failed answers, memory over the run, the same answer for the same capture."""
    from binpick.bench.scene import bench_soak
    from binpick.params import load_params

    checkpoint = _checkpoints(project_root(), ["t_joint"])["t_joint"]
    try:
        result = bench_soak(load_params(params), params.read_text(), requests, clients, per_client, checkpoint if checkpoint.is_file() else None)
    except (BinpickError, ValueError) as exc:
        _fail(str(exc))
    _write_json(out, result)


@bench_app.command("generate")
def bench_generate_cmd(
    out: Path = typer.Option(..., help="JSON file to write"),
    scenes: int = typer.Option(3, min=1, help="scenes per part and object count"),
    baseline_scenes: int = typer.Option(2, min=1, help="baseline scenes per part and object count"),
    part: list[str] = typer.Option(None, help="parts to use (default: the built-in part and every shared part)"),
    params: Path = typer.Option(Path("params.yaml")),
) -> None:
    """Placement + 1920 x 1200 rendering against the original rejection sampling, at 5, 10, 20 objects."""
    from binpick.bench.generation import bench_generate
    from binpick.params import load_params

    try:
        result = bench_generate(load_params(params), part or None, scenes, baseline_scenes)
    except (BinpickError, ValueError) as exc:
        _fail(str(exc))
    _write_json(out, result)


def _trained_part_paths(part: str, checkpoint: Path | None, scenes: Path | None) -> tuple[Path, Path]:
    """The part's checkpoint and generated data set, where the train and generate stages put them
    unless given."""
    root = project_root()
    return checkpoint or Layout(root).checkpoint(part), scenes or Layout(root).scenes(part)


@bench_app.command("segment")
def bench_segment_cmd(
    out: Path = typer.Option(..., help="JSON file to write"),
    part: str = typer.Option("t_joint", help="a trained part (its checkpoint and generated scenes)"),
    checkpoint: Path = typer.Option(None, help="default: data/fpcc/<part>/model.pt"),
    scenes: Path = typer.Option(None, help="default: data/scenes/<part>"),
    params: Path = typer.Option(Path("params.yaml")),
) -> None:
    """FPCC precision/recall against DBSCAN on held-out scenes, inference time, training throughput."""
    from binpick.bench.segmentation import bench_segment
    from binpick.params import load_params

    checkpoint, scenes = _trained_part_paths(part, checkpoint, scenes)
    try:
        p = load_params(params, part)
        result = bench_segment(checkpoint, scenes, p.segment, p.import_capture.voxel_size_m, p.seed, p.evaluate.iou_threshold)
    except (BinpickError, ValueError) as exc:
        _fail(str(exc))
    _write_json(out, {"part": part, **result})


@app.command()
def calibrate(
    out: Path = typer.Option(..., help="checkpoint to write (.pt)"),
    part: str = typer.Option("t_joint", help="the part (its params entry, checkpoint and scenes)"),
    checkpoint: Path = typer.Option(None, help="trained checkpoint; default: data/fpcc/<part>/model.pt"),
    scenes: Path = typer.Option(None, help="data set folder with a val/ split; default: data/scenes/<part>"),
    params: Path = typer.Option(Path("params.yaml")),
) -> None:
    """Choose a trained network's clustering settings again on the validation scenes, as the train
    stage does (for a network trained elsewhere, or after a change of segment settings); writes a
    copy of the checkpoint that holds them."""
    import numpy as np

    from binpick.network.calibrate import recalibrate
    from binpick.network.checkpoint import read_checkpoint
    from binpick.network.train import load_views
    from binpick.params import load_params
    from binpick.seeding import derive_seed

    checkpoint, scenes = _trained_part_paths(part, checkpoint, scenes)
    try:
        p = load_params(params, part)
        read_checkpoint(checkpoint)  # a damaged checkpoint is named before the scenes are read
        views = load_views(scenes / "val")
        chosen = recalibrate(checkpoint, out, views, p.segment, p.evaluate.iou_threshold, np.random.default_rng(derive_seed(p.seed, "calibrate", part)))
    except (BinpickError, ValueError, OSError) as exc:
        _fail(str(exc))
    log.info("%s: %s on %d validation scenes -> %s", part, ", ".join(f"{k} {v:.3g}" for k, v in chosen.items()), len(views), out)


@app.command("eval-labels")
def eval_labels(
    pred: Path = typer.Option(..., help="labelled scene to evaluate (text)"),
    gt: Path = typer.Option(..., help="ground-truth labelled scene (text)"),
    pred_columns: str = typer.Option("x,y,z,label", help="e.g. x,y,z,label or x,y,z,score,label"),
    gt_columns: str = typer.Option("x,y,z,label"),
    unit: str = typer.Option("m", help="unit of both files' coordinates"),
    match_distance_m: float = typer.Option(0.001, help="a predicted point labels the ground-truth point this close"),
    iou: float = typer.Option(0.5, help="IoU threshold of a match"),
) -> None:
    """Evaluate a foreign tool's labelled scene against ground truth with this project's metrics."""
    import json

    from binpick.io.labelled import load_labelled, transfer_labels
    from binpick.metrics.segmentation import scene_counts

    if not 0.0 < iou <= 1.0:
        _fail(f"--iou {iou:g} must lie in (0, 1]")
    if not match_distance_m >= 0.0:
        _fail(f"--match-distance-m {match_distance_m:g} must not be negative")
    try:
        p = load_labelled(pred, tuple(c.strip() for c in pred_columns.split(",")), unit)
        g = load_labelled(gt, tuple(c.strip() for c in gt_columns.split(",")), unit)
    except BinpickError as exc:
        _fail(str(exc))
    labels = transfer_labels(p.points_m, p.labels, g.points_m, match_distance_m)
    typer.echo(json.dumps(scene_counts(labels, g.labels, iou).summary(), indent=1, sort_keys=True))


@bench_app.command("ppf")
def bench_ppf_cmd(
    out: Path = typer.Option(..., help="JSON file to write"),
    trials: int = typer.Option(20, min=1, help="views per part"),
    part: list[str] = typer.Option(None, help="parts to use (default: the built-in part and every shared part)"),
    method: list[str] = typer.Option(None, help="methods to run (default: all)"),
    params: Path = typer.Option(Path("params.yaml")),
) -> None:
    """PPF registration against OpenCV PPF + ICP and Open3D FPFH + RANSAC + ICP on the same views."""
    from binpick.bench.ppf import METHODS, bench_ppf
    from binpick.params import load_params

    for m in method or []:
        if m not in METHODS:
            _fail(f"unknown method {m!r} (have: {', '.join(METHODS)})")
    if "opencv_ppf_icp" in (method or METHODS):
        try:
            import cv2  # noqa: F401
        except ImportError:
            _fail("the OpenCV peer needs opencv-contrib-python-headless: pip install -e .[bench]")
    try:
        result = bench_ppf(load_params(params), part or None, trials, method or None)
    except (BinpickError, ValueError) as exc:
        _fail(str(exc))
    _write_json(out, result)


if __name__ == "__main__":
    app()
