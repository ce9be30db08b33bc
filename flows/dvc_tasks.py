"""Prefect tasks that run DVC, so that DVC's cache skips every stage that is up to date."""


import os
import subprocess
import sys
from pathlib import Path

from prefect import task
from prefect.logging import get_run_logger


class StageFailed(RuntimeError):
    """A DVC stage failed; the message is the stage's own error line."""


def dvc_env() -> dict[str, str]:
    """The environment for DVC: this interpreter's folder first on PATH, so that the `python` of
    the stage commands is the project's own."""
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    return env


def prefect_run_env() -> dict[str, str]:
    """The current Prefect flow and task run, for the stages' MLflow tags (stages/common/__init__.py)."""
    from prefect.runtime import flow_run, task_run

    values = {
        "BINPICK_PREFECT_FLOW_RUN_ID": flow_run.id,
        "BINPICK_PREFECT_FLOW_RUN_NAME": flow_run.name,
        "BINPICK_PREFECT_FLOW_NAME": flow_run.flow_name,
        "BINPICK_PREFECT_TASK_RUN_ID": task_run.id,
    }
    return {k: str(v) for k, v in values.items() if v}


def repro(target: str, root: Path, extra_env: dict[str, str] | None = None) -> str:
    """`dvc repro <target>` in `root`; returns DVC's output, raises StageFailed with the error."""
    proc = subprocess.run(
        [sys.executable, "-m", "dvc", "repro", target], cwd=root, env={**dvc_env(), **(extra_env or {})}, text=True,
        stdout=subprocess.PIPE, stderr=subprocess.PIPE,
    )
    if proc.returncode != 0:
        lines = [line for line in (proc.stderr + proc.stdout).splitlines() if line.startswith("error:")]
        reason = lines[-1] if lines else (proc.stderr.strip().splitlines() or ["unknown error"])[-1]
        raise StageFailed(f"dvc repro {target} failed: {reason}")
    return proc.stdout


@task(name="dvc-repro", task_run_name="{target}", retries=1, retry_delay_seconds=2,
      retry_condition_fn=lambda task, run, state: "lock" in str(state.message or "").lower())
def repro_stage(target: str, root: Path) -> str:
    """One DVC stage; retried once only when another DVC process held the repository lock."""
    out = repro(target, root, prefect_run_env())
    logger = get_run_logger()
    skipped = "didn't change, skipping" in out or "is cached" in out
    logger.info("%s: %s", target, "up to date" if skipped else "ran")
    return out
