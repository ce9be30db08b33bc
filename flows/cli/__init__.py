"""The `binpick` command: one Typer app whose commands live in sub-app modules (pipeline, cell,
learn, bench), with one error boundary: a BinpickError from any command is one `error:` line and
exit status 2, never a traceback."""

from __future__ import annotations

import importlib
import sys

import typer

from binpick.errors import BinpickError
from flows.cli.common import app

__all__ = ["app", "main"]

# Importing a sub-app module registers its commands; --help lists them in this order.
for _module in ("pipeline", "cell", "learn", "bench"):
    importlib.import_module(f"flows.cli.{_module}")


def main() -> None:
    try:
        app()
    except BinpickError as exc:
        typer.echo(f"error: {exc}", err=True)
        sys.exit(2)
