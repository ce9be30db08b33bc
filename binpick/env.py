"""Process environment the project sets for itself: no telemetry, no update checks, no network.

Called first by every entry point (CLI, stages, flows), before MLflow or Prefect are imported.
Values already set by the user win, so a team can still point at a shared server.
"""

from __future__ import annotations

import os
from pathlib import Path

from binpick.layout import Layout

_DEFAULTS = {
    # MLflow ignores DO_NOT_TRACK=1; it wants the word.
    "MLFLOW_DISABLE_TELEMETRY": "true",
    "DO_NOT_TRACK": "true",
    "DVC_NO_ANALYTICS": "1",
    "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
    "PREFECT_CLOUD_ENABLE_ORCHESTRATION_TELEMETRY": "false",
    "PREFECT_UI_ENABLED": "false",
    # A flow run without PREFECT_API_URL starts a server in a subprocess, migrating a fresh
    # database first; Prefect's 20 s limit was too short on a busy 2-core CI machine.
    "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS": "180",
    # A flow run's calls to a local server that shares two busy cores with training: Prefect's
    # 60 s per request (retried 5 times) ran out in CI and crashed a finished scheduled run.
    "PREFECT_API_REQUEST_TIMEOUT": "300",
    "GIT_PYTHON_REFRESH": "quiet",
    "TQDM_MININTERVAL": "2",
    # The PPF voting loop runs on every core through OpenMP or numba's own pool; the TBB found on
    # some systems is too old for numba and would only print a warning. Read when numba loads.
    "NUMBA_THREADING_LAYER_PRIORITY": "omp workqueue tbb",
}


def project_root(start: Path | None = None) -> Path:
    """The folder holding params.yaml and dvc.yaml, searched from `start` (default: cwd) upward."""
    here = (start or Path.cwd()).resolve()
    for folder in (here, *here.parents):
        if (folder / "params.yaml").is_file() and (folder / "dvc.yaml").is_file():
            return folder
    return here


def configure_environment(root: Path | None = None) -> None:
    """Set the project's defaults; Prefect keeps its state in `<root>/data/prefect`."""
    for key, value in _DEFAULTS.items():
        os.environ.setdefault(key, value)
    root = root or project_root()
    os.environ.setdefault("PREFECT_HOME", str(Layout(root).prefect))
    os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
