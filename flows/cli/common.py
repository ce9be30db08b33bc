"""What the `binpick` command's sub-apps share: the apps, the one rule for `--params`, the one
error line, and the project the command runs in."""

from __future__ import annotations

import contextlib
import json
import logging
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn

import typer

from binpick.env import configure_environment, project_root
from binpick.layout import Layout
from binpick.log import loggers_raised, setup_logging

if TYPE_CHECKING:
    from binpick.io.capture import ImportOptions
    from binpick.params import CaptureParams, Params

app = typer.Typer(
    add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False, help="The `binpick` command."
)
bench_app = typer.Typer(no_args_is_help=True, help="Benchmarks: each writes its measurements as JSON.")
app.add_typer(bench_app, name="bench")
learn_app = typer.Typer(
    no_args_is_help=True, help="Learning from the cell: review labelled captures, fine-tune on them."
)
app.add_typer(learn_app, name="learn")
cell_app = typer.Typer(no_args_is_help=True, help="The robot cell: capture, pick, move, place, in a loop.")
app.add_typer(cell_app, name="cell")
log = logging.getLogger("binpick")

_state = {"verbose": False}


def fail(message: str) -> NoReturn:
    """The command's one error line, exit status 2 (flows.cli.main turns every BinpickError into it)."""
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(2)


def params_file(given: Path | None) -> Path:
    """The one `--params` rule: a path given is taken as given (relative to the current folder, as
    any command's file arguments); none means the project's params.yaml, found from the current
    folder upward."""
    return given if given is not None else project_root() / "params.yaml"


PARAMS = typer.Option(
    None, "--params", callback=params_file, help="settings file (default: params.yaml of the project this folder is in)"
)


def project() -> Path:
    """The project the command runs in (one error line when the current folder is in none)."""
    root = project_root()
    if not (root / "dvc.yaml").is_file():
        fail(f"{Path.cwd()}: not inside a binpick project (no params.yaml and dvc.yaml found)")
    return root


@contextlib.contextmanager
def quiet_prefect() -> Iterator[None]:
    """A failing flow ends in our one `error:` line; Prefect's own report of it (the exception
    with its traceback, for the task, the sub-flow and the flow) is shown only with --verbose."""
    if _state["verbose"]:
        yield
        return
    with loggers_raised(("prefect.flow_runs", "prefect.task_runs", "prefect.engine", "prefect"), logging.CRITICAL):
        yield


@app.callback()
def _main(
    verbose: bool = typer.Option(False, "--verbose", "-v", help="debug logging, and Prefect's reports of failures"),
) -> None:
    _state["verbose"] = verbose
    configure_environment()
    setup_logging(verbose)


def listed_capture(p: Params, params: Path, capture: str, root: Path) -> tuple[CaptureParams, ImportOptions]:
    """A capture listed in params.yaml and the options it is read with (one error line if absent)."""
    from binpick.io.capture import ImportOptions

    if capture not in p.captures:
        fail(
            f"{params}: capture {capture!r} is not listed under 'captures' (have: "
            f"{', '.join(sorted(p.captures)) or 'none'})"
        )
    entry = p.captures[capture]
    return entry, ImportOptions(
        unit=entry.unit, columns=tuple(entry.columns), intrinsics=root / entry.intrinsics if entry.intrinsics else None
    )


def checkpoints(root: Path, names: list[str]) -> dict[str, Path]:
    """Where each part's trained network lives (the benchmarks use those that exist)."""
    return {n: Layout(root).checkpoint(n) for n in names}


def write_json(out: Path, result: dict) -> None:
    from binpick.io.atomic import write_text

    write_text(out, json.dumps(result, indent=1, sort_keys=True) + "\n")
    typer.echo(json.dumps({k: v for k, v in result.items() if not isinstance(v, dict)}, indent=1, sort_keys=True))
    typer.echo(f"wrote {out}")


def trained_part_paths(part: str, checkpoint: Path | None, scenes: Path | None) -> tuple[Path, Path]:
    """The part's checkpoint and generated data set, where the train and generate stages put them
    unless given."""
    root = project_root()
    return checkpoint or Layout(root).checkpoint(part), scenes or Layout(root).scenes(part)
