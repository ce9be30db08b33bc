"""What every stage shares: the CLI wrapper (one error line, non-zero exit), params, metrics
files (MLflow runs: review.tracking). Stages import this; kernels never do."""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Protocol

from binpick.env import configure_environment, project_root
from binpick.errors import BinpickError
from binpick.io.atomic import write_text
from binpick.log import setup_logging
from review.tracking import mlflow_run

log = logging.getLogger("binpick.stage")


def parser(description: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--params", default="params.yaml", help="settings file (default: params.yaml)")
    p.add_argument("-v", "--verbose", action="store_true")
    return p


class Terminated(BaseException):
    """SIGTERM arrived (BaseException, like KeyboardInterrupt, so no `except Exception` swallows it)."""


def _terminate(signum: int, frame: Any) -> None:
    raise Terminated()


class StageMain(Protocol):
    def __call__(self, argv: Sequence[str] | None = None) -> int: ...


def entry(main: Callable[[Sequence[str] | None], int]) -> StageMain:
    """Wrap a stage's main: a BinpickError becomes one line on stderr and exit code 2."""

    def wrapped(argv: Sequence[str] | None = None) -> int:
        configure_environment()
        # SIGTERM (a stopped flow, a killed parent) unwinds like Ctrl-C: open MLflow runs end,
        # temporary outputs are removed, nothing half-written is left under a real name.
        signal.signal(signal.SIGTERM, _terminate)
        try:
            return main(argv)
        except BinpickError as exc:
            sys.stderr.write(f"error: {exc}\n")
            return 2
        except KeyboardInterrupt:
            sys.stderr.write("error: interrupted\n")
            return 130
        except Terminated:
            sys.stderr.write("error: terminated\n")
            return 143
        except OSError as exc:
            # A read-only folder, a full disk, a path through a file: the system's words, one line.
            if "-v" in sys.argv or "--verbose" in sys.argv:
                raise
            where = f"{exc.filename}: " if exc.filename else ""
            sys.stderr.write(f"error: {where}cannot read or write ({exc.strerror or exc})\n")
            return 2

    wrapped.__doc__ = main.__doc__
    return wrapped


def start(args: argparse.Namespace) -> None:
    """Logging, then, when DVC runs the stage, the check that data/pipeline.yaml (which DVC read
    the stage's names and paths from) still matches the whole, valid params.yaml."""
    import os

    setup_logging(args.verbose)
    if os.environ.get("DVC_STAGE"):
        from binpick.lifetime import die_with_parent, find_ancestor, watch_ancestor
        from binpick.project import verify_pipeline_vars

        # Killed with DVC: a stage whose `dvc repro` is gone must not write outputs DVC never records.
        die_with_parent()
        dvc = find_ancestor("dvc")
        if dvc is not None:
            watch_ancestor(dvc)
        verify_pipeline_vars(project_root())


def is_timing(key: str) -> bool:
    """Timings (`*_s`, `ms_per_*`) differ between runs: MLflow keeps them, the DVC metrics do not."""
    return key.endswith("_s") or key.startswith("ms_per_")


def write_metrics(path: str | Path, metrics: dict[str, Any]) -> None:
    """A metrics JSON for DVC (`dvc metrics show`), written atomically, keys sorted, without the
    timings: a re-run then leaves the git-tracked file as it was."""
    kept = {k: v for k, v in metrics.items() if not is_timing(k)}
    write_text(path, json.dumps(kept, indent=1, sort_keys=True) + "\n")


def log_timings(
    experiment: str,
    run_name: str,
    configured_uri: str | None,
    dvc_stage: str,
    metrics: dict[str, Any],
    tags: dict[str, str] | None = None,
) -> None:
    """The timings among metrics as an MLflow run of their own (stages that log no other run)."""
    timings = {k: float(v) for k, v in metrics.items() if is_timing(k)}
    if not timings:
        return
    with mlflow_run(experiment, run_name, configured_uri, {"dvc_stage": dvc_stage, **(tags or {})}):
        import mlflow

        mlflow.log_metrics(timings)
