"""What every stage shares: the CLI wrapper (one error line, non-zero exit), params, MLflow
runs, metrics files. Stages import this; kernels never do."""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import signal
import socket
import sys
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, Protocol

from binpick.env import configure_environment, project_root
from binpick.errors import BinpickError
from binpick.io.atomic import write_text
from binpick.io.digest import file_sha256
from binpick.layout import Layout
from binpick.log import setup_logging

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


def tracking_uri(configured: str | None) -> str:
    """The MLflow store: tracking.mlflow_uri from params, else the MLFLOW_TRACKING_URI variable,
    else a sqlite file in the project (absolute path, as MLflow requires)."""
    import os

    if configured:
        return configured
    if os.environ.get("MLFLOW_TRACKING_URI"):
        return os.environ["MLFLOW_TRACKING_URI"]
    return f"sqlite:///{Layout(project_root()).mlflow_store}"


def artifact_location(configured_uri: str | None) -> str | None:
    """Where a new experiment keeps its artifacts: beside the sqlite store (the project's, or a
    configured sqlite file); None for a server, which decides. Never MLflow's default, ./mlruns
    in whatever folder the process happens to run in."""
    uri = tracking_uri(configured_uri)
    if uri.startswith("sqlite:///"):
        return (Path(uri.removeprefix("sqlite:///")).parent / "artifacts").as_uri()
    return None


@contextlib.contextmanager
def mlflow_run(
    experiment: str, run_name: str, configured_uri: str | None, tags: dict[str, str] | None = None
) -> Iterator[Any]:
    """An MLflow run in `experiment`, artifacts under <project>/data/mlflow/artifacts for the local store."""
    import mlflow

    if not configured_uri:
        Layout(project_root()).mlflow.mkdir(parents=True, exist_ok=True)
    logging.getLogger("alembic").setLevel(logging.WARNING)
    import os

    # MLflow exports the URI it is given as MLFLOW_TRACKING_URI for child processes; a caller's
    # own variable (or its absence) is put back afterwards, so that the stages a flow starts later
    # do not inherit this run's store.
    before = os.environ.get("MLFLOW_TRACKING_URI")
    uri = tracking_uri(configured_uri)
    try:
        mlflow.set_tracking_uri(uri)
        if mlflow.get_experiment_by_name(experiment) is None:
            mlflow.create_experiment(experiment, artifact_location=artifact_location(configured_uri))
        mlflow.set_experiment(experiment)
        end_dead_runs(experiment)
        own = {"binpick.pid": str(os.getpid()), "binpick.host": socket.gethostname()}
        with mlflow.start_run(run_name=run_name, tags={**prefect_tags(), **own, **(tags or {})}) as run:
            yield run
    finally:
        if before is None:
            os.environ.pop("MLFLOW_TRACKING_URI", None)
        else:
            os.environ["MLFLOW_TRACKING_URI"] = before


def end_dead_runs(experiment: str) -> list[str]:
    """Mark KILLED the runs of `experiment` still RUNNING whose process (on this host) is gone: a
    stage killed with SIGKILL cannot end its own run. Returns their ids."""
    import mlflow

    from binpick.lifetime import pid_alive

    client = mlflow.MlflowClient()
    found = client.get_experiment_by_name(experiment)
    if found is None:
        return []
    ended = []
    for run in client.search_runs(
        [found.experiment_id], filter_string="attributes.status = 'RUNNING'", max_results=200
    ):
        pid, host = run.data.tags.get("binpick.pid"), run.data.tags.get("binpick.host")
        if host == socket.gethostname() and pid and pid.isdigit() and not pid_alive(int(pid)):
            client.set_terminated(run.info.run_id, status="KILLED")
            ended.append(run.info.run_id)
    if ended:
        log.warning("%s: marked %d run(s) of killed stages as KILLED", experiment, len(ended))
    return ended


# Set by flows/dvc_tasks.py for the stage commands it runs, so that a stage's MLflow run names
# the Prefect flow run (and task run) that started it.
PREFECT_ENV = {
    "prefect.flow_run_id": "BINPICK_PREFECT_FLOW_RUN_ID",
    "prefect.flow_run_name": "BINPICK_PREFECT_FLOW_RUN_NAME",
    "prefect.flow_name": "BINPICK_PREFECT_FLOW_NAME",
    "prefect.task_run_id": "BINPICK_PREFECT_TASK_RUN_ID",
}


def prefect_tags() -> dict[str, str]:
    import os

    return {tag: os.environ[var] for tag, var in PREFECT_ENV.items() if os.environ.get(var)}


def flat_params(prefix: str, model: Any) -> dict[str, Any]:
    """Flatten a params model into MLflow's 'section.key' form."""
    out: dict[str, Any] = {}

    def walk(p: str, v: Any) -> None:
        if isinstance(v, dict):
            for k, x in v.items():
                walk(f"{p}.{k}", x)
        else:
            out[p] = v

    walk(prefix, model.model_dump(by_alias=True) if hasattr(model, "model_dump") else model)
    return out


def model_name(part: str) -> str:
    return f"fpcc-{part}"


def add_model_version(part: str, checkpoint: Path, run: Any, dvc_stage: str) -> str:
    """A new version of the registered model fpcc-<part> pointing at the run's logged checkpoint,
    tagged with the checkpoint's SHA-256 so that evaluation can find it. Returns the version."""
    import mlflow

    client = mlflow.MlflowClient()
    name = model_name(part)
    if not client.search_registered_models(filter_string=f"name='{name}'"):
        client.create_registered_model(name, description=f"FPCC instance segmentation of part {part}")
    version = client.create_model_version(
        name,
        source=f"{run.info.artifact_uri}/model",
        run_id=run.info.run_id,
        tags={"checkpoint_sha256": file_sha256(checkpoint), "dvc_stage": dvc_stage},
    )
    return str(version.version)


def accept_checkpoint(part: str, checkpoint: Path, alias: str) -> str | None:
    """Point `alias` of fpcc-<part> at the version registered for this checkpoint file; the
    version, or None when no version holds this checkpoint."""
    import mlflow

    client = mlflow.MlflowClient()
    sha = file_sha256(checkpoint)
    for version in client.search_model_versions(f"name='{model_name(part)}'"):
        if version.tags.get("checkpoint_sha256") == sha:
            client.set_registered_model_alias(model_name(part), alias, version.version)
            return str(version.version)
    return None
