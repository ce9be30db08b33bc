"""`binpick` commands of a running cell: the pick service and its kept requests, the camera, the
bin, hand-eye calibration, overlays."""

from __future__ import annotations

import sys
from pathlib import Path

import typer

from binpick.env import project_root
from binpick.errors import BinpickError
from binpick.layout import Layout
from flows.cli.common import PARAMS, app, cell_app, fail, listed_capture, log


@app.command()
def service(
    host: str = typer.Option(None, help="address to bind (default service.host, 127.0.0.1)"),
    http_port: int = typer.Option(None, min=1, max=65535, help="default service.http_port"),
    tcp_port: int = typer.Option(
        None, min=0, max=65535, help="the JSON line protocol; 0 = off (default service.tcp_port)"
    ),
    params: Path = PARAMS,
) -> None:
    """The pick service: loads every trained part once, then answers "picks for this capture"
    over HTTP/JSON and a JSON line protocol until stopped (docs/guide/service.md)."""
    import socket

    from binpick.params import load_params
    from flows.service_http import run_service

    root = project_root()
    s = load_params(params).service
    for port in (http_port or s.http_port, s.tcp_port if tcp_port is None else tcp_port):
        if not port:
            continue
        with socket.socket() as probe:
            try:
                probe.bind((host or s.host, port))
            except OSError as exc:
                fail(
                    f"cannot listen on {host or s.host}:{port} ({exc.strerror}); another program holds it, or choose "
                    "another port"
                )
    try:
        run_service(root, params, host, http_port, tcp_port)
    except KeyboardInterrupt:
        typer.echo("stopped")


@app.command()
def requests(
    last: int = typer.Option(10, min=1, help="how many of the newest kept requests to list"),
    open_id: str = typer.Option(
        None, "--open", help="print the command that opens this request's recording (an id, or 'latest')"
    ),
    add: str = typer.Option(
        None, "--add", help="add this kept request (an id, or 'latest') to params.yaml as a capture, for dvc repro"
    ),
    params: Path = PARAMS,
) -> None:
    """The service's kept requests, newest first: when, part, picks, timings; open one in rerun,
    or add one to the batch pipeline as a capture."""
    import json
    import shutil
    import sys

    from binpick.params import add_captures, load_params
    from flows.service_keeper import list_requests

    root = project_root()
    p = load_params(params)
    kept = list_requests(root / p.service.keep_dir / "requests")
    if not kept:
        fail(
            f"no kept requests under {root / p.service.keep_dir / 'requests'} (is `binpick service` running, and "
            "asked?)"
        )

    def find(wanted: str) -> Path:
        for folder in kept:
            if wanted in ("latest", folder.name):
                return folder
        fail(f"no kept request {wanted!r} (newest: {kept[0].name})")
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
            fail(f"{folder}: the capture was not kept")
        target = Layout(root).service_captures / f"{folder.name}{capture.suffix}"
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(capture, target)
        name = folder.name.replace("T", "_", 1)[:64]
        parts = info.get("parts") or info["part"]  # a mixed bin's request names its parts
        try:
            add_captures(params, {name: target.relative_to(root).as_posix()}, parts, info.get("unit", "mm"))
        except BinpickError:
            target.unlink(missing_ok=True)
            raise
        shown = f"parts {', '.join(parts)}" if isinstance(parts, list) else f"part {parts}"
        typer.echo(f"added capture {name} ({target.relative_to(root)}, {shown}): `make repro` processes it")
        return
    for folder in kept[:last]:
        try:
            info = json.loads((folder / "request.json").read_text())
        except (OSError, ValueError):
            typer.echo(f"{folder.name}  (being written)")
            continue
        t, c = info["timings_s"], info["counts"]
        typer.echo(
            f"{folder.name}  {info.get('part') or ','.join(info.get('parts', []))}: {c['n_picks']:.0f} picks of "
            f"{c['n_parts']:.0f} parts, {t['total_s']:.2f} s"
        )


@app.command()
def grab(out: Path = typer.Option(..., help="capture to write (.ply, millimetres)"), params: Path = PARAMS) -> None:
    """Grab one frame from a connected Zivid camera and save it as a capture (needs the zivid package)."""
    from binpick.cell.zivid_camera import grab_to_file
    from binpick.params import load_params

    H, W = grab_to_file(out, load_params(params).zivid_camera)
    typer.echo(f"wrote {out} ({W} x {H})")


