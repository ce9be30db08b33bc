"""MLflow tracking for the stages, the learning flow and the service: where the store is, one run
per stage or request (tagged with the DVC stage and the Prefect flow run that started it), model
versions and their aliases. The library never calls MLflow; the application does, through here."""

from __future__ import annotations

import contextlib
import logging
import socket
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from binpick.env import project_root
from binpick.io.digest import file_sha256
from binpick.layout import Layout

log = logging.getLogger("binpick.tracking")


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
