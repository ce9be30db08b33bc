"""`binpick` commands that run the pipeline: the demo, the project check, repro, the watcher,
folders of captures, the schedule, the review commands."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import typer

from binpick.env import project_root
from binpick.errors import BinpickError
from binpick.io.mesh import METRES_PER_UNIT
from binpick.layout import Layout
from flows.cli.common import PARAMS, app, fail, project, quiet_prefect


@app.command("default-part")
def default_part(
    out: Path = typer.Option(Layout(Path()).parts_folder / "t_joint.stl", help="STL to write (millimetres)"),
) -> None:
    """Write the built-in T-joint pipe part as an STL file (millimetres)."""
    from binpick.io.mesh import save_mesh
    from binpick.part.model import build_t_joint_mesh

    mesh = build_t_joint_mesh()
    save_mesh(out, mesh.vertices, mesh.faces)
    typer.echo(f"wrote {out} ({len(mesh.faces)} faces, {mesh.extents.round(1).tolist()} mm)")


def review_commands(root: Path, capture: str = "demo") -> list[str]:
    """The commands that open the latest results (loopback only)."""
    bin_dir = Path(sys.executable).parent
    return [
        f"{bin_dir / 'mlflow'} ui --backend-store-uri sqlite:///{Layout(root).mlflow_store} --host 127.0.0.1 --port "
        "5000",
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
        (
            "parts found in the demo capture",
            f"{f(reg, 'n_found', '{:.0f}')} of {f(reg, 'n_ground_truth', '{:.0f}')} ({f(reg, 'n_pickable', '{:.0f}')} "
            "at least half visible)",
        ),
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
    root = project()
    from flows.dvc_tasks import StageFailed
    from flows.pipeline import demo as demo_flow

    t0 = time.perf_counter()
    try:
        with quiet_prefect():
            results = demo_flow(root)
    except (StageFailed, BinpickError) as exc:
        fail(str(exc))
    typer.echo("\nbinpick demo: the built-in part, trained and found in a rendered bin\n")
    typer.echo(summary_table(results, (time.perf_counter() - t0) / 60.0))
    typer.echo("\nReview the run:")
    for cmd in review_commands(root):
        typer.echo(f"  {cmd}")


@app.command()
def check() -> None:
    """Validate params.yaml as a whole and write data/pipeline.yaml, the names and paths dvc.yaml
    runs on (every project command does this first; run it before a bare `dvc repro`)."""
    from binpick.project import check_project

    root = project()
    result = check_project(root)
    aside = [f"{k}.{n}" for k, entries in result.set_aside.items() for n in entries]
    typer.echo(
        f"params.yaml is valid: {len(result.pipeline.parts)} parts, {len(result.pipeline.captures)} captures in the "
        "pipeline"
        + (f", {len(result.pipeline.mixed)} of mixed bins" if result.pipeline.mixed else "")
        + (f"; set aside: {', '.join(aside)}" if aside else "")
        + ("; data/pipeline.yaml updated" if result.vars_changed else "")
    )


@app.command()
def repro() -> None:
    """Check the project, then `dvc repro --keep-going`: a part or capture whose stage fails is set
    aside (data/set_aside.yaml) and the rest of the pipeline still runs."""
    from binpick.project import check_project
    from flows.repro import repro_all

    root = project()
    check_project(root)
    outcome = repro_all(root)
    typer.echo(outcome.summary("ran"))
    if outcome.failed:
        raise typer.Exit(1)


@app.command()
def watch() -> None:
    """Once: add new meshes in data/parts/ to params.yaml and train every part not up to date; a
    part that fails is set aside until its mesh or entry changes."""
    root = project()
    from flows.dvc_tasks import StageFailed
    from flows.watcher import watch_parts

    try:
        with quiet_prefect():
            outcome = watch_parts(root)
    except (StageFailed, BinpickError) as exc:
        fail(str(exc))
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
    root = project()
    if unit not in METRES_PER_UNIT:
        fail(f"unit {unit!r} is not one of {', '.join(METRES_PER_UNIT)}")
    from flows.dvc_tasks import StageFailed
    from flows.pipeline import process_folder

    try:
        with quiet_prefect():
            outcome, results = process_folder(
                root, folder.resolve() if folder.is_absolute() else Path.cwd() / folder, part, unit
            )
    except (StageFailed, BinpickError) as exc:
        fail(str(exc))
    for name, metrics in results.items():
        typer.echo(f"{name}: {metrics.get('n_found', 0):.0f} parts, mean score {metrics.get('score_mean', 0.0):.2f}")
    typer.echo(outcome.summary("processed"))
    if outcome.failed:
        raise typer.Exit(1)


@app.command()
def serve(
    interval_s: float = typer.Option(
        None, "--interval-s", min=1, help="run every N seconds instead of the cron schedule in params"
    ),
    port: int = typer.Option(4200, help="port of the local Prefect server (when PREFECT_API_URL is not set)"),
    params: Path = PARAMS,
) -> None:
    """Run the watcher on the schedule in params (default nightly) until stopped; starts a local
    Prefect server on 127.0.0.1 unless PREFECT_API_URL names a shared one."""
    root = project_root()
    if not (root / "dvc.yaml").is_file():
        fail(f"{Path.cwd()}: not inside a binpick project (no params.yaml and dvc.yaml found)")
    from binpick.params import load_params
    from flows.serve import serve_watcher

    try:
        serve_watcher(root, load_params(params).orchestration, interval_s, port)
    except KeyboardInterrupt:
        typer.echo("stopped")


@app.command()
def review(capture: str = typer.Option("demo", help="capture whose recording to show")) -> None:
    """Print the commands that open the latest run in the MLflow UI and the rerun viewer (native or
    in the browser), all bound to 127.0.0.1."""
    root = project_root()
    rrd = Layout(root).scene_recording(capture)
    if not rrd.is_file():
        fail(f"{rrd}: no recording yet (run `make demo` or `dvc repro register@{capture}` first)")
    for cmd in review_commands(root, capture):
        typer.echo(cmd)