@app.command("fit-bin")
def fit_bin(
    capture: str = typer.Option(..., help="a capture listed in params.yaml that shows the cell's bin"),
    apply: bool = typer.Option(False, "--apply", help="write the box into the capture's params entry (import_capture)"),
    force: bool = typer.Option(
        False, "--force", help="keep a box that does not look like a bin for the part and the camera"
    ),
    params: Path = PARAMS,
) -> None:
    """Fit the bin as a box from one capture (support plane, then the region standing on it where
    the camera looks, its smallest enclosing rectangle and height); write a recording to check it
    (data/results/<capture>/bin.rrd) and print the import_capture settings that crop to it. Keep
    them in the capture's entry (--apply), or in the import_capture section for every capture of
    the cell. A box larger than a bin gets, too small or long for the part, seen from the side, or
    ending at the edge of the camera's view is refused (exit 1) unless --force."""
    import numpy as np
    import yaml

    from binpick.cell.bin_box import WALL_SIDES
    from binpick.cell.bin_fit import fit_capture_bin, implausible, valid_points
    from binpick.geometry.transforms import invert_T, transform_points
    from binpick.io.capture import load_capture
    from binpick.params import load_params
    from review.recording import write_bin_recording

    root = project_root()
    try:
        p = load_params(params)
        entry, options = listed_capture(p, params, capture, root)
        settings = load_params(params, entry.part_names[0]).import_capture_for(capture)
        cap = load_capture(root / entry.file, options)
        xyz = cap.xyz_m.reshape(-1, 3)
        valid = valid_points(xyz, settings.min_range_m)
        pts = xyz[valid]
        box = fit_capture_bin(pts, settings, p.seed)
    except ValueError as exc:
        fail(f"{root / entry.file}: {exc}")
    in_bin = transform_points(invert_T(box.T_cam_from_bin), pts)
    inside = np.all((in_bin >= box.inner_min_m) & (in_bin <= box.inner_max_m), axis=1)
    rrd = Layout(root).bin_recording(capture)
    write_bin_recording(
        rrd,
        capture,
        pts,
        cap.rgb[valid] if cap.rgb is not None else None,
        inside,
        box.T_cam_from_bin,
        box.inner_min_m,
        box.inner_max_m,
    )
    size = 1000 * (box.inner_max_m - box.inner_min_m)
    heights = box.wall_heights_m if box.wall_heights_m is not None else np.full(4, box.inner_max_m[2])
    walls = ", ".join(
        f"{side} {1000 * h:.0f} mm" if h > 0 else f"{side} none" for side, h in zip(WALL_SIDES, heights, strict=True)
    )
    typer.echo(
        f"{capture}: bin {size[0]:.0f} x {size[1]:.0f} mm, {1000 * box.inner_max_m[2]:.0f} mm high; walls {walls}; "
        f"{100 * inside.mean():.0f}% of the points inside; check it: {Path(sys.executable).parent / 'rerun'} {rrd}"
    )
    from binpick.io.part_model import load_part_model

    # The largest part of the capture (of a mixed bin's parts) sets what a plausible bin is.
    models = [Layout(root).part_model(name) for name in entry.part_names]
    diameters = [load_part_model(m).diameter_m for m in models if m.is_file()]
    diameter = max(diameters) if diameters else None
    problems = implausible(box, diameter, pts)
    if problems:
        message = f"{root / entry.file}: the fitted box does not look like a bin: {'; '.join(problems)}"
        if not force:
            fail(message + " (check the recording; --force keeps it)")
        log.warning("%s (kept: --force)", message)
    snippet = {"import_capture": box.as_import_settings()}
    if apply:
        from binpick.params import set_capture_overrides

        set_capture_overrides(params, capture, box.as_import_settings())
        typer.echo(f"wrote captures.{capture}.import_capture in {params}")
    else:
        typer.echo(yaml.safe_dump({"captures": {capture: snippet}}, default_flow_style=None, sort_keys=False).rstrip())


@app.command("hand-eye")
def hand_eye(
    pairs: Path = typer.Option(
        ...,
        help='JSON: {"pairs": [{"capture": FILE, "T_base_from_flange": 4x4 metres, "unit": "mm", '
        '"image": PNG?, "intrinsics": JSON?}, ...]}',
    ),
    setup: str = typer.Option("eye-to-hand", help="eye-to-hand (camera fixed, board on the flange) or eye-in-hand"),
    pattern: str = typer.Option("9x6", help="inner corners of the checkerboard, columns x rows"),
    square_mm: float = typer.Option(25.0, min=0.1, help="side of a checkerboard square"),
    out: Path = typer.Option(Layout(Path()).hand_eye, help="result to write"),
    apply: bool = typer.Option(
        False, "--apply", help="eye-to-hand: write T_base_from_cam into params.yaml (pick.T_base_from_cam)"
    ),
    params: Path = PARAMS,
) -> None:
    """Hand-eye calibration from robot flange poses and captures of a checkerboard (OpenCV): the
    camera's pose in the robot base frame (eye-to-hand: T_base_from_cam) or on the flange
    (eye-in-hand: T_flange_from_cam), with residuals in mm and degrees. With --apply, picks are
    given in the robot base frame from then on."""
    import json

    import numpy as np

    from binpick.cell.hand_eye import board_pose, solve_hand_eye
    from binpick.io.atomic import write_text
    from binpick.io.capture import ImportOptions, load_capture
    from binpick.io.depth_image import load_intrinsics
    from binpick.registration.visibility import fit_intrinsics

    if setup not in ("eye-to-hand", "eye-in-hand"):
        fail(f"--setup {setup!r} is not eye-to-hand or eye-in-hand")
    try:
        cols, rows = (int(x) for x in pattern.lower().split("x"))
    except ValueError:
        fail(f"--pattern {pattern!r} is not COLSxROWS, e.g. 9x6")
    try:
        import cv2  # noqa: F401
    except ImportError:
        fail("hand-eye calibration needs OpenCV: pip install -e .[bench]")
    try:
        doc = json.loads(pairs.read_text())
        entries = doc["pairs"]
        flange = np.array([np.asarray(e["T_base_from_flange"], dtype=float).reshape(4, 4) for e in entries])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        fail(f"{pairs}: not a list of pairs with capture and T_base_from_flange ({type(exc).__name__}: {exc})")
    targets = []
    for e in entries:
        capture = pairs.parent / e["capture"]
        intrinsics = pairs.parent / e["intrinsics"] if e.get("intrinsics") else None
        cap = load_capture(capture, ImportOptions(unit=e.get("unit", "mm"), intrinsics=intrinsics))
        if cap.shape is None:
            fail(f"{capture}: not an organized capture: the board must be found in its image")
        H, W = cap.shape
        xyz = cap.xyz_m.reshape(H, W, 3)
        camera = (
            load_intrinsics(intrinsics, (H, W))
            if intrinsics is not None
            else fit_intrinsics(cap.xyz_m.reshape(-1, 3), (H, W))
        )
        if e.get("image"):
            from PIL import Image

            image = np.asarray(Image.open(pairs.parent / e["image"]).convert("RGB"))
        else:
            image = np.asarray(cap.rgb, dtype=np.uint8).reshape(H, W, 3)
        T = board_pose(image, (cols, rows), square_mm / 1000.0, camera.K, xyz)
        if T is None:
            fail(f"{capture}: no {cols}x{rows} checkerboard found in its image")
        targets.append(T)
    result = solve_hand_eye(flange, np.array(targets), "eye_to_hand" if setup == "eye-to-hand" else "eye_in_hand")
    key = "T_base_from_cam" if result.setup == "eye_to_hand" else "T_flange_from_cam"
    answer = {
        "setup": result.setup,
        key: result.T.round(9).tolist(),
        "n_poses": result.n_poses,
        "residual_mm_median": result.residual_mm_median,
        "residual_mm_max": result.residual_mm_max,
        "residual_deg_median": result.residual_deg_median,
        "residual_deg_max": result.residual_deg_max,
    }
    if apply and result.setup != "eye_to_hand":
        fail("--apply sets pick.T_base_from_cam, which an eye-in-hand result is not (it moves with the flange)")
    write_text(out, json.dumps(answer, indent=1) + "\n")
    typer.echo(
        f"{key} from {result.n_poses} poses: residuals {result.residual_mm_median:.2f} mm / "
        f"{result.residual_deg_median:.2f} deg "
        f"(median), {result.residual_mm_max:.2f} mm / {result.residual_deg_max:.2f} deg (largest); wrote {out}"
    )
    if apply:
        from binpick.params import set_section_key

        set_section_key(params, "pick", "T_base_from_cam", answer[key])
        typer.echo(f"set pick.T_base_from_cam in {params}: picks are given in the robot base frame")


@app.command()
def overlay(
    capture: str = typer.Option(..., help="a capture listed in params.yaml, processed (poses.json exists)"),
    out: Path = typer.Option(None, help="PNG to write; default data/results/<capture>/overlay.png"),
    image: Path = typer.Option(
        None,
        help="colour image of the capture (e.g. an RGB-D camera's rgb/0000.png); default: the capture's own colours",
    ),
    params: Path = PARAMS,
) -> None:
    """Draw a capture's poses over its colour image (each pose's visible model surface, tinted, with
    its index and score) and its first pick (a ring at the grasp, a line along the approach), for a
    look by eye beside the rerun recording."""
    from PIL import Image

    from binpick.io.atomic import atomic_path
    from binpick.params import load_params
    from binpick.scene.overlay import overlay_capture

    root = project_root()
    entry, options = listed_capture(load_params(params), params, capture, root)
    if entry.parts:
        fail(f"{params}: capture {capture!r} is a mixed bin; the overlay draws one-part captures (not mixed ones yet)")
    layout = Layout(root)
    picks = layout.picks(capture)
    drawn = overlay_capture(
        root / entry.file,
        options,
        layout.poses(capture),
        layout.part_model(entry.part),
        image,
        picks if picks.is_file() else None,
    )
    target = out or layout.overlay(capture)
    with atomic_path(target) as tmp:
        Image.fromarray(drawn).save(tmp)
    typer.echo(f"wrote {target}")


@cell_app.command("run")
def cell_run(
    part: str = typer.Option(..., help="the part in the bin (its models built: make repro)"),
    max_cycles: int = typer.Option(None, min=1, help="stop after this many cycles (default: until the bin is empty)"),
    max_failures: int | None = typer.Option(
        None, min=1, help="stop after this many failed attempts in a row (default: binpick.cell.robot's, 3)"
    ),
    sim_parts: int = typer.Option(10, min=1, help="sim: parts settled in the bin"),
    seed: int = typer.Option(0, help="sim: the bin's and the camera noise's seed"),
    params: Path = PARAMS,
) -> None:
    """Run the cell: capture, picks (the arm checked), move, grasp, place, until the bin is empty,
    a stop is asked for (Ctrl-C, or the file data/cell/STOP), the arm stops itself or
    --max-failures attempts in a row fail; cell.robot.driver chooses the physics cell (sim) or a
    UR arm (ur_rtde). Every cycle is kept in data/cell/runs/<run>/."""
    import threading

    from binpick.cell.robot import MAX_FAILURES_IN_A_ROW, Robot
    from binpick.params import load_params
    from binpick.scene.process import PartModels
    from flows.cell_run import Camera, ZividCamera, real_robot, run_cell, simulated_cell, stop_on_signals

    root = project_root()
    layout = Layout(root)
    p = load_params(params, part)
    if p.cell.arm is None or p.pick.T_base_from_cam is None:
        fail(f"{params}: the cell needs cell.arm and pick.T_base_from_cam (binpick hand-eye --apply)")
    needed = [layout.part_model(part), layout.ppf_model(part), layout.grasps(part)]
    missing = [str(path.relative_to(root)) for path in needed if not path.is_file()]
    if missing:
        fail(f"{part}: {', '.join(missing)} not built (run make repro)")
    checkpoint = layout.checkpoint(part) if layout.checkpoint(part).is_file() else None
    models = PartModels.load(p, needed[0], needed[1], checkpoint, needed[2], layout.verification(part))
    robot: Robot
    camera: Camera
    if p.cell.robot.driver == "sim":
        robot, camera = simulated_cell(p, models.part, sim_parts, seed)
    else:
        robot, camera = real_robot(p), ZividCamera(p)
    layout.cell_stop.unlink(missing_ok=True)
    stop = threading.Event()
    try:
        with stop_on_signals(stop):
            limit = max_failures or MAX_FAILURES_IN_A_ROW
            summary = run_cell(root, p, part, robot, camera, models, max_cycles, stop, limit)
    finally:
        robot.close()
    typer.echo(f"{summary.placed} placed in {summary.cycles} cycles; {summary.ended}")
    typer.echo(f"cycles kept in {summary.folder.relative_to(root)}")
